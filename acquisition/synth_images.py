"""Rendered marker images of a simulated rig, with the true 2-D positions beside them.

Each camera sees retro-reflective markers as bright discs of their apparent size
(``diameter * focal / depth``) on a skin-grey background with smooth shading, drawn with
antialiased edges at the projected marker centres, then lens blur (Gaussian), specular glints
(small bright spots, not markers), and sensor noise. Markers facing away from a camera are
hidden (self-occlusion by the markers' surface normals, as :func:`.projection.project_markers`);
two markers closer in the image than their radii plus the blur merge into one blob, as they
would, and are flagged ``merged`` in the truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .cameras import Camera, CameraRig
from .projection import project_markers

MARKER_DIAMETER_MM = 3.0
SKIN, MARKER = 100.0, 235.0  # grey levels
BLUR_PX = 0.7  # Gaussian sigma of the lens + motion blur
NOISE = 3.0  # sensor noise sigma, grey levels
GLINTS_PER_IMAGE = 2.0  # mean specular glints per image


@dataclass
class MarkerTruth:
    """What the cameras should see: ``pixels (C, F, M, 2)`` px (NaN hidden), ``radius (C, F, M)``
    px, ``merged (C, F, M)`` bool (another visible marker's blob touches this one)."""

    pixels: np.ndarray
    radius: np.ndarray
    merged: np.ndarray


def marker_truth(rig: CameraRig, points: np.ndarray,
                 normals: np.ndarray | Callable[[int, int], np.ndarray], *,
                 diameter_mm: float = MARKER_DIAMETER_MM, blur_px: float = BLUR_PX) -> MarkerTruth:
    """The visible markers' projections, apparent radii and merge flags for ``points (F, M, 3)``."""
    pixels = project_markers(rig, points, normals=normals)
    radius = np.full(pixels.shape[:3], np.nan)
    for c, camera in enumerate(rig):
        depth = points @ camera.rotation[2] + camera.tvec[2]
        radius[c] = 0.5 * diameter_mm * camera.focal_px / depth
    radius[np.isnan(pixels[..., 0])] = np.nan
    gap = np.linalg.norm(pixels[..., :, None, :] - pixels[..., None, :, :], axis=-1)
    reach = radius[..., :, None] + radius[..., None, :] + 2 * blur_px
    with np.errstate(invalid="ignore"):
        touching = gap < reach
    touching[..., np.arange(points.shape[1]), np.arange(points.shape[1])] = False
    return MarkerTruth(pixels=pixels, radius=radius, merged=touching.any(-1))


def skin_shading(camera: Camera, seed: int) -> np.ndarray:
    """A smooth skin-grey background ``(height, width)`` float32 for one camera."""
    width, height = camera.image_size
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    shade = np.full((height, width), SKIN, np.float32)
    for _ in range(4):
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        spread = rng.uniform(0.2, 0.5) * max(width, height)
        shade += rng.uniform(-25, 25) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * spread ** 2))
    return shade


def render_markers(background: np.ndarray, pixels: np.ndarray, radius: np.ndarray, *,
                   rng: np.random.Generator, blur_px: float = BLUR_PX, noise: float = NOISE,
                   glints: float = GLINTS_PER_IMAGE) -> tuple[np.ndarray, np.ndarray]:
    """One 8-bit image: discs at ``pixels (M, 2)`` px of ``radius (M,)`` px (NaN: hidden) on
    ``background``; returns the image and the glints' centres ``(G, 2)`` px."""
    import cv2

    height, width = background.shape
    signal = np.zeros((height, width), np.float32)
    visible = np.isfinite(pixels[:, 0])
    n_glints = rng.poisson(glints)
    glint_xy = rng.uniform([0, 0], [width - 1, height - 1], (n_glints, 2))
    glint_r = rng.uniform(0.4, 0.8, n_glints)  # px: a glint is far smaller than a marker
    centres = np.vstack([pixels[visible], glint_xy])
    radii = np.concatenate([radius[visible], glint_r])
    for (cx, cy), r in zip(centres, radii):
        half = int(np.ceil(r + 2))
        x0, y0 = max(int(cx) - half, 0), max(int(cy) - half, 0)
        x1, y1 = min(int(cx) + half + 2, width), min(int(cy) + half + 2, height)
        if x1 <= x0 or y1 <= y0:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        # coverage of each pixel by the disc, from the distance of its centre to the edge
        coverage = np.clip(r + 0.5 - np.hypot(xx - cx, yy - cy), 0.0, 1.0)
        patch = signal[y0:y1, x0:x1]
        np.maximum(patch, coverage, out=patch)
    if blur_px > 0:
        signal = cv2.GaussianBlur(signal, (0, 0), blur_px)
    image = background + signal * (MARKER - background)
    image += rng.normal(0.0, noise, image.shape).astype(np.float32)
    return np.clip(np.round(image), 0, 255).astype(np.uint8), glint_xy


def png_bytes(image: np.ndarray) -> bytes:
    """``image (H, W)`` uint8 as an 8-bit grey PNG, stored uncompressed and unfiltered: sensor
    noise leaves deflate little to gain (482 against 902 KiB per 1280x720 frame), and reading it
    back costs 1.8 CPU-ms instead of 13, which made decoding, not detection, bound ``detect``."""
    import cv2

    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 0,
                                        cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE])[1].tobytes()


