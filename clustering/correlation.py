"""Per-axis Pearson correlation of marker positions and the consolidated matrix C = Cx + Cy + Cz.

Gaps: pairwise-complete — each pair's correlation uses the frames where both markers are
present (numpy.corrcoef semantics on those frames). Without gaps the whole matrix is one matrix
product of the standardized, axis-stacked positions; with gaps, one product per axis of the
zero-filled positions plus sparse corrections over the absent frames (cost grows with the gap
count, memory stays a few (1,024, M) blocks). An axis on which a marker (or a pair's
common frames) has a standard deviation <= ``STATIC_SD_MM`` contributes 0 — correlation is
undefined there — and a pair with fewer than 3 common frames correlates 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas
from threadpoolctl import threadpool_limits

#: A standard deviation at or below this (mm) counts as no motion on that axis.
STATIC_SD_MM = 1e-6
#: Rows per block in the gap-aware computation (bounds the temporary memory).
_BLOCK = 1024
#: Regions of fewer markers correlate with one BLAS thread: their (frames x M) products are too
#: small to share (a 40-marker region over 14,400 frames: 300 -> 2 ms a product on 2 busy cores).
THREADED_MIN_MARKERS = 1024


@dataclass(frozen=True)
class Correlation:
    """Consolidated correlation of one region.

    ``matrix`` (M, M) float64, symmetric, in [-3, 3]; ``static_axes`` (M, 3) bool: marker has no
    motion on that axis; ``static`` (M,) bool: no motion on any axis.
    """

    matrix: np.ndarray
    static_axes: np.ndarray

    @property
    def static(self) -> np.ndarray:
        return self.static_axes.all(axis=1)


def consolidated_correlation(positions: np.ndarray) -> Correlation:
    """Consolidated correlation of marker positions.

    Parameters
    ----------
    positions : (frames, markers, 3) float
        Millimetres, NaN gaps (already sampled, e.g. every 5th frame).

    Returns
    -------
    Correlation
    """
    pos = np.asarray(positions, dtype=np.float64)
    n_frames, n_markers = pos.shape[:2]
    present = np.isfinite(pos).all(axis=2)  # a marker is present in a frame with all 3 coordinates
    counts = present.sum(axis=0)
    safe_counts = np.maximum(counts, 1)
    centred = np.where(present[:, :, None], pos, 0.0)
    centred -= centred.sum(axis=0) / safe_counts[:, None]
    centred[~present] = 0.0
    sd = np.sqrt((centred ** 2).sum(axis=0) / safe_counts[:, None])  # (M, 3)
    static_axes = (sd <= STATIC_SD_MM) | (counts < 3)[:, None]
    with threadpool_limits(limits=1 if n_markers < THREADED_MIN_MARKERS else None, user_api="blas"):
        if present.all():
            matrix = _complete_correlation(centred, sd, static_axes)
        else:
            matrix = _pairwise_correlation(centred, present, static_axes)
    np.clip(matrix, -3.0, 3.0, out=matrix)
    return Correlation(matrix, static_axes)


def _complete_correlation(centred: np.ndarray, sd: np.ndarray, static_axes: np.ndarray) -> np.ndarray:
    n_frames, n_markers = centred.shape[:2]
    scale = np.zeros_like(sd)
    np.divide(1.0, sd * np.sqrt(n_frames), out=scale, where=~static_axes)
    z = (centred * scale[None]).transpose(2, 0, 1).reshape(3 * n_frames, n_markers)
    # z.T @ z = sum over the three axes of the per-axis Pearson matrices; syrk computes one
    # triangle only (half the work), the other is copied in blocks (no full-size temporaries)
    matrix = blas.dsyrk(1.0, np.asfortranarray(z), trans=1, lower=0)
    for lo in range(0, n_markers, _BLOCK):
        hi = min(lo + _BLOCK, n_markers)
        matrix[lo:hi, :lo] = matrix[:lo, lo:hi].T
        block = matrix[lo:hi, lo:hi]
        block[np.tril_indices(hi - lo, -1)] = block.T[np.tril_indices(hi - lo, -1)]
    return matrix.T  # symmetric, so the transpose (a C-ordered view) is the same matrix


def _pairwise_correlation(centred: np.ndarray, present: np.ndarray, static_axes: np.ndarray) -> np.ndarray:
    """Pairwise-complete Pearson sums from masked Gram products, in blocks of rows.

    ``centred`` is zero where a marker is absent, so ``x_i . x_j`` already sums over the common
    frames (one dense product per axis, like the gap-free path); the per-pair sums and counts
    over common frames are the marker totals minus sparse products with the (few) absent
    frames, so gaps cost in proportion to their number, not another five dense products.
    """
    from scipy import sparse

    n_frames, n_markers = present.shape
    absent = sparse.csr_matrix(~present, dtype=np.float64)  # (F, M), 0.1-1 % non-zero
    absent_t = absent.T.tocsr()
    n_absent = n_frames - present.sum(axis=0).astype(np.float64)
    matrix = np.zeros((n_markers, n_markers))
    min_var = STATIC_SD_MM ** 2
    axes = []
    for axis in range(3):
        x = np.ascontiguousarray(centred[:, :, axis])
        xx = x * x
        axes.append((x, xx, x.sum(axis=0), xx.sum(axis=0), ~static_axes[:, axis]))
    for lo in range(0, n_markers, _BLOCK):  # upper triangle by blocks of rows, then mirrored
        hi = min(lo + _BLOCK, n_markers)
        n = n_frames - n_absent[lo:hi, None] - n_absent[None, lo:] \
            + (absent_t[lo:hi] @ absent[:, lo:]).toarray()  # frames where both are present
        for x, xx, total, total_sq, moving in axes:
            # sum of x_i over frames where j is present too = total_i - x_i over j's gaps
            s_i = _minus_transposed(total[lo:hi], absent_t[lo:] @ x[:, lo:hi])
            s_j = total[None, lo:] - absent_t[lo:hi] @ x[:, lo:]
            ss_i = _minus_transposed(total_sq[lo:hi], absent_t[lo:] @ xx[:, lo:hi])
            ss_j = total_sq[None, lo:] - absent_t[lo:hi] @ xx[:, lo:]
            ok = (n >= 3) & moving[lo:hi, None] & moving[None, lo:]
            inv_n = np.zeros_like(n)
            np.divide(1.0, n, out=inv_n, where=ok)
            mean_i = s_i * inv_n  # in-place arithmetic below: few (block, M) temporaries
            cov = x[:, lo:hi].T @ x[:, lo:]
            cov -= mean_i * s_j
            ss_i -= mean_i * s_i  # variance sums over the common frames
            s_j *= s_j
            s_j *= inv_n
            ss_j -= s_j
            ok &= (ss_i > min_var * n) & (ss_j > min_var * n)
            ss_i *= ss_j
            np.sqrt(ss_i, out=ss_i, where=ok)
            r = np.zeros_like(cov)
            np.divide(cov, ss_i, out=r, where=ok)
            np.clip(r, -1.0, 1.0, out=r)
            matrix[lo:hi, lo:] += r
    for lo in range(0, n_markers, _BLOCK):  # mirror the upper triangle (exact symmetry)
        hi = min(lo + _BLOCK, n_markers)
        matrix[lo:hi, :lo] = matrix[:lo, lo:hi].T
        block = matrix[lo:hi, lo:hi]
        lower = np.tril_indices(hi - lo, -1)
        block[lower] = block.T[lower]
    return matrix


def _minus_transposed(total: np.ndarray, product: np.ndarray, *, chunk: int = 32) -> np.ndarray:
    """``total[:, None] - product.T`` (B,) and (M, B) -> (B, M) in C order like every other
    (block, M) array (mixed orders made the arithmetic ~10x slower), ``chunk`` rows of
    ``product`` at a time (a transposed read of all of it is ~2x slower)."""
    out = np.empty(product.shape[::-1])
    for lo in range(0, product.shape[0], chunk):
        np.subtract(total[:, None], product[lo:lo + chunk].T, out=out[:, lo:lo + chunk])
    return out


def mean_off_diagonal(matrix: np.ndarray) -> float:
    """Mean of the off-diagonal entries of a square matrix (NaN for fewer than 2 rows)."""
    n = matrix.shape[0]
    if n < 2:
        return float("nan")
    return float((matrix.sum() - np.trace(matrix)) / (n * (n - 1)))
