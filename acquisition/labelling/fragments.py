"""Trajectory fragments of an unlabelled capture: the unit a label is voted for.

A fragment is a run of consecutive frames in which one column holds a point (capture software
breaks a trajectory at every occlusion; a column may hold several fragments one after another).
Untracked per-frame clouds (each frame's points in arbitrary columns) are first linked into
fragments here: a point continues the previous frame's nearest point when the two are mutual
nearest neighbours, well inside the marker spacing, and each clearly nearer to the other than
to any other point (both ways: a ghost passing close to a marker must not carry on its trajectory).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

#: Link clouds only within this fraction of the template's median marker spacing ...
LINK_SPACING = 0.35
#: ... and only when the second-nearest point is at least this many times farther.
LINK_RATIO = 2.0
#: A capture whose column steps exceed LINK_SPACING × spacing this often is untracked clouds.
CLOUD_JUMPS = 0.2


def column_fragments(positions: np.ndarray) -> np.ndarray:
    """(F, N) fragment id of every point (runs of points per column), -1 where no point."""
    present = ~np.isnan(positions).any(axis=2)
    starts = present & ~np.vstack([np.zeros((1, present.shape[1]), dtype=bool), present[:-1]])
    # number runs column by column: cumulative count of run starts in column-major order
    ids = np.cumsum(starts.T.ravel()).reshape(present.shape[1], -1).T - 1
    return np.where(present, ids, -1).astype(np.int32)


def looks_untracked(positions: np.ndarray, spacing_mm: float) -> bool:
    """True when the columns jump between markers frame to frame (per-frame clouds)."""
    step = np.linalg.norm(np.diff(positions, axis=0), axis=2)
    step = step[np.isfinite(step)]
    return bool(step.size) and float((step > LINK_SPACING * spacing_mm).mean()) > CLOUD_JUMPS


def link_clouds(positions: np.ndarray, spacing_mm: float, *, threads: int = 1) -> np.ndarray:
    """(F, N) fragment ids linking untracked clouds frame to frame (see module doc).

    Which point continues which depends on two frames only, so the frames are linked in
    ``threads`` ranges side by side (the kernel releases the GIL); the ids are then numbered in
    one pass, the same whatever ``threads``.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    ids = np.full(positions.shape[:2], -1, dtype=np.int32)
    edges = [len(ids) * k // max(threads, 1) for k in range(max(threads, 1) + 1)]
    ranges = [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    radius = LINK_SPACING * spacing_mm

    def back(bound: tuple[int, int]) -> None:
        _link_back(positions, radius, LINK_RATIO, bound[0], bound[1], ids)

    if len(ranges) > 1:
        with ThreadPoolExecutor(len(ranges)) as pool:
            list(pool.map(back, ranges))
    elif ranges:
        back(ranges[0])
    _number(positions, ids)
    return ids


@numba.njit(cache=True, nogil=True)
def _link_back(positions, radius, ratio, start, stop, ids):  # pragma: no cover - compiled
    """For the frames ``start..stop-1``, ``ids[f, c]``: the column of frame ``f - 1`` whose point
    ``c`` continues, -1 none. Brute-force nearest neighbours (a face's 40-200 points a frame:
    cheaper than a tree per frame, and no Python per frame), on each frame's points copied side by
    side once (a frame is read once, as the current frame, and kept as the next one's previous)."""
    n_cols = ids.shape[1]
    prev, cur = np.empty(n_cols, dtype=np.int64), np.empty(n_cols, dtype=np.int64)
    prev_pts, cur_pts = np.empty((n_cols, 3)), np.empty((n_cols, 3))
    back, nearest = np.empty(n_cols, dtype=np.int64), np.empty(n_cols, dtype=np.int64)
    scratch = np.empty((4, n_cols))
    first = max(start, 1)
    n_prev = _present(positions, first - 1, prev, prev_pts) if first < stop else 0
    p_order = np.argsort(prev_pts[:n_prev, 0], kind="mergesort")
    for f in range(first, stop):
        n = _present(positions, f, cur, cur_pts)
        c_order = np.argsort(cur_pts[:n, 0], kind="mergesort")  # stable: see _link_frame
        if n and n_prev >= 2:
            _link_frame(prev_pts, n_prev, p_order, cur_pts, n, c_order, radius, ratio, nearest, back, scratch)
            for i in range(n):
                if back[i] >= 0:
                    ids[f, cur[i]] = prev[back[i]]
        prev, cur, prev_pts, cur_pts, n_prev, p_order = cur, prev, cur_pts, prev_pts, n, c_order


@numba.njit(cache=True, nogil=True)
def _link_frame(prev_pts, n_prev, p_order, cur_pts, n, c_order, radius, ratio, nearest, back,
                scratch):  # pragma: no cover - compiled
    """One frame of :func:`_link_back`: ``back[i]`` the previous point (row of ``prev_pts``) that
    current point ``i`` continues, -1 none; ``p_order``, ``c_order``: the points' order by x;
    ``nearest`` and ``scratch (4, N)``: work space.

    Only points within ``ratio × radius`` of each other can decide a link (a farther nearest is
    beyond the radius, a farther second-nearest passes the ratio test), so each point is compared
    with the other frame's points in that band of x only (both sorted by x, stably: points at
    exactly the same place keep their column order, so ties resolve as in a full scan).
    """
    band = 1.001 * ratio * radius
    # each previous point's nearest current point, if clearly the nearest
    _two_nearest(prev_pts, p_order, n_prev, cur_pts, c_order, n, band, nearest, scratch[0], scratch[1])
    for j in range(n_prev):
        if scratch[1, j] < ratio * ratio * scratch[0, j]:  # a ghost beside the marker: either may continue it
            nearest[j] = -1
    # each current point's nearest and second-nearest previous points
    _two_nearest(cur_pts, c_order, n, prev_pts, p_order, n_prev, band, back, scratch[2], scratch[3])
    for i in range(n):
        near, d0, d1 = back[i], np.sqrt(scratch[2, i]), np.sqrt(scratch[3, i])
        back[i] = near if near >= 0 and nearest[near] == i and d0 <= radius and d1 >= ratio * d0 else -1


@numba.njit(cache=True, nogil=True)
def _two_nearest(a, a_order, n_a, b, b_order, n_b, band, near, best, second):  # pragma: no cover - compiled
    """For each of the first ``n_a`` points of ``a``: ``near`` its nearest point of ``b`` (row, -1
    none), ``best`` and ``second`` the squared distances to the nearest and second-nearest, among
    ``b``'s points within ``band`` of it in x (``a_order``, ``b_order``: the points' order by x)."""
    lo = 0
    for kk in range(n_a):
        k = a_order[kk]
        x = a[k, 0]
        while lo < n_b and b[b_order[lo], 0] < x - band:
            lo += 1
        d0, d1, near[k] = np.inf, np.inf, -1
        for jj in range(lo, n_b):
            j = b_order[jj]
            if b[j, 0] > x + band:
                break
            d = _d2(a, k, b, j)
            if d < d0:
                d0, d1, near[k] = d, d0, j
            elif d < d1:
                d1 = d
        best[k], second[k] = d0, d1


@numba.njit(cache=True, nogil=True)
def _number(positions, ids):  # pragma: no cover - compiled
    """Turn :func:`_link_back`'s columns into fragment ids, frame by frame, in place: a point
    continuing one takes its id, any other point a new one (in column order)."""
    next_id = 0
    for f in range(ids.shape[0]):
        for c in range(ids.shape[1]):
            if np.isnan(positions[f, c, 0]) or np.isnan(positions[f, c, 1]) or np.isnan(positions[f, c, 2]):
                continue
            if ids[f, c] >= 0:
                ids[f, c] = ids[f - 1, ids[f, c]]
            else:
                ids[f, c] = next_id
                next_id += 1


@numba.njit(cache=True, nogil=True)
def _present(positions, f, out, pts):  # pragma: no cover - compiled
    """The columns holding a point in frame ``f`` into ``out``, their points into ``pts``; their count."""
    n = 0
    for c in range(positions.shape[1]):
        x, y, z = positions[f, c, 0], positions[f, c, 1], positions[f, c, 2]
        if not (np.isnan(x) or np.isnan(y) or np.isnan(z)):
            out[n] = c
            pts[n, 0], pts[n, 1], pts[n, 2] = x, y, z
            n += 1
    return n


@numba.njit(cache=True, nogil=True, inline="always")
def _d2(a, i, b, j):  # pragma: no cover - compiled
    x = a[i, 0] - b[j, 0]
    y = a[i, 1] - b[j, 1]
    z = a[i, 2] - b[j, 2]
    return x * x + y * y + z * z
