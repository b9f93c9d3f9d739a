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

from .problem import LayoutProblem
from .reconstruction import CrossValidatedError, training_frames

#: Up to this many points the distances between all points are kept ((N, N), 32 MB at 2,000):
#: a layout's nearest points are then a gather and a sort of its columns, for several layouts at once.
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

    def _nearest_layout(self, targets: np.ndarray, layouts: np.ndarray, count: int) -> np.ndarray:
        """(L, T, count) nearest points of each layout (L, m) (rows sorted) to its targets (L, T)
        on the neutral face, nearest first, ties by index (as a stable sort of the layout columns).
        Up to ``ORDER_MAX_POINTS`` points from the distances between all points (computed once),
        else computed per layout."""
        n = self.neutral.shape[0]
        if n > ORDER_MAX_POINTS:
            return np.stack([layout[np.argsort(np.linalg.norm(
                self.neutral[t][:, None] - self.neutral[layout][None], axis=2), axis=1, kind="stable")[:, :count]]
                for t, layout in zip(targets, layouts)])
        if "distances" not in self._cache:  # (N, N), elementwise as the per-layout norms above
            self._cache["distances"] = np.concatenate([np.linalg.norm(
                self.neutral[lo:lo + 256, None] - self.neutral[None], axis=2) for lo in range(0, n, 256)])
        # (L, T, m) by flat indices: take is ~3x faster than fancy indexing at this size
        dist = self._cache["distances"].take(targets[:, :, None] * n + layouts[:, None, :])
        rows, cols = np.ogrid[:dist.shape[0], :dist.shape[1]]
        near = np.empty(dist.shape[:2] + (count,), dtype=np.intp)
        for rank in range(count):  # the first minimum: ties by index (count is a few: 5x a sort)
            pick = np.argmin(dist, axis=2)
            near[:, :, rank] = layouts[rows, pick]
            dist[rows, cols, pick] = np.inf
        return near

    def rmse(self, layout: Sequence[int] | np.ndarray) -> float:
        """RMSE (mm) over all points of the local reconstruction from ``layout``, mean over scales."""
        return self.rmse_many([layout])[0]

    def rmse_many(self, layouts: Sequence[Sequence[int] | np.ndarray]) -> list[float]:
        """:meth:`rmse` of each layout, layouts of one size together: their nearest points in one
        gather and sort, the point errors none has cached in one batch per scale (a swap search
        scores a slot's trials together)."""
        unique = [np.unique(np.asarray(layout, dtype=np.intp)) for layout in layouts]
        n = self.neutral.shape[0]
        sizes: dict[int, list[int]] = {}
        for i, layout in enumerate(unique):
            sizes.setdefault(layout.size, []).append(i)
        keys: list[list[tuple[int, list[bytes]]]] = [[] for _ in unique]  # per layout, per scale
        todo: dict[int, dict[bytes, np.ndarray]] = {}  # per k: uncached key -> (target, its k points)
        for size, members in sizes.items():
            group = np.stack([unique[i] for i in members])  # (L, m)
            is_target = np.ones((len(members), n), dtype=bool)
            is_target[np.arange(len(members))[:, None], group] = False
            targets = np.nonzero(is_target)[1].reshape(len(members), n - size)
            order = self._nearest_layout(targets, group, min(max(self.scales), size))
            for k in dict.fromkeys(min(k, size) for k in self.scales):
                errors = self._cache.setdefault(("errors", k), {})
                # key: the bytes of (target, its k layout points), one C-level pass (tuples: 3x slower)
                rows = np.concatenate([targets[:, :, None], order[:, :, :k]], axis=2).reshape(-1, k + 1)
                flat = rows.view(np.dtype((np.void, rows.itemsize * (k + 1)))).ravel().tolist()
                queued = todo.setdefault(k, {})
                for i in [i for i, known in enumerate(map(errors.__contains__, flat)) if not known]:
                    queued.setdefault(flat[i], rows[i])
                for j, i in enumerate(members):
                    keys[i].append((k, flat[j * (n - size):(j + 1) * (n - size)]))
        for k, queued in todo.items():
            if queued:
                rows = np.array(list(queued.values()))
                self._cache[("errors", k)].update(zip(queued, self._squared_errors(rows[:, 0], rows[:, 1:]).tolist()))
        out = []
        for layout, per_k in zip(unique, keys):
            found = dict((k, float(np.sum(list(map(self._cache[("errors", k)].__getitem__, flat)))))
                         for k, flat in per_k)
            total = 0.0
            for k in self.scales:
                total += found[min(k, layout.size)]
            if self.measured is not None:  # layout markers: their capture error in every test frame
                frames = self.folds.n_test_points / self.neutral.shape[0]
                total += len(self.scales) * frames * float(self.measured[layout].sum())
            out.append(float(np.sqrt(max(total, 0.0) / (self.folds.n_test_points * len(self.scales)))))
        return out


def local_error(problem: LayoutProblem, *, scales: tuple[int, ...] = (1, 2),
                charged: bool = True) -> LocalError:
    """The local error of the problem's gap-free training frames, fitted and scored in-sample
    (with ``charged``, layout markers charged the problem's ``measured_error_mm``, when it has one)."""
    if "local-fit" not in problem.cache:
        disp, _ = training_frames(problem)
        every = np.arange(disp.shape[0])
        problem.cache["local-fit"] = CrossValidatedError.from_displacements(disp, [(every, every)])
    charged = charged and problem.measured_error_mm is not None
    key = ("local-error", tuple(scales), charged)
    if key not in problem.cache:  # shared, so a point's error is computed once per neighbours
        measured = problem.measured_error_mm ** 2 if charged else None
        problem.cache[key] = LocalError(problem.cache["local-fit"], problem.neutral, tuple(scales), measured)
    return problem.cache[key]
