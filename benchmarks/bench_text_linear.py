"""Text readers take time linear in the file, also on adversarial shapes (issue 14, item 12).

Each shape is read at 100 kB and at 1 MB; the growth ratio t(1 MB) / t(100 kB) is ~10 for linear
time and ~100 for quadratic time (one line of semicolons took 10 s at 100 kB, 97 s at 300 kB).
Named baseline in the same run: an ordinary 1 MB TRC written by our writer (ratio of each shape's
1 MB time to it). Fails (exit 1) when a growth ratio exceeds 25.

Usage::

    python benchmarks/bench_text_linear.py            # prints a table; about a minute
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mocaptk import Trajectories
from mocaptk.acquisition.formats import read_trajectories, write_trajectories
from mocaptk.errors import MocaptkError

MAX_GROWTH = 25.0


def semicolons(size: int) -> bytes:
    return b";" * size + b"\n"


def one_char_cells(size: int) -> bytes:  # one headerless line of 1-character cells
    return b",".join([b"1"] * (size // 2)) + b"\n"


def long_cell_trc(size: int) -> bytes:  # a TRC whose one cell holds most of the file
    head = (b"PathFileType\t4\t(X/Y/Z)\tx.trc\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
            b"100\t100\t3\t1\tmm\nFrame#\tTime\tA\t\t\n\t\tX1\tY1\tZ1\n\n")
    return head + b"1\t0\t1\t2\t3\n2\t0.01\t1\t2\t" + b"x" * size + b"\n3\t0.02\t1\t2\t3\n"


def ragged_rows(size: int) -> bytes:  # headerless rows of very different lengths
    rows = [b",".join([b"1.5"] * (3 if i % 50 else 300)) for i in range(size // 60)]
    return b"\n".join(rows) + b"\n"


SHAPES = {"semicolon line": semicolons, "1-char cells": one_char_cells, "long TRC cell": long_cell_trc,
          "ragged rows": ragged_rows}


def read_seconds(path: Path, *, repeat: int = 3) -> tuple[float, str]:
    """Best time of ``repeat`` reads (s), and "loaded" or "refused"."""
    best, outcome = float("inf"), "loaded"
    for _ in range(repeat):
        start = time.perf_counter()
        try:
            read_trajectories(path, rate=100.0 if path.suffix == ".csv" else None)
        except MocaptkError:
            outcome = "refused"
        best = min(best, time.perf_counter() - start)
    return best, outcome


def ordinary_trc(folder: Path, size: int) -> Path:
    frames = max(1, size // 900)  # ~900 bytes per row of 30 markers
    traj = Trajectories(np.random.default_rng(0).normal(0, 50, (frames, 30, 3)),
                        [f"M{i:02d}" for i in range(30)], 100.0)
    return write_trajectories(traj, folder / "ordinary.trc")


def main() -> int:
    folder = Path(tempfile.mkdtemp(prefix="bench_text_linear_"))
    baseline, _ = read_seconds(ordinary_trc(folder, 1_000_000))
    print(f"baseline: ordinary 1 MB TRC read in {baseline:.3f} s (best of 3)")
    print(f"{'shape':<16}{'100 kB s':>10}{'1 MB s':>10}{'growth':>9}{'vs baseline':>13}  outcome")
    worst = 0.0
    for name, make in SHAPES.items():
        times, outcomes = [], []
        for size in (100_000, 1_000_000):
            path = folder / f"case_{size}{'.trc' if 'TRC' in name else '.csv'}"
            path.write_bytes(make(size))
            seconds, outcome = read_seconds(path)
            times.append(seconds)
            outcomes.append(outcome)
        growth = times[1] / max(times[0], 0.01)  # below 10 ms, timer noise dominates
        worst = max(worst, growth)
        print(f"{name:<16}{times[0]:>10.3f}{times[1]:>10.3f}{growth:>9.1f}{times[1] / baseline:>13.2f}"
              f"  {'/'.join(outcomes)}")
    print(f"worst growth {worst:.1f} (linear ~10, quadratic ~100; limit {MAX_GROWTH:g})")
    return 0 if worst <= MAX_GROWTH else 1


if __name__ == "__main__":
    sys.exit(main())
