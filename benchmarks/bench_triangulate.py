"""Benchmark: mocaptk triangulation vs a per-point SVD loop and aniposelib, same data.

8-camera room rig, markers all around a head-sized ellipsoid (visibility from surface
normals, so each marker is seen by the 2-6 cameras it faces),
0.5 px detection noise; without and with 5 % ghost views (mislabels / reflections).
Prints points/s and RMSE (mm) against ground truth, and speed ratios vs the baselines.

    python benchmarks/bench_triangulate.py [--frames 500] [--markers 200]

Every method gets the same (C, P, 2) detections and returns (P, 3) points. mocaptk does the
most work per point: undistortion, DLT + one reweighting step, per-view reprojection errors,
the outlier consensus, the residual (RMS reprojection error in the distorted image) and view
counts. Its kernel is compiled by numba (cached on disk; the first call is reported
separately, then it is timed warm) and runs on one thread per CPU; the 1-thread row
(``numba.set_num_threads(1)``) shows the serial speed. The per-point loop undistorts the seen
detections with ``cv2.undistortPoints`` and solves one SVD per point. Our two rows and aniposelib's take turns in each of ``--repeat``
rounds (the fastest round counts), so load changes on a shared machine hit them alike.

aniposelib (``pip install aniposelib``) is a benchmark-only dependency. Since 0.8 its
``CameraGroup.triangulate`` undistorts every entry with ``cv2.undistortPoints`` and solves a
JAX-vectorized SVD per point (no residuals, no outlier handling; timed after JIT warm-up); earlier
releases looped over points in Python (numba-compiled SVD): pass ``--legacy-aniposelib DIR``
(e.g. after ``pip install --no-deps --target DIR aniposelib==0.5.1``) to time that one too.
That loop and the exhaustive outlier search ``triangulate_ransac`` (loops over points and
camera subsets) are timed on the first ``--slow-points`` points.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import cv2
import numba
import numpy as np

from mocaptk.acquisition.cameras import CameraRig, room_rig
from mocaptk.acquisition.projection import ellipsoid_markers, project_markers
from mocaptk.acquisition.triangulate import triangulate


def per_point_loop(rig: CameraRig, observations: np.ndarray) -> np.ndarray:
    """Baseline (a): undistort per camera, then one DLT SVD per point in a Python loop."""
    n_cams, n_points, _ = observations.shape
    rays = np.full(observations.shape, np.nan)
    for c, cam in enumerate(rig):
        seen = np.isfinite(observations[c, :, 0])
        if not seen.any():
            continue
        rays[c, seen] = cv2.undistortPoints(observations[c, seen].reshape(-1, 1, 2), cam.matrix,
                                            cam.distortion).reshape(-1, 2)
    poses = [np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig]
    out = np.full((n_points, 3), np.nan)
    for p in range(n_points):
        rows = []
        for c in range(n_cams):
            u, v = rays[c, p]
            if np.isfinite(u):
                rows.append(u * poses[c][2] - poses[c][0])
                rows.append(v * poses[c][2] - poses[c][1])
        if len(rows) >= 4:
            vh = np.linalg.svd(np.array(rows))[2]
            out[p] = vh[-1, :3] / vh[-1, 3]
    return out


def aniposelib_group(rig: CameraRig, module):
    Camera, CameraGroup = module.cameras.Camera, module.cameras.CameraGroup
    return CameraGroup([Camera(matrix=cam.matrix, dist=cam.distortion, size=cam.image_size,
                               rvec=cam.rvec, tvec=cam.tvec, name=cam.name) for cam in rig])


def load_aniposelib(folder: str | None):
    """The installed aniposelib, or the copy in ``folder`` under another module name."""
    if folder is None:
        import aniposelib
        import aniposelib.cameras  # noqa: F401

        return aniposelib
    init = Path(folder) / "aniposelib" / "__init__.py"
    spec = importlib.util.spec_from_file_location("aniposelib_legacy", init,
                                                  submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["aniposelib_legacy"] = module
    spec.loader.exec_module(module)
    importlib.import_module("aniposelib_legacy.cameras")
    return module


def settle(quiet: float = 0.02, limit: float = 2.0) -> None:
    """Return once this process's threads have used < 1 ms of CPU over ``quiet`` s (at most
    ``limit`` s): aniposelib's JAX goes on working in its own threads after a call returns
    (measured: 7-21 ms of system time in our next 13 ms call), which would land in the next
    method's timing instead of its own."""
    end = time.perf_counter() + limit
    while time.perf_counter() < end:
        before = time.process_time()
        time.sleep(quiet)
        if time.process_time() - before < 1e-3:
            return


