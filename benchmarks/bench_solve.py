"""``mocaptk solve``: speed, memory, held-out accuracy, robustness and error maps.

    python benchmarks/bench_solve.py speed        # training time, frames/s to 139 markers / a 9,409-vertex mesh
    python benchmarks/bench_solve.py memory       # peak memory of a 72,000-frame solve (subprocess)
    python benchmarks/bench_solve.py memory-face  # the same through `mocaptk solve`: default face, head motion
    python benchmarks/bench_solve.py accuracy     # every model kind x 3 layout sizes x 4 data sets
    python benchmarks/bench_solve.py robustness   # RMSE as layout markers are lost
    python benchmarks/bench_solve.py maps OUT_DIR # per-vertex RMSE maps, default model vs ridge (PNG)
    python benchmarks/bench_solve.py skin-refit   # the pose refit predicting its few markers vs all (same run)

Data: the bundled sample (half face, 139 markers, separate 20 s performance), an ICT-FaceKit full
face made by ``mocaptk synth --full`` (260 markers; mesh truth from the face model), blenderFace
S01/S02 (16 markers, leave one take out). Layouts: k-means on the training displacements (the
strongest baseline of ``compare``). Timings are wall-clock on a shared machine: read the ratios.
"""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
ICT = SHARED / "face_mesh" / "ict_facekit" / "ict_facekit_FaceXModel_subset.tar.xz"
BLENDERFACE = SHARED / "facial_mocap" / "blenderface"
KINDS = ("ridge", "local-ridge", "tapered-ridge", "thin-shell", "pdm-linear", "pdm-biquadratic")


def kmeans(positions: np.ndarray, count: int) -> np.ndarray:
    from mocaptk.clustering.baselines import kmeans_layout
    from mocaptk.clustering.neutral import neutral_pose

    return np.unique(kmeans_layout(positions[::5] - neutral_pose(positions)[None], count, seed=0))


def region_indices(traj) -> dict[str, np.ndarray]:
    from mocaptk.clustering.regions import regions_from_prefixes

    return {name: traj.index(labels) for name, labels in regions_from_prefixes(traj.labels).items()}


def sample_data():
    from mocaptk.acquisition.formats import read_trajectories

    session = read_trajectories(REPO / "sample_c3d" / "dense_halfface.c3d")
    test = read_trajectories(REPO / "sample_c3d" / "dense_halfface_performance.c3d")
    return session, test, region_indices(session)


def ict_data(folder: Path):
    """(session, performance, regions, truth of the performance, face model) of a full-face synth."""
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth

    stem = folder / "full.c3d"
    if not stem.exists():
        subprocess.run([sys.executable, "-m", "mocaptk", "synth", str(stem), "--full", "--rig", "none",
                        "--noise", "0.2", "--seed", "3", "--expressions", "5", "--rest", "1.5",
                        "--hold", "2.0", "--performance", "20", "--force", "--model", str(ICT)],
                       check=True)
    session = read_trajectories(stem)
    test = read_trajectories(folder / "full_performance.c3d")
    truth = load_ground_truth(folder / "full_performance_truth.npz")
    return session, test, region_indices(session), truth, load_face_model(ICT)


