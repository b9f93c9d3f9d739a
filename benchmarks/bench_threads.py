"""``mocaptk evaluate`` on the bundled sample, idle and beside two busy processes, with mocaptk's
one-BLAS-thread policy (mocaptk/threads.py) and with as many BLAS threads as cores
(``MOCAPTK_BLAS_THREADS``, OpenBLAS's default): wall and CPU seconds, the load, and the ratio
busy / idle per policy (target: <= 1.5x with the policy).

Usage: python benchmarks/bench_threads.py [--seeds 3] [--repeat 1]
"""

from __future__ import annotations

import argparse
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


def timed(args: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s of the child) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        subprocess.run([*MOCAPTK, "cluster", str(SAMPLE), "--formats", "none", "--quiet", "--out",
                        str(folder / "lay")], check=True)
        command = [*MOCAPTK, "evaluate", str(SAMPLE), "--layout", str(folder / "lay" / "layout.json"),
                   "--seeds", str(args.seeds), "--quiet", "--force", "--out", str(folder / "e.json")]
        print(f"{cores} cores; load before: {os.getloadavg()[0]:.1f}")
        print(f"{'BLAS threads':<14}{'background':<12}{'wall s':>8}{'CPU s':>8}{'load':>6}")
        results = {}
        for threads in ("1", str(cores)):
            env = {**os.environ, "MOCAPTK_BLAS_THREADS": threads}
            for busy in (0, 2):
                spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
                try:
                    runs = [timed(command, env) for _ in range(args.repeat)]
                finally:
                    for spinner in spinners:  # only the processes started here
                        spinner.kill()
                        spinner.wait()
                wall = min(r[0] for r in runs)
                cpu = min(r[1] for r in runs)
                results[threads, busy] = wall
                print(f"{threads:<14}{busy:<12}{wall:>8.1f}{cpu:>8.1f}{os.getloadavg()[0]:>6.1f}")
        for threads in ("1", str(cores)):
            print(f"{threads} BLAS thread(s): busy / idle wall = {results[threads, 2] / results[threads, 0]:.2f}x")


if __name__ == "__main__":
    main()
