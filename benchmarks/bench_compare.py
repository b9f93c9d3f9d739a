"""Benchmark: ``compare``'s leave-one-take-out scoring, BLAS threads limited vs free, same run.

``compare_methods`` scores every layout of every fold by thousands of small solves (the held-out
reconstruction and, per layout marker, the layout without it). With BLAS free to start a thread
per core those solves contend on a busy machine; ``compare_methods`` now runs with one BLAS thread
(as ``select_layout`` and ``evaluate``'s lost-marker scores already did). Baseline in the same
run: the same function with BLAS threads free (``compare_methods.__wrapped__``, the code before).
Both must give the same rows. CPU seconds are this process's own (all its threads).

    python benchmarks/bench_compare.py [--counts 40,60] [--methods farthest-point,qr] [--repeat 1]
    python benchmarks/bench_compare.py --lost 60   # lost-marker scores: downdates vs a refit per marker
    python benchmarks/bench_compare.py --thin-shell  # thin-shell optimizer: blocks kept per layout
    python benchmarks/bench_compare.py --report      # report.html's held-out errors: shared moments
    python benchmarks/bench_compare.py --orders      # greedy / QR layouts: pick orders kept per problem

``--thin-shell``: the thin-shell optimizer as compare runs it (20/30/40/60 markers, 3 restarts,
on the whole session and two leave-one-take-out folds) with each layout's blocks kept for the
sweep (``WᵀX``, ``WᵀW``, and the system and projections from which each unit's trial moves take
their base's rows and columns), against the baseline in the same run, the same solver looking
every base's entries up anew (``_computed_base``, the code before), and, for reference, keeping
nothing (:class:`_Unkept`, products recomputed for every unit); all must give the same layouts,
training RMSE and solve counts.

``--report``: report.html's per-row held-out errors (the session's frames with gaps, every
take left out once) for 32 layouts (8 random per count 20/30/40/60, as compare's rows), from one
``RidgeMoments`` per training set (``heldout_errors_of_layouts``) against the baseline in the same
run, ``heldout_errors`` per layout (per-pattern fits over every training frame, the code before);
both must agree to 1e-8 mm.

``--orders``: the greedy and pivoted-QR layouts at compare's counts 20/30/40/60 on the whole
session and two leave-one-take-out folds, the pick orders kept per problem and extended (greedy's
forward selection, QR's pivots: neither depends on the count), against the baseline in the same
run, each count selected from scratch (the kept orders dropped before every call, the code before;
the training Gram stays shared, as before); both must give the same layouts.

``--lost L``: the worst-lost-marker scores of a random L-marker layout on every leave-one-take-out
fold, by ``lost_marker_rmse`` (one eigendecomposition per fold, a rank-3 downdate per marker)
against the baseline in the same run, a ridge refit per lost marker (``CrossValidatedError.rmse``
of each reduced layout, the code before); both must agree to 1e-9.

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


def lost_marker_bench(session, count: int) -> None:
    """Lost-marker scores on every fold: downdates against a refit per marker, same run."""
    from threadpoolctl import threadpool_limits

    from mocaptk.clustering.evaluation import holdout_splits
    from mocaptk.clustering.lost_marker import heldout_folds, lost_marker_rmse

    layout = np.sort(np.random.default_rng(0).choice(session.n_markers, count, replace=False))
    folds = [heldout_folds(session.positions, [f]) for f in holdout_splits(session.n_frames, session.takes,
                                                                             split="takes")]
    with threadpool_limits(limits=1, user_api="blas"):  # as compare_methods runs them
        new, wall, cpu = timed(lambda: [lost_marker_rmse(f, layout) for f in folds])
        old, base_wall, base_cpu = timed(lambda: [np.array([f.rmse(np.delete(layout, i)) for i in range(count)])
                                                  for f in folds])
    print(f"lost-marker scores, {count} markers x {len(folds)} folds | wall s | CPU s |\n|---|---:|---:|")
    print(f"| downdates (lost_marker_rmse) | {wall:.2f} | {cpu:.2f} |\n| refit per marker (baseline) | "
          f"{base_wall:.2f} | {base_cpu:.2f} |")
    worst = max(float(np.max(np.abs(a - b) / b)) for a, b in zip(new, old))
    print(f"baseline / ours: {base_wall / wall:.1f}x wall, {base_cpu / cpu:.1f}x CPU; largest relative "
          f"difference {worst:.1e} (equal to 1e-9: {worst < 1e-9}); load {os.getloadavg()[0]:.1f}")


class _Unkept(dict):
    """A per-layout memo that keeps nothing (the baseline: recomputed for every unit)."""

    def __setitem__(self, key, value) -> None:
        pass


def thin_shell_bench(session) -> None:
    """thin_shell_layout on compare's problems: per-layout blocks kept vs recomputed, same run."""
    from mocaptk.clustering.compare import _problem
    from mocaptk.clustering.evaluation import holdout_splits
    from mocaptk.clustering.methods.thin_shell_layout import ThinShellWeights, thin_shell_layout

    folds = holdout_splits(session.n_frames, session.takes, split="takes")[:2]
    problems = [_problem(session.positions, session, None, {})]
    problems += [_problem(session.positions, session, train, {}) for train, _ in folds]

    def run():
        return [thin_shell_layout(p, count, restarts=3) for p in problems for count in (20, 30, 40, 60)]

    run()  # factorizations and compressed data cached per problem, outside the timings
    reset, base_blocks = ThinShellWeights._reset, ThinShellWeights._base_blocks

    def unkept(self) -> None:
        reset(self)
        self._layouts = _Unkept()

    timings = {"blocks kept per layout": timed(run)}
    ThinShellWeights._base_blocks = lambda self, markers, keep, base: self._computed_base(base)
    try:
        timings["each base's blocks looked up anew (baseline, the code before)"] = timed(run)
        ThinShellWeights._reset = unkept
        timings["nothing kept per layout (before 87fe59c)"] = timed(run)
    finally:
        ThinShellWeights._reset, ThinShellWeights._base_blocks = reset, base_blocks
    print(f"thin-shell optimizer, {len(problems)} problems x 4 counts x 3 restarts | wall s | CPU s |\n|---|---:|---:|")
    for name, (_, wall, cpu) in timings.items():
        print(f"| {name} | {wall:.2f} | {cpu:.2f} |")
    (ours, wall, cpu), (base, base_wall, base_cpu), (none, _, _) = timings.values()
    same = all(np.array_equal(a.layout, b.layout) and a.rmse_mm == b.rmse_mm and a.solves == b.solves
               for other in (base, none) for a, b in zip(ours, other))
    print(f"baseline / ours: {base_wall / wall:.2f}x wall, {base_cpu / cpu:.2f}x CPU; same layouts, RMSE "
          f"and solves: {same}; load {os.getloadavg()[0]:.1f}")


