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
    cheaper than a tree per frame, and no Python per frame)."""
    n_cols = ids.shape[1]
    prev = np.empty(n_cols, dtype=np.int64)
    cur = np.empty(n_cols, dtype=np.int64)
    back = np.empty(n_cols, dtype=np.int64)
    for f in range(max(start, 1), stop):
        n_prev = _present(positions, f - 1, prev)
        n = _present(positions, f, cur)
        if not n or n_prev < 2:
            continue
        for j in range(n_prev):  # each previous point's nearest current point, if clearly the nearest
            best, second, back[j] = np.inf, np.inf, -1
            for i in range(n):
                d = _d2(positions, f - 1, prev[j], f, cur[i])
                if d < best:
                    best, second, back[j] = d, best, i
                elif d < second:
                    second = d
            if second < ratio * ratio * best:  # a ghost beside the marker: either may continue it
                back[j] = -1
        for i in range(n):  # each current point's nearest and second-nearest previous points
            d0, d1, near = np.inf, np.inf, -1
            for j in range(n_prev):
                d = _d2(positions, f, cur[i], f - 1, prev[j])
                if d < d0:
                    d0, d1, near = d, d0, j
                elif d < d1:
                    d1 = d
            d0, d1 = np.sqrt(d0), np.sqrt(d1)
            if back[near] == i and d0 <= radius and d1 >= ratio * d0:
                ids[f, cur[i]] = prev[near]


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
def _present(positions, f, out):  # pragma: no cover - compiled
    """The columns holding a point in frame ``f`` into ``out``; their count."""
    n = 0
    for c in range(positions.shape[1]):
        if not (np.isnan(positions[f, c, 0]) or np.isnan(positions[f, c, 1]) or np.isnan(positions[f, c, 2])):
            out[n] = c
            n += 1
    return n


@numba.njit(cache=True, nogil=True, inline="always")
def _d2(positions, f, c, g, e):  # pragma: no cover - compiled
    x = positions[f, c, 0] - positions[g, e, 0]
    y = positions[f, c, 1] - positions[g, e, 1]
    z = positions[f, c, 2] - positions[g, e, 2]
    return x * x + y * y + z * z
