"""The first triangulation after a fresh install (issue #27: target <= 10 s), wall and CPU.

    python benchmarks/bench_first_triangulation.py [--points 20000]
    python benchmarks/bench_first_triangulation.py --command

A fresh process with an empty numba cache (``NUMBA_CACHE_DIR`` a new temporary folder, as after
``pip install``) triangulates ``--points`` points of the room rig with 5 % ghost views; a second
fresh process then does the same with the cache the first one filled. Each prints the import
time, the first call (compile or cache load + run) and a warm call, wall and CPU (the process's
own CPU: numba compiles on one thread). The load average is printed beside them: on a shared
machine the wall time follows the load, the CPU time does not.

``--command`` times the command a user runs instead: the bundled sample performance
(``sample_c3d/dense_halfface_performance.c3d``, 139 markers x 1,200 frames) seen by the Cara rig
(0.3 px noise, 1 % ghost views) is written as ``OBS.npz`` with its ``RIG.json``, then
``mocaptk triangulate RIG.json OBS.npz OUT.c3d`` runs twice, with an empty then the filled
numba cache; wall and CPU (user + system) of the whole process, from ``os.wait4``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SAMPLE = Path(__file__).resolve().parent.parent / "sample_c3d" / "dense_halfface_performance.c3d"

CHILD = r"""
import json, sys, time
wall, cpu = time.perf_counter(), time.process_time()
import numpy as np
from mocaptk.acquisition.cameras import room_rig
from mocaptk.acquisition.projection import ellipsoid_markers, project_markers
from mocaptk.acquisition.triangulate import triangulate_points
rig = room_rig()
points, normals = ellipsoid_markers(100, int(sys.argv[1]) // 100)
obs = project_markers(rig, points, normals=normals, pixel_noise=0.3, ghost_rate=0.05, rng=1)
obs = obs.reshape(len(rig), -1, 2)
marks = [(time.perf_counter(), time.process_time())]
for _ in range(2):
    triangulate_points(rig, obs)
    marks.append((time.perf_counter(), time.process_time()))
out = {"setup": (marks[0][0] - wall, marks[0][1] - cpu)}
out["first"] = (marks[1][0] - marks[0][0], marks[1][1] - marks[0][1])
out["warm"] = (marks[2][0] - marks[1][0], marks[2][1] - marks[1][1])
print(json.dumps(out))
"""


def run(points: int, cache: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    done = subprocess.run([sys.executable, "-c", CHILD, str(points)], env=env, capture_output=True,
                          text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def sample_observations(folder: Path) -> tuple[Path, Path]:
    """``RIG.json`` and ``OBS.npz`` of the sample performance through the Cara rig."""
    import numpy as np

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.acquisition.cameras import cara_rig, save_rig
    from mocaptk.acquisition.projection import project_markers

    traj = read_c3d(SAMPLE)
    rig = cara_rig()
    points2d = project_markers(rig, traj.positions, pixel_noise=0.3, ghost_rate=0.01, rng=1)
    obs = folder / "obs.npz"
    np.savez(obs, points2d=points2d, labels=np.array(traj.labels), rate=traj.rate)
    return save_rig(rig, folder / "rig.json"), obs


def run_command(rig: Path, obs: Path, out: Path, cache: str) -> tuple[float, float]:
    """Wall and CPU seconds of one ``mocaptk triangulate`` process with ``NUMBA_CACHE_DIR=cache``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    mocaptk = Path(sys.executable).with_name("mocaptk")
    start = time.perf_counter()
    child = subprocess.Popen([str(mocaptk), "triangulate", str(rig), str(obs), str(out), "--force"],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    text = child.stdout.read().strip()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"mocaptk triangulate failed:\n{text}")
    print("   ", text.replace("\n", "\n    "))
    return wall, usage.ru_utime + usage.ru_stime


def main_command() -> None:
    with tempfile.TemporaryDirectory(prefix="first-triangulation-") as folder, \
            tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        rig, obs = sample_observations(Path(folder))
        for name in ("fresh install (empty numba cache)", "second process (cache filled)"):
            load = os.getloadavg()[0]
            wall, cpu = run_command(rig, obs, Path(folder) / "out.c3d", cache)
            print(f"{name}: mocaptk triangulate on the sample {wall:.1f} s wall / {cpu:.1f} CPU-s "
                  f"(load {load:.1f} before, {os.getloadavg()[0]:.1f} after)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--command", action="store_true",
                        help="time `mocaptk triangulate` on the bundled sample instead")
    args = parser.parse_args()
    if args.command:
        return main_command()
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        for name in ("fresh install (empty numba cache)", "second process (cache filled)"):
            load = os.getloadavg()[0]
            r = run(args.points, cache)
            print(f"{name}: import + data {r['setup'][0]:.1f} s wall / {r['setup'][1]:.1f} CPU-s; "
                  f"first triangulation {r['first'][0]:.1f} s wall / {r['first'][1]:.1f} CPU-s; "
                  f"warm {1000 * r['warm'][0]:.0f} ms wall / {1000 * r['warm'][1]:.0f} CPU-ms "
                  f"({args.points} points; load {load:.1f} before, {os.getloadavg()[0]:.1f} after)")


if __name__ == "__main__":
    main()
