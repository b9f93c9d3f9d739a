"""Unlabelled 2-D blobs of a calibrated rig -> unlabelled 3-D points -> fragments.

Per frame: every camera pair proposes the blob pairs within ``tolerance_px`` of each other's
epipolar line; each proposal is triangulated (two-view DLT in undistorted normalized
coordinates) and collects, in every other camera, the nearest blob within ``tolerance_px`` of
its reprojection (one compiled pass over all frames, :mod:`.correspondence_kernel`). Proposals
with the same views are one hypothesis. Hypotheses of three or more views are chosen by a
global assignment per frame: the set that uses each blob at most once with the largest total
weight (views minus half the mean error in tolerances: the most views explained, then the
smallest error), solved exactly per group of hypotheses that share blobs; a loser that lost a
blob keeps its free views, a two-view match when two remain (a marker hidden in one camera
where another's blob lies on its ray collects that blob, and would go with it). Then a two-view
hypothesis is accepted only when it lies within ``link_mm`` of a point of the previous frame,
when its two blobs are each other's only epipolar partner among the blobs still unused, or
when it lies within ``SURFACE_MM`` of the face as the points accepted so far sample it (two-view
matches are where ghosts come from: a ghost of two rays lies in front of or behind the face),
nearest first, each blob once (among conflicting two-view matches the closest wins; maximising
their number instead accepted twice the ghosts). Accepted points are
refitted by the robust triangulation kernel (:mod:`.triangulate`), which drops disagreeing
views (outlier rejection). Points are then linked frame to frame into fragments: a
constant-velocity prediction of each live fragment is matched to the next frame's points by an
optimal assignment (Hungarian) within ``link_mm``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

from mocaptk.threads import machine_workers, worker_threads

from .cameras import CameraRig
from .triangulate import triangulate_points

TOLERANCE_PX = 1.0
LINK_MM = 4.0
#: An ambiguous two-view match is kept when it lies within SURFACE_MM of the plane through its
#: SURFACE_NEIGHBOURS nearest points of >= 3 views (nearest to the face first, each blob once).
SURFACE_MM = 1.5
SURFACE_NEIGHBOURS = 6


@dataclass
class Reconstruction:
    """``points (F, P, 3)`` mm, NaN-padded per frame; ``views (F, P)`` inlier views;
    ``fragments (F, P)`` int fragment id of each point (-1 none)."""

    points: np.ndarray
    views: np.ndarray
    fragments: np.ndarray

    @property
    def n_fragments(self) -> int:
        return int(self.fragments.max()) + 1 if self.fragments.size else 0

    def trajectories_array(self) -> np.ndarray:
        """``(F, n_fragments, 3)`` positions of every fragment, NaN outside it."""
        out = np.full((self.points.shape[0], self.n_fragments, 3), np.nan)
        f, p = np.nonzero(self.fragments >= 0)
        out[f, self.fragments[f, p]] = self.points[f, p]
        return out

    def fragment_lengths(self) -> np.ndarray:
        return np.bincount(self.fragments[self.fragments >= 0], minlength=self.n_fragments)


def normalized_blobs(rig: CameraRig, blobs: np.ndarray) -> np.ndarray:
    """Undistorted normalized coordinates of ``blobs (C, ..., 2)`` px (NaN kept)."""
    out = np.full(blobs.shape, np.nan)
    for c, camera in enumerate(rig):
        finite = np.isfinite(blobs[c, ..., 0])
        if finite.any():
            out[c][finite] = cv2.undistortPoints(blobs[c][finite].reshape(-1, 1, 2), camera.matrix,
                                                 camera.distortion).reshape(-1, 2)
    return out


def _two_view(p_i: np.ndarray, p_j: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Linear (inhomogeneous DLT) points ``(N, 3)`` mm from normalized ``x_i, x_j (N, 2)`` and
    projections ``(3, 4)``: 4 equations, 3 unknowns, normal equations solved per point."""
    rows = np.stack([x_i[:, :1] * p_i[2] - p_i[0], x_i[:, 1:] * p_i[2] - p_i[1],
                     x_j[:, :1] * p_j[2] - p_j[0], x_j[:, 1:] * p_j[2] - p_j[1]], axis=1)
    a, b = rows[:, :, :3], -rows[:, :, 3]
    normal = np.einsum("nki,nkj->nij", a, a)
    return np.linalg.solve(normal, np.einsum("nki,nk->ni", a, b)[..., None])[..., 0]


