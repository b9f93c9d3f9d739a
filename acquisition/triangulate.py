"""Robust, vectorized multi-view triangulation of labelled 2-D detections.

All points are solved together: every camera's detections are undistorted at once, the DLT
normal equations of all points come from one matrix product and are solved in closed form
(batched 3x3). Outlier views are rejected by consensus: every camera pair proposes a
two-view point for all doubtful points at once, the proposal with most views within
``outlier_threshold_px`` wins per point, and the point is refit on those inlier views.
Reweighting steps (rows scaled by focal / depth, so the algebraic error becomes the
reprojection error in px: a Gauss-Newton-like refinement) finish each fit.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations

import cv2
import numpy as np

from mocaptk.trajectories import Trajectories

from .cameras import CameraRig

# 6 fixed-point iterations: < 1e-4 px error over a whole Cara image; an eps test is 3x slower
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 6, 0.0)


def triangulate(rig: CameraRig, observations: np.ndarray, *, labels: Sequence[str] | None = None,
                rate: float | None = None, min_views: int = 2,
                outlier_threshold_px: float = 4.0, refine_iterations: int = 1) -> Trajectories:
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
                       outlier_threshold_px: float = 4.0, refine_iterations: int = 1,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation of P points from ``observations (C, P, 2)`` px.

    Returns ``points (P, 3)`` mm (NaN with fewer than ``min_views`` agreeing views) and the
    inlier views ``(C, P)`` bool.
    """
    system = _System.build(rig, observations)
    valid = system.valid
    # 1) all views; points whose views all agree are done
    points = system.solve(valid, refine_iterations)
    inliers = valid & (system.errors_px(points) <= outlier_threshold_px)
    n_valid = valid.sum(axis=0)
    suspect = np.nonzero((inliers.sum(axis=0) < n_valid) & (n_valid >= 2))[0]

    # 2) consensus over all two-view hypotheses for the points with disagreeing views
    if suspect.size:
        sub = system.subset(suspect)
        best_count = np.zeros(suspect.size, dtype=np.int64)
        best_cost = np.full(suspect.size, np.inf)
        best_inliers = np.zeros_like(sub.valid)
        for i, j in combinations(range(len(rig)), 2):
            index = np.nonzero(sub.valid[i] & sub.valid[j])[0]
            if not index.size:
                continue
            pair = sub.subset(index)
            err = pair.errors_px(pair.solve_pair(i, j))
            agree = err <= outlier_threshold_px
            count = agree.sum(axis=0)
            cost = np.where(agree, err, 0.0).sum(axis=0)
            better = (count > best_count[index]) | ((count == best_count[index])
                                                    & (cost < best_cost[index]))
            chosen = index[better]
            best_count[chosen] = count[better]
            best_cost[chosen] = cost[better]
            best_inliers[:, chosen] = agree[:, better]
        refit = sub.solve(best_inliers, refine_iterations)
        # views that agree with the refit consensus point join it (one more pass)
        final = sub.errors_px(refit) <= outlier_threshold_px
        grow = final.sum(axis=0) > best_inliers.sum(axis=0)
        if grow.any():
            best_inliers[:, grow] = final[:, grow]
            refit[grow] = sub.subset(np.nonzero(grow)[0]).solve(best_inliers[:, grow],
                                                                 refine_iterations)
        points[suspect] = refit
        inliers[:, suspect] = best_inliers

    points[inliers.sum(axis=0) < min_views] = np.nan
    inliers[:, ~np.all(np.isfinite(points), axis=1)] = False
    return points, inliers


def reprojection_rms(rig: CameraRig, points: np.ndarray, observations: np.ndarray,
                     views: np.ndarray) -> np.ndarray:
    """RMS distance in px between ``observations (C, P, 2)`` and ``points (P, 3)`` reprojected
    with full distortion, over the ``views (C, P)``; NaN where no view is used."""
    squared = np.zeros(points.shape[0])
    for c, camera in enumerate(rig):
        used = np.nonzero(views[c])[0]
        cam = camera.rotation @ points[used].T + camera.tvec[:, None]  # (3, used)
        u, v = camera.pixels_from_normalized(cam[0] / cam[2], cam[1] / cam[2])
        squared[used] += (u - observations[c, used, 0]) ** 2 + (v - observations[c, used, 1]) ** 2
    count = views.sum(axis=0)
    rms = np.full(points.shape[0], np.nan)
    rms[count > 0] = np.sqrt(squared[count > 0] / count[count > 0])
    return rms


