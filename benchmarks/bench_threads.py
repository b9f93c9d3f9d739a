"""``mocaptk evaluate`` on the bundled sample, idle and beside two busy processes, with mocaptk's
one-BLAS-thread policy (mocaptk/threads.py) and with as many BLAS threads as cores
(``MOCAPTK_BLAS_THREADS``, OpenBLAS's default): wall and CPU seconds, the load, and the ratio
busy / idle per policy (target: <= 1.5x with the policy).

``--against TREE`` instead times this tree's ``evaluate`` against another checkout's (e.g.
``git archive f566eba | tar -x -C /tmp/old``; run through this venv with its package folders
mapped to TREE), alternating old and new, idle and beside two busy processes, with the one-thread
policy; both must write the same bytes.

Usage: python benchmarks/bench_threads.py [--seeds 3] [--repeat 1] [--against TREE]
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


def timed(args: list[str], env: dict[str, str], *, cwd: Path | None = None) -> tuple[float, float]:
    """(wall s, CPU s of the child and the processes it waited for) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL, cwd=cwd)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


#: Runs ``python -m mocaptk`` with the editable install's package folders mapped to another tree (argv[1]).
OLD_TREE = ("import runpy, sys\n"
            "import __editable___mocaptk_0_1_0_finder as finder\n"
            "for key, value in list(finder.MAPPING.items()):\n"
            "    finder.MAPPING[key] = sys.argv[1] + value[len(%r):]\n"
            "sys.argv = ['mocaptk', *sys.argv[2:]]\n"
            "runpy.run_module('mocaptk', run_name='__main__')\n") % str(REPO)


def spinning(busy: int):
    """``busy`` processes spinning on a core (started here, killed by the caller)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]


def against(tree: Path, folder: Path, args: list[str], repeat: int) -> None:
    """Old (``tree``) and new ``evaluate`` alternating, idle and beside two busy processes."""
    env = {**os.environ, "MOCAPTK_BLAS_THREADS": "1"}
    commands = {"old": [sys.executable, "-c", OLD_TREE, str(tree.resolve()), *args],
                "new": [*MOCAPTK, *args]}
    print(f"{'tree':<6}{'background':<12}{'wall s':>8}{'CPU s':>8}{'load':>6}")
    runs: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for _ in range(repeat):
        for busy in (0, 2):
            for name, command in commands.items():
                out = folder / name
                spinners = spinning(busy)
                try:
                    wall, cpu = timed([*command, "--out", str(out)], env, cwd=folder)
                finally:
                    for spinner in spinners:
                        spinner.kill()
                        spinner.wait()
                runs.setdefault((name, busy), []).append((wall, cpu))
                print(f"{name:<6}{busy:<12}{wall:>8.1f}{cpu:>8.1f}{os.getloadavg()[0]:>6.1f}", flush=True)
            same = all((folder / "old" / f).read_bytes() == (folder / "new" / f).read_bytes()
                       for f in ("evaluation.json", "evaluation.html"))
            print(f"outputs byte-identical: {same}")
    best = {key: (min(r[0] for r in value), min(r[1] for r in value)) for key, value in runs.items()}
    for name in commands:
        print(f"{name}: idle {best[name, 0][0]:.1f} s / {best[name, 0][1]:.1f} CPU-s, busy {best[name, 2][0]:.1f} s / "
              f"{best[name, 2][1]:.1f} CPU-s, busy / idle wall {best[name, 2][0] / best[name, 0][0]:.2f}x (best runs)")
    print(f"new busy / old idle wall: {best['new', 2][0] / best['old', 0][0]:.2f}x; "
          f"new / old wall idle {best['new', 0][0] / best['old', 0][0]:.2f}x, busy {best['new', 2][0] / best['old', 2][0]:.2f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--against", type=Path, help="another checkout's tree to time against (see above)")
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        subprocess.run([*MOCAPTK, "cluster", str(SAMPLE), "--formats", "none", "--quiet", "--out",
                        str(folder / "lay")], check=True)
        evaluate = ["evaluate", str(SAMPLE), "--layout", str(folder / "lay" / "layout.json"),
                    "--seeds", str(args.seeds), "--quiet", "--force"]
        print(f"{cores} cores; load before: {os.getloadavg()[0]:.1f}")
        if args.against is not None:
            against(args.against, folder, evaluate, args.repeat)
            return
        command = [*MOCAPTK, *evaluate, "--out", str(folder / "e.json")]
        print(f"{'BLAS threads':<14}{'background':<12}{'wall s':>8}{'CPU s':>8}{'load':>6}")
        results = {}
        for threads in ("1", str(cores)):
            env = {**os.environ, "MOCAPTK_BLAS_THREADS": threads}
            for busy in (0, 2):
                spinners = spinning(busy)
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
