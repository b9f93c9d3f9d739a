"""A calibration wand: two markers a known distance apart, waved through the capture volume and
seen by the rig's cameras in synchronised frames.

Board views fix a rig poorly where each board faces one camera: a narrow lens cannot tell its
focal length from its distance (both scale the board's image alike), so each camera's distance
along its axis drifts with its focal-length error. The wand's markers are seen from all around
at once, so the other cameras pin each camera's distance, and the wand's length fixes the scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import CameraRig
from .correspondence import essential_matrix, normalized_blobs
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
    finite = np.isfinite(points2d[..., 0])
    two = finite.sum(axis=2) == 2  # (C, F)
    first = np.argsort(~finite, axis=2, kind="stable")[..., :2]  # an image's blobs in their order
    pairs = np.take_along_axis(points2d, first[..., None], axis=2)  # (C, F, 2, 2)
    pairs[~two] = np.nan
    usable = two.sum(axis=0) >= MIN_CAMERAS
    reference = np.argmax(two, axis=0)  # per frame, the first camera that sees both ends
    norm = normalized_blobs(rig, pairs)
    norm = np.concatenate([norm, np.ones(norm.shape[:-1] + (1,))], axis=-1)  # homogeneous
    projections = np.array([np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig])
    pixels = np.full((n_cams, n_frames, 2, 2), np.nan)
    for a in range(n_cams):
        mine = usable & (reference == a)
        pixels[a, mine] = pairs[a, mine]
        for b in range(a + 1, n_cams):
            frames = np.nonzero(mine & two[b])[0]
            if len(frames):
                pixels[b, frames] = _ordered_like(norm[a, frames], norm[b, frames], pairs[b, frames],
                                                  essential_matrix(projections, a, b))
    ends, _ = triangulate_points(rig, pixels.reshape(n_cams, -1, 2))
    measured = np.linalg.norm(ends[0::2] - ends[1::2], axis=1)
    with np.errstate(invalid="ignore"):
        good = np.abs(measured / length - 1) <= LENGTH_TOLERANCE
    if not good.any():
        candidates = np.isfinite(measured)
        seen = (f"; their median length is {np.median(measured[candidates]):.1f} mm"
                if candidates.any() else "")
        raise ValueError(f"the wand was not found: {int(usable.sum())} of {n_frames} frames show two blobs "
                         f"in >= {MIN_CAMERAS} cameras{seen}, none within {LENGTH_TOLERANCE:.0%} of "
                         f"{length:g} mm")
    return Wand(pixels=pixels[:, good], length=float(length))


def _ordered_like(norm_a: np.ndarray, norm_b: np.ndarray, pixels_b: np.ndarray,
                  essential: np.ndarray) -> np.ndarray:
    """Camera ``b``'s two blobs ``pixels_b (N, 2, 2)`` per frame, swapped where the other order
    matches camera ``a``'s better: the smaller summed epipolar error of the homogeneous
    normalised ends ``norm_a, norm_b (N, 2, 3)`` under ``essential`` (b relative to a)."""
    error = np.abs(np.einsum("nbi,ij,naj->nba", norm_b, essential, norm_a))  # (frame, end in b, end in a)
    kept = error[:, 0, 0] + error[:, 1, 1] <= error[:, 0, 1] + error[:, 1, 0]
    return np.where(kept[:, None, None], pixels_b, pixels_b[:, ::-1])


def wand_ends(wand: Wand, rig: CameraRig) -> np.ndarray:
    """Starting 3-D ends ``(N, 2, 3)`` mm of every wand frame, triangulated through ``rig``."""
    points, _ = triangulate_points(rig, wand.pixels.reshape(len(rig), -1, 2))
    return points.reshape(-1, 2, 3)
