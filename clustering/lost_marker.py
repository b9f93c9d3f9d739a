"""Held-out error of a layout when one of its markers is lost mid-shoot (worst case over markers).

A studio loses markers: one falls off, or the cameras stop seeing it. For a layout ``L`` and a
lost marker ``m``, the face is reconstructed from ``L \\ {m}`` (the same ridge model as
:mod:`mocaptk.clustering.evaluation`, refitted without ``m``; ``m`` itself is then reconstructed
like every other dense marker). The worst case is the marker whose loss raises the held-out
error most. Computed from Gram matrices of the gap-free frames
(:class:`~mocaptk.clustering.methods.reconstruction.CrossValidatedError`), so a 48-marker
layout costs 48 small solves, not 48 evaluations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .evaluation import DEFAULT_RIDGE
from .methods.reconstruction import CrossValidatedError


@dataclass(frozen=True)
class LostMarker:
    """Held-out RMSE (mm, gap-free test frames) of the intact layout and with its worst marker lost.

    ``marker``: index (into the dense markers) of the marker whose loss hurts most.
    """

    intact_rmse_mm: float
    lost_rmse_mm: float
    marker: int

    def as_dict(self, labels: Sequence[str] | None = None) -> dict:
        return {"intact_rmse_mm": self.intact_rmse_mm, "lost_rmse_mm": self.lost_rmse_mm,
                "marker": labels[self.marker] if labels is not None else self.marker}


def _complete(positions: np.ndarray) -> np.ndarray:
    """(F,) True for the frames without any gap."""
    return np.isfinite(positions).all(axis=(1, 2))


def heldout_folds(positions: np.ndarray, splits: Sequence[tuple[np.ndarray, np.ndarray]] = (), *,
                  test: np.ndarray | None = None, ridge: float = DEFAULT_RIDGE) -> CrossValidatedError:
    """Gram matrices of the held-out protocol of ``evaluate``, restricted to gap-free frames.

    With ``test`` (a separate performance): train on the session, test on it. Otherwise the
    ``splits`` (train, test frame indices of ``positions``).
    """
    positions = np.asarray(positions, dtype=np.float64)
    if test is not None:
        train = positions[_complete(positions)]
        held = np.asarray(test, dtype=np.float64)
        held = held[_complete(held)]
        frames = np.concatenate([train, held])
        folds = [(np.arange(train.shape[0]), np.arange(train.shape[0], frames.shape[0]))]
        return CrossValidatedError.from_displacements(frames, folds, ridge=ridge)
    kept = np.flatnonzero(_complete(positions))
    remap = np.full(positions.shape[0], -1)
    remap[kept] = np.arange(kept.size)
    folds = [(remap[tr][remap[tr] >= 0], remap[te][remap[te] >= 0]) for tr, te in splits]
    return CrossValidatedError.from_displacements(positions[kept], [f for f in folds if f[0].size and f[1].size],
                                                  ridge=ridge)


def lost_marker_rmse(folds: CrossValidatedError, layout: Sequence[int] | np.ndarray) -> np.ndarray:
    """(L,) pooled held-out RMSE (mm) of the layout without each of its (sorted) markers.

    Equal to ``folds.rmse`` of each reduced layout (to ~1e-10 relative): per fold one
    eigendecomposition of the layout's Gram block, then a rank-3 downdate per lost marker."""
    layout = np.unique(np.asarray(layout, dtype=np.intp))
    if layout.size < 2 or not all(isinstance(g, np.ndarray) for g in folds.train_gram + folds.test_gram):
        return np.array([folds.rmse(np.delete(layout, i)) for i in range(layout.size)])
    cols = (3 * layout[:, None] + np.arange(3)).ravel()
    total = sum(_lost_squared_errors(gram, test, cols, folds.ridge)
                for gram, test in zip(folds.train_gram, folds.test_gram))
    return np.sqrt(np.maximum(total, 0.0) / folds.n_test_points)


