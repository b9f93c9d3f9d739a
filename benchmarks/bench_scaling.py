"""Benchmark: `mocaptk cluster` wall time, CPU time and peak memory from 100 to 10,000 markers and
1,000 to 72,000 frames, on sessions made from the bundled sample (with gaps).

Each session is the bundled head-mounted capture (139 markers x 6,841 frames, real facial motion
from our synthetic face model), its markers repeated with a few mm offset and independent 0.1 mm
noise up to the marker count, its frames tiled up to the frame count, 0.5 % of the samples made
gaps; written as C3D by ``write_c3d``. Every run is a fresh ``mocaptk cluster`` process
(``--formats none``: the layout only; ``default``: every output); wall, CPU (user + system) and
peak RSS are that process's own (``os.wait4``), its modules' bytecode compiled beforehand (as a pip
install has it). The issue-17 goals are printed met / not met.

    python benchmarks/bench_scaling.py [--quick] [--folder /work/scratch/scaling] [--timeout 1800]

Prints a Markdown table (docs/performance.md holds the last run).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("mocaptk", "acquisition", "clustering", "retarget")
#: (markers, frames, cluster options, formats) rows; goals keyed by (markers, frames, formats).
ROWS = [(100, 1_000, [], "none"), (1_000, 1_000, [], "none"), (10_000, 1_000, [], "none"),
        (200, 1_000, [], "none"), (200, 10_000, [], "none"), (200, 72_000, [], "none"),
        (200, 72_000, [], "default"),
        (10_000, 400, ["--step", "1"], "none"), (10_000, 400, ["--step", "1"], "default"),
        # the same without the hybrid's (3N, 3N) Gram products: what the rest of the command costs
        (10_000, 400, ["--step", "1", "--method", "paper"], "none"),
        (10_000, 400, ["--step", "1", "--method", "paper"], "default")]
QUICK = [(100, 1_000, [], "none"), (200, 10_000, [], "none")]
GOALS = {(200, 72_000, "none"): (5.0, None), (200, 72_000, "default"): (15.0, None),
         (10_000, 400, "none"): (30.0, 4.0), (10_000, 400, "default"): (30.0, 4.0)}


def make_session(path: Path, markers: int, frames: int) -> None:
    """Write the scaled session (run in its own process: the benchmark parent stays small)."""
    import numpy as np

    from mocaptk import Trajectories
    from mocaptk.acquisition import read_c3d, write_c3d

    sample = read_c3d(REPO / "sample_c3d" / "dense_halfface.c3d")
    rng = np.random.default_rng(markers * 7 + frames)
    copies = -(-markers // sample.n_markers)
    base = np.resize(sample.positions, (frames,) + sample.positions.shape[1:]) if \
        frames > sample.n_frames else sample.positions[:frames]
    pos = np.empty((frames, markers, 3))
    labels = []
    for c in range(copies):
        lo, hi = c * sample.n_markers, min(markers, (c + 1) * sample.n_markers)
        pos[:, lo:hi] = base[:, :hi - lo] + np.array([2.0, 1.0, 0.5]) * c
        pos[:, lo:hi] += rng.normal(scale=0.1, size=(frames, hi - lo, 3)) if c else 0.0
        labels += [f"{label}_{c}" if c else label for label in sample.labels[:hi - lo]]
    pos[rng.random((frames, markers)) < 0.005] = np.nan
    write_c3d(Trajectories(pos, labels, sample.rate), path)


def bytecode_env() -> dict[str, str]:
    """The environment with bytecode kept (``__pycache__``, git-ignored), compiled once for every
    package module: each run imports as a pip install does (not recompiling ~70 modules, 0.25 s);
    installed dependencies keep their own bytecode (a cache prefix would recompile them all)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONDONTWRITEBYTECODE", "PYTHONPYCACHEPREFIX")}
    subprocess.run([sys.executable, "-m", "compileall", "-q", *(str(REPO / p) for p in PACKAGES)],
                   env=env, check=True, stdout=subprocess.DEVNULL)
    return env


