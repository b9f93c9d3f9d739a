"""Benchmark: cleaning and text I/O speed, each against a named baseline in the same run.

* head-pose fit: mocaptk's batched weighted Kabsch (one SVD call for all frames) vs a per-frame
  Python loop of ``numpy.linalg.svd`` (the straightforward implementation), same data and result;
* gap filling on the bundled facial sample: ``fill_gaps`` (auto) time, and the neighbour method vs
  cubic splines on held-out 0.5 s gaps (RMSE vs the noise-free truth);
* Nexus CSV read: mocaptk vs ``csv`` module + ``float()`` per cell (the naive reader).

CPU seconds (``time.process_time``) are printed next to wall seconds: on a busy machine the CPU
ratio is the reliable one.

    python benchmarks/bench_cleaning.py [--frames 20000] [--folder /work/scratch/bench_cleaning]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mocaptk import Trajectories
from mocaptk.acquisition.formats import read_trajectories, write_trajectories
from mocaptk.acquisition.gapfill import fill_gaps, held_out_errors, held_out_gaps
from mocaptk.acquisition.stabilize import kabsch

REPO = Path(__file__).resolve().parents[1]


def timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def loop_kabsch(reference, moving, weights):
    rots = np.full((len(moving), 3, 3), np.nan)
    for f in range(len(moving)):
        w = weights[f] > 0
        if w.sum() < 3:
            continue
        a, b = reference[w], moving[f, w]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        rots[f] = vt.T @ np.diag([1, 1, d]) @ u.T
    return rots


def naive_csv(path):
    rows = list(csv.reader(open(path, newline="")))
    return np.array([[float(c) if c else np.nan for c in row[2:]] for row in rows[5:]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20000)
    parser.add_argument("--folder", type=Path, default=Path("/work/scratch/bench_cleaning"))
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    ref = rng.normal(0, 50, (6, 3))
    rot = Rotation.random(args.frames, random_state=1).as_matrix()
    moving = np.einsum("fij,mj->fmi", rot, ref) + rng.normal(0, 0.1, (args.frames, 6, 3))
    weights = (rng.random((args.frames, 6)) > 0.1).astype(float)
    (batched, _), wall_b, cpu_b = timed(kabsch, ref, moving, weights)
    loop, wall_l, cpu_l = timed(loop_kabsch, ref, moving, weights)
    same = np.allclose(np.nan_to_num(batched), np.nan_to_num(loop), atol=1e-9)
    print(f"head-pose fit, {args.frames} frames x 6 markers: batched {wall_b:.3f} s wall / {cpu_b:.3f} s CPU, "
          f"per-frame loop {wall_l:.3f} s / {cpu_l:.3f} s -> {cpu_l / cpu_b:.1f}x (CPU); same result: {same}")

    from mocaptk.acquisition.synth_session import load_ground_truth

    sample = read_trajectories(REPO / "sample_c3d" / "dense_halfface_performance.c3d")
    truth = load_ground_truth(REPO / "sample_c3d" / "dense_halfface_performance_truth.npz").positions
    session, holes = held_out_gaps(sample, rng=rng)
    for method, max_gap in (("cubic", 1000), ("neighbours", 10), ("auto", 10)):
        (filled, report), wall, cpu = timed(fill_gaps, session, max_gap=max_gap, method=method)
        err = held_out_errors(filled.positions, truth, holes)
        print(f"fill_gaps {method:10s} facial sample ({sample.n_markers} markers x {sample.n_frames} frames, "
              f"{len(report.records)} gaps): {wall:.2f} s wall / {cpu:.2f} s CPU; held-out 30-frame gaps RMSE "
              f"{np.sqrt(np.mean(err ** 2)):.3f} mm")

    args.folder.mkdir(parents=True, exist_ok=True)
    big = args.folder / "session.csv"
    positions = rng.normal(0, 100, (12000, 150, 3))
    positions[rng.random((12000, 150)) < 0.02] = np.nan
    write_trajectories(Trajectories(positions, [f"S:M{i:03d}" for i in range(150)], 120.0), big)
    ours, wall_o, cpu_o = timed(read_trajectories, big)
    naive, wall_n, cpu_n = timed(naive_csv, big)
    same = np.allclose(ours.positions.reshape(len(naive), -1), naive, equal_nan=True)
    print(f"Nexus CSV read, 12000 frames x 150 markers ({big.stat().st_size / 1e6:.0f} MB): mocaptk {wall_o:.2f} s / "
          f"{cpu_o:.2f} s CPU, csv+float() {wall_n:.2f} s / {cpu_n:.2f} s -> {cpu_n / cpu_o:.1f}x (CPU); "
          f"same values: {same}")


if __name__ == "__main__":
    main()
