"""The paper's correlation-clustered layout (Will, De Martino & Bezerra) as a layout method.

Wraps :mod:`mocaptk.clustering.threshold` per region. The paper's knob is the refinement factor;
to compare methods at equal marker counts the factor is found by bisection (the number of
representatives grows with the factor, stepwise). When no factor gives exactly ``count``, the
smallest layout above it is trimmed by dropping the representatives created last (the paper
creates them in order of decreasing displacement, so the least-moving go first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocaptk.errors import OptionError

from ..correlation import consolidated_correlation
from ..neutral import max_displacement
from ..threshold import cluster_region, region_statistics
from .problem import LayoutProblem, problem_regions


@dataclass(frozen=True)
class PaperLayout:
    """Representatives (sorted point indices), the factor used and every point's cluster."""

    layout: np.ndarray
    factor: float
    clusters: np.ndarray  # (N,) index into ``representatives_in_order``, -1 = in no region
    representatives_in_order: np.ndarray  # creation order (largest displacement first per region)


def _regions(problem: LayoutProblem) -> list[np.ndarray]:
    return [np.asarray(v, dtype=np.intp) for _, v in sorted(problem_regions(problem).items()) if len(v)]


@dataclass(frozen=True)
class _RegionData:
    points: np.ndarray  # (M,) point indices
    matrix: np.ndarray  # (M, M) consolidated correlation
    displacement: np.ndarray  # (M,) largest displacement, mm
    statistics: tuple[float, float]  # region_statistics of matrix (the same for every factor)


def _region_data(problem: LayoutProblem, step: int) -> list[_RegionData]:
    positions = problem.positions
    sampled = positions[::step] if positions.shape[0] >= 3 * step else positions
    disp = max_displacement(positions, problem.neutral)
    matrices = [(idx, consolidated_correlation(sampled[:, idx]).matrix) for idx in _regions(problem)]
    return [_RegionData(idx, matrix, disp[idx], region_statistics(matrix)) for idx, matrix in matrices]


def correlation_clusters(problem: LayoutProblem, *, factor: float, step: int = 5,
                         regions: list[_RegionData] | None = None) -> PaperLayout:
    """The paper's clusters of every region at ``factor`` (frames sampled every ``step``)."""
    clusters = np.full(problem.n_points, -1, dtype=np.intp)
    reps: list[int] = []
    order: list[tuple[int, float, int]] = []  # (creation in region, -displacement, rep) for trimming
    for region in regions if regions is not None else _region_data(problem, step):
        idx, disp = region.points, region.displacement
        result = cluster_region(region.matrix, disp, factor=factor, statistics=region.statistics)
        for k, rep in enumerate(result.representatives):
            clusters[idx[result.assignment == k]] = len(reps)
            order.append((k, -float(disp[rep]), len(reps)))
            reps.append(int(idx[rep]))
    ranked = np.array([reps[i] for _, _, i in sorted(order)], dtype=np.intp)
    return PaperLayout(np.sort(np.array(reps, dtype=np.intp)), float(factor), clusters, ranked)


def paper_layout(problem: LayoutProblem, count: int | None = None, *, factor: float | None = None,
                 step: int = 5, seed: int = 0) -> PaperLayout:
    """The paper's layout at ``factor``, or at the factor (bisection) that gives ``count`` markers."""
    if count is None:
        return correlation_clusters(problem, factor=1.1 if factor is None else factor, step=step)
    if not 1 <= count <= problem.n_points:
        raise OptionError(f"layout size must be between 1 and {problem.n_points}, got {count}")
    # correlations depend on neither the factor nor the count: once per problem (compare asks 4 counts)
    regions = problem.cached(("paper-regions", step), lambda: _region_data(problem, step))
    lo, hi = 1e-3, 1.0
    result_hi = correlation_clusters(problem, factor=hi, regions=regions)
    while result_hi.layout.size < count and hi < 64:
        lo, hi = hi, hi * 2.0
        result_hi = correlation_clusters(problem, factor=hi, regions=regions)
    for _ in range(40):
        if result_hi.layout.size == count or hi - lo < 1e-6:
            break
        mid = 0.5 * (lo + hi)
        result = correlation_clusters(problem, factor=mid, regions=regions)
        if result.layout.size >= count:
            hi, result_hi = mid, result
        else:
            lo = mid
    if result_hi.layout.size < count:
        raise OptionError(f"the correlation rule cannot give {count} markers "
                          f"(at most {result_hi.layout.size} here)")
    # trim: keep the representatives created first (per region, largest displacement first)
    keep = result_hi.representatives_in_order[:count]
    return PaperLayout(np.sort(keep), result_hi.factor, result_hi.clusters,
                       result_hi.representatives_in_order)
