"""Neutral pose and per-marker displacement from it (NaN-aware, warning-free)."""

from __future__ import annotations

import numpy as np


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
    dist = np.linalg.norm(np.asarray(positions, dtype=np.float64) - neutral[None], axis=2)
    dist = np.where(np.isfinite(dist), dist, -np.inf)
    out = dist.max(axis=0, initial=-np.inf)
    return np.where(np.isfinite(out), out, 0.0)