def orders_bench(session) -> None:
    """Greedy and QR layouts of compare's counts: pick orders kept per problem vs from scratch, same run."""
    from mocaptk.clustering.compare import _problem
    from mocaptk.clustering.evaluation import holdout_splits
    from mocaptk.clustering.methods.reconstruction import greedy_layout, pivoted_qr_layout, training_gram

    folds = holdout_splits(session.n_frames, session.takes, split="takes")[:2]
    problems = [_problem(session.positions, session, None, {})]
    problems += [_problem(session.positions, session, train, {}) for train, _ in folds]
    for problem in problems:
        training_gram(problem)  # shared before and after the change: outside the timings

    def run(kept: bool):
        out = []
        for problem in problems:
            for count in (20, 30, 40, 60):
                if not kept or count == 20:
                    problem.cache.pop(("greedy-order", ()), None)
                    problem.cache.pop("qr-order", None)
                out.append((greedy_layout(problem, count), pivoted_qr_layout(problem, count)))
        return out

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):  # as select_layout runs them
        ours, wall, cpu = timed(run, True)
        base, base_wall, base_cpu = timed(run, False)
    print(f"greedy + QR layouts, {len(problems)} problems x 4 counts | wall s | CPU s |\n|---|---:|---:|")
    print(f"| pick orders kept per problem | {wall:.2f} | {cpu:.2f} |\n| each count from scratch (baseline) | "
          f"{base_wall:.2f} | {base_cpu:.2f} |")
    same = all(np.array_equal(a, b) for pair, other in zip(ours, base) for a, b in zip(pair, other))
    print(f"baseline / ours: {base_wall / wall:.2f}x wall, {base_cpu / cpu:.2f}x CPU; same layouts: {same}; "
          f"load {os.getloadavg()[0]:.1f}")


def report_bench(session) -> None:
    """The report's per-row held-out errors: shared moments vs per-layout fits, same run."""
    from threadpoolctl import threadpool_limits

    from mocaptk.clustering.evaluation import heldout_errors, heldout_errors_of_layouts, holdout_splits

    rng = np.random.default_rng(0)
    layouts = [np.sort(rng.choice(session.n_markers, c, replace=False)) for c in (20, 30, 40, 60) for _ in range(8)]
    splits = holdout_splits(session.n_frames, session.takes, split="takes")
    with threadpool_limits(limits=1):  # as write_compare_report runs them
        ours, wall, cpu = timed(lambda: list(heldout_errors_of_layouts(session.positions, layouts, splits)))
        base, base_wall, base_cpu = timed(lambda: [heldout_errors(session.positions, l, splits) for l in layouts])
    print(f"report held-out errors, {len(layouts)} layouts x {len(splits)} folds | wall s | CPU s |\n|---|---:|---:|")
    print(f"| one RidgeMoments per fold (heldout_errors_of_layouts) | {wall:.2f} | {cpu:.2f} |\n"
          f"| per-layout fits (heldout_errors, baseline) | {base_wall:.2f} | {base_cpu:.2f} |")
    worst = max(float(np.nanmax(np.abs(a - b))) for a, b in zip(ours, base))
    print(f"baseline / ours: {base_wall / wall:.1f}x wall, {base_cpu / cpu:.1f}x CPU; largest difference "
          f"{worst:.1e} mm (within 1e-8: {worst < 1e-8}); load {os.getloadavg()[0]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", default="40,60")
    parser.add_argument("--methods", default="farthest-point,qr")
    parser.add_argument("--repeat", type=int, default=1, help="rounds, limited and free taking turns")
    parser.add_argument("--lost", type=int, default=0, metavar="L",
                        help="only the lost-marker benchmark, at L markers")
    parser.add_argument("--thin-shell", action="store_true",
                        help="only the thin-shell optimizer: per-layout blocks kept vs recomputed")
    parser.add_argument("--orders", action="store_true",
                        help="only the greedy and QR layouts: pick orders kept per problem vs from scratch")
    parser.add_argument("--report", action="store_true",
                        help="only report.html's per-row held-out errors: shared moments vs per-layout fits")
    args = parser.parse_args()

    from mocaptk.clustering.compare import compare_methods
    from mocaptk.clustering.pipeline import load_session_and_test

    session, _, _ = load_session_and_test(SAMPLE, None, stabilized=True, rate=None, units=None, rigid=None)
    if args.lost:
        return lost_marker_bench(session, args.lost)
    if args.thin_shell:
        return thin_shell_bench(session)
    if args.report:
        return report_bench(session)
    if args.orders:
        return orders_bench(session)
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
