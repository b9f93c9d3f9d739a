"""The studio path end to end through the CLI, on both generators (issue #27's "Must show").

    python benchmarks/bench_studio_path.py OUT_DIR [independent|own ...]

Per generator (``independent``: ``benchmarks/testbed`` set ``tb-full-a-hb``, tb-full-a's actor
with a 4-marker headband; ``own``: the bundled ``synth`` sample): the ROM session →
``mocaptk cluster`` (default method, and ``--method kmeans`` at the same count) → a production
capture holding only the layout's measured markers (plus its rigid head markers, when it has
some): the held-out performance's noise-free truth, moved by a head motion, projected through a
camera rig (0.3 px noise, 2 % dropouts, 1 % ghosts or none), triangulated
(``acquisition/triangulate.py``), written as C3D → ``mocaptk solve`` (default model for the
default layout, ``--model-kind ridge`` for k-means) → dense RMSE over the skin markers against the
noise-free truth in the capture's (world) frame.

Scenarios: rig ``cara`` (head moving ±8° / 15 mm) and ``room`` (±15° / 30 mm), each also without
head motion, each with and without ghosts. Targets (issue #27): with head motion ≤ 1.3× the same
capture without; ghosts add < 10 %; default layout + default solve ≤ 0.9× k-means + ridge.
A marker is hidden from a camera that sees its surface from behind (normals of the marker surface
through the dense markers, per frame).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from testbed.sets import ensure_set, ict_tarball  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
COUNT = {"independent": 40, "own": 30}
MOTION = {"cara": (8.0, 15.0), "room": (15.0, 30.0)}


def mocaptk(*args: object) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "mocaptk", *map(str, args)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mocaptk {' '.join(map(str, args))}: {done.stderr.strip()}")
    return done


def generator(name: str, out: Path) -> tuple[Path, np.ndarray, tuple[str, ...]]:
    """(ROM session file, performance truth (F, M, 3) mm head-relative, dense labels)."""
    from mocaptk.acquisition.formats import read_trajectories

    if name == "independent":
        from testbed.session import load_truth

        folder = ensure_set(ict_tarball(), out / "sets", "tb-full-a-hb")
        truth, header = load_truth(folder / "performance_truth.npz")
        return folder / "rom.c3d", truth, tuple(header["labels"])
    from mocaptk.acquisition.synth_session import load_ground_truth

    session = REPO / "sample_c3d" / "dense_halfface.c3d"
    truth = load_ground_truth(REPO / "sample_c3d" / "dense_halfface_performance_truth.npz")
    return session, truth.positions, read_trajectories(session).labels


def production_capture(truth: np.ndarray, labels: tuple[str, ...], measured: list[str], *, rig_name: str,
                       motion: bool, ghosts: bool, seed: int, path: Path) -> np.ndarray:
    """Write the capture of the ``measured`` markers to ``path``; return the world truth (F, M, 3)."""
    from mocaptk.acquisition.c3d_write import write_c3d
    from mocaptk.acquisition.cameras import RIG_PRESETS
    from mocaptk.acquisition.projection import project_markers
    from mocaptk.acquisition.triangulate import triangulate
    from mocaptk.clustering.camera_cost import surface_normals
    from testbed.session import apply_pose, head_motion

    if motion:
        rot, shift = head_motion(len(truth), max_deg=MOTION[rig_name][0], max_mm=MOTION[rig_name][1], seed=seed)
        world = apply_pose(truth, rot, shift)
    else:
        world = truth.copy()
    rig = RIG_PRESETS[rig_name]()
    idx = [labels.index(m) for m in measured]
    normals = surface_normals(world, truth[0])[:, idx]  # back-facing markers are hidden from a camera
    obs = project_markers(rig, world[:, idx], normals=normals, pixel_noise=0.3, dropout=0.02,
                          ghost_rate=0.01 if ghosts else 0.0, rng=seed)
    write_c3d(triangulate(rig, obs, labels=measured, rate=60.0), path)
    return world


def rmse(path: Path, world: np.ndarray, labels: tuple[str, ...]) -> dict:
    """Dense RMSE / p95 / max (mm) over the skin markers (not the headband's ``hb*``), solved frames."""
    from mocaptk.acquisition.formats import read_trajectories

    dense = read_trajectories(path)
    skin = [i for i, m in enumerate(labels) if not m.startswith("hb")]
    pred = dense.positions[:, [dense.labels.index(labels[i]) for i in skin]]
    err = np.linalg.norm(pred - world[:, skin], axis=2)
    solved = np.isfinite(err).all(axis=1)
    e = err[solved]
    return {"rmse_mm": float(np.sqrt(np.mean(e ** 2))), "p95_mm": float(np.percentile(e, 95)),
            "max_mm": float(e.max()), "frames_solved": int(solved.sum()), "frames": int(len(err))}


def run(name: str, out: Path) -> dict:
    work = out / name
    work.mkdir(parents=True, exist_ok=True)
    session, truth, labels = generator(name, out)
    n = COUNT[name]
    result: dict = {"markers": n}
    for method, kind in (("hybrid", None), ("kmeans", "ridge")):
        lay_dir = work / f"layout_{method}"
        if not (lay_dir / "layout.json").exists():  # a rerun keeps the layouts (cluster is the slow step)
            mocaptk("cluster", session, "--out", lay_dir, "--markers", n, "--method", method, "--formats", "none",
                    "--force", "--quiet")
        layout = json.loads((lay_dir / "layout.json").read_text())
        measured = [c["representative"] for c in layout["clusters"] if not c.get("mirrored_from")]
        # the head markers the layout stabilizes with are worn in production too
        rigid = (layout.get("stabilization") or {}).get("rigid_labels") or []
        measured += [m for m in rigid if m in labels and m not in measured]
        model = None
        for rig_name in MOTION:
            for motion in (False, True):
                for ghosts in (False, True):
                    key = f"{method}/{rig_name}/{'motion' if motion else 'still'}/{'ghosts' if ghosts else 'clean'}"
                    cap = work / f"{key.replace('/', '_')}.c3d"
                    world = production_capture(truth, labels, measured, rig_name=rig_name, motion=motion,
                                               ghosts=ghosts, seed=7, path=cap)
                    solve_dir = work / f"solve_{key.replace('/', '_')}"
                    args = ["solve", lay_dir / "layout.json", cap, "--out", solve_dir, "--formats", "npz",
                            "--force", "--quiet"]
                    if model is not None:
                        args += ["--model", model]
                    else:
                        args += ["--session", session] + (["--model-kind", kind] if kind else [])
                    started = time.time()
                    mocaptk(*args)
                    model = model or solve_dir / "model.npz"
                    row = rmse(solve_dir / "dense.c3d", world, labels)
                    row["wall_s"] = round(time.time() - started, 1)
                    result[key] = row
                    print(name, key, round(row["rmse_mm"], 3), "max", round(row["max_mm"], 1), flush=True)
    return result


def ratios(result: dict) -> dict:
    """The issue's three targets from one generator's rows."""
    r = {k: v["rmse_mm"] for k, v in result.items() if isinstance(v, dict)}
    out = {}
    for rig_name in MOTION:
        for ghosts in ("clean", "ghosts"):
            out[f"motion/still {rig_name} {ghosts}"] = r[f"hybrid/{rig_name}/motion/{ghosts}"] / r[f"hybrid/{rig_name}/still/{ghosts}"]
        for motion in ("still", "motion"):
            out[f"ghosts/clean {rig_name} {motion}"] = r[f"hybrid/{rig_name}/{motion}/ghosts"] / r[f"hybrid/{rig_name}/{motion}/clean"]
            out[f"default/kmeans+ridge {rig_name} {motion}"] = (r[f"hybrid/{rig_name}/{motion}/ghosts"]
                                                               / r[f"kmeans/{rig_name}/{motion}/ghosts"])
    return out


def main(argv: list[str]) -> None:
    out = Path(argv[0])
    report = {}
    for name in argv[1:] or ("independent", "own"):
        started, cpu = time.time(), time.process_time()
        result = run(name, out)
        report[name] = {"rows": result, "ratios": ratios(result), "wall_s": round(time.time() - started, 1),
                        "load": os.getloadavg()}
        for k, v in report[name]["ratios"].items():
            print(f"{name:12s} {k:40s} {v:.2f}")
    (out / "studio_path.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
