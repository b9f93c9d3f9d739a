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
from dataclasses import dataclass

import numpy as np

from .reconstruction import CrossValidatedError


@dataclass(frozen=True, eq=False)
class LocalError:
    """Error (mm) of reconstructing each point from its ``k`` nearest layout points.

    ``folds``: train/test Gram matrices (train = test for the in-sample fit); ``neutral`` (N, 3)
    mm; ``scales``: the values of ``k``, whose mean squared errors are averaged. Layout points
    are measured (error 0), as in the evaluation.
    """

    folds: CrossValidatedError
    neutral: np.ndarray
    scales: tuple[int, ...] = (1, 2)

    def rmse(self, layout: Sequence[int] | np.ndarray) -> float:
        """RMSE (mm) over all points of the local reconstruction from ``layout``, mean over scales."""
        layout = np.unique(np.asarray(layout, dtype=np.intp))
        n = self.neutral.shape[0]
        targets = np.setdiff1d(np.arange(n), layout)
        dist = np.linalg.norm(self.neutral[targets, None] - self.neutral[None, layout], axis=2)
        order = layout[np.argsort(dist, axis=1, kind="stable")]
        dst = 3 * targets[:, None] + np.arange(3)  # (T, 3)
        total = 0.0
        for k in self.scales:
            k = min(k, layout.size)
            src = (3 * order[:, :k, None] + np.arange(3)).reshape(targets.size, 3 * k)  # (T, 3k)
            ss, sd = (src[:, :, None], src[:, None, :]), (src[:, :, None], dst[:, None, :])
            eye = np.eye(3 * k)
            for gram, test in zip(self.folds.train_gram, self.folds.test_gram):
                g_ss = gram[ss]
                lam = self.folds.ridge * np.maximum(np.trace(g_ss, axis1=1, axis2=2) / (3 * k), 1e-12)
                coef = np.linalg.solve(g_ss + lam[:, None, None] * eye, gram[sd])  # (T, 3k, 3)
                own = np.trace(test[dst[:, :, None], dst[:, None, :]], axis1=1, axis2=2).sum()
                total += (own - 2.0 * np.sum(coef * test[sd])
                          + np.einsum("tsj,tsu,tuj->", coef, test[ss], coef, optimize=True))
        return float(np.sqrt(max(total, 0.0) / (self.folds.n_test_points * len(self.scales))))
