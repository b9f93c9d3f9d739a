"""A calibration wand: two markers a known distance apart, waved through the capture volume and
seen by the rig's cameras in synchronised frames.

Board views fix a rig poorly where each board faces one camera: a narrow lens cannot tell its
focal length from its distance (both scale the board's image alike), so each camera's distance
along its axis drifts with its focal-length error. The wand's markers are seen from all around
at once, so the other cameras pin each camera's distance, and the wand's length fixes the scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .cameras import CameraRig
from .triangulate import triangulate_points

#: A frame whose triangulated wand length is off by more than this fraction is dropped: an end
#: mismatched across cameras, or a glint taken for a marker.
LENGTH_TOLERANCE = 0.02
#: Cameras that must see both ends for a frame to count.
MIN_CAMERAS = 2


@dataclass
class Wand:
    """Wand observations: ``pixels (C, N, 2, 2)`` px (camera, frame, end A/B, xy; NaN unseen),
    the same end labelled alike in every camera; ``length`` mm between the markers' centres."""

    pixels: np.ndarray
    length: float

    @property
    def n_frames(self) -> int:
        return self.pixels.shape[1]


def wand_from_blobs(points2d: np.ndarray, rig: CameraRig, length: float) -> Wand:
    """Wand observations from blob detections ``points2d (C, F, B, 2)`` px (NaN-padded) of a
    wand: frames where at least ``MIN_CAMERAS`` cameras see exactly two blobs; the ends are
    matched across cameras by ``rig``'s epipolar geometry (a board calibration is close enough)
    and a frame is kept when its triangulated length is within ``LENGTH_TOLERANCE``.

    Raises ValueError (saying what was seen) when no frame is kept."""
    n_cams, n_frames = points2d.shape[:2]
    counts = np.isfinite(points2d[..., 0]).sum(axis=2)
    pixels = np.full((n_cams, n_frames, 2, 2), np.nan)
    for f in range(n_frames):
        two = np.nonzero(counts[:, f] == 2)[0]
        if len(two) < MIN_CAMERAS:
            continue
        blobs = {c: points2d[c, f][np.isfinite(points2d[c, f, :, 0])] for c in two}
        ref = two[0]
        pixels[ref, f] = blobs[ref]
        for c in two[1:]:
            pixels[c, f] = blobs[c] if _kept_order(rig, ref, c, blobs[ref], blobs[c]) else blobs[c][::-1]
    ends, _ = triangulate_points(rig, pixels.reshape(n_cams, -1, 2))
    measured = np.linalg.norm(ends[0::2] - ends[1::2], axis=1)
    with np.errstate(invalid="ignore"):
        good = np.abs(measured / length - 1) <= LENGTH_TOLERANCE
    if not good.any():
        candidates = np.isfinite(measured)
        seen = (f"; their median length is {np.median(measured[candidates]):.1f} mm"
                if candidates.any() else "")
        raise ValueError(f"the wand was not found: {candidates.sum()} of {n_frames} frames show two blobs "
                         f"in >= {MIN_CAMERAS} cameras{seen}, none within {LENGTH_TOLERANCE:.0%} of "
                         f"{length:g} mm")
    return Wand(pixels=pixels[:, good], length=float(length))


def _kept_order(rig: CameraRig, a: int, b: int, ends_a: np.ndarray, ends_b: np.ndarray) -> bool:
    """Whether camera ``b``'s two blobs in their order (not swapped) match camera ``a``'s: the
    smaller summed epipolar error in normalised coordinates."""
    cam_a, cam_b = rig[a], rig[b]
    xa = _normalized(cam_a, ends_a)
    xb = _normalized(cam_b, ends_b)
    rotation = cam_b.rotation @ cam_a.rotation.T
    t = cam_b.tvec - rotation @ cam_a.tvec
    essential = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rotation
    error = np.abs(np.einsum("bi,ij,aj->ba", xb, essential, xa))  # (end in b, end in a)
    return bool(error[0, 0] + error[1, 1] <= error[0, 1] + error[1, 0])


def _normalized(camera, pixels: np.ndarray) -> np.ndarray:
    """Homogeneous normalised image coordinates ``(K, 3)`` of distorted ``pixels (K, 2)``."""
    xy = cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), camera.matrix,
                             camera.distortion).reshape(-1, 2)
    return np.column_stack([xy, np.ones(len(xy))])


def wand_ends(wand: Wand, rig: CameraRig) -> np.ndarray:
    """Starting 3-D ends ``(N, 2, 3)`` mm of every wand frame, triangulated through ``rig``."""
    points, _ = triangulate_points(rig, wand.pixels.reshape(len(rig), -1, 2))
    return points.reshape(-1, 2, 3)
