"""Hybrid layout: the paper's correlation clusters, refined and chosen for *local* reconstruction.

1. **Clusters as influence regions.** The paper's rule (factor by bisection to ``count`` clusters)
   splits the face into correlated groups; one marker per cluster keeps its structure (every
   correlated group is measured, which is what a rig's influence regions need).
2. **Reconstruction-aware representative per cluster.** Instead of the member with the largest
   displacement, each cluster keeps the member that explains most of *all* markers' motion given
   the other clusters' representatives (coordinate descent over clusters, until no
   representative changes). Skipped when the others' columns already span the few frames'
   design (:func:`spans_design`, e.g. 229 markers x 3 > 400 frames): the largest-displacement
   member is kept.
3. **Contenders.** The clustered layout, the thin-shell optimizer (Le et al.) started from it, the
   column-pivoted QR, the greedy and the k-means layouts; the thin-shell and k-means layouts also
   compete refined by swaps with spatial neighbours while their local error (below, 2 nearest
   markers) drops (with capture costs: refined with and without them).
4. **Choice by local reconstruction.** A training session moves one region at a time, a
   performance all of them: a layout judged by how well a *global* regression fits the training
   takes is rewarded for cross-region correlations the performance does not have (the previous
   choice, leave-one-take-out CV of the global model, picked such layouts). The contenders are
   compared by the local error instead — every point predicted only from its nearest one and two
   layout markers (:mod:`.local_fit`, mean of both), fitted on the training frames. Only
   training frames are used.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mocaptk.errors import OptionError

from .kmeans import kmeans_points
from .local_fit import LocalError, local_error
from .paper import paper_layout
from .problem import LayoutProblem
from .region_cover import cover_regions, region_groups
from .reconstruction import (GRAM_MAX_POINTS, DesignGram, gains_given, gram_jitter, greedy_layout,
                             pivoted_qr_layout, swap_descent, training_gram)


def cluster_representatives(problem: LayoutProblem, clusters: np.ndarray, start: np.ndarray, *,
                            max_passes: int = 5) -> np.ndarray:
    """Per cluster, the member that explains most of all markers' motion given the others.

    Coordinate descent over clusters on the training fit (block Gram–Schmidt gains, see
    :mod:`.reconstruction`) until no representative changes. ``clusters`` (N,) cluster id per
    point (-1: none); ``start`` (K,) one point per cluster. Returned as given (sorted) when the
    other representatives' 3(K-1) columns can span the centred (F, 3N) design, of rank <= F-1
    (frame-space Grams only, :func:`spans_design`): every member's residual is then rounding.
    """
    cand = problem.candidate_points()
    gram = training_gram(problem)
    if spans_design(gram, len(start) - 1):
        return np.sort(np.asarray(start, dtype=np.intp))
    jitter = gram_jitter(gram)
    allowed = np.zeros(problem.n_points, dtype=bool)
    allowed[cand] = True
    layout = [int(p) for p in start]
    changes, settled = 0, {}  # per slot: the change count its others had when it was last searched
    for _ in range(max_passes):
        changed = False
        for slot, rep in enumerate(list(layout)):
            if settled.get(slot) == changes:  # the same others as then: the same gains, no change
                continue
            others = layout[:slot] + layout[slot + 1:]
            members = np.flatnonzero((clusters == clusters[rep]) & allowed)
            members = members[~np.isin(members, others)]
            if clusters[rep] < 0 or members.size < 2:
                continue
            points = np.union1d(members, [rep])
            gain = dict(zip(points.tolist(), gains_given(gram, others, points, jitter).tolist()))
            best = int(members[np.argmax([gain[int(m)] for m in members])])
            if best != rep and gain[best] > gain[rep] * (1.0 + 1e-9):
                layout[slot] = best
                changed, changes = True, changes + 1
            settled[slot] = changes
        if not changed:
            break
    return np.sort(np.array(layout, dtype=np.intp))


def spans_design(gram: np.ndarray | DesignGram, points: int) -> bool:
    """Whether ``points`` points' 3 columns each can span a frame-space Gram's centred (F, 3N)
    design (rank <= F-1): gains given them are then ~1e-8 of a column, ranked by rounding
    (measured at 10,000 markers x 400 frames); False for a whole (3N, 3N) Gram."""
    return isinstance(gram, DesignGram) and 3 * points >= gram.design.shape[0] - 1


def local_swaps(problem: LayoutProblem, layout: np.ndarray, score: LocalError, *,
                neighbours: int = 6, max_passes: int = 4) -> tuple[np.ndarray, float]:
    """Swap layout points for one of their ``neighbours`` nearest unused points while the error drops.

    First improvement per point, ``max_passes`` sweeps. Returns (sorted layout, local RMSE mm).
    """
    allowed = np.zeros(problem.n_points, dtype=bool)
    allowed[problem.candidate_points()] = True
    near: dict[int, np.ndarray] = {}  # per layout point, all points nearest first (rows on demand)

    def candidates(slot: int, current: list[int]) -> list[int]:
        point = current[slot]
        if point not in near:
            near[point] = np.argsort(np.linalg.norm(problem.neutral[point] - problem.neutral, axis=1),
                                     kind="stable")
        free = allowed.copy()
        free[current] = False
        order = near[point]
        return order[free[order]][:neighbours].tolist()

    return swap_descent(layout, candidates, score.rmse_many, max_passes=max_passes)


#: The contender layouts of the hybrid and the ones also refined by local swaps.
CONTENDERS = ("clusters", "thin-shell", "qr", "greedy", "kmeans")
REFINED = ("thin-shell", "kmeans")


def hybrid_contenders(problem: LayoutProblem, count: int, *, seed: int = 0,
                      contenders: tuple[str, ...] = CONTENDERS) -> dict[str, np.ndarray]:
    """The unrefined contender layouts (sorted point indices) by name."""
    layouts: dict[str, np.ndarray] = {}
    large = problem.n_points > GRAM_MAX_POINTS  # thin-shell and greedy need whole (3N, 3N) matrices
    if "clusters" in contenders:
        try:
            paper = problem.cached(("paper", count, 5), lambda: paper_layout(problem, count, step=5))
        except OptionError:
            paper = None
        if paper is not None:
            clusters = paper.clusters.copy()
            kept = set(int(p) for p in paper.layout)
            # clusters of trimmed representatives join no region; their members stay unassigned
            for c, rep in enumerate(paper.representatives_in_order):
                if int(rep) not in kept:
                    clusters[clusters == c] = -1
            layouts["clusters"] = cluster_representatives(problem, clusters, paper.layout)
    if "thin-shell" in contenders and not large and problem.has_surface():
        from .thin_shell_layout import thin_shell_layout
        start = layouts.get("clusters")
        layouts["thin-shell"] = thin_shell_layout(problem, count, restarts=1, seed=seed,
                                                  initial=None if start is None else list(start)).layout
    if "qr" in contenders:
        layouts["qr"] = problem.cached(("qr", count), lambda: pivoted_qr_layout(problem, count))
    if "greedy" in contenders and not large:
        layouts["greedy"] = problem.cached(("greedy", count), lambda: greedy_layout(problem, count))
    if "kmeans" in contenders:
        layouts["kmeans"] = kmeans_points(problem, count, seed=seed)
    if not layouts:
        raise OptionError("no hybrid contender could produce a layout")
    return layouts


def hybrid_layout(problem: LayoutProblem, count: int, *, seed: int = 0,
                  contenders: tuple[str, ...] = CONTENDERS, refine: tuple[str, ...] = REFINED,
                  cover: bool = True) -> tuple[np.ndarray, dict[str, Any]]:
    """The hybrid layout of ``count`` points and the local error (mm) of every contender.

    The ``refine`` contenders also compete after :func:`local_swaps` (``<name>+local``; swaps
    judged with each point from its 2 nearest layout points); all are compared by the mean of
    the 1- and 2-nearest local errors (:func:`local_error`). With capture costs
    (``measured_error_mm``) the swaps and the choice charge them, and the camera-blind swaps
    (``<name>+blind-local``) compete as well, so the choice is never worse under the charged
    error than the camera-blind hybrid's (on the same candidates).

    With ``cover``, the winner then gets a marker in every region-side that moves on its own
    (:mod:`.region_cover`); the swaps are in ``details["region_cover"]`` (and its notes).
    """
    layouts = hybrid_contenders(problem, count, seed=seed, contenders=contenders)
    details: dict[str, Any] = {}
    if problem.n_points > GRAM_MAX_POINTS:
        skipped = [name for name in ("thin-shell", "greedy") if name in contenders] + \
            [name + "+local" for name in refine if name in layouts]
        refine = ()
        if skipped:
            details["notes"] = [f"hybrid: {problem.n_points} points (> {GRAM_MAX_POINTS}): contenders "
                                f"{', '.join(skipped)} skipped (they do not scale); chosen among "
                                f"{', '.join(sorted(layouts))}"]
    charged = problem.measured_error_mm is not None
    for name in refine:
        if name in layouts:
            start = layouts[name]
            layouts[name + "+local"] = local_swaps(problem, start, local_error(problem, scales=(2,)))[0]
            if charged:  # the camera-blind refinement competes too: the choice never scores worse than it
                layouts[name + "+blind-local"] = local_swaps(
                    problem, start, local_error(problem, scales=(2,), charged=False))[0]
    score = local_error(problem, scales=(1, 2))
    scores = {name: score.rmse(layout) for name, layout in layouts.items()}
    winner = min(sorted(scores), key=lambda n: scores[n])
    layout = layouts[winner]
    if cover:
        layout, swaps = cover_regions(problem, layout, region_groups(problem))
        if swaps:
            details["region_cover"] = [s.as_dict(problem.labels) for s in swaps]
            details["notes"] = details.get("notes", []) + [s.note(problem.labels) for s in swaps]
    return layout, {"winner": winner, "local_rmse_mm": scores, **details}
