"""Local reconstruction error: every point predicted from its few nearest layout points only.

A training session moves one region at a time, a performance moves all of them together: the
correlations a global regression learns *between* regions of the training takes do not hold in
the performance, the motion shared by physical neighbours does. Scoring a layout by how well each
point is explained by its ``k`` nearest layout markers (on the neutral face) — the evaluation's
ridge model restricted to those inputs — rewards layouts that capture every area's own motion
instead of correlations that only the training takes have.

Computed from the per-fold Gram matrices of :class:`.reconstruction.CrossValidatedError`, so a
layout costs one batch of (3k × 3k) solves per fold, never a pass over the frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .reconstruction import CrossValidatedError

#: Up to this many points every point's nearest-first order of all points is kept ((N, N)
#: indices, 32 MB at 2,000): a layout's nearest points are then a lookup, not a sort per call.
ORDER_MAX_POINTS = 2000


@dataclass(frozen=True, eq=False)
class LocalError:
    """Error (mm) of reconstructing each point from its ``k`` nearest layout points.

    ``folds``: train/test Gram matrices (train = test for the in-sample fit); ``neutral`` (N, 3)
    mm; ``scales``: the values of ``k``, whose mean squared errors are averaged. Layout points
    are measured (error 0, as in the evaluation; with ``measured`` (N,) mm², that expected squared
    error of each point when it is a captured layout marker). A point's error depends only on its ``k``
    nearest layout points, so it is cached by them: a swap search recomputes only the points
    whose neighbours changed.
    """

    folds: CrossValidatedError
    neutral: np.ndarray
    scales: tuple[int, ...] = (1, 2)
    measured: np.ndarray | None = None
    _cache: dict[Any, Any] = field(default_factory=dict, repr=False)  # point errors per k, "order"

    def _squared_errors(self, targets: np.ndarray, near: np.ndarray, *, block: int = 2048) -> np.ndarray:
        """(T,) squared error of each target from its layout points ``near`` (T, k), summed over
        folds; ``block`` targets at a time (a design-kept Gram gathers (F, block, 3k) columns)."""
        if targets.size > block:
            return np.concatenate([self._squared_errors(targets[lo:lo + block], near[lo:lo + block])
                                   for lo in range(0, targets.size, block)])
        k = near.shape[1]
        dst = 3 * targets[:, None] + np.arange(3)  # (T, 3)
        src = (3 * near[:, :, None] + np.arange(3)).reshape(targets.size, 3 * k)  # (T, 3k)
        ss, sd = (src[:, :, None], src[:, None, :]), (src[:, :, None], dst[:, None, :])
        eye = np.eye(3 * k)
        total = np.zeros(targets.size)
        for gram, test in zip(self.folds.train_gram, self.folds.test_gram):
            g_ss = gram[ss]
            lam = self.folds.ridge * np.maximum(np.trace(g_ss, axis1=1, axis2=2) / (3 * k), 1e-12)
            g_sd = gram[sd]
            coef = np.linalg.solve(g_ss + lam[:, None, None] * eye, g_sd)  # (T, 3k, 3)
            own = test.diagonal()[dst].sum(axis=1)
            t_ss, t_sd = (g_ss, g_sd) if test is gram else (test[ss], test[sd])  # in-sample: the same blocks
            total += own + np.sum(coef * (t_ss @ coef - 2.0 * t_sd), axis=(1, 2))
        return total

    def _nearest_layout(self, targets: np.ndarray, layout: np.ndarray, count: int) -> np.ndarray:
        """(T, count) nearest ``layout`` points (sorted indices) of each target on the neutral face,
        nearest first, ties by index. Up to ``ORDER_MAX_POINTS`` points from every point's
        order of all points (sorted once), else by sorting the layout columns."""
        n = self.neutral.shape[0]
        if n > ORDER_MAX_POINTS:
            dist = np.linalg.norm(self.neutral[targets][:, None] - self.neutral[layout][None], axis=2)
            return layout[np.argsort(dist, axis=1, kind="stable")[:, :count]]
        if "order" not in self._cache:  # (N, N): each row all points, nearest first
            self._cache["order"] = np.concatenate([np.argsort(np.linalg.norm(
                self.neutral[lo:lo + 256, None] - self.neutral[None], axis=2), axis=1, kind="stable")
                for lo in range(0, n, 256)]).astype(np.intp)
        order = self._cache["order"].take(targets, axis=0)
        in_layout = np.zeros(n, dtype=bool)
        in_layout[layout] = True
        # every row holds each layout point once: row-major selection keeps each target's own
        # (take and flat indices: ~3x faster than fancy and 2-D boolean indexing at this size)
        picked = order.ravel()[np.flatnonzero(in_layout.take(order))]
        return picked.reshape(targets.size, layout.size)[:, :count]

    def rmse(self, layout: Sequence[int] | np.ndarray) -> float:
        """RMSE (mm) over all points of the local reconstruction from ``layout``, mean over scales."""
        layout = np.unique(np.asarray(layout, dtype=np.intp))
        is_target = np.ones(self.neutral.shape[0], dtype=bool)
        is_target[layout] = False
        targets = np.flatnonzero(is_target)
        order = self._nearest_layout(targets, layout, min(max(self.scales), layout.size))
        total = 0.0
        for k in self.scales:
            k = min(k, layout.size)
            near = order[:, :k]
            errors = self._cache.setdefault(("errors", k), {})
            # key: the bytes of (target, its k layout points), one C-level pass (tuples: 3x slower)
            rows = np.column_stack([targets, near])
            keys = rows.view(np.dtype((np.void, rows.itemsize * (k + 1)))).ravel().tolist()
            values = list(map(errors.get, keys))
            missing = [i for i, value in enumerate(values) if value is None]
            if missing:
                at = np.array(missing, dtype=np.intp)
                for i, value in zip(missing, self._squared_errors(targets[at], near[at]).tolist()):
                    errors[keys[i]] = values[i] = value
            total += float(np.sum(values))
        if self.measured is not None:  # layout markers: their capture error in every test frame
            frames = self.folds.n_test_points / self.neutral.shape[0]
            total += len(self.scales) * frames * float(self.measured[layout].sum())
        return float(np.sqrt(max(total, 0.0) / (self.folds.n_test_points * len(self.scales))))
