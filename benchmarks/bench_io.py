"""Benchmark: C3D read of mocaptk vs py-c3d (and raw ezc3d) on the issue-17 file shapes.

Shapes: the bundled sample (139 markers x 6,841 frames), and generated sessions of
1,000 x 10,000 and 200 x 72,000 (float storage, 2 % gaps, written by ``write_c3d`` into
``--folder``). Timed, each the best of ``--repeat`` runs:

* mocaptk: ``read_c3d(path)`` (header/parameter check, our numpy reader, NaN gaps, mm);
* py-c3d: ``c3d.Reader`` + ``read_frames()`` stacked into one array (the goal's baseline);
* raw ezc3d: ``ezc3d.c3d(path)`` in-process + ``points[:3].transpose(2, 1, 0)`` (files of at
  most 65,535 frames: ezc3d 1.7 reads no more).

Each read runs in a fresh interpreter (imports excluded), readers alternating. Wall and CPU
seconds are shown (CPU = the process + its children); on a busy machine the CPU ratio is the
reliable one. "peak MB" is the rise of the process's peak RSS over its RSS before the read;
"decoded MB" is the size of the (frames, markers, 3) float64 positions.

    python benchmarks/bench_io.py [--quick] [--repeat 3] [--folder /work/scratch/io-c3d]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from mocaptk import Trajectories
from mocaptk.acquisition import c3d_ezc3d, c3d_raw
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.c3d_write import write_c3d

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"
SIZES = [(1_000, 10_000), (200, 72_000)]
#: ezc3d's memory per (frame, marker) sample, measured (~210 B) with margin.
EZC3D_BYTES_PER_SAMPLE = 300


def generate(folder: Path, markers: int, frames: int) -> Path:
    """A session file of ``markers`` x ``frames`` (random walks, 2 % gaps), made once."""
    path = folder / f"bench_{markers}x{frames}.c3d"
    if path.exists() and c3d_raw.read_structure(path).n_frames == frames:
        return path
    rng = np.random.default_rng(markers)
    pos = rng.normal(0, 3, (frames, markers, 3)).cumsum(axis=0)
    pos[rng.random((frames, markers)) < 0.02] = np.nan
    return write_c3d(Trajectories(pos, [f"Actor:M{k:04d}" for k in range(markers)], 120.0,
                                  first_frame=1), path)


def _rss(field: str = "VmRSS") -> int:
    """Current (``VmRSS``) or peak (``VmHWM``) resident memory of this process in bytes (Linux)."""
    with open("/proc/self/status", encoding="ascii") as handle:
        for line in handle:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    return 0


def _reset_peak() -> None:
    """Reset this process's peak RSS (it survives exec from the benchmark's big parent)."""
    with open("/proc/self/clear_refs", "w", encoding="ascii") as handle:
        handle.write("5")


def _cpu() -> float:
    """CPU seconds used so far by this process and its reaped children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def measure(reader: str, path: Path) -> tuple[float, float, float]:
    """(wall s, CPU s, peak MB over the start) of one read in this process (call it fresh).

    CPU includes child processes (mocaptk's ezc3d child, up to its exit): background threads
    (mocaptk reaps its child in one) are joined before CPU time is taken.
    """
    import c3d  # noqa: F401 - imports outside the timing
    import ezc3d  # noqa: F401

    func = {"mocaptk": read_c3d, "ezc3d": raw_ezc3d, "py-c3d": py_c3d}[reader]
    _reset_peak()
    before = _rss()
    wall, cpu = time.perf_counter(), _cpu()
    result = func(path)
    wall = time.perf_counter() - wall
    for thread in threading.enumerate():
        if thread is not threading.main_thread():
            thread.join(timeout=120)
    del result
    peak = _rss("VmHWM") - before
    return wall, _cpu() - cpu, peak / 2**20


def time_fresh(reader: str, path: Path) -> tuple[float, float, float]:
    """(wall, CPU, peak MB) of one read in a fresh interpreter (no heap left from others)."""
    out = subprocess.run([sys.executable, __file__, "--measure", reader, str(path)],
                         check=True, capture_output=True, text=True).stdout.split()
    return float(out[-3]), float(out[-2]), float(out[-1])


def raw_ezc3d(path: Path) -> np.ndarray:
    import ezc3d

    return np.ascontiguousarray(ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0))


def py_c3d(path: Path) -> np.ndarray:
    import c3d

    with open(path, "rb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.array([points[:, :3] for _, points, _ in c3d.Reader(handle).read_frames()])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the bundled sample")
    parser.add_argument("--repeat", type=int, default=3, help="runs per reader (best is shown)")
    parser.add_argument("--folder", type=Path, default=Path("/work/scratch/io-c3d"),
                        help="where the generated files go")
    parser.add_argument("--measure", nargs=2, metavar=("READER", "PATH"),
                        help=argparse.SUPPRESS)  # internal: one timed read in this process
    args = parser.parse_args()
    if args.measure:
        print(*measure(args.measure[0], Path(args.measure[1])))
        return
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    args.folder.mkdir(parents=True, exist_ok=True)
    print(f"| markers | frames | MB | mocaptk wall s | py-c3d wall s | ezc3d wall s | "
          f"py-c3d/mocaptk wall | CPU | mocaptk peak MB | decoded MB | peak/decoded | "
          f"py-c3d peak MB |")
    print("|" + "---|" * 12)
    nan = (float("nan"),) * 3
    paths = [SAMPLE] + ([] if args.quick else [generate(args.folder, m, f) for m, f in SIZES])
    for path in paths:
        s = c3d_raw.read_structure(path)
        size_mb = path.stat().st_size / 2**20
        repeat = args.repeat if size_mb < 100 else 1
        readers = ["mocaptk", "py-c3d"]
        if s.n_frames <= 0xFFFF and EZC3D_BYTES_PER_SAMPLE * s.n_frames * s.n_points <= \
                0.5 * (c3d_ezc3d.available_memory() or 0):
            readers.append("ezc3d")
        times: dict[str, tuple[float, float, float]] = {}
        for _ in range(repeat):  # alternate readers so load drifts hit all of them
            for name in readers:
                new = time_fresh(name, path)
                old = times.get(name, new)
                times[name] = tuple(min(a, b) for a, b in zip(old, new))
        ours, py, ez = times["mocaptk"], times["py-c3d"], times.get("ezc3d", nan)
        decoded = s.n_frames * s.n_points * 3 * 8 / 2**20
        print(f"| {s.n_points} | {s.n_frames} | {size_mb:.0f} | {ours[0]:.2f} | {py[0]:.2f} | "
              f"{ez[0]:.2f} | {py[0] / ours[0]:.1f}x | {py[1] / ours[1]:.1f}x | {ours[2]:.0f} | "
              f"{decoded:.0f} | {ours[2] / decoded:.2f} | {py[2]:.0f} |", flush=True)


if __name__ == "__main__":
    main()
