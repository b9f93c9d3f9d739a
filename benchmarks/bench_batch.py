"""Benchmark: ``mocaptk batch`` on a 2-worker local cluster vs the serial command in a shell loop.

Sessions "like the sample": every one of the sample's 139 markers and its 6 per-region takes, each
take cut to ``--frames`` frames at a different offset per session (the full sample, 6,841 frames,
costs ~12 CPU-s per session; ``--frames 0`` uses whole takes). Both sides run
``cluster --formats none`` on the same files; their outputs are compared byte for byte.

Reported: wall time of the serial loop (``mocaptk cluster`` once per session, as a studio's shell
loop does), of ``mocaptk batch --workers 2`` (cluster start included), the ratio; the per-session
CPU cost (user + sys of the serial children) for the farm projection, and batch's CPU (the
sessions' own CPU in the runners, from batch.json, plus the batch process tree that was reaped); the scheduler's own cost per
task (2-worker LocalCluster, 400 empty tasks submitted and gathered, per task), and batch's whole
per-session overhead (a re-run in which every session is skipped: hashing, runner round trip).
The machine's load average is printed before and after: timings on a shared machine are only
comparable within one run.

Run: ``python benchmarks/bench_batch.py [--sessions 40] [--frames 200]``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"
MOCAPTK = [sys.executable, "-m", "mocaptk"]


def make_sessions(folder: Path, count: int, frames: int) -> list[Path]:
    """``count`` sessions from the sample: every take cut to ``frames`` frames, offset per session."""
    from mocaptk.acquisition.formats import read_trajectories, write_trajectories
    from mocaptk.trajectories import concatenate_takes

    traj = read_trajectories(SAMPLE)
    paths = []
    for k in range(count):
        parts = []
        for take in traj.takes:
            length = take.end - take.start
            size = min(frames, length) if frames else length
            start = (k * 23) % max(length - size, 1) if size < length else 0
            parts.append(traj.frames(take.start + start, take.start + start + size))
        session = concatenate_takes(parts, names=[t.name for t in traj.takes], regions=[t.region for t in traj.takes])
        paths.append(write_trajectories(session, folder / f"session_{k:03d}.c3d"))
    return paths


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def scheduler_overhead_ms(tasks: int = 400) -> float:
    """Milliseconds per task of submitting, running and gathering empty tasks on 2 local workers."""
    import logging

    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                      silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
        client.gather(client.map(abs, range(-20, 0), pure=False))  # warm the connections
        start = time.perf_counter()
        client.gather(client.map(abs, range(tasks), pure=False))
        return 1000 * (time.perf_counter() - start) / tasks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sessions", type=int, default=40)
    parser.add_argument("--frames", type=int, default=200, help="frames per take (0: whole takes)")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} (2 cores, shared)")
    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        root = Path(tmp)
        (root / "sessions").mkdir()
        paths = make_sessions(root / "sessions", args.sessions, args.frames)
        print(f"{len(paths)} sessions, 139 markers, 6 takes x {args.frames or 'all'} frames")

        cpu0, start = children_cpu(), time.perf_counter()
        for path in paths:
            subprocess.run([*MOCAPTK, "cluster", str(path), "--formats", "none", "--quiet",
                            "--out", str(root / "serial" / path.stem)], check=True, stderr=subprocess.DEVNULL)
        serial = time.perf_counter() - start
        cpu_per_session = (children_cpu() - cpu0) / len(paths)
        print(f"serial loop: {serial:.1f} s ({serial / len(paths):.2f} s/session wall, "
              f"{cpu_per_session:.2f} CPU-s/session)  load {os.getloadavg()[0]:.1f}")

        batch_line = [*MOCAPTK, "batch", str(root / "sessions" / "*.c3d"), "--do", "cluster", "--formats", "none",
                      "--out", str(root / "batch"), "--workers", "2", "--quiet"]
        cpu0, start = children_cpu(), time.perf_counter()
        subprocess.run(batch_line, check=True)
        batch = time.perf_counter() - start
        reaped = children_cpu() - cpu0  # client + workers; runners die with their worker, unreaped
        runners = sum(r["cpu_seconds"] for r in json.loads((root / "batch" / "batch.json").read_text())["sessions"])
        print(f"batch, 2 workers: {batch:.1f} s ({batch / len(paths):.2f} s/session wall, "
              f"{runners / len(paths):.2f} CPU-s/session in the runners, {reaped:.1f} CPU-s in client + "
              f"workers)  load {os.getloadavg()[0]:.1f}")
        print(f"ratio serial / batch: {serial / batch:.2f}x")

        for path in paths:
            a, b = root / "serial" / path.stem, root / "batch" / path.stem
            assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir()), path.stem
            assert all((a / p.name).read_bytes() == (b / p.name).read_bytes() for p in a.iterdir()), path.stem
        print("outputs: batch == serial, byte for byte, for every session")

        start = time.perf_counter()
        subprocess.run(batch_line, check=True)
        rerun = time.perf_counter() - start
        records = json.loads((root / "batch" / "batch.json").read_text())["sessions"]
        assert all(r["status"] == "skipped" for r in records)
        print(f"re-run, all {len(records)} skipped: {rerun:.1f} s (cluster start + hashing + runner round trips)")
    print(f"scheduler overhead: {scheduler_overhead_ms():.2f} ms per task (2 local workers, empty tasks)")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
