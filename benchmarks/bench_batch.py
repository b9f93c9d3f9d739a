"""Benchmark: ``mocaptk batch`` on a 2-worker local cluster vs the serial command in a shell loop.

Sessions "like the sample": every one of the sample's 139 markers and its 6 per-region takes, each
take cut to ``--frames`` frames at a different offset per session (the full sample, 6,841 frames,
costs ~12 CPU-s per session; ``--frames 0`` uses whole takes). Both sides run
``cluster --formats none`` on the same files; their outputs are compared byte for byte.

Reported: wall time of the serial loop (``mocaptk cluster`` once per session, as a studio's shell
loop does), of ``mocaptk batch --workers 2`` (cluster start included), the ratio; CPU beside wall:
the serial children's user + sys per session, and batch's (the whole process tree: client,
scheduler, workers, runners, all reaped) against the sessions' own CPU in the runners (from
batch.json): the difference per session is batch's per-session CPU overhead. Also: a re-run in
which every session is skipped (wall per session: hashing, runner round trip), and the scheduler's
own cost per task (2-worker LocalCluster, 400 empty tasks). The load average is printed before
and after: timings on a shared machine are only comparable within one run.

``--faults``: the fault campaign instead (tests/batch_faults.py): a ``dask scheduler`` + 2
``dask worker`` processes, a clean batch for reference, then 3 batches in which one worker is
SIGKILLed and 3 that are Ctrl-C'd (SIGINT), each at a random moment once sessions run; after each,
files hashed on return and 10 s later, attempts, outputs vs the clean run, runner processes left.

Run: ``python benchmarks/bench_batch.py [--sessions 24] [--frames 200] [--faults] [--seed 31]``.
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


def fault_campaign(count: int, frames: int, seed: int) -> None:
    """3 worker kills and 3 Ctrl-C at random moments on a 2-worker ``dask scheduler`` farm."""
    import random

    sys.path.insert(0, str(REPO / "tests"))
    import batch_faults as faults

    rng = random.Random(seed)
    with tempfile.TemporaryDirectory(prefix="bench_batch_faults_") as tmp:
        root = Path(tmp)
        (root / "sessions").mkdir()
        paths = [str(p) for p in make_sessions(root / "sessions", count, frames)]
        with faults.dask_farm(root) as farm:
            start = time.perf_counter()
            subprocess.run([*MOCAPTK, "batch", *paths, "--do", "cluster", "--formats", "none", "--quiet",
                            "--out", str(root / "runs" / "clean"), "--scheduler", farm], check=True)
            clean = time.perf_counter() - start
            print(f"clean batch: {count} sessions in {clean:.1f} s; the k-th fault of a kind at a random "
                  f"moment in the k-th third of 0..{0.8 * clean:.0f} s after the first session started")
            reference = {Path(p).stem: {k: v for k, v in faults.tree_hashes(root / "runs" / "clean" / Path(p).stem).items()
                                        if k != "log.txt"} for p in paths}
            trials = []
            for k, kind in enumerate(["kill", "interrupt"] * 3):
                faults.wait_for_workers(farm, 2)
                third = 0.8 * clean / 3  # early, middle, late: a late kill hits finished sessions' worker
                trial = faults.run_trial(kind, sessions=paths, out=root / "runs" / f"{kind}{k}", scheduler=farm,
                                         rng=rng, window=(k // 2 * third, (k // 2 + 1) * third))
                statuses = [r["status"] for r in trial.records.values()]
                retried = {n: [a["ended"] for a in r["attempts"]] for n, r in trial.records.items()
                           if len(r["attempts"]) > 1 or r["status"] != "done"}
                print(f"{kind:9} at +{trial.delay:4.1f} s: exit {trial.exit_code}, returned {trial.stop_seconds:4.1f} s "
                      f"after the fault; {statuses.count('done')} done, {statuses.count('interrupted')} interrupted, "
                      f"{count - len(statuses)} not started; attempts of the others: {retried}", flush=True)
                trials.append(trial)
            found = [p for trial in trials for p in faults.problems(trial, reference)]
            print(f"after 10 s: {len(found)} problems (changed files, leftovers, runners, lost attempts, "
                  f"outputs != clean run){': ' if found else ''}{found if found else ''}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sessions", type=int, default=24)
    parser.add_argument("--frames", type=int, default=200, help="frames per take (0: whole takes)")
    parser.add_argument("--faults", action="store_true", help="run the fault campaign instead")
    parser.add_argument("--seed", type=int, default=31, help="random moments of the fault campaign")
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores, shared)")
    if args.faults:
        fault_campaign(args.sessions, args.frames, args.seed)
        print(f"load average after: {os.getloadavg()[0]:.1f}")
        return
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
        tree = children_cpu() - cpu0  # client, scheduler, workers and their runners (all waited for)
        sessions_cpu = sum(r["cpu_seconds"] for r in json.loads((root / "batch" / "batch.json").read_text())["sessions"])
        n = len(paths)
        print(f"batch, 2 workers: {batch:.1f} s ({batch / n:.2f} s/session wall; CPU {tree:.1f} s in all, "
              f"{tree / n:.2f} CPU-s/session, of which the sessions' own work {sessions_cpu / n:.2f})  "
              f"load {os.getloadavg()[0]:.1f}")
        print(f"ratio serial / batch: {serial / batch:.2f}x wall, {cpu_per_session * n / tree:.2f}x CPU")
        print(f"per-session overhead of batch: {(tree - sessions_cpu) / n:.2f} CPU-s (cluster start, "
              f"runners' imports, scheduling, hashing, summary) vs {cpu_per_session - sessions_cpu / n:.2f} "
              "CPU-s of the serial loop (a new process and its imports per session)")

        for path in paths:
            a, b = root / "serial" / path.stem, root / "batch" / path.stem
            outputs = sorted(p.name for p in b.iterdir() if p.name != "log.txt")  # batch's own log beside them
            assert sorted(p.name for p in a.iterdir()) == outputs, path.stem
            assert all((a / name).read_bytes() == (b / name).read_bytes() for name in outputs), path.stem
        print("outputs: batch == serial, byte for byte, for every session (batch's log.txt aside)")

        start = time.perf_counter()
        subprocess.run(batch_line, check=True)
        rerun = time.perf_counter() - start
        records = json.loads((root / "batch" / "batch.json").read_text())["sessions"]
        assert all(r["status"] == "skipped" for r in records)
        print(f"re-run, all {len(records)} skipped: {rerun:.1f} s, {rerun / len(records):.2f} s/session "
              "(cluster start + runner start + hashing + round trips)")
    print(f"scheduler overhead: {scheduler_overhead_ms():.2f} ms per task (2 local workers, empty tasks)")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
