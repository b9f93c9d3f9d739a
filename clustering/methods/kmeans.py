"""The k-means layout of a :class:`LayoutProblem`, shared by the ``kmeans`` method and the hybrid's
contenders so it is computed once per problem, count and seed."""

from __future__ import annotations

import numpy as np

from ..baselines import kmeans_layout
from .problem import LayoutProblem


def kmeans_points(problem: LayoutProblem, count: int, *, seed: int = 0) -> np.ndarray:
    """The k-means layout (sorted point indices), computed once per problem, count and seed."""
    def compute() -> np.ndarray:
        cand = problem.candidate_points()
        # every point a candidate (sorted, unique): the displacements themselves, no (F, N, 3) copy
        disp = problem.displacements if cand.size == problem.n_points else problem.displacements[:, cand]
        return np.sort(cand[kmeans_layout(disp, count, seed=seed)])
    return problem.cached(("kmeans", count, seed), compute)
