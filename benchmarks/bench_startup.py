"""Benchmark: how long ``mocaptk info FILE`` takes from the shell, against the floor of starting
Python and importing numpy, measured in the same run (issue 17 goal: <= 0.6 s wall).

Every run is a fresh process; wall, CPU (user + system) and peak RSS are that process's own
(``os.wait4``). The commands are run in turn, ``--repeat`` times each, after one warm-up run
each with bytecode written (to a temporary folder; a user's install has its ``.pyc`` files:
pip compiles them).

    python benchmarks/bench_startup.py [--repeat 10] [--against OTHER/bin/mocaptk] [FILE]

Prints a Markdown table of medians (docs/performance.md holds the last run).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MOCAPTK = str(Path(sys.executable).with_name("mocaptk"))


def run(argv: list[str], env: dict[str, str]) -> tuple[float, float, float]:
    """(wall s, CPU s, peak RSS MB) of one child process, which must succeed."""
    start = time.perf_counter()
    child = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=REPO)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status):
        raise SystemExit(f"{' '.join(argv)} failed: {child.stderr.read().decode()[-800:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", nargs="?", type=Path, default=REPO / "sample_c3d" / "dense_halfface.c3d")
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--against", metavar="MOCAPTK", help="another install's mocaptk script, timed too")
    args = parser.parse_args()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = str(Path(tempfile.gettempdir()) / "mocaptk-bench-startup-pycache")
    commands = {
        "python -c pass": [sys.executable, "-c", "pass"],
        "python -c 'import numpy' (floor)": [sys.executable, "-c", "import numpy"],
        f"mocaptk info {args.file.name}": [MOCAPTK, "info", str(args.file)],
        "mocaptk --help": [MOCAPTK, "--help"],
    }
    if args.against:
        commands[f"{args.against} info {args.file.name}"] = [args.against, "info", str(args.file)]
    for argv in commands.values():
        run(argv, env)  # warm-up: bytecode written, files in the page cache
    load = os.getloadavg()[0]
    times = {name: [run(argv, env) for _ in range(args.repeat)] for name, argv in commands.items()}
    load_end = os.getloadavg()[0]
    floor = statistics.median(w for w, _, _ in times["python -c 'import numpy' (floor)"])
    print(f"load average {load:.1f} at start, {load_end:.1f} at end; medians of {args.repeat} runs\n")
    print("| command | wall s | CPU s | peak MB | wall / floor |")
    print("|---|---|---|---|---|")
    for name, rows in times.items():
        wall, cpu, rss = (statistics.median(col) for col in zip(*rows))
        print(f"| {name} | {wall:.3f} | {cpu:.3f} | {rss:.0f} | {wall / floor:.2f} |")
    info_wall, info_cpu = (statistics.median(col) for col in list(zip(*times[f"mocaptk info {args.file.name}"]))[:2])
    print(f"\ngoal `mocaptk info` <= 0.6 s wall: {'met' if info_wall <= 0.6 else 'not met'} "
          f"({info_wall:.3f} s wall, {info_cpu:.3f} CPU-s)")


if __name__ == "__main__":
    main()