def run(argv: list[str], timeout: float, env: dict[str, str] | None = None, *,
        one_cpu: bool = False) -> tuple[float, float, float, int]:
    """(wall s, CPU s, peak RSS GB, exit code) of one child process, killed after ``timeout`` s;
    ``one_cpu``: confined to one CPU (as ``taskset -c 0``), where mocaptk writes every output in
    one process (``mocaptk.background``)."""
    start = time.perf_counter()
    confine = (lambda: os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})) if one_cpu else None
    child = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                             preexec_fn=confine)
    timer = threading.Timer(timeout, child.kill)
    timer.start()
    _, status, usage = os.wait4(child.pid, 0)
    timer.cancel()
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        sys.stderr.write(child.stderr.read().decode()[-800:])
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 2**20, child.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two small rows only")
    parser.add_argument("--folder", type=Path, default=Path("/work/scratch/scaling"))
    parser.add_argument("--only", nargs="*", default=None, metavar="MxF[:formats]",
                        help="run only these rows, e.g. 200x72000:none 10000x400:default")
    parser.add_argument("--method", default=None, help="run only the rows with (paper) or without "
                        "(hybrid) --method paper")
    parser.add_argument("--timeout", type=float, default=1800.0, help="kill a row after this many s")
    parser.add_argument("--one-cpu", action="store_true", help="each row also confined to one CPU "
                        "(the baseline of the second process's outputs): its wall s and the ratio")
    parser.add_argument("--make", nargs=3, help=argparse.SUPPRESS)  # internal: PATH MARKERS FRAMES
    args = parser.parse_args()
    if args.make:
        make_session(Path(args.make[0]), int(args.make[1]), int(args.make[2]))
        return
    args.folder.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {' '.join(f'{v:.1f}' for v in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs")
    extra = " one-CPU wall s | one-CPU / wall |" if args.one_cpu else ""
    print("| markers | frames | options | outputs | wall s | CPU s | peak GB | goal |" + extra)
    print("|---|---|---|---|---|---|---|---|" + "---|---|" * args.one_cpu)
    env = bytecode_env()
    rows = QUICK if args.quick else ROWS
    if args.only is not None:
        rows = [r for r in ROWS if f"{r[0]}x{r[1]}" in args.only or f"{r[0]}x{r[1]}:{r[3]}" in args.only]
    if args.method is not None:
        rows = [r for r in rows if ("paper" in r[2]) == (args.method == "paper")]
    for markers, frames, options, formats in rows:
        path = args.folder / f"session_{markers}x{frames}.c3d"
        if not path.exists():
            subprocess.run([sys.executable, __file__, "--make", str(path), str(markers),
                            str(frames)], check=True)
        out = args.folder / f"out_{markers}x{frames}_{formats}{'_paper' if 'paper' in options else ''}"
        argv = [sys.executable, "-m", "mocaptk", "cluster", str(path), "--out", str(out),
                "--force", *options] + (["--formats", "none"] if formats == "none" else [])
        wall, cpu, peak, code = run(argv, args.timeout, env)
        goal = None if "--method" in options else GOALS.get((markers, frames, formats))
        verdict = "" if goal is None else (
            f"< {goal[0]:g} s" + (f", < {goal[1]:g} GB" if goal[1] else "") + ": " +
            ("met" if code == 0 and wall < goal[0] and (goal[1] is None or peak < goal[1])
             else "not met"))
        shown = " ".join(options) or "-"
        status = "" if code == 0 else " (killed)" if wall >= args.timeout else f" (exit {code})"
        if args.one_cpu:
            single = run(argv, args.timeout, env, one_cpu=True)[0]
            verdict += f" | {single:.1f} | {single / wall:.2f}x"
        print(f"| {markers} | {frames} | {shown} | {formats} | {wall:.1f}{status} | {cpu:.1f} | "
              f"{peak:.2f} | {verdict} |", flush=True)
    print(f"load average at end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