def reconstruct(rig: CameraRig, blobs: np.ndarray, *, tolerance_px: float = TOLERANCE_PX,
                link_mm: float = LINK_MM, outlier_threshold_px: float = 3.0) -> Reconstruction:
    """Unlabelled 3-D points and fragments from ``blobs (C, F, B, 2)`` px (NaN padding) of
    ``rig`` (the halves of split merged blobs among them: a poor split is an outlier view)."""
    blobs = np.asarray(blobs, dtype=np.float64)
    n_cams, n_frames = blobs.shape[:2]
    norm = normalized_blobs(rig, blobs)
    projections = np.array([np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig])
    focal = np.array([cam.focal_px for cam in rig])
    frame, keys, error, point = _hypotheses(norm, projections, focal, tolerance_px)
    n_views = (keys >= 0).sum(axis=1)
    # >= 3 views: the most views (then the smallest error) over each whole frame at once
    many = np.nonzero(n_views >= 3)[0]
    chosen = many[_packing(frame[many], keys[many], _weight(n_views[many], error[many] / tolerance_px))]
    frame, keys, error, point = _lost_pairs(frame, keys, error, point, np.setdiff1d(many, chosen), chosen)
    n_views = (keys >= 0).sum(axis=1)
    chosen = list(_two_view_choices(frame, keys, point, n_views, chosen, n_frames, link_mm))
    if not chosen:
        empty = np.zeros((n_frames, 0))
        return Reconstruction(np.zeros((n_frames, 0, 3)), empty.astype(int), empty.astype(int))
    picks = np.concatenate(chosen)
    picks = picks[np.lexsort((np.arange(len(picks)), frame[picks]))]
    frames = frame[picks]
    observations = np.full((n_cams, len(picks), 2), np.nan)
    for c in range(n_cams):
        used = keys[picks, c] >= 0
        observations[c, used] = blobs[c, frames[used], keys[picks[used], c]]
    points, inliers = triangulate_points(rig, observations, min_views=2,
                                         outlier_threshold_px=outlier_threshold_px)
    good = np.isfinite(points[:, 0])
    points, frames, counts = points[good], frames[good], inliers[:, good].sum(axis=0)
    per_frame = np.bincount(frames, minlength=n_frames)
    width = int(per_frame.max()) if len(per_frame) else 0
    out = np.full((n_frames, width, 3), np.nan)
    out_views = np.zeros((n_frames, width), int)
    slot = np.arange(len(frames)) - np.concatenate([[0], np.cumsum(per_frame)[:-1]])[frames]
    out[frames, slot] = points
    out_views[frames, slot] = counts
    return Reconstruction(out, out_views, link_fragments(out, link_mm=link_mm))


def _lost_pairs(frame, keys, error, point, lost, chosen):
    """The hypotheses with the two-view ones that the packing's losers leave: a hypothesis of
    >= 3 views that lost a blob to a chosen one (a marker hidden in a camera where another
    marker's blob lies on its ray) keeps its free views, offered as a two-view match when two
    remain and no such hypothesis exists (it then meets the two-view tests like any other)."""
    n_cams, width = keys.shape[1], int(keys.max()) + 2 if len(keys) else 1

    def codes(rows):  # (rows, C) one integer per (frame, camera, blob); -1 where no blob
        k = keys[rows]
        return np.where(k >= 0, (frame[rows, None] * n_cams + np.arange(n_cams)) * width + k, -1)

    taken = codes(chosen)
    reduced = np.where(np.isin(codes(lost), taken[taken >= 0]), -1, keys[lost])
    two = (reduced >= 0).sum(axis=1) == 2
    rows, reduced = lost[two], reduced[two]
    existing = np.nonzero((keys >= 0).sum(axis=1) == 2)[0]
    codes = _set_codes(np.concatenate([frame[existing], frame[rows]]), np.vstack([keys[existing], reduced]),
                       n_frames=int(frame.max()) + 1 if len(frame) else 1, base=width)
    old, new = codes[:len(existing)], codes[len(existing):]
    values, first = np.unique(new, return_index=True)  # each new pair once, where it first comes
    exists = np.zeros(len(values), bool)  # and none that exists already (few new, many old)
    if len(values):
        at = np.minimum(np.searchsorted(values, old), len(values) - 1)
        exists[at[values[at] == old]] = True
    index = np.sort(first[~exists])
    rows, reduced = rows[index], reduced[index]
    return (np.concatenate([frame, frame[rows]]), np.concatenate([keys, reduced]),
            np.concatenate([error, error[rows]]), np.concatenate([point, point[rows]]))


