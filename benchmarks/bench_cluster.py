"""Benchmark: consolidated correlation + threshold clustering of one region.

Target (issue 4): 10,000 markers x 400 sampled frames in < 30 s and < 4 GB peak memory.
Baseline in the same run: a naive implementation (per-pair ``np.corrcoef`` per axis, Python loops
for clustering and reassignment) on a smaller region, compared with the vectorized code on the
same data, as a speed ratio. Run: ``python benchmarks/bench_cluster.py [--markers 10000]``.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from mocaptk.clustering.correlation import consolidated_correlation, mean_off_diagonal
from mocaptk.clustering.threshold import cluster_region


def synthetic_region(n_markers: int, n_frames: int, *, groups: int, seed: int = 0) -> np.ndarray:
    """(frames, markers, 3) mm: markers in ``groups`` groups driven by shared smooth signals + noise."""
    rng = np.random.default_rng(seed)
    signals = rng.normal(size=(n_frames, groups, 3)).cumsum(axis=0)
    group = rng.integers(groups, size=n_markers)
    pos = signals[:, group] * rng.uniform(0.5, 1.5, size=(1, n_markers, 1))
    pos += rng.normal(scale=0.5, size=pos.shape)
    return pos


def naive_cluster(pos: np.ndarray, factor: float) -> int:
    """Reference: pairwise np.corrcoef and Python loops (what a first implementation looks like)."""
    n = pos.shape[1]
    matrix = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            matrix[i, j] = sum(np.corrcoef(pos[:, i, a], pos[:, j, a])[0, 1] for a in range(3))
    mean = (matrix.sum() - np.trace(matrix)) / (n * (n - 1))
    disp = np.linalg.norm(pos - np.median(pos, axis=0), axis=2).max(axis=0)
    order = sorted(range(n), key=lambda k: -disp[k])
    cluster_of = [-1] * n
    reps = []
    for r in order:
        if cluster_of[r] >= 0:
            continue
        cluster_of[r] = len(reps)
        for j in range(n):
            if cluster_of[j] < 0 and matrix[r, j] >= factor * mean:
                cluster_of[j] = len(reps)
        reps.append(r)
    for j in range(n):
        if j not in reps:
            cluster_of[j] = max(range(len(reps)), key=lambda k: matrix[reps[k], j])
    return len(reps)


def vectorized_cluster(pos: np.ndarray, factor: float) -> int:
    corr = consolidated_correlation(pos)
    disp = np.linalg.norm(pos - np.median(pos, axis=0), axis=2).max(axis=0)
    return len(cluster_region(corr.matrix, disp, factor=factor).representatives)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markers", type=int, default=10_000)
    parser.add_argument("--frames", type=int, default=400)
    parser.add_argument("--baseline-markers", type=int, default=150)
    args = parser.parse_args()

    small = synthetic_region(args.baseline_markers, args.frames, groups=15, seed=1)
    t0 = time.perf_counter()
    naive_count = naive_cluster(small, 1.1)
    t_naive = time.perf_counter() - t0
    t0 = time.perf_counter()
    fast_count = vectorized_cluster(small, 1.1)
    t_fast = time.perf_counter() - t0
    print(f"baseline (naive pairwise corrcoef + loops), {args.baseline_markers} markers x {args.frames} frames: "
          f"{t_naive:.2f} s; vectorized: {t_fast:.4f} s; speed-up x{t_naive / t_fast:.0f}; "
          f"same layout size: {naive_count == fast_count} ({naive_count})")

    big = synthetic_region(args.markers, args.frames, groups=400, seed=2)
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    corr = consolidated_correlation(big)
    t_corr = time.perf_counter() - t0
    disp = np.linalg.norm(big - np.median(big, axis=0), axis=2).max(axis=0)
    t0 = time.perf_counter()
    result = cluster_region(corr.matrix, disp, factor=1.1)
    t_cluster = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    t0, c0 = time.perf_counter(), time.process_time()  # worst case: every marker a representative
    worst = cluster_region(corr.matrix, disp, factor=3.5 / mean_off_diagonal(corr.matrix))
    t_worst, c_worst = time.perf_counter() - t0, time.process_time() - c0
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    total = t_corr + t_cluster
    print(f"{args.markers} markers x {args.frames} sampled frames: correlation {t_corr:.2f} s, "
          f"clustering + reassignment {t_cluster:.2f} s, total {total:.2f} s wall, {cpu:.2f} s CPU "
          f"(target < 30 s); "
          f"peak RSS {peak_gb:.2f} GB (target < 4 GB); mean C {mean_off_diagonal(corr.matrix):.3f}, "
          f"{len(result.representatives)} representatives; worst case ({len(worst.representatives)} "
          f"representatives) clustering {t_worst:.2f} s wall, {c_worst:.2f} s CPU")
    print("(wall times on a shared, loaded machine can far exceed CPU time; CPU time counts all threads)")
    print("PASS" if total < 30 and peak_gb < 4 else "FAIL")


if __name__ == "__main__":
    main()
