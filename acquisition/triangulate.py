"""Robust, vectorized multi-view triangulation of labelled 2-D detections.

All points are solved together: per camera we undistort every detection at once, build the
DLT rows, and solve the batched 3x3 normal equations of the inhomogeneous DLT for every point
in one ``np.linalg.solve``. Outlier views are rejected by consensus: every camera pair
proposes a two-view point for all points at once, the proposal with most views within
``outlier_threshold_px`` wins per point, and the point is refit on those inlier views.
A few reweighting steps (depth-normalized DLT = Gauss-Newton-like refinement on the
reprojection error) finish each fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations

import cv2
import numpy as np

from mocaptk.trajectories import Trajectories

from .cameras import CameraRig
from .projection import project_points

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)


def triangulate(rig: CameraRig, observations: np.ndarray, *, labels: Sequence[str] | None = None,
                rate: float | None = None, min_views: int = 2,
                outlier_threshold_px: float = 4.0, refine_iterations: int = 3) -> Trajectories:
    """Triangulate labelled 2-D detections of all cameras into marker trajectories.

    Parameters
    ----------
    rig : CameraRig with C cameras.
    observations : (C, F, M, 2) float, px; NaN where a camera did not see a marker.
    labels : M marker labels (default ``M001``, ``M002``, ...).
    rate : frame rate in Hz (default: the rig's rate, else 60).
    min_views : a point needs at least this many agreeing views (>= 2), else it is a gap.
    outlier_threshold_px : a view whose reprojection error exceeds this is an outlier.
    refine_iterations : reweighting steps after each linear fit (0: plain DLT).

    Returns
    -------
    Trajectories
        ``positions (F, M, 3)`` mm; ``residuals (F, M)`` = RMS reprojection error over the
        inlier views in px (distorted image, as detected); ``metadata["view_counts"]``
        ``(F, M)`` int = number of inlier views used; ``metadata["camera_names"]``.
    """
    observations = np.asarray(observations, dtype=np.float64)
    if observations.ndim != 4 or observations.shape[-1] != 2:
        raise ValueError(f"observations must have shape (cameras, frames, markers, 2), "
                         f"got {observations.shape}")
    if observations.shape[0] != len(rig):
        raise ValueError(f"observations have {observations.shape[0]} cameras, "
                         f"the rig has {len(rig)}")
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2, got {min_views}")
    if outlier_threshold_px <= 0:
        raise ValueError(f"outlier_threshold_px must be > 0, got {outlier_threshold_px}")
    _, n_frames, n_markers, _ = observations.shape
    if labels is None:
        labels = [f"M{m + 1:03d}" for m in range(n_markers)]
    flat = observations.reshape(len(rig), -1, 2)
    points, inliers = triangulate_points(rig, flat, min_views=min_views,
                                         outlier_threshold_px=outlier_threshold_px,
                                         refine_iterations=refine_iterations)
    residuals = reprojection_rms(rig, points, flat, inliers)
    rate = rate if rate is not None else (rig.rate or 60.0)
    return Trajectories(
        positions=points.reshape(n_frames, n_markers, 3), labels=labels, rate=rate,
        residuals=residuals.reshape(n_frames, n_markers),
        metadata={"view_counts": inliers.sum(axis=0).reshape(n_frames, n_markers),
                  "camera_names": rig.names})


def triangulate_points(rig: CameraRig, observations: np.ndarray, *, min_views: int = 2,
                       outlier_threshold_px: float = 4.0, refine_iterations: int = 3,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation of P points from ``observations (C, P, 2)`` px.

    Returns ``points (P, 3)`` mm (NaN with fewer than ``min_views`` agreeing views) and the
    inlier views ``(C, P)`` bool.
    """
    rays = _normalized_rays(rig, observations)  # (C, P, 2), NaN where unseen
    valid = np.isfinite(rays[..., 0])
    poses = np.stack([np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig])  # (C,3,4)
    focal = np.array([cam.focal_px for cam in rig])
    rays = np.where(valid[..., None], rays, 0.0)

    # 1) all views; points whose views all agree are done
    points = _solve(poses, focal, rays, valid, refine_iterations)
    errors = _errors_px(poses, focal, rays, valid, points)
    inliers = valid & (errors <= outlier_threshold_px)
    suspect = np.nonzero((inliers.sum(axis=0) < valid.sum(axis=0)) & (valid.sum(axis=0) >= 2))[0]

    # 2) consensus over all two-view hypotheses for the points with disagreeing views
    if suspect.size:
        sub_rays, sub_valid = rays[:, suspect], valid[:, suspect]
        best_count = np.zeros(suspect.size, dtype=np.int64)
        best_cost = np.full(suspect.size, np.inf)
        best_inliers = np.zeros_like(sub_valid)
        for i, j in combinations(range(len(rig)), 2):
            pair = np.zeros_like(sub_valid)
            pair[[i, j]] = sub_valid[[i, j]]
            usable = pair[i] & pair[j]
            if not usable.any():
                continue
            hypothesis = _solve(poses, focal, sub_rays, pair, 0)
            err = _errors_px(poses, focal, sub_rays, sub_valid, hypothesis)
            agree = sub_valid & (err <= outlier_threshold_px)
            count = np.where(usable, agree.sum(axis=0), 0)
            cost = np.where(agree, err, 0.0).sum(axis=0)
            better = (count > best_count) | ((count == best_count) & (cost < best_cost) & usable)
            best_count = np.where(better, count, best_count)
            best_cost = np.where(better, cost, best_cost)
            best_inliers[:, better] = agree[:, better]
        refit = _solve(poses, focal, sub_rays, best_inliers, refine_iterations)
        # views that agree with the refit consensus point join it (one more pass)
        err = _errors_px(poses, focal, sub_rays, sub_valid, refit)
        final = sub_valid & (err <= outlier_threshold_px)
        grow = final.sum(axis=0) > best_inliers.sum(axis=0)
        if grow.any():
            refit[grow] = _solve(poses, focal, sub_rays[:, grow], final[:, grow],
                                 refine_iterations)
            best_inliers[:, grow] = final[:, grow]
        points[suspect] = refit
        inliers[:, suspect] = best_inliers
        unsolved = ~np.all(np.isfinite(refit), axis=1)
        inliers[:, suspect[unsolved]] = False

    points[inliers.sum(axis=0) < min_views] = np.nan
    inliers[:, ~np.all(np.isfinite(points), axis=1)] = False
    return points, inliers


def reprojection_rms(rig: CameraRig, points: np.ndarray, observations: np.ndarray,
                     views: np.ndarray) -> np.ndarray:
    """RMS distance in px between ``observations (C, P, 2)`` and ``points (P, 3)`` reprojected
    with full distortion, over the ``views (C, P)``; NaN where no view is used."""
    squared = np.zeros(points.shape[0])
    for c, camera in enumerate(rig):
        used = views[c]
        if used.any():
            pixels, _ = project_points(camera, points[used])
            squared[used] += np.sum((pixels - observations[c, used]) ** 2, axis=1)
    count = views.sum(axis=0)
    rms = np.full(points.shape[0], np.nan)
    rms[count > 0] = np.sqrt(squared[count > 0] / count[count > 0])
    return rms


def _normalized_rays(rig: CameraRig, observations: np.ndarray) -> np.ndarray:
    """Undistorted normalized image coordinates ``(C, P, 2)`` of pixel observations."""
    rays = np.full(observations.shape, np.nan)
    for c, camera in enumerate(rig):
        seen = np.all(np.isfinite(observations[c]), axis=1)
        if seen.any():
            undistorted = cv2.undistortPoints(
                observations[c, seen].reshape(-1, 1, 2), camera.matrix, camera.distortion,
                criteria=_UNDISTORT_CRITERIA)
            rays[c, seen] = undistorted.reshape(-1, 2)
    return rays


def _solve(poses: np.ndarray, focal: np.ndarray, rays: np.ndarray, use: np.ndarray,
           refine_iterations: int) -> np.ndarray:
    """Weighted inhomogeneous DLT for all points at once; NaN where < 2 views are used.

    Rows are ``u * P3 - P1`` and ``v * P3 - P2`` in normalized coordinates, weighted by
    ``focal / depth`` so the algebraic residual equals the reprojection error in px; the
    depths come from the previous solution (reweighting steps).
    """
    n_points = rays.shape[1]
    usable = use.sum(axis=0) >= 2
    weights = np.where(use, focal[:, None], 0.0)
    points = np.full((n_points, 3), np.nan)
    for step in range(refine_iterations + 1):
        normal = np.zeros((n_points, 3, 3))
        rhs = np.zeros((n_points, 3))
        for c in range(poses.shape[0]):
            w = weights[c][:, None]
            for axis in (0, 1):
                row = rays[c, :, axis, None] * poses[c, 2] - poses[c, axis]  # (P, 4)
                row = row * w
                normal += row[:, :3, None] * row[:, None, :3]
                rhs -= row[:, :3] * row[:, 3:]
        normal[~usable] = np.eye(3)  # keeps the batched solve regular; discarded below
        singular = np.abs(np.linalg.det(normal)) < 1e-300
        normal[singular] = np.eye(3)
        points = np.linalg.solve(normal, rhs[..., None])[..., 0]
        points[~usable | singular] = np.nan
        if step < refine_iterations:
            depth = np.einsum("ck,pk->cp", poses[:, 2, :3], points) + poses[:, 2, 3, None]
            ok = np.isfinite(depth) & (depth > 0)
            weights = np.where(use & ok, focal[:, None] / np.where(ok, depth, 1.0), 0.0)
    return points


def _errors_px(poses: np.ndarray, focal: np.ndarray, rays: np.ndarray, use: np.ndarray,
               points: np.ndarray) -> np.ndarray:
    """Reprojection errors ``(C, P)`` in px (normalized coordinates times focal length);
    ``inf`` where unused, behind the camera or the point is NaN."""
    cam = np.einsum("cij,pj->cpi", poses[:, :, :3], np.nan_to_num(points)) + poses[:, None, :, 3]
    finite = np.all(np.isfinite(points), axis=1)[None, :] & (cam[..., 2] > 0) & use
    depth = np.where(finite, cam[..., 2], 1.0)
    diff = cam[..., :2] / depth[..., None] - rays
    errors = focal[:, None] * np.sqrt(np.sum(diff * diff, axis=-1))
    return np.where(finite, errors, np.inf)
