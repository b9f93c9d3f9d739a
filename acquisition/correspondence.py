"""Unlabelled 2-D blobs of a calibrated rig -> unlabelled 3-D points -> fragments.

Per frame: every camera pair proposes the blob pairs within ``tolerance_px`` of each other's
epipolar line; each proposal is triangulated (two-view DLT in undistorted normalized
coordinates) and collects, in every other camera, the nearest blob within ``tolerance_px`` of
its reprojection. Proposals with the same views are one hypothesis. Hypotheses of three or more
views are accepted best first over the whole frame (most views, then smallest reprojection
error), each blob used once; then a two-view hypothesis is accepted only when it lies within
``link_mm`` of a point of the previous frame, when its two blobs are each other's only epipolar
partner among the blobs still unused, or when it lies within ``SURFACE_MM`` of the face as the
points accepted so far sample it (two-view matches are where ghosts come from: a ghost of two
rays lies in front of or behind the face). Accepted points are refitted
by the robust triangulation kernel (:mod:`.triangulate`), which drops disagreeing views
(outlier rejection). Points are then linked frame to frame into fragments: a constant-velocity
prediction of each live fragment is matched to the next frame's points by an optimal
assignment (Hungarian) within ``link_mm``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

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


def _normalized(rig: CameraRig, blobs: np.ndarray) -> np.ndarray:
    """Undistorted normalized coordinates of ``blobs (C, F, B, 2)`` px (NaN kept)."""
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
    norm = _normalized(rig, blobs)
    projections = [np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig]
    focal = np.array([cam.focal_px for cam in rig])
    essentials = {}
    for i in range(n_cams):
        for j in range(i + 1, n_cams):
            rotation = rig[j].rotation @ rig[i].rotation.T
            t = rig[j].tvec - rotation @ rig[i].tvec
            cross = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            essentials[i, j] = cross @ rotation
    chosen_views: list[np.ndarray] = []  # (C,) blob index or -1, per accepted point
    chosen_frame: list[int] = []
    previous = np.zeros((0, 3))
    for f in range(n_frames):
        views, previous = _frame_hypotheses(norm[:, f], projections, essentials, focal,
                                            tolerance_px, previous, link_mm)
        chosen_views += views
        chosen_frame += [f] * len(views)
    if not chosen_views:
        empty = np.zeros((n_frames, 0))
        return Reconstruction(np.zeros((n_frames, 0, 3)), empty.astype(int), empty.astype(int))
    picks = np.array(chosen_views)
    frames = np.array(chosen_frame)
    observations = np.full((n_cams, len(picks), 2), np.nan)
    for c in range(n_cams):
        used = picks[:, c] >= 0
        observations[c, used] = blobs[c, frames[used], picks[used, c]]
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


def _frame_hypotheses(norm: np.ndarray, projections: list[np.ndarray], essentials: dict,
                      focal: np.ndarray, tolerance_px: float, previous: np.ndarray,
                      near_mm: float) -> tuple[list[np.ndarray], np.ndarray]:
    """Accepted view sets ``(C,)`` (blob index per camera, -1 unused) of one frame and their
    two-view points ``(A, 3)`` mm; ``norm (C, B, 2)`` normalized blobs (NaN padding),
    ``previous (P, 3)`` the last frame's points (to pick among ambiguous two-view matches)."""
    n_cams = len(projections)
    present = [np.nonzero(np.isfinite(norm[c, :, 0]))[0] for c in range(n_cams)]
    trees = [cKDTree(norm[c, present[c]] * focal[c]) if len(present[c]) else None for c in range(n_cams)]
    keys, errs, pts = [], [], []  # per proposal: views (C,), error px, point mm
    for (i, j), essential in essentials.items():
        if not len(present[i]) or not len(present[j]):
            continue
        xi = np.column_stack([norm[i, present[i]], np.ones(len(present[i]))])
        xj = np.column_stack([norm[j, present[j]], np.ones(len(present[j]))])
        lines = xi @ essential.T  # epipolar lines in camera j of the blobs of camera i
        distance = np.abs(lines @ xj.T) / np.hypot(lines[:, :1], lines[:, 1:2]) * focal[j]
        a, b = np.nonzero(distance < tolerance_px)
        if not len(a):
            continue
        points = _two_view(projections[i], projections[j], norm[i, present[i][a]], norm[j, present[j][b]])
        support = np.full((len(a), n_cams), -1)
        support[:, i], support[:, j] = present[i][a], present[j][b]
        errors = np.zeros(len(a))
        for k in range(n_cams):
            cam = projections[k]
            depth = points @ cam[2, :3] + cam[2, 3]
            projected = (points @ cam[:2, :3].T + cam[:2, 3]) / depth[:, None] * focal[k]
            if k in (i, j):
                residual = np.linalg.norm(projected - norm[k, support[:, k]] * focal[k], axis=1)
                errors += np.where(depth > 0, residual, np.inf)
            elif trees[k] is not None:
                gap, nearest = trees[k].query(projected, distance_upper_bound=tolerance_px)
                hit = np.isfinite(gap) & (depth > 0)
                support[hit, k] = present[k][nearest[hit]]
                errors += np.where(hit, gap, 0.0)
        keys.append(support)
        errs.append(errors / (support >= 0).sum(axis=1))
        pts.append(points)
    if not keys:
        return [], np.zeros((0, 3))
    keys, errs, pts = np.concatenate(keys), np.concatenate(errs), np.concatenate(pts)
    n_views = (keys >= 0).sum(axis=1)
    order = np.lexsort((errs, -n_views))  # most views, then smallest error
    order = order[np.isfinite(errs[order])]
    width = int(keys.max()) + 2
    used = np.zeros((n_cams, width), bool)  # column -1 (unused camera) is never set
    cams = np.arange(n_cams)
    accepted: list[int] = []

    def take(rows) -> None:
        for row in rows:
            key = keys[row]
            if not used[cams, key].any():  # an index of -1 reads the last column: always False
                used[cams[key >= 0], key[key >= 0]] = True
                accepted.append(row)

    take(order[n_views[order] >= 3])  # >= 3 views: best first over the whole frame
    pairs = order[n_views[order] == 2]
    # two views near a point of the last frame (a marker moves < near_mm per frame), nearest first
    if len(previous) and len(pairs):
        distance = cKDTree(previous).query(pts[pairs])[0]
        near = np.argsort(distance, kind="stable")
        take(pairs[near[distance[near] < near_mm]])
    # two views: only a pair of blobs that are each other's only unused epipolar partner
    for _ in range(2):  # accepting unique pairs can make others unique
        free = pairs[~used[cams, keys[pairs]].any(axis=1)]
        if not len(free):
            break
        cam_a = np.argmax(keys[free] >= 0, axis=1)
        cam_b = n_cams - 1 - np.argmax(keys[free][:, ::-1] >= 0, axis=1)
        blob_a, blob_b = keys[free, cam_a], keys[free, cam_b]
        count = np.zeros((n_cams, width), int)
        np.add.at(count, (cam_a, blob_a), 1)
        np.add.at(count, (cam_b, blob_b), 1)
        take(free[(count[cam_a, blob_a] == 1) & (count[cam_b, blob_b] == 1)])
    # ambiguous two views: the candidate on the face, as sampled by the points accepted so far
    free = pairs[~used[cams, keys[pairs]].any(axis=1)]
    if len(free) and len(accepted) >= SURFACE_NEIGHBOURS:
        off = _off_surface(pts[np.array(accepted)], pts[free])
        near = np.argsort(off, kind="stable")
        take(free[near[off[near] < SURFACE_MM]])
    accepted_rows = np.array(accepted, dtype=int)
    return list(keys[accepted_rows]), pts[accepted_rows].reshape(-1, 3)


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
    frame's points by the Hungarian assignment within ``link_mm``; unmatched points start new
    fragments, unmatched fragments end."""
    n_frames, width = points.shape[:2]
    ids = np.full((n_frames, width), -1)
    live: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}  # id -> (last, previous)
    next_id = 0
    for f in range(n_frames):
        present = np.nonzero(np.isfinite(points[f, :, 0]))[0]
        current = points[f, present]
        keys = list(live)
        matched_rows: dict[int, int] = {}
        if keys and len(present):
            predicted = np.array([2 * last - prev if prev is not None else last
                                  for last, prev in (live[k] for k in keys)])
            cost = np.linalg.norm(predicted[:, None] - current[None], axis=2)
            rows, cols = linear_sum_assignment(np.where(cost < link_mm, cost, 1e6))
            matched_rows = {c: keys[r] for r, c in zip(rows, cols) if cost[r, c] < link_mm}
        new_live = {}
        for col, index in enumerate(present):
            fragment = matched_rows.get(col)
            if fragment is None:
                fragment, next_id = next_id, next_id + 1
                new_live[fragment] = (current[col], None)
            else:
                new_live[fragment] = (current[col], live[fragment][0])
            ids[f, index] = fragment
        live = new_live
    return ids