def _lost_squared_errors(gram: np.ndarray, test: np.ndarray, cols: np.ndarray, ridge: float) -> np.ndarray:
    """(L,) held-out squared error of one fold (train / test Gram (3N, 3N)) when the layout
    (columns ``cols``, 3 per marker) loses each marker: :meth:`CrossValidatedError.rmse`'s sum.

    With ``G_SS = V·diag(e)·Vᵀ`` and the ridge ``λ`` of the reduced layout, the zero-padded inverse
    of its ridge matrix is ``V·(D − W·K⁻¹·Wᵀ)·Vᵀ`` (``D = (e + λ)⁻¹``, ``W = D·V[I]ᵀ``, ``K = V[I]·W``):
    every term of the error is then a trace with rank-3 corrections, O((3L)²) per marker."""
    n = cols.size
    rest = np.setdiff1d(np.arange(gram.shape[0]), cols)
    values, vecs = np.linalg.eigh(gram[np.ix_(cols, cols)])
    g_rot = vecs.T @ gram[np.ix_(cols, rest)]  # Vᵀ G_SR
    t_rot = vecs.T @ test[np.ix_(cols, rest)]  # Vᵀ T_SR
    c_hat = g_rot @ g_rot.T  # Vᵀ G_SR G_RS V
    h_hat = g_rot @ t_rot.T  # Vᵀ G_SR T_RS V
    t_hat = vecs.T @ test[np.ix_(cols, cols)] @ vecs  # Vᵀ T_SS V
    ct = c_hat * t_hat
    own_rest = float(test.diagonal()[rest].sum())
    gram_trace = float(np.trace(gram[np.ix_(cols, cols)]))
    out = np.empty(n // 3)
    for k in range(n // 3):
        idx = np.arange(3 * k, 3 * k + 3)
        u = vecs[idx].T  # (n, 3) Vᵀ e_I
        lam = ridge * max((gram_trace - float(np.trace(gram[np.ix_(cols[idx], cols[idx])]))) / (n - 3), 1e-12)
        d = 1.0 / (values + lam)
        w = d[:, None] * u
        k_inv = np.linalg.inv(u.T @ w)
        a, b = values[:, None] * u, t_hat @ u  # Vᵀ G_SI, Vᵀ T_SI: the lost marker joins the targets
        # tr(P·H) with H = H_R + a bᵀ
        hw = h_hat @ w + a @ (b.T @ w)
        term_h = float(d @ (np.diagonal(h_hat) + np.einsum("ic,ic->i", a, b))) - float(np.sum(k_inv * (w.T @ hw).T))
        # tr(P·C·P·T) with C = C_R + a aᵀ, P = D − W K⁻¹ Wᵀ
        da = d[:, None] * a
        cw, tw = c_hat @ w + a @ (a.T @ w), t_hat @ w
        first = float(d @ ct @ d) + float(np.einsum("ic,ic->", da, t_hat @ da))
        cross = float(np.sum(k_inv * ((cw.T * d) @ tw).T))
        last = float(np.sum(k_inv * ((w.T @ cw) @ k_inv @ (w.T @ tw)).T))
        term_c = first - 2.0 * cross + last
        own = own_rest + float(np.trace(test[np.ix_(cols[idx], cols[idx])]))
        out[k] = own - 2.0 * term_h + term_c
    return out


def worst_lost_marker(folds: CrossValidatedError, layout: Sequence[int] | np.ndarray) -> LostMarker:
    """The intact error and the error when the marker whose loss hurts most is lost."""
    layout = np.unique(np.asarray(layout, dtype=np.intp))
    intact = folds.rmse(layout)
    if layout.size < 2:  # losing the only marker leaves nothing to reconstruct from
        return LostMarker(intact, float("nan"), int(layout[0]))
    lost = lost_marker_rmse(folds, layout)
    worst = int(np.argmax(lost))
    return LostMarker(intact, float(lost[worst]), int(layout[worst]))


def pooled_worst_lost(folds: Sequence[CrossValidatedError], layouts: Sequence[np.ndarray]) -> float:
    """Held-out RMSE (mm) pooled over folds when each fold's layout loses the marker whose loss
    hurts that fold most (``compare`` chooses a layout per fold). ``folds``: one single-split
    :class:`CrossValidatedError` per layout; a fold without gap-free frames adds nothing (NaN
    when none has any, or a layout has a single marker)."""
    sse, points = 0.0, 0
    for fold, layout in zip(folds, layouts):
        if fold.n_test_points == 0:
            continue
        layout = np.unique(np.asarray(layout, dtype=np.intp))
        # worst_lost_marker's lost error, without the intact error it also computes
        lost = float(np.max(lost_marker_rmse(fold, layout))) if layout.size >= 2 else float("nan")
        sse, points = sse + lost ** 2 * fold.n_test_points, points + fold.n_test_points
    return float(np.sqrt(sse / points)) if points else float("nan")


def lost_marker_summaries(folds: CrossValidatedError, layouts: dict[str, Sequence[np.ndarray]],
                          labels: Sequence[str] | None = None) -> dict[str, dict]:
    """Per named method: intact and worst-lost-marker RMSE (mm; mean over its layouts, e.g. random
    seeds) and, for a single layout, the label of the marker whose loss hurts most. The layouts
    are shared among the CPUs (:func:`~mocaptk.background.shared_map`: the same bits)."""
    from mocaptk.background import shared_map

    done = iter(shared_map(lambda layout: worst_lost_marker(folds, layout),
                           [layout for group in layouts.values() for layout in group], what="a lost-marker error"))
    out = {}
    for name, group in layouts.items():
        results = [next(done) for _ in group]
        entry = {"intact_rmse_mm": float(np.mean([r.intact_rmse_mm for r in results])),
                 "lost_rmse_mm": float(np.mean([r.lost_rmse_mm for r in results]))}
        if len(results) == 1:
            entry["marker"] = results[0].as_dict(labels)["marker"]
        out[name] = entry
    return out