def ict_mesh_truth(model, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face-region mesh (rest (V, 3), faces) and true vertices (F, V, 3) mm of a synthetic take."""
    nv = model.face_vertex_count
    rest = model.neutral[:nv] + np.einsum("i,ivc->vc", truth.identity_coefficients, model.identities[:, :nv])
    faces = model.faces[:model.face_triangle_count]
    verts = rest[None] + np.einsum("fb,bvc->fvc", truth.weights, model.blendshapes[:, :nv])
    return rest, faces, verts


def ict_learned_map(model, session, rest, faces, folder: Path, *, step: int = 3, neighbours: int = 16):
    """``MeshMap.learned`` on the synthetic session's own true mesh (every ``step``-th frame)."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.solve import MeshMap

    weights = load_ground_truth(folder / "full_truth.npz").weights[::step]
    nv = len(rest)
    verts = (rest[None] + np.einsum("fb,bvc->fvc", weights, model.blendshapes[:, :nv])).astype(np.float32)
    return MeshMap.learned(rest, faces, session.positions[::step], verts, neighbours=neighbours)


def rmse_p95(err: np.ndarray) -> tuple[float, float]:
    e = err[np.isfinite(err)]
    return float(np.sqrt(np.mean(e ** 2))), float(np.percentile(e, 95))


def accuracy(kinds: tuple[str, ...] = KINDS) -> dict:
    from mocaptk.clustering.evaluation import error_summary, heldout_errors, holdout_splits
    from mocaptk.clustering.reconstruction_models import fit_model
    from mocaptk.clustering.pipeline import load_session
    from mocaptk.retarget.solve import MeshMap

    out: dict = {}
    session, test, regions = sample_data()
    for count in (20, 40, 80):
        idx = kmeans(session.positions, count)
        for kind in kinds:
            err = heldout_errors(session.positions, idx, [], test=test.positions, model_kind=kind)
            out[f"sample/{count}/{kind}"] = error_summary(err, regions=regions)
            print("sample", count, kind, round(out[f"sample/{count}/{kind}"]["rmse_mm"], 3), flush=True)
    if ICT.exists():
        folder = Path(tempfile.gettempdir()) / "mocaptk_bench_solve_ict"
        folder.mkdir(exist_ok=True)
        session, test, regions, truth, face = ict_data(folder)
        rest, faces, true_verts = ict_mesh_truth(face, truth)
        learned = ict_learned_map(face, session, rest, faces, folder)
        for count in (20, 40, 80):
            idx = kmeans(session.positions, count)
            for kind in kinds:
                model = fit_model(session.positions, idx, kind=kind, expected_error=False)
                pred = model.predict(test.positions[:, model.layout]).positions
                # markers: against the noise-free truth (the capture's own noise is not an error)
                err = np.linalg.norm(pred - truth.positions, axis=2)
                summary = error_summary(err, regions=regions)
                mesh = MeshMap.anchored(rest, faces, truth.vertices, model.neutral)
                verts = mesh.apply(pred)
                summary["mesh_rmse_mm"], summary["mesh_p95_mm"] = rmse_p95(
                    np.linalg.norm(verts - true_verts, axis=2))
                # the map learned on the session's true mesh (vertices beyond the markers too)
                summary["learned_mesh_rmse_mm"], summary["learned_mesh_p95_mm"] = rmse_p95(
                    np.linalg.norm(learned.apply(pred) - true_verts, axis=2))
                out[f"ict/{count}/{kind}"] = summary
                print("ict", count, kind, round(summary["rmse_mm"], 3), round(summary["mesh_rmse_mm"], 3),
                      round(summary["learned_mesh_rmse_mm"], 3), flush=True)
    for subject in ("Subject_01", "Subject_02"):
        path = BLENDERFACE / f"{subject}.csv"
        if not path.exists():
            continue
        traj, _ = load_session(str(path), rate=25, units="187")
        splits = holdout_splits(traj.n_frames, traj.takes, split="takes")
        for count in (3, 6, 8):
            idx = kmeans(traj.positions, count)
            for kind in kinds:
                err = heldout_errors(traj.positions, idx, splits, model_kind=kind)
                out[f"{subject}/{count}/{kind}"] = error_summary(err)
                print(subject, count, kind, round(out[f"{subject}/{count}/{kind}"]["rmse_mm"], 3), flush=True)
    return out


def robustness(kinds: tuple[str, ...] = KINDS, step: int = 1) -> dict:
    """RMSE (mm, sample performance (every ``step``-th frame), 40-marker k-means layout) as layout
    markers are lost: 0/1/2/5/20 % at random per frame, and the lower-lip layout markers lost for
    the whole take."""
    from mocaptk.clustering.reconstruction_models import fit_model

    session, test, _ = sample_data()
    test = test.replace(positions=test.positions[::step], residuals=None, metadata={})
    idx = kmeans(session.positions, 40)
    labels = [session.labels[i] for i in idx]
    lower_lip = np.array([label.startswith(("MOUTH", "CHIN")) and session.positions[:, i, 1].mean()
                          < np.nanmedian(session.positions[:, idx, 1]) for label, i in zip(labels, idx)])
    out: dict = {"lower_lip_markers": [lab for lab, low in zip(labels, lower_lip) if low]}
    rng = np.random.default_rng(0)
    for kind in kinds:
        model = fit_model(session.positions, idx, kind=kind)
        x = test.positions[:, model.layout]
        row = {}
        for rate in (0.0, 0.01, 0.02, 0.05, 0.2):
            lost = x.copy()
            lost[rng.random(x.shape[:2]) < rate] = np.nan
            pred = model.predict(lost)
            ok = np.isfinite(pred.positions).all(axis=(1, 2))
            err = np.linalg.norm(pred.positions[ok] - test.positions[ok], axis=2)
            row[f"{rate:.0%}"] = {"rmse_mm": rmse_p95(err)[0], "max_mm": float(np.nanmax(err)),
                                  "expected_mm": float(np.nanmean(pred.expected_error_mm))}
        lost = x.copy()
        lost[:, lower_lip] = np.nan
        pred = model.predict(lost)
        err = np.linalg.norm(pred.positions - test.positions, axis=2)
        row["lower lip"] = {"rmse_mm": rmse_p95(err)[0], "max_mm": float(np.nanmax(err)),
                            "expected_mm": float(np.nanmean(pred.expected_error_mm))}
        out[kind] = row
        print(kind, {k: round(v["rmse_mm"], 3) for k, v in row.items()}, flush=True)
    return out


def speed(kinds: tuple[str, ...] = KINDS) -> dict:
    """Training time and frames/s: 86 layout markers -> 139 dense markers and -> the ICT face."""
    from mocaptk.clustering.reconstruction_models import fit_model
    from mocaptk.retarget.solve import MeshMap, solve_chunks, FaceSolver

    session, test, _ = sample_data()
    idx = kmeans(session.positions, 86)
    frames = np.tile(test.positions[:, idx], (10, 1, 1))  # 12,000 frames
    lossy = frames.copy()
    lossy[np.random.default_rng(1).random(lossy.shape[:2]) < 0.002] = np.nan  # occasional dropouts
    out: dict = {"frames": int(len(frames))}
    mesh = None
    if ICT.exists():
        from mocaptk.acquisition.face_model import load_face_model

        face = load_face_model(ICT)
        nv = face.face_vertex_count
        # the sample's markers are anchored on the ICT face: take each marker's nearest face vertex
        from scipy.spatial import cKDTree

        rest = face.neutral[:nv]
        model0 = fit_model(session.positions[:100], idx, kind="ridge")
        anchors = cKDTree(rest).query(model0.neutral)[1]
        mesh = MeshMap.anchored(rest, face.faces[:face.face_triangle_count], anchors, model0.neutral)
        out["mesh_vertices"] = int(nv)
    for kind in kinds:
        t0 = time.perf_counter()
        model = fit_model(session.positions, idx, kind=kind)
        train_s = time.perf_counter() - t0
        solver = FaceSolver(model, session.labels, tuple(session.labels[i] for i in model.layout), (),
                            None, {})
        row = {"train_s": train_s}
        for name, data in (("clean", frames), ("0.2% lost", lossy)):
            t0, c0 = time.perf_counter(), time.process_time()
            for part in solve_chunks(solver, data):
                pass
            row[f"markers_fps_{name}"] = len(data) / (time.perf_counter() - t0)
            row[f"markers_fps_per_cpu_s_{name}"] = len(data) / (time.process_time() - c0)
        if mesh is not None:
            t0, c0 = time.perf_counter(), time.process_time()
            for part in solve_chunks(solver, frames):
                mesh.apply(part.positions)
            row["mesh_fps_clean"] = len(frames) / (time.perf_counter() - t0)
            row["mesh_fps_per_cpu_s_clean"] = len(frames) / (time.process_time() - c0)
        out[kind] = row
        print(kind, {k: round(v, 1) for k, v in row.items()}, flush=True)
    return out


def memory() -> dict:
    """Peak RSS of writing a 72,000-frame solve (dense.c3d + mesh_frames.npy of the 511-vertex
    mesh, 441 MB on disk) in a fresh process."""
    code = f"""
import resource, numpy as np, sys, tempfile, pathlib
sys.path.insert(0, {str(REPO)!r})
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.clustering.pipeline import load_session
from mocaptk.clustering.layout import read_layout
from mocaptk.retarget.solve import train_solver
from mocaptk.retarget.solve_outputs import write_solve_outputs
session, source = load_session({str(REPO / 'sample_c3d' / 'dense_halfface.c3d')!r})
test = read_trajectories({str(REPO / 'sample_c3d' / 'dense_halfface_performance.c3d')!r})
from mocaptk.clustering.baselines import kmeans_layout
from mocaptk.clustering.neutral import neutral_pose
idx = np.unique(kmeans_layout(session.positions[::5] - neutral_pose(session.positions)[None], 86, seed=0))
labels = [session.labels[i] for i in idx]
class L: labels = labels
solver = train_solver(L, session, source)  # the default model kind
capture = test.select(labels)
capture = capture.replace(positions=np.tile(capture.positions, (60, 1, 1)), residuals=None, metadata={{}})
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
with tempfile.TemporaryDirectory() as d:
    write_solve_outputs(solver, capture, {{"path": "long.c3d"}}, pathlib.Path(d), formats=("npz",),
                        subdivisions=1)
print(capture.n_frames, base, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    frames, before, peak = map(int, done.stdout.split())
    out = {"frames": frames, "rss_before_solve_mb": before / 1024, "peak_rss_mb": peak / 1024,
           "seconds": time.perf_counter() - t0}
    print(out)
    return out


def memory_face(frames_per_take: int = 60) -> dict:
    """Peak anonymous memory (RssAnon: the mesh_frames.npy memmap's file pages left out) of
    ``mocaptk solve`` with ``--formats npz`` and with the default formats (mesh.usd in value clips,
    mesh.glb) on the sample performance tiled ``frames_per_take`` times (72,000 frames) with head
    motion added (±5°, ±10 mm), through the sample's layout and the default face (~9,400
    vertices); sampled every 20 ms in the solving process."""
    from scipy.spatial.transform import Rotation

    from mocaptk.acquisition.formats import read_trajectories, write_trajectories
    from mocaptk.retarget.solve_outputs import SOLVE_FORMATS

    watcher = """
import os, sys, threading, time
from mocaptk.cli import main
peak = [0]
def watch():
    while True:
        with open("/proc/self/status") as f:
            peak[0] = max(peak[0], next(int(l.split()[1]) for l in f if l.startswith("RssAnon")))
        time.sleep(0.02)
threading.Thread(target=watch, daemon=True).start()
try:
    main(sys.argv[1:])
except SystemExit as exit:
    assert not exit.code, exit.code
print(peak[0])
"""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        subprocess.run([sys.executable, "-m", "mocaptk", "cluster", str(REPO / "sample_c3d" / "dense_halfface.c3d"),
                        "--factor", "1.1", "--out", str(tmp / "layout"), "-q"], check=True)
        take = read_trajectories(REPO / "sample_c3d" / "dense_halfface_performance.c3d")
        positions = np.tile(take.positions, (frames_per_take, 1, 1))
        seconds = np.arange(len(positions)) / take.rate
        angles = np.stack([5 * np.sin(2 * np.pi * seconds / p) for p in (7.1, 5.3, 9.7)], axis=1)
        shift = np.stack([a * np.sin(2 * np.pi * seconds / p) for a, p in ((10, 6.1), (5, 8.3), (8, 4.9))], axis=1)
        centre = np.nanmean(take.positions[0], axis=0)
        rotation = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
        positions = np.einsum("fij,fmj->fmi", rotation, positions - centre) + centre + shift[:, None]
        write_trajectories(take.replace(positions=positions, residuals=None, metadata={}), tmp / "moving.c3d")
        out = {"frames": len(positions)}
        for formats in ("npz", ",".join(SOLVE_FORMATS)):
            t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
            done = subprocess.run([sys.executable, "-c", watcher, "solve", str(tmp / "layout" / "layout.json"),
                                   str(tmp / "moving.c3d"), "--out", str(tmp / formats), "--formats", formats,
                                   "-q"], capture_output=True, text=True, check=True)
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            files = [p for p in (tmp / formats).rglob("*") if p.is_file()]
            out[formats] = {"peak_anonymous_mb": int(done.stdout.split()[-1]) / 1024,
                            "outputs_mb": {p.name: p.stat().st_size / 2**20 for p in files
                                           if p.parent == tmp / formats},
                            "usd_clips": sum(p.suffix == ".usdc" for p in files),
                            "seconds": time.perf_counter() - t0,
                            "cpu_seconds": c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime}
            print(formats, out[formats], flush=True)
            shutil.rmtree(tmp / formats)
    print(out)
    return out


def maps(folder: Path) -> None:
    """Per-marker RMSE on the sample performance (20-marker layout), the default model vs ridge, drawn
    on the marker surface; and per-vertex RMSE on the ICT face (40 markers)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    from mocaptk.clustering.reconstruction_models import DEFAULT_KIND, fit_model
    from mocaptk.retarget.solve import MeshMap

    folder.mkdir(parents=True, exist_ok=True)
    session, test, _ = sample_data()
    idx = kmeans(session.positions, 20)
    sets = []
    for kind in ("ridge", DEFAULT_KIND):
        model = fit_model(session.positions, idx, kind=kind)
        err = np.linalg.norm(model.predict(test.positions[:, model.layout]).positions - test.positions, axis=2)
        sets.append((kind, np.sqrt(np.nanmean(err ** 2, axis=0))))
    mesh = MeshMap.marker_surface(model.neutral, subdivisions=0)
    _draw(plt, Triangulation(mesh.vertices[:, 0], mesh.vertices[:, 1], mesh.faces), sets, model.neutral[idx],
          folder / "error_map_sample.png", "sample half face, 20 layout markers, held-out performance")
    if ICT.exists():
        session, test, _, truth, face = ict_data(Path(tempfile.gettempdir()) / "mocaptk_bench_solve_ict")
        rest, faces, true_verts = ict_mesh_truth(face, truth)
        idx = kmeans(session.positions, 40)
        sets = []
        for kind in ("ridge", DEFAULT_KIND):
            model = fit_model(session.positions, idx, kind=kind)
            pred = model.predict(test.positions[:, model.layout]).positions
            verts = MeshMap.anchored(rest, faces, truth.vertices, model.neutral).apply(pred)
            sets.append((kind, np.sqrt(np.mean(np.sum((verts - true_verts) ** 2, axis=2), axis=0))))
        _draw(plt, Triangulation(rest[:, 0], rest[:, 1], faces), sets, truth.marker_neutral[idx],
              folder / "error_map_ict.png", "ICT full face, 40 layout markers, per mesh vertex")


def skin_refit(repeat: int = 5) -> dict:
    """``solve``'s skin-following pose refit (``retarget.solve._following_skin``) with the model
    predicting only the pose markers it keeps (``predict_markers`` of the ridge kinds) against
    predicting every dense marker and keeping those (``FaceModel.predict_markers``: the code
    before), alternating in one process, CPU seconds of ``head_poses`` (best of ``repeat``) and the
    largest pose difference. Data: the independent generator's headband actor (tb-full-a-hb): its
    ROM trains the default model on ``cluster``'s 40-marker layout, its 60 s performance (3,600
    frames, 184 markers) moves with the head (8° / 15 mm) and holds the layout's markers only."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from testbed.session import apply_pose, head_motion, load_truth
    from testbed.sets import ensure_set, ict_tarball

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.clustering.layout import layout_rigid_set, read_layout
    from mocaptk.clustering.reconstruction_models import FaceModel
    from mocaptk.retarget.solve import head_poses, train_solver
    from mocaptk.threads import one_thread
    from mocaptk.trajectories import Trajectories

    with tempfile.TemporaryDirectory() as tmp, one_thread():
        folder = ensure_set(ict_tarball(), Path(tmp), "tb-full-a-hb")
        subprocess.run([sys.executable, "-m", "mocaptk", "cluster", str(folder / "rom.c3d"), "--markers", "40",
                        "--formats", "none", "--quiet", "--out", str(Path(tmp) / "lay")], check=True)
        layout = read_layout(Path(tmp) / "lay" / "layout.json")
        session = read_trajectories(folder / "rom.c3d")
        solver = train_solver(layout, session, {"path": "rom.c3d"}, rigid_labels=layout_rigid_set(layout))
        truth, header = load_truth(folder / "performance_truth.npz")
        world = apply_pose(truth, *head_motion(len(truth), max_deg=8.0, max_mm=15.0, seed=7))
        worn = [header["labels"].index(m) for m in (*solver.layout_labels, *solver.rigid_labels)]
        capture = Trajectories(world[:, worn], tuple(header["labels"][i] for i in worn), 60.0)
        timings: dict[str, list[float]] = {"all markers (before)": [], "pose markers only (now)": []}
        poses = {}
        for _ in range(repeat):
            for name in timings:
                if name.startswith("all"):  # the instance's attribute shadows its class's method
                    solver.model.predict_markers = FaceModel.predict_markers.__get__(solver.model)
                else:
                    vars(solver.model).pop("predict_markers", None)
                started = time.process_time()
                poses[name] = head_poses(solver, capture)
                timings[name].append(time.process_time() - started)
        before, now = poses.values()
        result = {"model": solver.model.kind, "frames": capture.n_frames, "dense markers": len(solver.labels),
                  "pose markers predicted": sum(label not in solver.layout_labels for label in before.labels),
                  **{f"{name}, CPU s": min(t) for name, t in timings.items()},
                  "max rotation difference": float(np.nanmax(np.abs(before.rotations - now.rotations))),
                  "max translation difference mm": float(np.nanmax(np.abs(before.translations - now.translations)))}
        result["speed-up"] = result["all markers (before), CPU s"] / result["pose markers only (now), CPU s"]
        print(json.dumps(result, indent=1))
        return result


def _draw(plt, tri, sets, layout_points, path: Path, title: str) -> None:
    vmax = max(float(np.nanpercentile(v, 99)) for _, v in sets)
    fig, axes = plt.subplots(1, len(sets), figsize=(5 * len(sets), 5.6), constrained_layout=True)
    for ax, (kind, values) in zip(axes, sets):
        shade = ax.tripcolor(tri, np.nan_to_num(values), shading="gouraud", cmap="magma", vmin=0, vmax=vmax)
        ax.plot(layout_points[:, 0], layout_points[:, 1], "o", ms=3, mfc="none", mec="cyan")
        ax.set_title(f"{kind}: RMSE {np.sqrt(np.nanmean(values ** 2)):.3f} mm")
        ax.set_aspect("equal")
        ax.set_xticks([]), ax.set_yticks([])
    fig.colorbar(shade, ax=list(axes), label="per-point RMSE over the take (mm)", shrink=0.8)
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print("wrote", path)


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "speed"
    print(f"load: {open('/proc/loadavg').read().split()[:3]}")
    if what == "maps":
        maps(Path(sys.argv[2] if len(sys.argv) > 2 else "."))
    elif what == "speed" and len(sys.argv) > 3:  # speed OUT.json KIND,KIND
        Path(sys.argv[2]).write_text(json.dumps(speed(tuple(sys.argv[3].split(","))), indent=1))
    elif what == "accuracy" and len(sys.argv) > 3:  # accuracy OUT.json KIND,KIND
        Path(sys.argv[2]).write_text(json.dumps(accuracy(tuple(sys.argv[3].split(","))), indent=1, sort_keys=True))
    elif what == "robustness" and len(sys.argv) > 3:  # robustness OUT.json KIND,KIND STEP
        result = robustness(tuple(sys.argv[3].split(",")), int(sys.argv[4]) if len(sys.argv) > 4 else 1)
        Path(sys.argv[2]).write_text(json.dumps(result, indent=1, sort_keys=True))
    else:
        result = {"speed": speed, "memory": memory, "memory-face": memory_face, "accuracy": accuracy,
                  "robustness": robustness, "skin-refit": skin_refit}[what]()
        if len(sys.argv) > 2:
            Path(sys.argv[2]).write_text(json.dumps(result, indent=1, sort_keys=True))
