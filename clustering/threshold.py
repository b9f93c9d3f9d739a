"""Threshold clustering of one region (Will, De Martino & Bezerra) and the final reassignment.

Member rule (see docs/method.md): marker j joins representative r when ``C[r, j] >= tau`` with
``tau = factor * mean off-diagonal C`` of the region; representatives are taken in order of
decreasing displacement (ties: lower index first).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocaptk.errors import OptionError

from .correlation import mean_off_diagonal

#: Columns per block in the reassignment (bounds memory for very large regions).
_BLOCK = 2048


@dataclass(frozen=True)
class RegionClusters:
    """Clusters of one region; indices refer to the region's markers.

    ``representatives`` (K,) in creation order; ``assignment`` (M,) cluster number (index into
    ``representatives``) after reassignment; ``first_assignment`` (M,) before it;
    ``member_correlation`` (M,) ``C[representative, j]`` of each marker's final cluster.
    """

    representatives: np.ndarray
    assignment: np.ndarray
    first_assignment: np.ndarray
    member_correlation: np.ndarray
    mean_correlation: float
    threshold: float
    max_correlation: float  # largest off-diagonal C (NaN for one marker)

    @property
    def moved(self) -> int:
        """Markers the reassignment moved to another representative."""
        return int((self.assignment != self.first_assignment).sum())

    @property
    def unreachable(self) -> bool:
        """The threshold is at or above every correlation: each marker is its own cluster."""
        return bool(self.threshold >= self.max_correlation)

    def clustering_factor(self) -> float:
        """The largest factor (3 decimals) whose threshold some pair still reaches (NaN if none)."""
        if not (self.mean_correlation > 0 and np.isfinite(self.max_correlation)):
            return float("nan")
        return float(np.floor(self.max_correlation / self.mean_correlation * 1000.0) / 1000.0)


def keep_representatives(matrix: np.ndarray, clusters: RegionClusters, keep: int) -> RegionClusters:
    """``clusters`` with only its first ``keep`` representatives (creation order); the members of
    the dropped ones join the kept representative they correlate with most (ties: created first)."""
    if keep >= clusters.representatives.size:
        return clusters
    if keep < 1:
        raise OptionError("a region must keep at least one representative")
    reps = clusters.representatives[:keep]
    assignment = clusters.assignment.copy()
    moved = assignment >= keep
    assignment[moved] = np.argmax(matrix[np.ix_(reps, np.flatnonzero(moved))], axis=0)
    member_corr = matrix[reps[assignment], np.arange(matrix.shape[0])]
    return RegionClusters(reps, assignment, clusters.first_assignment, member_corr,
                          clusters.mean_correlation, clusters.threshold, clusters.max_correlation)


def threshold_clusters(matrix: np.ndarray, displacement: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """First pass: (representatives (K,), assignment (M,)) by the threshold rule."""
    n = matrix.shape[0]
    remaining = np.argsort(-np.asarray(displacement, dtype=np.float64), kind="stable")  # unclustered, in order
    assignment = np.full(n, -1, dtype=np.intp)
    representatives: list[int] = []
    while remaining.size:
        rep = remaining[0]
        joins = matrix[rep, remaining] >= threshold  # only unclustered markers are compared
        joins[0] = True
        assignment[remaining[joins]] = len(representatives)
        representatives.append(int(rep))
        remaining = remaining[~joins]
    return np.array(representatives, dtype=np.intp), assignment


def reassign(matrix: np.ndarray, representatives: np.ndarray, assignment: np.ndarray) -> np.ndarray:
    """Move every non-representative to the representative it correlates with most.

    A marker stays where it is when its current representative ties for the best.
    """
    out = assignment.copy()
    members = np.setdiff1d(np.arange(matrix.shape[0]), representatives)  # representatives stay put
    for lo in range(0, members.size, _BLOCK):
        cols = members[lo:lo + _BLOCK]
        corr = matrix[np.ix_(representatives, cols)]  # (K, B)
        best = corr.argmax(axis=0)
        current = corr[assignment[cols], np.arange(cols.size)]
        keep = current >= corr[best, np.arange(cols.size)]
        out[cols] = np.where(keep, assignment[cols], best)
    return out


def max_off_diagonal(matrix: np.ndarray) -> float:
    """Largest off-diagonal entry of a square matrix (in row blocks: no full copy)."""
    n = matrix.shape[0]
    largest = -np.inf
    for lo in range(0, n, _BLOCK):
        block = np.array(matrix[lo:lo + _BLOCK], dtype=np.float64)
        rows = np.arange(block.shape[0])
        block[rows, lo + rows] = -np.inf
        largest = max(largest, float(block.max()))
    return largest


def region_statistics(matrix: np.ndarray) -> tuple[float, float]:
    """(mean, largest) off-diagonal correlation of a region (NaN, NaN for one marker): what
    :func:`cluster_region` needs whatever the factor (a factor search computes them once)."""
    if matrix.shape[0] < 2:
        return float("nan"), float("nan")
    return mean_off_diagonal(matrix), max_off_diagonal(matrix)


def cluster_region(matrix: np.ndarray, displacement: np.ndarray, *, factor: float,
                   statistics: tuple[float, float] | None = None) -> RegionClusters:
    """Threshold clustering followed by reassignment.

    Parameters
    ----------
    matrix : (M, M) float
        Consolidated correlation of the region's markers.
    displacement : (M,) float, mm
        Largest displacement of each marker (picks the representatives).
    factor : float
        Refinement factor (> 0); threshold = factor × mean off-diagonal correlation.
    statistics : (float, float), optional
        :func:`region_statistics` of ``matrix`` when the caller has them.
    """
    if not factor > 0:
        raise OptionError(f"refinement factor must be > 0, got {factor}")
    n = matrix.shape[0]
    mean, largest = region_statistics(matrix) if statistics is None else statistics
    threshold = factor * mean if n > 1 else float("nan")
    reps, first = threshold_clusters(matrix, displacement, threshold if n > 1 else np.inf)
    final = reassign(matrix, reps, first)
    member_corr = matrix[reps[final], np.arange(n)]
    return RegionClusters(reps, final, first, member_corr, mean, threshold, largest)
