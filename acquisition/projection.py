"""Simulated 2-D marker detections: project 3-D markers into every camera of a rig."""

from __future__ import annotations

import cv2
import numpy as np

from .cameras import Camera, CameraRig


def project_points(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into one camera with ``cv2.projectPoints``.

    Parameters
    ----------
    points : (..., 3) float, mm; NaN allowed.

    Returns
    -------
    pixels : (..., 2) float, px (NaN where the input is NaN)
    depth : (...) float, mm along the optical axis (<= 0: behind the camera)
    """
    points = np.asarray(points, dtype=np.float64)
    flat = points.reshape(-1, 3)
    finite = np.all(np.isfinite(flat), axis=1)
    pixels = np.full((flat.shape[0], 2), np.nan)
    depth = np.full(flat.shape[0], np.nan)
    if finite.any():
        inside = flat[finite]
        projected, _ = cv2.projectPoints(inside.reshape(-1, 1, 3), camera.rvec, camera.tvec,
                                         camera.matrix, camera.distortion)
        pixels[finite] = projected.reshape(-1, 2)
        depth[finite] = inside @ camera.rotation[2] + camera.tvec[2]
    return pixels.reshape(points.shape[:-1] + (2,)), depth.reshape(points.shape[:-1])


def project_markers(rig: CameraRig, points: np.ndarray, *, normals: np.ndarray | None = None,
                    pixel_noise: float = 0.0, dropout: float = 0.0, ghost_rate: float = 0.0,
                    min_view_cos: float = 0.0, max_view_angle_deg: float = 50.0,
                    rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Simulate what each camera of ``rig`` detects of the markers ``points``.

    Parameters
    ----------
    rig : CameraRig with C cameras.
    points : (F, M, 3) float, mm; NaN markers are unseen.
    normals : (F, M, 3) float, optional
        Outward surface normals at the markers; a marker is hidden from a camera when
        ``cos(normal, direction to camera) <= min_view_cos`` (back-facing / grazing).
    pixel_noise : float
        Standard deviation of Gaussian detection noise per image axis, px.
    dropout : float
        Fraction of visible observations randomly lost (occlusion, blobs merged).
    ghost_rate : float
        Fraction of visible observations replaced by a wrong 2-D position: half of them the
        detection of another marker of the same frame (mislabel), half a random point within
        200 px (reflection).
    max_view_angle_deg : float
        Markers further than this from a camera's optical axis are unseen (lens field
        of view), which also keeps the distortion polynomial in its valid range.
    rng : numpy Generator or seed.

    Returns
    -------
    observations : (C, F, M, 2) float, px; NaN where a camera does not see a marker
        (behind the camera, outside the image, back-facing, dropped).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points must have shape (frames, markers, 3), got {points.shape}")
    if normals is not None:
        normals = np.asarray(normals, dtype=np.float64)
        if normals.shape != points.shape:
            raise ValueError(f"normals must have shape {points.shape}, got {normals.shape}")
    for name, value in (("dropout", dropout), ("ghost_rate", ghost_rate)):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be within [0, 1], got {value}")
    if pixel_noise < 0:
        raise ValueError(f"pixel_noise must be >= 0, got {pixel_noise}")
    rng = np.random.default_rng(rng)
    n_frames, n_markers = points.shape[:2]
    observations = np.full((len(rig), n_frames, n_markers, 2), np.nan)
    min_axis_cos = np.cos(np.deg2rad(max_view_angle_deg))
    for c, camera in enumerate(rig):
        pixels, depth = project_points(camera, points)
        with np.errstate(invalid="ignore"):
            to_camera = camera.center - points
            distance = np.linalg.norm(to_camera, axis=-1)
            seen = depth > distance * min_axis_cos  # in front, within the lens field of view
            width, height = camera.image_size
            seen &= ((pixels[..., 0] >= -0.5) & (pixels[..., 0] < width - 0.5)
                     & (pixels[..., 1] >= -0.5) & (pixels[..., 1] < height - 0.5))
            if normals is not None:
                facing = np.einsum("fmk,fmk->fm", normals, to_camera)
                seen &= facing > min_view_cos * distance * np.linalg.norm(normals, axis=-1)
        observations[c][seen] = pixels[seen]
    if pixel_noise > 0:
        observations += rng.normal(0.0, pixel_noise, observations.shape)
    visible = np.isfinite(observations[..., 0])
    if ghost_rate > 0:
        _add_ghosts(observations, visible, ghost_rate, rng)
    if dropout > 0:
        observations[visible & (rng.random(visible.shape) < dropout)] = np.nan
    return observations


def ellipsoid_markers(frames: int, markers: int, *, max_yaw: float = np.pi,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random points on a head-sized ellipsoid (half-axes 80 × 110 × 60 mm, centre 40 mm ahead of
    the origin, +Z forward) with outward normals, for projection and triangulation tests.

    ``max_yaw`` (rad): how far around the head from the front they go (π: all around; ~1.1:
    the face). Returns ``points (frames, markers, 3)`` mm and ``normals`` of the same shape.
    """
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-max_yaw, max_yaw, (frames, markers))
    pitch = rng.uniform(-0.9, 0.9, (frames, markers))
    axes = np.array([80.0, 110.0, 60.0])
    unit = np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)
    normals = unit / axes
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return unit * axes + np.array([0.0, 0.0, 40.0]), normals


def _add_ghosts(observations: np.ndarray, visible: np.ndarray, rate: float,
                rng: np.random.Generator) -> None:
    """Replace a fraction ``rate`` of the visible observations in place by wrong positions."""
    cams, frames, markers = np.nonzero(visible & (rng.random(visible.shape) < rate))
    if cams.size == 0:
        return
    clean = observations.copy()
    other = rng.integers(0, observations.shape[2], cams.size)
    swapped = clean[cams, frames, other]
    random_offset = clean[cams, frames, markers] + rng.uniform(-200.0, 200.0, (cams.size, 2))
    use_swap = (rng.random(cams.size) < 0.5) & np.isfinite(swapped[:, 0]) & (other != markers)
    observations[cams, frames, markers] = np.where(use_swap[:, None], swapped, random_offset)
