"""Reconstruction-aware selection: markers whose motion best explains every other marker's.

All in the Gram space of the (frames × 3·N) displacement matrix, so a step costs O(N²) instead
of touching the frames:

* ``pivoted_qr_layout`` — column-pivoted QR (LAPACK ``geqp3``) of the centred matrix; markers in the
  order their first coordinate column is pivoted.
* ``greedy_layout`` — forward selection over 3-column marker blocks: add the marker whose block
  removes the most residual variance from all columns (block Gram–Schmidt), then optionally
* ``swap_refine`` — exchange a layout marker for an unused one while the cross-validated error of
  the team's ridge reconstruction (:mod:`mocaptk.clustering.evaluation`, the same model
  and ridge) goes down. Folds are the session's takes (leave one out) or contiguous blocks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg as sla

from mocaptk.errors import OptionError

from ..evaluation import DEFAULT_RIDGE, holdout_splits
from mocaptk.trajectories import Take

from .problem import LayoutProblem


def _design(disp: np.ndarray) -> np.ndarray:
    """(F, 3N) centred displacement matrix from (F, N, 3)."""
    flat = disp.reshape(disp.shape[0], -1)
    return flat - flat.mean(axis=0)


#: Above this many points (and more columns 3N than frames) Gram matrices are kept as their
#: (F, 3N) design, :class:`DesignGram`: a (3N, 3N) float64 matrix is 7.2 GB at 10,000 points.
GRAM_MAX_POINTS = 2000


def frame_space(frames: int, points: int) -> bool:
    """Whether Gram products of ``frames`` x ``points`` displacements work on the design."""
    return points > GRAM_MAX_POINTS and frames < 3 * points


@dataclass(frozen=True, eq=False)
class DesignGram:
    """The Gram matrix ``Dᵀ D`` of a (F, 3N) design ``D``, kept as ``D``: entries on demand.

    Indexing takes what the layout methods ask of a Gram matrix: ``[:, cols]``, ``[rows]`` and the
    outer patterns ``[a[..., :, None], b[..., None, :]]`` (``np.ix_`` and batched blocks), each
    one product over the F frames; :meth:`gains_given` works in the (F, F) frame space.
    """

    design: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return (self.design.shape[1], self.design.shape[1])

    def trace(self) -> float:
        return float(np.einsum("fi,fi->", self.design, self.design))

    def diagonal(self) -> np.ndarray:
        return self._diagonal

    @cached_property
    def _diagonal(self) -> np.ndarray:
        diagonal = np.einsum("fi,fi->i", self.design, self.design)
        diagonal.flags.writeable = False  # shared by every caller
        return diagonal

    def __getitem__(self, key: object) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key, slice(None))
        rows, cols = key
        if isinstance(rows, slice) or isinstance(cols, slice):
            return self.design[:, rows].T @ self.design[:, cols]
        rows, cols = np.asarray(rows)[..., 0], np.asarray(cols)[..., 0, :]
        left = self._columns[rows]  # (..., m, F)
        same = rows.shape == cols.shape and np.array_equal(rows, cols)  # a diagonal block: one gather
        return left @ np.swapaxes(left if same else self._columns[cols], -1, -2)

    @cached_property
    def _columns(self) -> np.ndarray:
        """(3N, F) ``Dᵀ`` in C order: a column gather reads F contiguous values (5x faster than
        gathering along the rows of ``D``)."""
        return np.ascontiguousarray(self.design.T)

    @cached_property
    def frames(self) -> np.ndarray:
        """(F, F) ``D Dᵀ``."""
        return self.design @ self.design.T

    def gains_given(self, chosen: Sequence[int], points: np.ndarray, jitter: float) -> np.ndarray:
        """:func:`gains_given` from the residual of the points' design columns: the residual Gram
        columns are ``Dᵀ R``, so their squares sum to ``Rᵀ (D Dᵀ) R`` with the (F, F) ``D Dᵀ``."""
        cols_s, cols_p = _blocks(np.asarray(chosen, dtype=np.intp)), _blocks(points)
        design = self.design
        resid = design[:, cols_p]
        if cols_s.size:
            d_s = design[:, cols_s]
            g_ss = d_s.T @ d_s + jitter * np.eye(cols_s.size)
            resid = resid - d_s @ np.linalg.solve(g_ss, d_s.T @ resid)
        n_p = len(points)
        blocks = resid.reshape(-1, n_p, 3)
        cross = np.einsum("fan,fam->anm", blocks, (self.frames @ resid).reshape(-1, n_p, 3))
        own = np.einsum("fan,fam->anm", design[:, cols_p].reshape(-1, n_p, 3), blocks) + jitter * np.eye(3)
        return np.einsum("anm,amn->a", np.linalg.inv(own), cross)


def training_gram(problem: LayoutProblem) -> np.ndarray | DesignGram:
    """(3N, 3N) Gram matrix of the centred gap-free training displacements (cached on the problem);
    a :class:`DesignGram` above :data:`GRAM_MAX_POINTS` points."""
    if "gram" not in problem.cache:
        design = _design(training_frames(problem)[0])
        problem.cache["gram"] = DesignGram(design) if frame_space(*design.shape[:1], problem.n_points) \
            else design.T @ design
    return problem.cache["gram"]


def gram_jitter(gram: np.ndarray | DesignGram) -> float:
    """The ridge added to a Gram block before solving: 1e-9 x its mean diagonal."""
    return 1e-9 * max(float(gram.trace()) / gram.shape[0], 1e-12)


def _blocks(points: np.ndarray) -> np.ndarray:
    """Column indices (3·len,) of the points' x, y, z columns."""
    return (3 * np.asarray(points, dtype=np.intp)[:, None] + np.arange(3)).ravel()


