"""Neutral pose and per-marker displacement from it (NaN-aware, warning-free)."""

from __future__ import annotations

import numpy as np

#: Frames per block of :func:`max_displacement` (a few MB of temporaries at 200 markers).
BLOCK_FRAMES = 4096


def neutral_pose(positions: np.ndarray, *, rest_frames: np.ndarray | slice | None = None) -> np.ndarray:
    """Per-marker neutral position, mm.

    Parameters
    ----------
    positions : (frames, markers, 3) float
        Millimetres, NaN gaps.
    rest_frames : index or slice, optional
        Frames known to be at rest; default: all frames.

    Returns
    -------
    (markers, 3) float
        Per-marker, per-axis median over the (rest) frames; NaN for a marker never seen there.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if rest_frames is not None:
        pos = pos[rest_frames]
    seen = np.isfinite(pos).all(axis=2).any(axis=0)
    out = np.full(pos.shape[1:], np.nan)
    if seen.any():
        out[seen] = np.nanmedian(pos[:, seen], axis=0)
    return out


def max_displacement(positions: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Largest distance of each marker from its neutral position over the frames, mm.

    Parameters
    ----------
    positions : (frames, markers, 3) float, NaN gaps
    neutral : (markers, 3) float

    Returns
    -------
    (markers,) float
        0 for a marker with no valid frame.
    """
    pos = np.asarray(positions, dtype=np.float64)
    squared = np.full(pos.shape[1], -np.inf)
    for start in range(0, pos.shape[0], BLOCK_FRAMES):  # blocks: no (frames, markers, 3) temporaries
        d = pos[start:start + BLOCK_FRAMES] - neutral[None]
        d *= d
        sq = d[..., 0] + d[..., 1]  # the sum np.linalg.norm takes, in its order
        sq += d[..., 2]
        sq[sq == np.inf] = np.nan  # an infinite sample is no valid frame
        np.fmax(squared, np.fmax.reduce(sq, axis=0, initial=-np.inf), out=squared)
    seen = squared > -np.inf
    # sqrt is monotonic and correctly rounded: the root of the largest square is the largest norm
    return np.where(seen, np.sqrt(np.where(seen, squared, 0.0)), 0.0)