class _System:
    """The DLT normal equations of all points, for batched weighted solves.

    Camera c contributes the rows ``u * P3 - P1`` and ``v * P3 - P2`` (normalized image
    coordinates ``u, v``; ``P1..P3`` the rows of ``[R | t]``). Their weighted outer products
    expand to ``w² ((u² + v²) P3P3ᵀ - u (P3P1ᵀ + P1P3ᵀ) - v (P3P2ᵀ + P2P3ᵀ) + P1P1ᵀ + P2P2ᵀ)``,
    so the normal equations of every point are one matrix product of per-point coefficients
    ``(4C, P)`` with constant per-camera terms ``(9, 4C)`` (the 9 entries we need).
    """

    _ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3))

    def __init__(self, poses: np.ndarray, focal: np.ndarray, u: np.ndarray, v: np.ndarray,
                 valid: np.ndarray) -> None:
        self.poses, self.focal, self.u, self.v, self.valid = poses, focal, u, v, valid
        self.radius2 = u * u + v * v
        p1, p2, p3 = poses[:, 0], poses[:, 1], poses[:, 2]

        def sym(a: np.ndarray, b: np.ndarray) -> np.ndarray:
            return np.einsum("ci,cj->cij", a, b) + np.einsum("ci,cj->cij", b, a)

        terms = np.stack([np.einsum("ci,cj->cij", p3, p3), -sym(p3, p1), -sym(p3, p2),
                          np.einsum("ci,cj->cij", p1, p1) + np.einsum("ci,cj->cij", p2, p2)])
        rows, cols = zip(*self._ENTRIES)
        self.terms = terms[:, :, rows, cols].reshape(-1, len(rows)).T  # (9, 4C)

    @classmethod
    def build(cls, rig: CameraRig, observations: np.ndarray) -> _System:
        rays = _normalized_rays(rig, observations)
        valid = np.isfinite(rays[..., 0])
        rays[~valid] = 0.0
        poses = np.stack([np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig])
        return cls(poses, np.array([cam.focal_px for cam in rig]),
                   np.ascontiguousarray(rays[..., 0]), np.ascontiguousarray(rays[..., 1]), valid)

    def subset(self, index: np.ndarray) -> _System:
        return _System(self.poses, self.focal, self.u[:, index], self.v[:, index],
                       self.valid[:, index])

    def solve(self, use: np.ndarray, refine_iterations: int) -> np.ndarray:
        """Weighted inhomogeneous DLT of all points at once over the views ``use (C, P)``;
        NaN where fewer than 2 views are used or the system is degenerate.

        Rows are weighted by ``focal / depth`` (depth from the previous solution), so after
        the first step the algebraic residual is the reprojection error in px.
        """
        usable = use.sum(axis=0) >= 2
        weights = np.where(use, self.focal[:, None], 0.0)
        for step in range(refine_iterations + 1):
            w2 = weights * weights
            coefficients = np.concatenate([w2 * self.radius2, w2 * self.u, w2 * self.v, w2])
            m = self.terms @ coefficients  # (9, P)
            points = _solve_symmetric3(*m[:6], -m[6], -m[7], -m[8])
            points[~usable] = np.nan
            if step < refine_iterations:
                depth = self.poses[:, 2, :3] @ points.T + self.poses[:, 2, 3:]  # (C, P)
                ok = use & (depth > 0)  # NaN depth compares False
                weights = np.where(ok, self.focal[:, None] / np.where(ok, depth, 1.0), 0.0)
        return points

    def solve_pair(self, i: int, j: int) -> np.ndarray:
        """Two-view DLT from cameras ``i`` and ``j`` (both must see every point), ``(P, 3)``."""
        n_cams = len(self.focal)
        columns = [k * n_cams + c for k in range(4) for c in (i, j)]
        w2 = (self.focal[[i, j]] ** 2)[:, None]
        coefficients = np.concatenate([w2 * self.radius2[[i, j]], w2 * self.u[[i, j]],
                                       w2 * self.v[[i, j]], np.broadcast_to(w2, (2, len(self.u[0])))])
        m = self.terms[:, columns] @ coefficients
        return _solve_symmetric3(*m[:6], -m[6], -m[7], -m[8])

    def errors_px(self, points: np.ndarray) -> np.ndarray:
        """Reprojection errors ``(C, P)`` in px (normalized coordinates times focal length);
        ``inf`` where unseen, behind the camera or the point is NaN."""
        finite = np.all(np.isfinite(points), axis=1)
        n_cams = len(self.focal)
        # one (3C, 3) @ (3, P) product: numpy's stacked small matmul is far slower
        cam = (self.poses[:, :, :3].reshape(-1, 3) @ np.where(finite[:, None], points, 0.0).T
               ).reshape(n_cams, 3, -1) + self.poses[:, :, 3:]  # (C, 3, P)
        ok = self.valid & finite & (cam[:, 2] > 0)
        depth = np.where(ok, cam[:, 2], 1.0)
        du = cam[:, 0] / depth - self.u
        dv = cam[:, 1] / depth - self.v
        return np.where(ok, self.focal[:, None] * np.sqrt(du * du + dv * dv), np.inf)


def _solve_symmetric3(a, b, c, d, e, f, r0, r1, r2) -> np.ndarray:
    """Solve ``[[a b c] [b d e] [c e f]] x = r`` for many systems at once (adjugate);
    NaN where the matrix is (nearly) singular. Returns ``(P, 3)``."""
    A00, A01, A02 = d * f - e * e, c * e - b * f, b * e - c * d
    A11, A12, A22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A00 + b * A01 + c * A02
    scale = (a + d + f) ** 3
    good = np.abs(det) > 1e-12 * scale
    det = np.where(good, det, 1.0)
    x = np.stack([A00 * r0 + A01 * r1 + A02 * r2, A01 * r0 + A11 * r1 + A12 * r2,
                  A02 * r0 + A12 * r1 + A22 * r2], axis=1) / det[:, None]
    x[~good] = np.nan
    return x


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
