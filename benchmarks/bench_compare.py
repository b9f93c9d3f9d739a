"""Benchmark: ``compare``'s leave-one-take-out scoring, BLAS threads limited vs free, same run.

``compare_methods`` scores every layout of every fold by thousands of small solves (the held-out
reconstruction and, per layout marker, the layout without it). With BLAS free to start a thread
per core those solves contend on a busy machine; ``compare_methods`` now runs with one BLAS thread
(as ``select_layout`` and ``evaluate``'s lost-marker scores already did). Baseline in the same
run: the same function with BLAS threads free (``compare_methods.__wrapped__``, the code before).
Both must give the same rows. CPU seconds are this process's own (all its threads).

    python benchmarks/bench_compare.py [--counts 40,60] [--methods farthest-point,qr] [--repeat 1]

The whole command (``mocaptk compare sample_c3d/dense_halfface.c3d``, issue 17 goal ≤ 120 s)
is timed with ``/usr/bin/time -v``; see docs/performance.md.
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from pathlib import Path

import numpy as np

SAMPLE = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def timed(function, *args, **kwargs):
    wall, cpu = time.perf_counter(), cpu_seconds()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - wall, cpu_seconds() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", default="40,60")
    parser.add_argument("--methods", default="farthest-point,qr")
    parser.add_argument("--repeat", type=int, default=1, help="rounds, limited and free taking turns")
    args = parser.parse_args()

    from mocaptk.clustering.compare import compare_methods
    from mocaptk.clustering.pipeline import load_session_and_test

    session, _, _ = load_session_and_test(SAMPLE, None, stabilized=True, rate=None, units=None, rigid=None)
    counts = [int(c) for c in args.counts.split(",")]
    methods = [m.strip() for m in args.methods.split(",")]
    print(f"{SAMPLE.name}: {session.n_markers} markers x {session.n_frames} frames, {len(session.takes)} takes; "
          f"methods {', '.join(methods)}, counts {args.counts}; load {os.getloadavg()[0]:.1f}")
    best: dict[str, tuple[float, float]] = {}
    rows: dict[str, list] = {}
    for _ in range(args.repeat):
        for name, function in (("1 BLAS thread (compare_methods)", compare_methods),
                               ("BLAS threads free (baseline, the code before)", compare_methods.__wrapped__)):
            rows[name], wall, cpu = timed(function, session, counts=counts, methods=methods)
            best[name] = min(best.get(name, (np.inf, np.inf)), (wall, cpu))
    ours, base = best.values()
    print("| scoring | wall s | CPU s |\n|---|---:|---:|")
    for name, (wall, cpu) in best.items():
        print(f"| {name} | {wall:.1f} | {cpu:.1f} |")
    print(f"baseline / ours: {base[0] / ours[0]:.1f}x wall, {base[1] / ours[1]:.1f}x CPU; "
          f"load {os.getloadavg()[0]:.1f} at the end")
    first, second = rows.values()
    same = all(a.method == b.method and a.count == b.count and np.array_equal(a.layout, b.layout)
               and np.isclose(a.rmse_mm, b.rmse_mm, rtol=1e-9) and np.isclose(a.p95_mm, b.p95_mm, rtol=1e-9)
               and np.isclose(a.lost_rmse_mm, b.lost_rmse_mm, rtol=1e-9) for a, b in zip(first, second))
    print("rows equal (layouts exactly, errors to 1e-9):", same and len(first) == len(second))


if __name__ == "__main__":
    main()