def _weight(n_views: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Weight of a hypothesis of ``n_views`` views and mean error ``error`` (in tolerances)."""
    return n_views - 0.5 * error


def essential_matrix(projections: np.ndarray, i: int, j: int) -> np.ndarray:
    """Essential matrix ``(3, 3)`` of camera ``j`` relative to camera ``i``."""
    rotation = projections[j, :, :3] @ projections[i, :, :3].T
    t = projections[j, :, 3] - rotation @ projections[i, :, 3]
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rotation


def _hypotheses(norm: np.ndarray, projections: np.ndarray, focal: np.ndarray,
                tolerance_px: float) -> tuple[np.ndarray, ...]:
    """Every frame's distinct view sets: ``frame (H,)``, ``keys (H, C)`` blob per camera (-1
    none), ``error (H,)`` mean px, ``point (H, 3)`` mm (two-view), from ``norm (C, F, B, 2)``
    normalized blobs (the compiled :func:`.correspondence_kernel.proposals_kernel`)."""
    from .correspondence_kernel import proposals_kernel

    n_cams = len(projections)
    essentials = np.zeros((n_cams, n_cams, 3, 3))
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            essentials[i, j] = essential_matrix(projections, i, j)
    pixels = norm * focal[:, None, None, None]
    order = np.argsort(pixels[..., 1], axis=2, kind="stable")  # NaN last
    by_y = np.take_along_axis(pixels, order[..., None], axis=2)

    def proposals(first: int, last: int) -> tuple[np.ndarray, ...]:  # of frames first..last-1
        inputs = [np.ascontiguousarray(a[:, first:last]) for a in (norm, by_y, order)]
        capacity = 8 * (last - first) * norm.shape[2] + 1
        while True:
            frame, keys = np.empty(capacity, np.int64), np.empty((capacity, n_cams), np.int64)
            error, point = np.empty(capacity), np.empty((capacity, 3))
            count = proposals_kernel(*inputs, essentials, projections, focal, float(tolerance_px),
                                     frame, keys, error, point)
            if count <= capacity:
                return frame[:count] + first, keys[:count], error[:count], point[:count]
            capacity = count

    # frames are independent: one range per thread (the kernel releases the GIL), joined in order
    edges = np.linspace(0, norm.shape[1], max(1, min(machine_workers(), norm.shape[1])) + 1).astype(int)
    helpers = [worker_threads().submit(proposals, first, last) for first, last in zip(edges[1:-1], edges[2:])]
    parts = [proposals(edges[0], edges[1]), *(helper.result() for helper in helpers)]
    frame, keys, error, point = (np.concatenate(arrays) for arrays in zip(*parts))
    # the same view set proposed by several pairs is one hypothesis (its smallest error kept,
    # the first proposed among equal ones); a two-view set has only one pair to propose it
    finite = np.isfinite(error)
    n_views = (keys >= 0).sum(axis=1)
    many = np.nonzero(finite & (n_views >= 3))[0]
    code = _set_codes(frame[many], keys[many], n_frames=norm.shape[1], base=norm.shape[2] + 1)
    by_error = np.argsort(error[many], kind="stable")
    order = by_error[np.argsort(code[by_error], kind="stable")]  # by set, then error, then index
    first = np.ones(len(order), bool)  # each set's first
    first[1:] = code[order[1:]] != code[order[:-1]]
    best = order[first]
    keep = np.sort(np.concatenate([np.nonzero(finite & (n_views == 2))[0], many[best]]))
    return frame[keep], keys[keep], error[keep], point[keep]


def _set_codes(frame: np.ndarray, keys: np.ndarray, *, n_frames: int, base: int) -> np.ndarray:
    """One integer per row of ``frame (N,)`` and view set ``keys (N, C)`` (blobs -1 .. base - 2),
    equal for equal rows: frame and view set as one number, or with many cameras the row's rank
    among the distinct ones (as sorting whole rows, which costs far more)."""
    if n_frames * float(base) ** keys.shape[1] < 2.0 ** 62:
        code = frame.astype(np.int64)
        for c in range(keys.shape[1]):
            code = code * base + keys[:, c] + 1
        return code
    return np.unique(np.column_stack([frame, keys]), axis=0, return_inverse=True)[1].ravel()


def _packing(frame: np.ndarray, keys: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Indices of the hypotheses that use every ``(frame, camera, blob)`` at most once with the
    largest total ``weight``: an exact weighted set packing per group of hypotheses that share
    blobs (most are alone; a group of up to ``_SEARCH`` by branch and bound, a larger one by
    HiGHS' integer programming)."""
    n = len(frame)
    if n == 0:
        return np.zeros(0, int)
    n_cams = keys.shape[1]
    rows, cams = np.nonzero(keys >= 0)
    blob = (frame[rows] * n_cams + cams) * (int(keys.max()) + 1) + keys[rows, cams]
    blob_ids, blob_index = np.unique(blob, return_inverse=True)
    if len(blob_ids) == len(blob):  # no blob wanted twice
        return np.arange(n)
    # groups: the smallest hypothesis index reachable through shared blobs (label propagation)
    group = np.arange(n)
    while True:
        lowest = np.full(len(blob_ids), n)
        np.minimum.at(lowest, blob_index, group[rows])
        spread = group.copy()
        np.minimum.at(spread, rows, lowest[blob_index])
        if (spread == group).all():
            break
        group = spread
    size = np.bincount(group)
    alone = size[group] == 1
    # two hypotheses that share a blob: the heavier
    two = np.nonzero(size[group] == 2)[0]
    two = two[np.argsort(group[two], kind="stable")].reshape(-1, 2)
    chosen = [np.nonzero(alone)[0], two[np.arange(len(two)), np.argmax(weight[two], axis=1)]]
    members = np.nonzero(size[group] > 2)[0]
    members = members[np.argsort(group[members], kind="stable")]
    for hyps in np.split(members, np.cumsum(size[np.unique(group[members])])[:-1]) if len(members) else []:
        k = keys[hyps]  # one frame: hypotheses conflict when they share a blob of one camera
        conflict = ((k[:, None] == k[None]) & (k[:, None] >= 0)).any(axis=2)
        chosen.append(hyps[_best_set(conflict, weight[hyps])])
    return np.sort(np.concatenate(chosen))


