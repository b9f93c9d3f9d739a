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
    """(L,) pooled held-out RMSE (mm) of the layout without each of its (sorted) markers."""
    layout = np.unique(np.asarray(layout, dtype=np.intp))
    return np.array([folds.rmse(np.delete(layout, i)) for i in range(layout.size)])


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
        lost = worst_lost_marker(fold, layout).lost_rmse_mm
        sse, points = sse + lost ** 2 * fold.n_test_points, points + fold.n_test_points
    return float(np.sqrt(sse / points)) if points else float("nan")


def lost_marker_summaries(folds: CrossValidatedError, layouts: dict[str, Sequence[np.ndarray]],
                          labels: Sequence[str] | None = None) -> dict[str, dict]:
    """Per named method: intact and worst-lost-marker RMSE (mm; mean over its layouts, e.g. random
    seeds) and, for a single layout, the label of the marker whose loss hurts most."""
    out = {}
    for name, group in layouts.items():
        results = [worst_lost_marker(folds, layout) for layout in group]
        entry = {"intact_rmse_mm": float(np.mean([r.intact_rmse_mm for r in results])),
                 "lost_rmse_mm": float(np.mean([r.lost_rmse_mm for r in results]))}
        if len(results) == 1:
            entry["marker"] = results[0].as_dict(labels)["marker"]
        out[name] = entry
    return out