def pivoted_qr_layout(problem: LayoutProblem, count: int, *, seed: int = 0) -> np.ndarray:
    """``count`` points by column-pivoted QR of the centred displacements (sorted indices)."""
    cand = problem.candidate_points()
    _check(count, cand.size)
    chosen = problem.cached("qr-order", lambda: _pivot_order(problem, cand))[:count]
    if len(chosen) < count:  # fewer informative columns than points: pad deterministically
        chosen += [i for i in range(cand.size) if i not in set(chosen)][: count - len(chosen)]
    return np.sort(cand[np.array(chosen, dtype=np.intp)])


def _pivot_order(problem: LayoutProblem, cand: np.ndarray) -> list[int]:
    """Candidate positions in the order of the pivoted QR's first column of each (the same for
    every count: compare asks for several)."""
    cols = _blocks(cand)
    # Same pivots as QR of the tall design matrix (D = U·S with U orthonormal), on a square
    # factor S of its Gram matrix: 3N×3N instead of frames×3N.
    gram = training_gram(problem)
    if isinstance(gram, DesignGram):  # the design itself: (F, 3N), F < 3N
        square = gram.design[:, cols]
    else:
        vals, vecs = np.linalg.eigh(gram[np.ix_(cols, cols)])
        square = np.sqrt(np.maximum(vals, 0.0))[:, None] * vecs.T
    _, piv = sla.qr(square, pivoting=True, mode="r", check_finite=False)
    return list(dict.fromkeys(int(c) // 3 for c in piv))


def _residual_gram(gram: np.ndarray, chosen: Sequence[int], jitter: float) -> np.ndarray:
    """Gram of the residual after projecting out the chosen points' columns."""
    cols = _blocks(np.asarray(chosen, dtype=np.intp))
    if cols.size == 0:
        return gram.copy()
    g_sc = gram[cols]
    g_ss = gram[np.ix_(cols, cols)] + jitter * np.eye(cols.size)
    return gram - g_sc.T @ np.linalg.solve(g_ss, g_sc)


def _gains(resid: np.ndarray, jitter: float) -> np.ndarray:
    """(N,) residual variance of all columns that each point's block would explain."""
    n = resid.shape[0] // 3
    blocks = resid.reshape(3 * n, n, 3)
    cross = np.einsum("ian,iam->anm", blocks, blocks)  # Σ_i G[i,J]ᵀ G[i,J] per point
    at = np.arange(n)  # each point's own (3, 3) diagonal block, one gather
    own = resid.reshape(n, 3, n, 3)[at, :, at, :] + jitter * np.eye(3)
    return np.einsum("anm,amn->a", np.linalg.inv(own), cross)


def gains_given(gram: np.ndarray, chosen: Sequence[int], points: np.ndarray, jitter: float) -> np.ndarray:
    """(len(points),) what :func:`_gains` gives ``points`` after projecting out ``chosen``, from
    their residual columns only (O(3N·3L·3P) instead of the whole residual Gram matrix)."""
    if isinstance(gram, DesignGram):
        return gram.gains_given(chosen, points, jitter)
    cols_s, cols_p = _blocks(np.asarray(chosen, dtype=np.intp)), _blocks(points)
    resid = gram[:, cols_p]
    if cols_s.size:
        g_ss = gram[np.ix_(cols_s, cols_s)] + jitter * np.eye(cols_s.size)
        resid = resid - gram[:, cols_s] @ np.linalg.solve(g_ss, gram[np.ix_(cols_s, cols_p)])
    n_p = len(points)
    blocks = resid.reshape(resid.shape[0], n_p, 3)
    cross = np.einsum("ian,iam->anm", blocks, blocks)
    square = resid[cols_p].reshape(n_p, 3, n_p, 3)
    own = square[np.arange(n_p), :, np.arange(n_p), :] + jitter * np.eye(3)
    return np.einsum("anm,amn->a", np.linalg.inv(own), cross)


def greedy_layout(problem: LayoutProblem, count: int, *, fixed: Sequence[int] = (),
                  seed: int = 0) -> np.ndarray:
    """Greedy forward selection of ``count`` points (``fixed`` ones are kept and counted).

    The order of the picks does not depend on ``count``: it is kept per problem (and ``fixed``)
    and only extended, so layouts of several counts (compare's, the hybrid's) cost the largest
    one's picks, the same points as a selection of its own."""
    cand = problem.candidate_points()
    _check(count, cand.size)
    key = ("greedy-order", tuple(int(p) for p in fixed))
    if key not in problem.cache:
        problem.cache[key] = _GreedyOrder.start(problem, cand, fixed)
    order = problem.cache[key]
    order.extend(count)
    chosen = order.chosen[:max(count, len(fixed))]
    return np.sort(cand[np.array(chosen, dtype=np.intp)])


@dataclass(eq=False)
class _GreedyOrder:
    """The forward selection so far: candidate positions ``chosen`` in pick order, the residual
    Gram matrix after them and the jitter."""

    chosen: list[int]
    resid: np.ndarray
    jitter: float

    @classmethod
    def start(cls, problem: LayoutProblem, cand: np.ndarray, fixed: Sequence[int]) -> _GreedyOrder:
        cols = _blocks(cand)
        gram = training_gram(problem)[np.ix_(cols, cols)]
        jitter = gram_jitter(gram)
        pos = {int(p): i for i, p in enumerate(cand)}
        chosen = [pos[int(p)] for p in fixed]
        return cls(chosen, _residual_gram(gram, chosen, jitter), jitter)

    def extend(self, count: int) -> None:
        """Pick until ``count`` points are chosen."""
        while len(self.chosen) < count:
            gain = _gains(self.resid, self.jitter)
            gain[self.chosen] = -np.inf
            best = int(np.argmax(gain))
            cols = _blocks(np.array([best]))
            g_bc = self.resid[cols]
            self.resid = self.resid - g_bc.T @ np.linalg.solve(
                self.resid[np.ix_(cols, cols)] + self.jitter * np.eye(3), g_bc)
            self.chosen.append(best)


@dataclass(frozen=True, eq=False)
class CrossValidatedError:
    """Held-out error of the ridge reconstruction for any layout, from per-fold Gram matrices.

    Reproduces :func:`mocaptk.clustering.evaluation.heldout_errors` (same model, intercept, ridge,
    layout markers copied) on gap-free frames, at O((3L)²·3N) per layout instead of touching frames.
    """

    train_gram: tuple[np.ndarray | DesignGram, ...]   # centred on the training mean, (3N, 3N) each
    test_gram: tuple[np.ndarray | DesignGram, ...]    # test frames centred on the training mean
    n_test_points: int
    ridge: float

    @classmethod
    def from_displacements(cls, disp: np.ndarray, splits: Sequence[tuple[np.ndarray, np.ndarray]], *,
                           ridge: float = DEFAULT_RIDGE) -> CrossValidatedError:
        flat = disp.reshape(disp.shape[0], -1)
        if frame_space(flat.shape[0], disp.shape[1]):  # each fold's centred design, no (3N, 3N) matrix
            train_d, test_d = [], []
            for train, test in splits:
                mean = flat[train].mean(axis=0)
                train_d.append(DesignGram(flat[train] - mean))
                # an in-sample fold tests on the training design itself: its blocks are shared
                same = np.array_equal(train, test)
                test_d.append(train_d[-1] if same else DesignGram(flat[test] - mean))
            points = sum(test.size for _, test in splits) * disp.shape[1]
            return cls(tuple(train_d), tuple(test_d), points, float(ridge))
        total: tuple[np.ndarray, np.ndarray] | None = None
        train_g, test_g, points = [], [], 0
        for train, test in splits:
            test_sum, test_raw = flat[test].sum(axis=0), flat[test].T @ flat[test]
            if train.size + test.size == flat.shape[0]:
                # train statistics as total minus test (one pass over the frames for all folds)
                if total is None:
                    total = flat.sum(axis=0), flat.T @ flat
                train_sum, train_raw = total[0] - test_sum, total[1] - test_raw
            elif np.array_equal(train, test):  # an in-sample fit: the same sums, computed once
                train_sum, train_raw = test_sum, test_raw
            else:
                train_sum, train_raw = flat[train].sum(axis=0), flat[train].T @ flat[train]
            mean = train_sum / train.size
            train_g.append(train_raw - train.size * np.outer(mean, mean))
            cross = np.outer(test_sum, mean)
            test_g.append(test_raw - cross - cross.T + test.size * np.outer(mean, mean))
            points += test.size * disp.shape[1]
        return cls(tuple(train_g), tuple(test_g), points, float(ridge))

    def rmse(self, layout: Sequence[int] | np.ndarray) -> float:
        """Pooled held-out RMSE (mm) of reconstructing every point from ``layout``."""
        cols = _blocks(np.unique(np.asarray(layout, dtype=np.intp)))
        rest = np.setdiff1d(np.arange(self.train_gram[0].shape[0]), cols)
        total = 0.0
        for gram, test in zip(self.train_gram, self.test_gram):
            g_ss = gram[np.ix_(cols, cols)]
            lam = self.ridge * max(float(np.trace(g_ss)) / cols.size, 1e-12)
            coef = np.linalg.solve(g_ss + lam * np.eye(cols.size), gram[np.ix_(cols, rest)])
            t_sr = test[np.ix_(cols, rest)]
            total += (float(test.diagonal()[rest].sum())
                      + float(np.sum(coef * (test[np.ix_(cols, cols)] @ coef - 2.0 * t_sr))))
        return float(np.sqrt(max(total, 0.0) / self.n_test_points))


def training_frames(problem: LayoutProblem) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Gap-free training displacements (F', N, 3) and their cross-validation folds (cached on
    the problem: the Gram matrix, the local error and the cross-validation share them; read-only).

    Folds leave one take out when ≥ 3 takes keep frames, else 5 contiguous blocks.
    """
    if "training-frames" not in problem.cache:
        problem.cache["training-frames"] = _training_frames(problem)
    return problem.cache["training-frames"]


def _training_frames(problem: LayoutProblem) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    complete = np.isfinite(problem.displacements).all(axis=(1, 2))
    gappy = complete.sum() < 10
    if gappy:
        complete[:] = True
    kept = np.flatnonzero(complete)
    disp = problem.displacements[kept]
    if gappy:  # complete frames hold no NaN to set at rest
        disp = np.nan_to_num(disp, nan=0.0, copy=False)
    takes = []
    for i, (start, end) in enumerate(problem.segments):
        lo, hi = np.searchsorted(kept, [start, end])
        if hi > lo:
            takes.append(Take(f"take{i}", int(lo), int(hi)))
    if len(takes) >= 3:
        return disp, holdout_splits(len(kept), takes, split="takes")
    return disp, holdout_splits(len(kept), split="blocks", folds=5)


def cv_scorer(problem: LayoutProblem, *, ridge: float = DEFAULT_RIDGE) -> CrossValidatedError:
    """The cross-validated error of the problem's training frames (cached on the problem)."""
    key = f"cv-{ridge}"
    if key not in problem.cache:
        problem.cache[key] = CrossValidatedError.from_displacements(*training_frames(problem), ridge=ridge)
    return problem.cache[key]


def swap_refine(problem: LayoutProblem, layout: Sequence[int] | np.ndarray, *,
                fixed: Sequence[int] = (), candidates_per_swap: int = 8, max_passes: int = 3,
                ridge: float = DEFAULT_RIDGE) -> tuple[np.ndarray, float]:
    """Swap layout points for unused ones while the cross-validated RMSE drops.

    For each layout point, the ``candidates_per_swap`` unused points that would explain most of
    the residual left without it are tried; the best improving swap is kept (first-improvement per
    point, ``max_passes`` sweeps). ``fixed`` points never leave. Returns (sorted layout, CV RMSE mm).
    """
    scorer = cv_scorer(problem, ridge=ridge)
    gram = training_gram(problem)
    jitter = gram_jitter(gram)
    allowed = np.zeros(problem.n_points, dtype=bool)
    allowed[problem.candidate_points()] = True
    keep = {int(i) for i in fixed}

    def candidates(slot: int, current: list[int]) -> list[int]:
        if current[slot] in keep:
            return []
        others = current[:slot] + current[slot + 1:]
        gain = _gains(_residual_gram(gram, others, jitter), jitter)
        gain[~allowed] = -np.inf
        gain[current] = -np.inf
        order = np.argsort(-gain, kind="stable")[:candidates_per_swap]
        return [int(c) for c in order if np.isfinite(gain[c])]

    return swap_descent(layout, candidates, lambda layouts: [scorer.rmse(t) for t in layouts],
                        max_passes=max_passes)


def swap_descent(layout: Sequence[int] | np.ndarray,
                 candidates: Callable[[int, list[int]], Sequence[int]],
                 scores: Callable[[list[list[int]]], Sequence[float]], *,
                 max_passes: int) -> tuple[np.ndarray, float]:
    """First-improvement swap search: for each slot of the layout in turn, try the points
    ``candidates(slot, layout)`` (listed once per slot) in its place and keep every swap that
    lowers the score; repeat until a sweep improves nothing or ``max_passes`` sweeps.
    ``scores`` scores several layouts at once: a slot's trials differ from the layout at that
    slot only, whichever of them are kept, so they are scored together before the scan.
    Returns (sorted layout, its score)."""
    current = [int(i) for i in layout]
    best = scores([current])[0]
    for _ in range(max_passes):
        improved = False
        for slot in range(len(current)):
            trials = [current[:slot] + [int(cand)] + current[slot + 1:] for cand in candidates(slot, current)]
            for trial, value in zip(trials, scores(trials) if trials else []):
                if value < best - 1e-12:
                    best, current, improved = value, trial, True
        if not improved:
            break
    return np.sort(np.array(current, dtype=np.intp)), best


def _check(count: int, available: int) -> None:
    if not 1 <= count <= available:
        raise OptionError(f"layout size must be between 1 and {available} markers, got {count}")