#: Largest group of conflicting hypotheses solved by branch and bound (beyond: HiGHS).
_SEARCH = 20


def _best_set(conflict: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Indices of the independent set of largest total ``weight`` (> 0) of the graph
    ``conflict (n, n)`` bool (diagonal True)."""
    n = len(weight)
    if n > _SEARCH:
        from scipy.optimize import LinearConstraint, milp

        rows, cols = np.nonzero(np.triu(conflict, 1))
        pair = coo_matrix((np.ones(2 * len(rows)), (np.repeat(np.arange(len(rows)), 2),
                                                     np.column_stack([rows, cols]).ravel())),
                          shape=(len(rows), n))
        result = milp(-weight, constraints=LinearConstraint(pair, -np.inf, 1), integrality=np.ones(n),
                      bounds=(0, 1))
        return np.nonzero(result.x > 0.5)[0]
    order = np.argsort(-weight, kind="stable")
    w = weight[order].tolist()
    blocked = [int(sum(1 << q for q in np.nonzero(conflict[order[p], order])[0])) for p in range(n)]
    rest = np.concatenate([np.cumsum(w[::-1])[::-1], [0.0]]).tolist()
    best = [0.0, 0]

    def search(p: int, taken: int, value: float) -> None:
        if value + rest[p] <= best[0]:
            return
        if p == n:
            best[0], best[1] = value, taken
            return
        if not taken & blocked[p]:
            search(p + 1, taken | (1 << p), value + w[p])
        search(p + 1, taken, value)

    search(0, 0, 0.0)
    return np.sort(order[[p for p in range(n) if best[1] >> p & 1]])


def _two_view_choices(frame, keys, point, n_views, chosen, n_frames, link_mm):
    """Accepted hypotheses of every frame (arrays of indices): ``chosen`` (>= 3 views), then
    the two-view ones: near a point of the last frame, each other's only partner, on the face
    — nearest first (a two-view match is where a ghost comes from: among conflicting ones the
    closest wins, not the largest number; counting accepted twice the ghosts)."""
    from .correspondence_kernel import first_come

    n_cams = keys.shape[1]
    cams = np.arange(n_cams)
    pairs = np.nonzero(n_views == 2)[0]
    pairs = pairs[np.argsort(frame[pairs], kind="stable")]  # the lost pairs come last
    bounds = np.searchsorted(frame[pairs], np.arange(n_frames + 1))
    chosen_bounds = np.searchsorted(frame[chosen], np.arange(n_frames + 1))
    width = int(keys.max()) + 2 if len(keys) else 1
    previous = np.zeros((0, 3))
    for f in range(n_frames):
        accepted = chosen[chosen_bounds[f]:chosen_bounds[f + 1]]
        candidates = pairs[bounds[f]:bounds[f + 1]]
        used = np.zeros((n_cams, width), bool)  # column -1 (unused camera) is never set
        picked = [accepted]

        def mark(rows):
            k = keys[rows]
            used[np.broadcast_to(cams, k.shape)[k >= 0], k[k >= 0]] = True

        def free(rows):
            return rows[~used[cams, keys[rows]].any(axis=1)]

        def take(rows):  # in this order, each while its blobs are free
            best = np.empty(len(rows), np.int64)
            picked.append(best[:first_come(keys, rows.astype(np.int64), used, best)])

        mark(accepted)
        candidates = free(candidates)
        # two views near a point of the last frame (a marker moves < link_mm per frame)
        if len(previous) and len(candidates):
            distance = cKDTree(previous).query(point[candidates])[0]
            near = np.argsort(distance, kind="stable")
            take(candidates[near[distance[near] < link_mm]])
            candidates = free(candidates)
        # two views: a pair of blobs that are each other's only unused epipolar partner
        for _ in range(2):  # accepting unique pairs can make others unique
            if not len(candidates):
                break
            cam_a = np.argmax(keys[candidates] >= 0, axis=1)
            cam_b = n_cams - 1 - np.argmax(keys[candidates][:, ::-1] >= 0, axis=1)
            blob_a, blob_b = keys[candidates, cam_a], keys[candidates, cam_b]
            count = np.zeros((n_cams, width), int)
            np.add.at(count, (cam_a, blob_a), 1)
            np.add.at(count, (cam_b, blob_b), 1)
            unique = (count[cam_a, blob_a] == 1) & (count[cam_b, blob_b] == 1)
            take(candidates[unique])
            candidates = free(candidates)
        # ambiguous two views: the candidates on the face, as sampled by the points accepted so far
        so_far = np.concatenate(picked)
        if len(candidates) and len(so_far) >= SURFACE_NEIGHBOURS:
            off = _off_surface(point[so_far], point[candidates])
            near = np.argsort(off, kind="stable")
            take(candidates[near[off[near] < SURFACE_MM]])
        rows = np.concatenate(picked)
        previous = point[rows]
        yield rows


def _off_surface(surface: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance (mm) of each of ``points (N, 3)`` from the plane through its
    ``SURFACE_NEIGHBOURS`` nearest ``surface (S, 3)`` points (a ghost of two rays lies in front
    of or behind the face)."""
    _, index = cKDTree(surface).query(points, k=SURFACE_NEIGHBOURS)
    patch = surface[index]  # (N, k, 3)
    centre = patch.mean(axis=1)
    normal = np.linalg.svd(patch - centre[:, None])[2][:, -1]
    return np.abs(np.einsum("ni,ni->n", points - centre, normal))


def link_fragments(points: np.ndarray, *, link_mm: float = LINK_MM) -> np.ndarray:
    """Fragment id ``(F, P)`` of every point of ``points (F, P, 3)`` (NaN padding: -1): each
    live fragment's next position is predicted at constant velocity and matched to the next
    frame's points by the Hungarian assignment within ``link_mm`` (a prediction and a point that
    are each other's only candidate are matched without it); unmatched points start new
    fragments, unmatched fragments end."""
    n_frames, width = points.shape[:2]
    ids = np.full((n_frames, width), -1)
    live = np.zeros(0, int)  # fragment ids, their last and previous positions (NaN: none)
    last, before = np.zeros((0, 3)), np.zeros((0, 3))
    next_id = 0
    for f in range(n_frames):
        present = np.nonzero(np.isfinite(points[f, :, 0]))[0]
        current = points[f, present]
        match = np.full(len(present), -1)  # row of live per current point
        if len(live) and len(present):
            predicted = np.where(np.isfinite(before), 2 * last - before, last)
            near = cKDTree(predicted).sparse_distance_matrix(cKDTree(current), link_mm, output_type="ndarray")
            rows, cols = near["i"].astype(int), near["j"].astype(int)
            per_row, per_col = np.bincount(rows, minlength=len(live)), np.bincount(cols, minlength=len(present))
            alone = (per_row[rows] == 1) & (per_col[cols] == 1)
            match[cols[alone]] = rows[alone]
            rest_rows, rest_cols = np.unique(rows[~alone]), np.unique(cols[~alone])
            if len(rest_rows):
                cost = np.linalg.norm(predicted[rest_rows, None] - current[None, rest_cols], axis=2)
                r, c = linear_sum_assignment(np.where(cost < link_mm, cost, 1e6))
                ok = cost[r, c] < link_mm
                match[rest_cols[c[ok]]] = rest_rows[r[ok]]
        new = match < 0
        fragment = np.empty(len(present), int)
        fragment[~new] = live[match[~new]]
        fragment[new] = next_id + np.arange(new.sum())
        next_id += int(new.sum())
        previous = np.full((len(present), 3), np.nan)
        previous[~new] = last[match[~new]]
        ids[f, present] = fragment
        live, last, before = fragment, current, previous
    return ids
