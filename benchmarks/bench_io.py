"""Benchmark: C3D read time of mocaptk vs raw ezc3d vs py-c3d on generated sessions.

Files of 100 / 300 markers x 12,000 / 60,000 / 120,000 frames (float storage, 5 % gaps) are
generated once into ``--folder``. Timed, each the best of ``--repeat`` runs:

* mocaptk: ``read_c3d(path)`` (header/parameter check, ezc3d in a guarded child, NaN gaps, mm);
* raw ezc3d: ``ezc3d.c3d(path)`` in-process + ``points[:3].transpose(2, 1, 0)`` into one array;
* py-c3d: ``c3d.Reader`` + ``read_frames()`` stacked into one array.

Each read runs in a fresh interpreter (imports excluded from the timing), readers alternating.
Wall and CPU seconds are both shown (CPU = the process + its child processes, which includes
mocaptk's ezc3d child); on a busy machine the CPU ratio is the reliable one.

Note ezc3d 1.7.2 reads at most 65,535 frames (the C3D header field), so on the 120,000-frame
files it returns only the first 65,535 (shown in the table); mocaptk reads those files with its
own reader. A reader whose estimated memory exceeds half the available memory is skipped.

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

SIZES = [(100, 12_000), (300, 12_000), (100, 60_000), (300, 60_000), (100, 120_000),
         (300, 120_000)]
QUICK = [(100, 12_000), (300, 12_000)]
#: ezc3d's memory per (frame, marker) sample, measured (~210 B) with margin; py-c3d's is small.
EZC3D_BYTES_PER_SAMPLE = 300
BLOCK_FRAMES = 12_000


def generate(folder: Path, markers: int, frames: int) -> Path:
    """A session file, written by write_c3d in blocks of 12,000 frames and tiled to ``frames``.

    Tiling keeps ezc3d's writer memory small: the data block is repeated and the frame counts
    in the header and parameters (POINT:FRAMES, TRIAL:ACTUAL_END_FIELD) are patched.
    """
    path = folder / f"bench_{markers}x{frames}.c3d"
    if path.exists() and c3d_raw.read_structure(path).n_frames == frames:
        return path
    rng = np.random.default_rng(markers)
    block = min(frames, BLOCK_FRAMES)
    pos = rng.normal(0, 300, (block, markers, 3)).cumsum(axis=0) * 0.01
    pos[rng.random((block, markers)) < 0.05] = np.nan
    seed = write_c3d(Trajectories(pos, [f"Actor:M{k:03d}" for k in range(markers)], 120.0,
                                  first_frame=1), folder / f"seed_{markers}x{block}.c3d")
    if frames == block:
        return seed.rename(path)
    data = bytearray(seed.read_bytes())
    structure = c3d_raw.read_structure(seed)
    head = data[:structure.data_offset]
    body = bytes(data[structure.data_offset:structure.data_offset + block * structure.frame_bytes])
    shown = min(frames, 0xFFFF)
    head[8:10] = shown.to_bytes(2, "little")  # header last frame (first frame is 1)
    _patch(head, b"FRAMES", 4, shown.to_bytes(2, "little"))
    _patch(head, b"ACTUAL_END_FIELD", 5, frames.to_bytes(4, "little"))
    with open(path, "wb") as handle:
        handle.write(head)
        for start in range(0, frames, block):
            handle.write(body[:(min(block, frames - start)) * structure.frame_bytes])
    seed.unlink()
    assert c3d_raw.read_structure(path).n_frames == frames
    return path


def _patch(head: bytearray, name: bytes, skip: int, value: bytes) -> None:
    at = head.index(name, 512) + len(name) + skip
    head[at:at + len(value)] = value


def _cpu() -> float:
    """CPU seconds used so far by this process and its reaped children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def measure(reader: str, path: Path) -> tuple[float, float]:
    """(wall, CPU) seconds of one read in this process (call it in a fresh one).

    CPU includes child processes (mocaptk's ezc3d child, up to its exit): background threads
    (mocaptk reaps its child in one) are joined before CPU time is taken.
    """
    import c3d  # noqa: F401 - imports outside the timing
    import ezc3d  # noqa: F401

    func = {"mocaptk": read_c3d, "ezc3d": raw_ezc3d, "py-c3d": py_c3d}[reader]
    wall, cpu = time.perf_counter(), _cpu()
    result = func(path)
    wall = time.perf_counter() - wall
    for thread in threading.enumerate():
        if thread is not threading.main_thread():
            thread.join(timeout=120)
    del result
    return wall, _cpu() - cpu


def time_fresh(reader: str, path: Path) -> tuple[float, float]:
    """(wall, CPU) of one read in a fresh interpreter (no heap left over from other readers)."""
    out = subprocess.run([sys.executable, __file__, "--measure", reader, str(path)],
                         check=True, capture_output=True, text=True).stdout.split()
    return float(out[-2]), float(out[-1])


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
    parser.add_argument("--quick", action="store_true", help="only the 12,000-frame files")
    parser.add_argument("--repeat", type=int, default=3, help="runs per reader (best is shown)")
    parser.add_argument("--folder", type=Path, default=Path("/work/scratch/io-c3d"),
                        help="where the generated files go")
    parser.add_argument("--no-py-c3d", action="store_true", help="skip py-c3d (slow)")
    parser.add_argument("--measure", nargs=2, metavar=("READER", "PATH"),
                        help=argparse.SUPPRESS)  # internal: one timed read in this process
    args = parser.parse_args()
    if args.measure:
        print(*measure(args.measure[0], Path(args.measure[1])))
        return
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    args.folder.mkdir(parents=True, exist_ok=True)
    print(f"{'markers':>7} {'frames':>7} {'MB':>5} | {'reader':>7} | wall s: "
          f"{'mocaptk':>7} {'ezc3d':>7} {'py-c3d':>7} | CPU s: {'mocaptk':>7} {'ezc3d':>7} "
          f"{'py-c3d':>7} | mocaptk/ezc3d wall {'CPU':>5} | ezc3d frames")
    nan = (float("nan"), float("nan"))
    for markers, frames in (QUICK if args.quick else SIZES):
        path = generate(args.folder, markers, frames)
        size_mb = path.stat().st_size / 2**20
        repeat = args.repeat if size_mb < 100 else 1
        reader = read_c3d(path).metadata["reader"]
        n_ez = min(frames, 0xFFFF)
        readers = ["mocaptk"]
        if EZC3D_BYTES_PER_SAMPLE * n_ez * markers <= 0.5 * (c3d_ezc3d.available_memory() or 0):
            readers.append("ezc3d")
        if not args.no_py_c3d:
            readers.append("py-c3d")
        times = {}
        for _ in range(repeat):  # alternate readers so load drifts hit all of them
            for name in readers:
                new = time_fresh(name, path)
                old = times.get(name, new)
                times[name] = (min(old[0], new[0]), min(old[1], new[1]))
        ours, ez, py = times["mocaptk"], times.get("ezc3d", nan), times.get("py-c3d", nan)
        n_ez = n_ez if "ezc3d" in times else 0
        print(f"{markers:>7} {frames:>7} {size_mb:>5.0f} | {reader:>7} | wall s: "
              f"{ours[0]:>7.2f} {ez[0]:>7.2f} {py[0]:>7.2f} | CPU s: {ours[1]:>7.2f} {ez[1]:>7.2f} "
              f"{py[1]:>7.2f} | {ours[0] / ez[0]:>18.2f} {ours[1] / ez[1]:>5.2f} | {n_ez:>6}",
              flush=True)


if __name__ == "__main__":
    main()
