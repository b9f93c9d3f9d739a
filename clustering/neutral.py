"""Neutral pose and per-marker displacement from it (NaN-aware, warning-free)."""

from __future__ import annotations

import numpy as np

#: Frames per block of :func:`seen_markers`.
BLOCK_FRAMES = 4096
#: Values (frames x markers x 3) per block of :func:`max_displacement`: 512 KiB of float64, so
#: a block's temporaries stay in a core's L2 cache (4,096-frame blocks of 200 markers, 19 MB,
#: went through memory: 1.7x the time).
DISPLACEMENT_BLOCK_VALUES = 2 ** 16
#: Columns (x, y, z of up to 32 markers) per block of :func:`neutral_pose`, at most
#: ``MEDIAN_BLOCK_VALUES`` values (16 MB: a 55 MB block of 72,000 frames cost 0.06-0.12 s of
#: page faults), and frames per transposed tile.
MEDIAN_COLUMNS = 96
MEDIAN_BLOCK_VALUES = 2 ** 21
MEDIAN_TILE_FRAMES = 512


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
    frames, markers = pos.shape[:2]
    columns = pos.reshape(frames, markers * 3)
    out = np.full(markers * 3, np.nan)
    width = max(3, min(MEDIAN_COLUMNS, MEDIAN_BLOCK_VALUES // max(frames, 1)) // 3 * 3)  # whole markers
    block = np.empty((min(width, markers * 3), frames))
    for start in range(0, markers * 3, width):
        part = block[:min(width, markers * 3 - start)]
        for tile in range(0, frames, MEDIAN_TILE_FRAMES):  # tiled transposition: cache-friendly
            part[:, tile:tile + MEDIAN_TILE_FRAMES] = \
                columns[tile:tile + MEDIAN_TILE_FRAMES, start:start + width].T
        seen = np.isfinite(part).reshape(len(part) // 3, 3, frames).all(axis=1).any(axis=1)
        valid = frames - np.isnan(part).sum(axis=1)
        for j in np.flatnonzero(np.repeat(seen, 3)):
            out[start + j] = _median_of_valid(part[j], int(valid[j]))
    return out.reshape(markers, 3)


def _median_of_valid(column: np.ndarray, n: int) -> float:
    """``np.median`` of the ``n`` non-NaN values of ``column`` (partitioned in place; NaN sorts
    last): one selection at rank n // 2, as np.partition at two ranks costs ~6x."""
    k = n // 2
    column.partition(k)
    return column[k] if n % 2 else (column[:k].max() + column[k]) / 2


def seen_markers(positions: np.ndarray) -> np.ndarray:
    """(markers,) bool: the marker has all three coordinates finite in at least one frame.

    ``positions`` (frames, markers, 3) mm; in blocks of frames, axes compared as strided columns
    (``isfinite(...).all(axis=2)`` over the whole session is ~3x slower)."""
    pos = np.asarray(positions)
    flat = pos.reshape(pos.shape[0], pos.shape[1] * 3)
    seen = np.zeros(pos.shape[1], dtype=bool)
    for start in range(0, pos.shape[0], BLOCK_FRAMES):
        finite = np.isfinite(flat[start:start + BLOCK_FRAMES])
        seen |= (finite[:, 0::3] & finite[:, 1::3] & finite[:, 2::3]).any(axis=0)
    return seen


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
    step = max(1, DISPLACEMENT_BLOCK_VALUES // max(1, 3 * pos.shape[1]))
    for start in range(0, pos.shape[0], step):  # blocks: no (frames, markers, 3) temporaries
        d = pos[start:start + step] - neutral[None]
        d *= d
        sq = d[..., 0] + d[..., 1]  # the sum np.linalg.norm takes, in its order
        sq += d[..., 2]
        sq[sq == np.inf] = np.nan  # an infinite sample is no valid frame
        np.fmax(squared, np.fmax.reduce(sq, axis=0, initial=-np.inf), out=squared)
    seen = squared > -np.inf
    # sqrt is monotonic and correctly rounded: the root of the largest square is the largest norm
    return np.where(seen, np.sqrt(np.where(seen, squared, 0.0)), 0.0)
