"""Hybrid layout: the paper's correlation clusters, made reconstruction-aware, against pivoted QR.

1. **Clusters as influence regions.** The paper's rule (factor by bisection to ``count`` clusters)
   splits the face into correlated groups; one marker per cluster keeps its structure (every
   correlated group is measured, which is what a rig's influence regions need).
2. **Reconstruction-aware representative per cluster.** Instead of the member with the largest
   displacement, each cluster keeps the member that explains most of *all* markers' motion given
   the other clusters' representatives (coordinate descent over clusters, until no
   representative changes).
3. **Clusters initialize the thin-shell optimizer** (Le et al.; one start from the clustered
   layout): its spatially smooth model generalizes where regression-chosen layouts overfit
   the training takes.
4. **Choice by cross-validation.** The clustered layout, the thin-shell layout, the column-pivoted
   QR and the greedy layouts compete; the one with the lowest cross-validated error on the training
   takes (leave one take out, the team's ridge model) wins. Only training frames are used.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ...errors import OptionError
from .paper import paper_layout
from .problem import LayoutProblem
from .reconstruction import (_gains, _residual_gram, cv_scorer, greedy_layout, pivoted_qr_layout,
                             training_gram)


def cluster_representatives(problem: LayoutProblem, clusters: np.ndarray, start: np.ndarray, *,
                            max_passes: int = 5) -> np.ndarray:
    """Per cluster, the member that explains most of all markers' motion given the others.

    Coordinate descent over clusters on the training fit (block Gram–Schmidt gains, see
    :mod:`.reconstruction`) until no representative changes. ``clusters`` (N,) cluster id per
    point (-1: none); ``start`` (K,) one point per cluster.
    """
    cand = problem.candidate_points()
    gram = training_gram(problem)
    jitter = 1e-9 * max(float(np.trace(gram)) / gram.shape[0], 1e-12)
    allowed = np.zeros(problem.n_points, dtype=bool)
    allowed[cand] = True
    layout = [int(p) for p in start]
    for _ in range(max_passes):
        changed = False
        for slot, rep in enumerate(list(layout)):
            others = layout[:slot] + layout[slot + 1:]
            members = np.flatnonzero((clusters == clusters[rep]) & allowed)
            members = members[~np.isin(members, others)]
            if clusters[rep] < 0 or members.size < 2:
                continue
            gain = _gains(_residual_gram(gram, others, jitter), jitter)
            best = int(members[np.argmax(gain[members])])
            if best != rep and gain[best] > gain[rep] * (1.0 + 1e-9):
                layout[slot] = best
                changed = True
        if not changed:
            break
    return np.sort(np.array(layout, dtype=np.intp))


def hybrid_layout(problem: LayoutProblem, count: int, *, seed: int = 0,
                  contenders: tuple[str, ...] = ("clusters", "thin-shell", "qr", "greedy")
                  ) -> tuple[np.ndarray, dict[str, Any]]:
    """The hybrid layout of ``count`` points and how each contender scored (CV RMSE, mm)."""
    scorer = cv_scorer(problem)
    scores: dict[str, float] = {}
    layouts: dict[str, np.ndarray] = {}
    if "clusters" in contenders:
        try:
            paper = paper_layout(problem, count)
        except OptionError:
            paper = None
        if paper is not None:
            clusters = paper.clusters.copy()
            kept = set(int(p) for p in paper.layout)
            # clusters of trimmed representatives join no region; their members stay unassigned
            for k, rep in enumerate(paper.representatives_in_order):
                if int(rep) not in kept:
                    clusters[clusters == k] = -1
            layouts["clusters"] = cluster_representatives(problem, clusters, paper.layout)
            scores["clusters"] = scorer.rmse(layouts["clusters"])
    if "thin-shell" in contenders and problem.n_points <= 2000:
        from .thin_shell_layout import thin_shell_layout
        start = layouts.get("clusters")
        layouts["thin-shell"] = thin_shell_layout(problem, count, restarts=1, seed=seed,
                                                  initial=None if start is None else list(start)).layout
        scores["thin-shell"] = scorer.rmse(layouts["thin-shell"])
    if "qr" in contenders:
        layouts["qr"] = pivoted_qr_layout(problem, count)
        scores["qr"] = scorer.rmse(layouts["qr"])
    if "greedy" in contenders:
        layouts["greedy"] = greedy_layout(problem, count)
        scores["greedy"] = scorer.rmse(layouts["greedy"])
    if not layouts:
        raise OptionError("no hybrid contender could produce a layout")
    winner = min(sorted(scores), key=lambda k: scores[k])
    return layouts[winner], {"winner": winner, "cv_rmse_mm": scores}