def timed_together(functions: dict, repeat: int = 1) -> dict:
    """For each named function: its result, fastest wall time and fastest CPU time (all
    threads of this process, including the work its call leaves running in the background
    until the process is quiet again), s. The functions take turns in every round, so a change
    of load on a shared machine hits all of them alike; the CPU time is the steadier measure.
    """
    best = {name: [None, np.inf, np.inf] for name in functions}
    for _ in range(repeat):
        for name, function in functions.items():
            settle()
            wall, cpu = time.perf_counter(), time.process_time()
            entry = best[name]
            entry[0] = function()
            entry[1] = min(entry[1], time.perf_counter() - wall)
            settle()
            entry[2] = min(entry[2], time.process_time() - cpu)
    return {name: (result, (wall, cpu)) for name, (result, wall, cpu) in best.items()}


def timed(function, repeat: int = 1):
    """Result, fastest wall time and fastest CPU time of one function, s."""
    return timed_together({"": function}, repeat)[""]


def accuracy(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float, float, float]:
    """RMSE and median error (mm) over solved points, fraction of solved points off by
    more than 5 mm, fraction of points solved."""
    err = np.linalg.norm(estimate - truth, axis=-1)
    solved = np.isfinite(err)
    return (float(np.sqrt(np.mean(err[solved] ** 2))), float(np.median(err[solved])),
            float(np.mean(err[solved] > 5.0)), float(solved.mean()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--markers", type=int, default=200)
    parser.add_argument("--slow-points", type=int, default=1000,
                        help="points given to the slow per-point baselines (rate extrapolated)")
    parser.add_argument("--repeat", type=int, default=5,
                        help="rounds of the fast methods (ours, aniposelib), taking turns; "
                             "the fastest counts (shared machines)")
    parser.add_argument("--legacy-aniposelib", metavar="DIR",
                        help="folder holding an older aniposelib package to time as well")
    args = parser.parse_args()

    rig = room_rig(n_cameras=8)
    truth, normals = ellipsoid_markers(args.frames, args.markers, seed=0)  # all around the head
    flat_truth = truth.reshape(-1, 3)
    n_points = flat_truth.shape[0]
    # first of all: the kernel is compiled or loaded from numba's cache (as in a `mocaptk` run)
    first = time.perf_counter()
    triangulate(rig, np.full((len(rig), 1, 1, 2), np.nan))
    threads = numba.get_num_threads()
    print(f"mocaptk first call in this process (kernel compile, or load from numba's cache): "
          f"{time.perf_counter() - first:.1f} s, not timed below; {threads} threads")
    try:
        current = load_aniposelib(None)
        group = aniposelib_group(rig, current)
        print(f"aniposelib {getattr(current, '__version__', '?')}")
    except ImportError:
        group = None
        print("aniposelib is not installed (pip install aniposelib): its rows are skipped")
    legacy = None
    if args.legacy_aniposelib:
        legacy_module = load_aniposelib(args.legacy_aniposelib)
        legacy = aniposelib_group(rig, legacy_module)
        print(f"legacy aniposelib {getattr(legacy_module, '__version__', '?')} "
              f"from {args.legacy_aniposelib}")

    print(f"{len(rig)} cameras, {n_points} points, 0.5 px noise; "
          f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n")
    print("| data | method | points/s (wall) | points/CPU-s | RMSE mm | median mm | > 5 mm | solved "
          "| ours faster (wall / CPU) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    summary = []
    for ghost_rate in (0.0, 0.05):
        obs = project_markers(rig, truth, normals=normals, pixel_noise=0.5,
                              ghost_rate=ghost_rate, rng=1)
        flat = obs.reshape(len(rig), -1, 2)
        data = "clean" if ghost_rate == 0 else "5 % ghosts"
        def one_thread():
            numba.set_num_threads(1)
            try:
                return triangulate(rig, obs).positions.reshape(-1, 3)
            finally:
                numba.set_num_threads(threads)

        fast = {f"mocaptk triangulate (robust, {threads} threads)":
                lambda: triangulate(rig, obs).positions.reshape(-1, 3),
                "mocaptk triangulate (robust, 1 thread)": one_thread}
        if group is not None:
            group.triangulate(flat[:, :1000])  # JAX compiles on first use; not timed
            fast["aniposelib triangulate"] = lambda: group.triangulate(flat)
        fast = timed_together(fast, repeat=args.repeat)
        rows = [(name, result, seconds, n_points) for name, (result, seconds) in fast.items()]
        ours, t_ours = rows[0][1], rows[0][2]
        loop, t_loop = timed(lambda: per_point_loop(rig, flat))
        rows.insert(2, ("per-point SVD loop", loop, t_loop, n_points))
        if legacy is not None:
            legacy.triangulate(flat[:, :100])  # numba compiles on first use; not timed
            old, t_old = timed(lambda: legacy.triangulate(flat[:, :args.slow_points]))
            rows.append(("legacy aniposelib triangulate (per-point loop, subset)", old, t_old,
                         args.slow_points))
        if group is not None and ghost_rate > 0:
            ransac, t_ransac = timed(lambda: group.triangulate_ransac(flat[:, :args.slow_points]))
            if isinstance(ransac, tuple):
                ransac = ransac[0]
            rows.append(("aniposelib triangulate_ransac (subset)",
                         np.asarray(ransac).reshape(-1, 3), t_ransac, args.slow_points))
            rows.append(("mocaptk triangulate, same subset (accuracy only)", ours,
                         (np.nan, np.nan), args.slow_points))
        ours_rates = n_points / np.array(t_ours)
        for name, estimate, seconds, count in rows:
            error, median, gross, solved = accuracy(estimate[:count], flat_truth[:count])
            rates = count / np.array(seconds)
            ratio = ("—" if name.startswith("mocaptk")
                     else " / ".join(f"{r:.1f}×" for r in ours_rates / rates))
            shown = ["—" if np.isnan(r) else f"{r:,.0f}" for r in rates]
            print(f"| {data} | {name} | {shown[0]} | {shown[1]} | {error:.3f} | {median:.3f} "
                  f"| {gross:.2%} | {solved:.1%} | {ratio} |")
            summary.append((data, name, ours_rates / rates, error))
    print(f"\nload average after: {os.getloadavg()[0]:.1f}. Issue targets (wall / CPU ratios; "
          "RMSE mm ours vs theirs):")
    for data in ("clean", "5 % ghosts"):
        ours_rmse = next(e for d, n, _, e in summary if d == data and n.startswith("mocaptk"))
        for baseline, target in (("aniposelib triangulate", 20), ("per-point SVD loop", 5)):
            found = [(r, e) for d, n, r, e in summary if d == data and n == baseline]
            if found:
                (wall, cpu), rmse = found[0]
                speed = {(True, True): "met (wall and CPU time)",
                         (True, False): "met in wall time only",
                         (False, True): "met in CPU time only",
                         (False, False): "NOT met"}[wall >= target, cpu >= target]
                verdict = speed if ours_rmse <= rmse else "NOT met (RMSE)"
                print(f"  {data}: >= {target}x {baseline}: {wall:.1f}x / {cpu:.1f}x, RMSE "
                      f"{ours_rmse:.3f} vs {rmse:.3f} -> {verdict}")

if __name__ == "__main__":
    main()
