"""Rendered views of a calibration wand (two markers a known distance apart) waved through a
simulated rig's volume: the images a rig's cameras record while the wand is waved, for
``calibrate --wand`` and its tests."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .cameras import Camera, CameraRig
from .synth_board_views import aim_point
from .synth_images import png_bytes, render_markers

WAND_LENGTH_MM = 400.0
WAND_MARKER_MM = 14.0
BACKGROUND = 40.0  # grey level of a dim room seen by a marker camera


def wand_positions(rig: CameraRig, n_frames: int, *, length: float = WAND_LENGTH_MM,
                   spread_mm: float = 600.0, seed: int = 0) -> np.ndarray:
    """``(n_frames, 2, 3)`` mm: the wand's two ends, its centre within ``spread_mm`` of where the
    rig looks (``spread_mm / 2`` along the vertical) and its direction uniform on the sphere."""
    rng = np.random.default_rng(seed)
    centres = aim_point(rig) + rng.uniform(-spread_mm, spread_mm, (n_frames, 3)) * [1.0, 0.5, 1.0]
    direction = rng.standard_normal((n_frames, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    half = 0.5 * length * direction
    return np.stack([centres - half, centres + half], axis=1)


def wand_pixels(camera: Camera, ends: np.ndarray, *,
                diameter_mm: float = WAND_MARKER_MM) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(N, 2, 2)`` (NaN outside the image or behind the camera) and apparent radii
    ``(N, 2)`` px of the wand's ends ``(N, 2, 3)`` mm; its markers are spheres, seen from any side."""
    import cv2

    flat = ends.reshape(-1, 3)
    depth = flat @ camera.rotation[2] + camera.tvec[2]
    pixels = cv2.projectPoints(flat, camera.rvec, camera.tvec, camera.matrix,
                               camera.distortion)[0].reshape(-1, 2)
    width, height = camera.image_size
    radius = 0.5 * diameter_mm * camera.focal_px / np.where(depth > 0, depth, np.nan)
    inside = (depth > 0) & np.all((pixels >= 0) & (pixels <= [width - 1, height - 1]), axis=1)
    pixels[~inside] = np.nan
    return pixels.reshape(ends.shape[:2] + (2,)), radius.reshape(ends.shape[:2])


def wand_images(camera: Camera, ends: np.ndarray, *, seed: int = 0) -> Iterator[np.ndarray]:
    """One camera's 8-bit image of every wand frame: blurred, noisy, with glints."""
    rng = np.random.default_rng(seed)
    width, height = camera.image_size
    background = np.full((height, width), BACKGROUND, np.float32)
    pixels, radius = wand_pixels(camera, ends)
    for f in range(len(ends)):
        yield render_markers(background, pixels[f], radius[f], rng=rng)[0]


def write_wand_views(folder, rig: CameraRig, *, n_frames: int, length: float = WAND_LENGTH_MM,
                     spread_mm: float = 600.0, seed: int = 0) -> np.ndarray:
    """Render a wand waved ``n_frames`` times into ``folder/<camera>/wand_NNN.png`` (frame k of
    every camera is the same instant), the input of ``mocaptk detect`` then ``calibrate --wand``;
    returns its ends ``(n_frames, 2, 3)`` mm. ``folder`` must exist (staged by the caller)."""
    from pathlib import Path

    from mocaptk.atomic import write_bytes

    folder = Path(folder)
    ends = wand_positions(rig, n_frames, length=length, spread_mm=spread_mm, seed=seed)
    for c, camera in enumerate(rig):
        (folder / camera.name).mkdir()
        for f, image in enumerate(wand_images(camera, ends, seed=seed + c)):
            write_bytes(folder / camera.name / f"wand_{f:03d}.png", png_bytes(image))
    return ends
