"""Robust layout: the hybrid layout, moved until losing any one marker costs least.

Studios lose markers mid-shoot. The score is the worst case over the layout's markers of the
hybrid's local error (:mod:`.local_fit`, 1 and 2 nearest markers) when that marker is lost,
on the training frames only. Each step looks at the marker whose loss hurts most and tries moving
one of its nearest layout neighbours onto one of the unused points nearest to it (a backup for
that area); the best such move is kept while the worst case drops.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .hybrid import hybrid_layout, local_error
from .local_fit import LocalError
from .problem import LayoutProblem


def worst_lost(score: LocalError, layout: np.ndarray) -> tuple[float, int]:
    """(local RMSE mm with the worst marker lost, its slot in the sorted ``layout``)."""
    if layout.size < 2:
        return float("inf"), 0
    lost = score.rmse_many([np.delete(layout, i) for i in range(layout.size)])
    slot = int(np.argmax(lost))
    return float(lost[slot]), slot


def robust_layout(problem: LayoutProblem, count: int, *, seed: int = 0, steps: int = 8,
                  neighbours: int = 6) -> tuple[np.ndarray, dict[str, Any]]:
    """``count`` points: the hybrid layout improved for its worst single lost marker.

    ``steps``: at most this many accepted moves; ``neighbours``: layout neighbours of the worst
    marker that may move, and unused points near it they may move to.
    """
    layout, hybrid = hybrid_layout(problem, count, seed=seed)
    score = local_error(problem, scales=(1, 2))
    allowed = np.zeros(problem.n_points, dtype=bool)
    allowed[problem.candidate_points()] = True
    worst, slot = worst_lost(score, layout)
    start = worst
    for _ in range(steps):
        lost_point = problem.neutral[layout[slot]]
        order = np.argsort(np.linalg.norm(problem.neutral[layout] - lost_point, axis=1), kind="stable")
        movers = [int(s) for s in order if s != slot][:neighbours]
        free = allowed.copy()
        free[layout] = False
        spots = np.flatnonzero(free)
        spots = spots[np.argsort(np.linalg.norm(problem.neutral[spots] - lost_point, axis=1), kind="stable")]
        best = (worst, None)
        for mover in movers:
            for spot in spots[:neighbours]:
                trial = np.sort(np.append(np.delete(layout, mover), spot))
                value, trial_slot = worst_lost(score, trial)
                if value < best[0] - 1e-12:
                    best = (value, (trial, trial_slot))
        if best[1] is None:
            break
        worst, (layout, slot) = best[0], best[1]
    return layout, {"hybrid_winner": hybrid["winner"], "worst_lost_local_rmse_mm": {"hybrid": start, "robust": worst},
                    "local_rmse_mm": score.rmse(layout)}