def write_marker_images(folder, rig: CameraRig, points: np.ndarray,
                        normals: np.ndarray | Callable[[int, int], np.ndarray], *,
                        labels: list[str], seed: int = 0) -> MarkerTruth:
    """Render ``points (F, M, 3)`` through ``rig`` into ``folder/<camera>/frame_NNNNN.png`` and
    write ``folder/markers_truth.npz`` (``points2d (C, F, M, 2)`` NaN hidden, ``merged``,
    ``radius``, ``glints (C, F, G, 2)`` NaN-padded, ``labels``, ``camera_names``) and
    ``folder/rig.json``. ``folder`` must exist and be empty (staged by the caller)."""
    from pathlib import Path

    from mocaptk.atomic import write_bytes
    from mocaptk.npz import npz_bytes

    from .cameras import save_rig

    folder = Path(folder)
    truth = marker_truth(rig, points, normals)
    rng = np.random.default_rng(seed)
    glints: list[list[np.ndarray]] = []
    for c, camera in enumerate(rig):
        (folder / camera.name).mkdir()
        background = skin_shading(camera, seed + c)
        glints.append([])
        for f in range(points.shape[0]):
            image, glint_xy = render_markers(background, truth.pixels[c, f], truth.radius[c, f], rng=rng)
            write_bytes(folder / camera.name / f"frame_{f:05d}.png", png_bytes(image))
            glints[c].append(glint_xy)
    most = max((len(g) for row in glints for g in row), default=0)
    padded = np.full((len(rig), points.shape[0], most, 2), np.nan)
    for c, row in enumerate(glints):
        for f, g in enumerate(row):
            padded[c, f, :len(g)] = g
    write_bytes(folder / "markers_truth.npz", npz_bytes({
        "points2d": truth.pixels, "merged": truth.merged, "radius": truth.radius, "glints": padded,
        "points3d": points, "labels": np.array(labels), "camera_names": np.array(rig.names)}))
    save_rig(rig, folder / "rig.json")
    return truth


def write_image_set(folder, model, truth, rig: CameraRig, *, rig_name: str, frames: int,
                    seed: int = 0, force: bool = False) -> str:
    """``folder/markers``: the first ``frames`` frames of a synthetic session (``truth``, a
    :class:`.synth_session.GroundTruth` of the face ``model``) rendered through ``rig``;
    ``folder/charuco``: calibration views of the rig's preset board. Written whole or not at
    all; returns a one-line summary."""
    from pathlib import Path

    from mocaptk.atomic import staged_folder

    from .synth_board_views import PRESET_BOARDS, write_board_views
    from .synth_session import marker_normals

    frames = min(frames, truth.n_frames)
    normals = marker_normals(model, truth)
    with staged_folder(Path(folder), force=force) as staging:
        (staging / "markers").mkdir()
        marker_set = write_marker_images(staging / "markers", rig, truth.positions[:frames],
                                         lambda start, stop: normals(start, min(stop, frames)),
                                         labels=list(truth.labels), seed=seed)
        (staging / "charuco").mkdir()
        board = PRESET_BOARDS[rig_name]
        write_board_views(staging / "charuco", rig, board, n_views=24, seed=seed)
    seen = np.isfinite(marker_set.pixels[..., 0])
    return (f"wrote {folder}: {frames} frames x {len(rig)} cameras of {seen.shape[2]} markers "
            f"({seen.mean():.0%} of marker views visible, {marker_set.merged[seen].mean():.1%} merged) "
            f"and 24 ChArUco views (board {board.corners[0]}x{board.corners[1]}, {board.square:g} mm)")


@dataclass
class DetectionScore:
    """Detections against the truth of one or more images."""

    isolated: int  # visible, unmerged markers
    found: int  # of those, with a detection within ``match_px``
    squared_error: float  # sum of squared centre errors of the found, px^2
    blobs: int  # detections
    false: int  # detections farther than their radius + 1 px from every visible marker
    merged_flagged: int  # detections flagged merged that do lie on merged markers
    merged_blobs: int  # detections flagged merged

    @property
    def recall(self) -> float:
        return self.found / max(self.isolated, 1)

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(self.squared_error / max(self.found, 1)))

    @property
    def false_rate(self) -> float:
        return self.false / max(self.blobs, 1)

    def __add__(self, other: DetectionScore) -> DetectionScore:
        return DetectionScore(*(a + b for a, b in zip(vars(self).values(), vars(other).values())))


def score_detections(pixels: np.ndarray, radius: np.ndarray, merged: np.ndarray,
                     centres: np.ndarray, flagged: np.ndarray, *, match_px: float = 1.0) -> DetectionScore:
    """Score one image: truth ``pixels (M, 2)`` (NaN hidden), ``radius``, ``merged (M,)``;
    detected ``centres (B, 2)`` and their ``flagged (B,)`` merge flags."""
    from scipy.spatial import cKDTree

    visible = np.isfinite(pixels[:, 0])
    truth, radius, merged = pixels[visible], radius[visible], merged[visible]
    if len(centres) == 0 or len(truth) == 0:
        return DetectionScore(int((~merged).sum()), 0, 0.0, len(centres), len(centres), 0, 0)
    distance, nearest = cKDTree(centres).query(truth)
    hit = ~merged & (distance <= match_px)
    to_marker, which = cKDTree(truth).query(centres)
    false = to_marker > radius[which] + 1.0
    return DetectionScore(isolated=int((~merged).sum()), found=int(hit.sum()),
                          squared_error=float(np.sum(distance[hit] ** 2)), blobs=len(centres),
                          false=int(false.sum()), merged_flagged=int((flagged & merged[which]).sum()),
                          merged_blobs=int(flagged.sum()))
