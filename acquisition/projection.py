"""Simulated 2-D marker detections: project 3-D markers into every camera of a rig."""

from __future__ import annotations

from collections.abc import Callable

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


#: Frames projected (and random numbers drawn) at a time: bounds the temporaries to a few
#: (block, M, 3) arrays whatever the session length; results do not depend on it.
FRAME_BLOCK = 1000


def project_markers(rig: CameraRig, points: np.ndarray, *,
                    normals: np.ndarray | Callable[[int, int], np.ndarray] | None = None,
                    pixel_noise: float = 0.0, dropout: float = 0.0, ghost_rate: float = 0.0,
                    min_view_cos: float = 0.0, max_view_angle_deg: float = 50.0,
                    rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Simulate what each camera of ``rig`` detects of the markers ``points``.

    Parameters
    ----------
    rig : CameraRig with C cameras.
    points : (F, M, 3) float, mm; NaN markers are unseen.
    normals : (F, M, 3) float, or a function ``(start, stop) -> (stop - start, M, 3)`` giving
        them for :data:`FRAME_BLOCK`-aligned frame ranges (never the whole array), optional
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
    if normals is not None and not callable(normals):
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
    for start, stop in _frame_blocks(n_frames):
        block = points[start:stop]
        block_normals = normals(start, stop) if callable(normals) else \
            None if normals is None else normals[start:stop]
        for c, camera in enumerate(rig):
            pixels, depth = project_points(camera, block)
            with np.errstate(invalid="ignore"):
                to_camera = camera.center - block
                distance = np.linalg.norm(to_camera, axis=-1)
                seen = depth > distance * min_axis_cos  # in front, within the lens field of view
                width, height = camera.image_size
                seen &= ((pixels[..., 0] >= -0.5) & (pixels[..., 0] < width - 0.5)
                         & (pixels[..., 1] >= -0.5) & (pixels[..., 1] < height - 0.5))
                if block_normals is not None:
                    facing = np.einsum("fmk,fmk->fm", block_normals, to_camera)
                    seen &= facing > min_view_cos * distance * np.linalg.norm(block_normals, axis=-1)
            observations[c, start:stop][seen] = pixels[seen]
    # random numbers are drawn block by block in the array's order: the same as one draw
    blocks = [(c, start, stop) for c in range(len(rig)) for start, stop in _frame_blocks(n_frames)]
    if pixel_noise > 0:
        for c, start, stop in blocks:
            view = observations[c, start:stop]
            view += rng.normal(0.0, pixel_noise, view.shape)
    visible = np.isfinite(observations[..., 0])
    if ghost_rate > 0:
        _add_ghosts(observations, visible, ghost_rate, rng, blocks)
    if dropout > 0:
        for c, start, stop in blocks:
            seen = visible[c, start:stop]
            observations[c, start:stop][seen & (rng.random(seen.shape) < dropout)] = np.nan
    return observations


def _frame_blocks(n_frames: int) -> list[tuple[int, int]]:
    return [(start, min(start + FRAME_BLOCK, n_frames)) for start in range(0, n_frames, FRAME_BLOCK)]


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
                rng: np.random.Generator, blocks: list[tuple[int, int, int]]) -> None:
    """Replace a fraction ``rate`` of the visible observations in place by wrong positions
    (``blocks``: (camera, start, stop) frame ranges in array order, for the draws)."""
    if not blocks:
        return
    picked = []
    for c, start, stop in blocks:
        seen = visible[c, start:stop]
        frames, markers = np.nonzero(seen & (rng.random(seen.shape) < rate))
        picked.append((np.full(frames.size, c), frames + start, markers))
    cams, frames, markers = (np.concatenate(column).astype(np.intp) for column in zip(*picked))
    if cams.size == 0:
        return
    other = rng.integers(0, observations.shape[2], cams.size)
    swapped = observations[cams, frames, other]  # gathered (copies) before any is replaced
    random_offset = observations[cams, frames, markers] + rng.uniform(-200.0, 200.0, (cams.size, 2))
    use_swap = (rng.random(cams.size) < 0.5) & np.isfinite(swapped[:, 0]) & (other != markers)
    observations[cams, frames, markers] = np.where(use_swap[:, None], swapped, random_offset)
