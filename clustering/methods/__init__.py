"""Layout methods side by side: one interface, dense data → layout of ``count`` points.

>>> result = select_layout(problem, 30, method="hybrid")   # doctest: +SKIP
>>> result.layout                                          # sorted point indices

Every method takes a :class:`LayoutProblem` (training displacements from neutral, neutral
positions, optional surface mesh / regions / mirror map) and returns a :class:`LayoutResult`.
See ``docs/layout-methods.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocaptk.errors import OptionError

from ..baselines import farthest_point_layout, random_layout
from .kmeans import kmeans_points
from .problem import LayoutProblem, layout_problem


@dataclass(frozen=True)
class LayoutResult:
    """A layout: sorted point indices, the method that chose it, run time (s) and details."""

    layout: np.ndarray
    method: str
    seconds: float
    details: dict[str, Any] = field(default_factory=dict)


MethodFunction = Callable[..., tuple[np.ndarray, dict[str, Any]]]


def _random(problem: LayoutProblem, count: int, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    cand = problem.candidate_points()
    return cand[random_layout(cand.size, count, seed=seed)], {}


def _farthest_point(problem: LayoutProblem, count: int, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    cand = problem.candidate_points()
    return cand[farthest_point_layout(problem.neutral[cand], count)], {}


def _kmeans(problem: LayoutProblem, count: int, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    return kmeans_points(problem, count, seed=seed), {}


def _paper(problem: LayoutProblem, count: int, *, seed: int = 0, step: int = 5) -> tuple[np.ndarray, dict]:
    from .paper import paper_layout
    result = problem.cached(("paper", count, step), lambda: paper_layout(problem, count, step=step))
    return result.layout, {"factor": result.factor}


def _qr(problem: LayoutProblem, count: int, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    from .reconstruction import pivoted_qr_layout
    return problem.cached(("qr", count), lambda: pivoted_qr_layout(problem, count)), {}


def _greedy(problem: LayoutProblem, count: int, *, seed: int = 0, swap: bool = False,
            candidates_per_swap: int = 8) -> tuple[np.ndarray, dict]:
    from .reconstruction import greedy_layout, swap_refine
    layout = problem.cached(("greedy", count), lambda: greedy_layout(problem, count))
    if not swap:
        return layout, {}
    refined, cv = swap_refine(problem, layout, candidates_per_swap=candidates_per_swap)
    return refined, {"cv_rmse_mm": cv, "swapped": int(np.setdiff1d(refined, layout).size)}


def _thin_shell(problem: LayoutProblem, count: int, *, seed: int = 0, iterations: int = 10,
                restarts: int = 10, symmetric: bool = False, border_markers: int = 0,
                verify: bool = True) -> tuple[np.ndarray, dict]:
    from .thin_shell_layout import thin_shell_layout
    result = thin_shell_layout(problem, count, iterations=iterations, restarts=restarts, seed=seed,
                               symmetric=symmetric, border_markers=border_markers, verify=verify)
    return result.layout, {"train_rmse_mm": result.rmse_mm, "sweeps": result.iterations,
                           "moves": result.moves, "solves": result.solves}


def _set_cover(problem: LayoutProblem, count: int, *, seed: int = 0, epsilon: float = 0.3,
               symmetric: bool = False) -> tuple[np.ndarray, dict]:
    from .set_cover import set_cover_layout
    result = set_cover_layout(problem, count, epsilon=epsilon, symmetric=symmetric)
    return result.layout, {"covers": result.covers, "status": result.status, "epsilon": epsilon}


def _hybrid(problem: LayoutProblem, count: int, *, seed: int = 0, **options: Any) -> tuple[np.ndarray, dict]:
    from .hybrid import hybrid_layout
    return hybrid_layout(problem, count, seed=seed, **options)


def _robust(problem: LayoutProblem, count: int, *, seed: int = 0, **options: Any) -> tuple[np.ndarray, dict]:
    from .robust import robust_layout
    return robust_layout(problem, count, seed=seed, **options)


#: name → method; every method: ``(problem, count, *, seed, **options) -> (layout, details)``.
LAYOUT_METHODS: dict[str, MethodFunction] = {
    "paper": _paper,
    "random": _random,
    "farthest-point": _farthest_point,
    "kmeans": _kmeans,
    "qr": _qr,
    "greedy": _greedy,
    "thin-shell": _thin_shell,
    "set-cover": _set_cover,
    "hybrid": _hybrid,
    "robust": _robust,
}


def method_names() -> list[str]:
    """Registered method names (the paper's rule first)."""
    return list(LAYOUT_METHODS)


def select_layout(problem: LayoutProblem, count: int, *, method: str = "hybrid", seed: int = 0,
                  **options: Any) -> LayoutResult:
    """Choose ``count`` points of ``problem`` with ``method`` (see :func:`method_names`)."""
    if method not in LAYOUT_METHODS:
        raise OptionError(f"unknown layout method {method!r} (choose from {', '.join(LAYOUT_METHODS)})")
    cand = problem.candidate_points()
    if not 1 <= count <= cand.size:
        raise OptionError(f"layout size must be between 1 and {cand.size} markers, got {count}")
    from mocaptk.threads import one_thread

    started = time.perf_counter()
    # many small dense products: BLAS threads only contend (measured 26x slower on 2 busy cores)
    with one_thread():
        layout, details = LAYOUT_METHODS[method](problem, count, seed=seed, **options)
    layout = np.sort(np.asarray(layout, dtype=np.intp))
    if layout.size != np.unique(layout).size:  # a method bug, not a user error
        raise AssertionError(f"{method} returned duplicate points")
    return LayoutResult(layout, method, time.perf_counter() - started, details)


__all__ = ["LAYOUT_METHODS", "LayoutProblem", "LayoutResult", "layout_problem", "method_names",
           "select_layout"]
