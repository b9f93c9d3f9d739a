"""Per-frame blendshape weights from marker displacements: a bounded, sparse, smooth least squares.

For each frame ``t`` with displacements ``d_t`` (L, 3) mm of the markers from the actor's
neutral (head-relative) and the actor basis ``A`` (S, L, 3) mm (how each marker moves at weight
1 of each shape), the weights ``w_t`` (S,) minimise

    ||A w - d_t||²  (over the markers seen in frame t)
    + l1 · a · Σ_k w_k  +  smooth · a · ||w - w_{t-1}||²,     0 ≤ w ≤ 1,

where ``a`` is the mean squared norm of the basis columns (so ``l1`` and ``smooth`` are unitless:
the same values work for any marker count or face size). Lost markers (NaN) are dropped from
that frame's system, never filled. The smoothness term is causal (the previous frame's solved
weights), so the solve streams chunk by chunk with the last weights carried over.

Solver: projected Gauss-Seidel (coordinate descent) on the box-constrained quadratic, compiled
with numba, warm-started from the previous frame. Each frame's Gram matrix is the full one minus
the lost markers' rows, so a frame costs O(S² · lost + S · L + sweeps · S²). Why not
``scipy.optimize.lsq_linear`` or an active-set NNLS per frame: their per-call overhead alone
(~1 ms) caps a Python loop at a few hundred frames/s, and neither takes the L1 + smoothness
terms or a warm start; coordinate descent converges in a few sweeps from the previous frame's
weights (the bench compares both, ``benchmarks/bench_retarget.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["DEFAULT_L1", "DEFAULT_SMOOTH", "SolvedWeights", "solve_weights"]

#: Sparsity weight (unitless, see the module docstring).
DEFAULT_L1 = 1e-3
#: Temporal smoothness weight (unitless).
DEFAULT_SMOOTH = 0.05
#: Coordinate-descent stop: largest weight change in a sweep.
TOLERANCE = 1e-6
MAX_SWEEPS = 500


@dataclass(frozen=True)
class SolvedWeights:
    """``weights`` (F, S) in [0, 1]; ``residual_mm`` (F,) RMS marker misfit over the seen
    markers (NaN where none is seen); ``lost`` (F,) lost markers per frame."""

    weights: np.ndarray
    residual_mm: np.ndarray
    lost: np.ndarray


def basis_scale(basis: np.ndarray) -> float:
    """``a``: the mean squared norm of the basis columns (mm²), 1 if the basis is zero."""
    a = float(np.mean(np.sum(np.asarray(basis, dtype=np.float64) ** 2, axis=(1, 2))))
    return a if a > 0 else 1.0


def solve_weights(basis: np.ndarray, displacements: np.ndarray, *, l1: float = DEFAULT_L1,
                  smooth: float = DEFAULT_SMOOTH, previous: np.ndarray | None = None,
                  upper: float = 1.0) -> SolvedWeights:
    """Weights (F, S) for ``displacements`` (F, L, 3) mm (NaN: lost) with ``basis`` (S, L, 3) mm.

    ``previous`` (S,) the weights of the frame before the first (default 0: the neutral);
    ``upper`` the bound (1 for a rig's range).
    """
    a = np.ascontiguousarray(np.asarray(basis, dtype=np.float64).reshape(len(basis), -1))  # (S, 3L)
    n_shapes, n_markers = len(basis), a.shape[1] // 3
    d = np.asarray(displacements, dtype=np.float64).reshape(len(displacements), n_markers, 3)
    seen = np.isfinite(d).all(axis=2)
    scale = basis_scale(basis)
    start = np.zeros(n_shapes) if previous is None else np.asarray(previous, dtype=np.float64)
    weights, residual = _solve(a, np.ascontiguousarray(np.where(seen[..., None], d, 0.0).reshape(len(d), -1)),
                               np.ascontiguousarray(seen), a @ a.T, l1 * scale, smooth * scale,
                               start.copy(), float(upper))
    return SolvedWeights(weights, residual, (~seen).sum(axis=1))


@numba.njit(cache=True, nogil=True)
def _solve(a, d, seen, gram, l1, smooth, w, upper):  # pragma: no cover - compiled
    n_frames, n_shapes = d.shape[0], a.shape[0]
    n_markers = seen.shape[1]
    out = np.empty((n_frames, n_shapes))
    residual = np.empty(n_frames)
    g = np.empty((n_shapes, n_shapes))
    h = np.empty(n_shapes)
    for t in range(n_frames):
        g[:, :] = gram
        h[:] = 0.0
        count = 0
        for m in range(n_markers):
            for c in range(3):
                col = 3 * m + c
                if seen[t, m]:
                    h += a[:, col] * d[t, col]
                else:  # a lost marker: its rows leave the system
                    g -= np.outer(a[:, col], a[:, col])
            count += seen[t, m]
        for k in range(n_shapes):
            g[k, k] += smooth
            h[k] += smooth * w[k] - l1
        grad = g @ w - h  # kept up to date as weights move
        for _ in range(MAX_SWEEPS):
            change = 0.0
            for k in range(n_shapes):
                if g[k, k] <= 0.0:
                    continue
                new = min(max(w[k] - grad[k] / g[k, k], 0.0), upper)
                step = new - w[k]
                if step != 0.0:
                    grad += step * g[:, k]
                    w[k] = new
                    change = max(change, abs(step))
            if change < TOLERANCE:
                break
        out[t] = w
        if count == 0:
            residual[t] = np.nan
            continue
        fit = w @ a
        total = 0.0
        for m in range(n_markers):
            if seen[t, m]:
                for c in range(3):
                    total += (fit[3 * m + c] - d[t, 3 * m + c]) ** 2
        residual[t] = np.sqrt(total / count)
    return out, residual
