"""``mocaptk retarget``: weight recovery against ground truth, lost markers, speed and memory.

    python benchmarks/bench_retarget.py accuracy [default,20,40]   # actors x characters x layout sizes, baselines
    BENCH_RETARGET_CHARACTERS=generic ...                          # the generic rig only (no stylized character)
    BENCH_RETARGET_SETS=1 BENCH_RETARGET_CLUSTER="--method set-cover --character arkit" \
        python benchmarks/bench_retarget.py accuracy 20,40            # the character's own layouts
    python benchmarks/bench_retarget.py gain         # where the ROM calibration's gain is (range step / learned shapes)
    python benchmarks/bench_retarget.py reach        # ROM extremes vs truth; Ribera's alignment variants
    python benchmarks/bench_retarget.py lost         # 0/5/20 % lost per frame, lower lip lost 10 s
    python benchmarks/bench_retarget.py speed        # frames/s: 52 shapes from 50 markers, vs lsq_linear
    python benchmarks/bench_retarget.py memory       # peak memory of a 72,000-frame retarget (subprocess)

Data: the bundled sample (half face, its held-out 20 s performance and truth) and a full face made
by ``mocaptk synth --full --identity 1.5,-1.0,0.8`` (ICT-FaceKit identity ≠ the generic rig's
face), both onto ``--character arkit``. Truth: the ICT weights per frame as ARKit's 52 (split
``_L``/``_R`` shapes averaged). Figures over the shapes that move (truth > 0.1 somewhere): per-shape
MAE and Pearson r, their means; mesh RMSE = the generic rig driven by solved vs true weights (mm,
every face vertex). Baselines: unconstrained least squares (calibrated shapes, no bounds),
NNLS on raw displacements with the character's shapes and no ROM calibration (Zell's protocol),
and ``solve`` → dense markers → NNLS (every dense marker, the character's shapes).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_c3d"
ICT = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data")) / "face_mesh" / "ict_facekit" / "ict_facekit_FaceXModel_subset.tar.xz"
IDENTITY = "1.5,-1.0,0.8"
#: ROM reaches compared: Ribera's full protocol (1) and about what our synthetic ROMs reach (their
#: truth: median 0.77-0.79 of each shape's range; each expression at 0.45-1 intensity).
REACHES = (1.0, 0.8)


def mocaptk(*args) -> None:
    env = {**os.environ, "MOCAPTK_ICT_FACEKIT": str(ICT)}
    done = subprocess.run([sys.executable, "-m", "mocaptk", *map(str, args)], capture_output=True,
                          text=True, env=env)
    if done.returncode:
        raise SystemExit(done.stderr)


def datasets(work: Path) -> list[tuple[str, Path, Path, Path]]:
    """(name, session, performance, performance truth) for the sample, the synthetic full face and
    the same actor with a fuller ROM (20 expressions per region: every action several times, so
    its extremes come closer to the rig's 1); ``BENCH_RETARGET_SETS`` picks some (0,1,2), and 3
    adds ``benchmarks/testbed``'s ``tb-full-a-hb`` (no mocaptk code made it; its markers leave
    the eyelids out, its performance has gaze saccades)."""
    sets = []
    for folder, expressions in (("full", 5), ("fullrom", 20)):
        full = work / folder
        if not (full / "actor.c3d").is_file():
            full.mkdir(parents=True, exist_ok=True)
            mocaptk("synth", full / "actor.c3d", "--full", "--identity", IDENTITY, "--spacing", "10",
                    "--rig", "none", "--seed", "11", "--noise", "0.2", "--expressions", expressions,
                    "--rest", "1.5", "--hold", "2.0", "--performance", "20", "--quiet", "--force")
        sets.append((f"synth --full --identity {IDENTITY} --expressions {expressions}", full / "actor.c3d",
                     full / "actor_performance.c3d", full / "actor_performance_truth.npz"))
    every = [("sample (half face)", SAMPLES / "dense_halfface.c3d", SAMPLES / "dense_halfface_performance.c3d",
              SAMPLES / "dense_halfface_performance_truth.npz"), *sets]
    chosen = os.environ.get("BENCH_RETARGET_SETS")
    if chosen and "3" in chosen.split(","):  # the independent generator: made on demand (minutes)
        sys.path.insert(0, str(REPO / "benchmarks"))
        from testbed.sets import ensure_set, ict_tarball

        folder = ensure_set(ict_tarball(), work / "sets", "tb-full-a-hb")
        every.append(("testbed tb-full-a-hb (independent generator)", folder / "rom.c3d",
                      folder / "performance.c3d", folder / "performance_truth.npz"))
    return [every[int(i)] for i in chosen.split(",")] if chosen else every


def arkit_truth(truth) -> np.ndarray:
    from mocaptk.retarget.character import ARKIT_NAMES, arkit_name

    out = np.zeros((len(truth.weights), 52))
    for j, name in enumerate(truth.blendshape_names):
        split = arkit_name(name) is None
        target = arkit_name(name) or arkit_name(name[:-2])
        if target is None:  # the testbed's ICT cheekRaiser_L/_R: no ARKit shape
            continue
        out[:, ARKIT_NAMES.index(target)] += truth.weights[:, j] * (0.5 if split else 1.0)
    return out


def truth_weights(path: Path, *, rom: bool = False) -> np.ndarray:
    """(F, 52) ARKit weights of a performance truth file (``rom``: of its session's truth), from
    ``synth``'s truth or the testbed's (its ICT expression names from the testbed's own reader)."""
    from types import SimpleNamespace

    from mocaptk.acquisition.synth_session import load_ground_truth

    if path.name == "performance_truth.npz":  # the testbed
        from testbed.ict import load_ict
        from testbed.sets import ict_tarball

        with np.load(path.with_name("rom_truth.npz") if rom else path) as data:
            weights = data["weights"].astype(np.float64)
        return arkit_truth(SimpleNamespace(blendshape_names=load_ict(ict_tarball()).expression_names,
                                           weights=weights))
    return arkit_truth(load_ground_truth(path.with_name(path.name.replace("_performance", "")) if rom else path))


def scores(weights: np.ndarray, truth: np.ndarray, rig) -> dict:
    moving = (truth > 0.1).any(axis=0)
    mae = np.abs(weights - truth).mean(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.array([np.corrcoef(weights[:, k], truth[:, k])[0, 1] if weights[:, k].std() > 0 else 0.0
                      for k in range(truth.shape[1])])
    step = max(1, len(truth) // 200)  # mesh RMSE on 200 frames (9,409 vertices each)
    diff = np.tensordot((weights - truth)[::step].astype(np.float32), rig.deltas, axes=(1, 0))
    return {"mae": float(mae[moving].mean()), "r": float(r[moving].mean()),
            "mesh_rmse_mm": float(np.sqrt(np.mean(np.sum(diff ** 2, axis=2)))),
            "per_shape": {rig.names[k]: (round(float(mae[k]), 4), round(float(r[k]), 3))
                          for k in np.flatnonzero(moving)}}


def stylized(rig):
    """A character with other proportions *and* other motion: the generic rig with a 20 % wider
    jaw and an 8 mm longer nose (its shapes bent with it), every shape's amplitude scaled by a
    fixed factor in [0.6, 1.6] (blinks kept at 1: the lids must still close) — where the ROM
    calibration should matter: the character's shapes at the markers are not the actor's motion."""
    def warp(v: np.ndarray) -> np.ndarray:
        v = v.copy()
        v[..., 0] *= 1 + 0.2 * np.clip((-40.0 - v[..., 1]) / 40.0, 0, 1)
        tip = rig.vertices[np.argmax(rig.vertices[:, 2])]
        v[..., 2] += 8.0 * np.exp(-np.sum((v - tip) ** 2, axis=-1) / (2 * 15.0 ** 2))
        return v

    factor = np.random.default_rng(3).uniform(0.6, 1.6, len(rig.names))
    factor[[i for i, n in enumerate(rig.names) if "Blink" in n]] = 1.0
    vertices = warp(rig.vertices.astype(np.float64))
    deltas = (warp(rig.vertices[None] + rig.deltas.astype(np.float64)) - vertices) * factor[:, None, None]
    return rig.replace(vertices=vertices, deltas=deltas.astype(np.float32), source="stylized"), factor


class Actor:
    """A session fitted once per character (correspondence + calibration, both alignments)."""

    def __init__(self, session_path: Path, character) -> None:
        from mocaptk.acquisition.c3d_read import read_c3d
        from mocaptk.retarget.retarget_outputs import fit_retargeter

        self.session = read_c3d(session_path)
        self.rig = character
        start = time.perf_counter(), time.process_time()
        self.retargeter = fit_retargeter(self.rig, self.session)
        self.fit_seconds = (time.perf_counter() - start[0], time.process_time() - start[1])
        self.reached = {q: fit_retargeter(self.rig, self.session, reach=q) for q in REACHES}
        self.geometric = fit_retargeter(self.rig, self.session, by_motion=False)  # before the motion step

    def methods(self, layout_path: Path, capture) -> dict[str, np.ndarray]:
        from scipy.optimize import nnls

        from mocaptk.clustering.layout import read_layout
        from mocaptk.retarget.retarget_outputs import Retargeter, retarget_capture
        from mocaptk.retarget.rom_calibration import Calibration
        from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver

        layout = read_layout(layout_path)
        solver = train_solver(layout, self.session, {"path": None, "sha256": None})
        ours = retarget_capture(self.retargeter, solver, capture, "capture")
        n = len(self.rig.names)
        uncalibrated = Retargeter(self.rig, None, Calibration(
            self.retargeter.correspondence.shape_basis(self.rig), self.retargeter.calibration.neutral,
            self.retargeter.calibration.ties, np.ones(n), np.ones(n)), self.retargeter.labels)
        same_solve = retarget_capture(uncalibrated, solver, capture, "capture")
        corr, labels = self.retargeter.correspondence, list(self.retargeter.labels)
        prior = corr.shape_basis(self.rig)
        cal = self.retargeter.calibration
        rows = np.array([labels.index(label) for label in solver.layout_labels])
        d = layout_frames(solver, capture, "capture") - cal.neutral[rows]
        ties = cal.ties

        def tied(basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            variables, inverse = np.unique(ties, return_inverse=True)
            out = np.zeros((len(variables), *basis.shape[1:]))
            np.add.at(out, inverse, basis)
            return out, inverse

        def per_frame(basis: np.ndarray, disp: np.ndarray, bounded: bool) -> np.ndarray:
            b, inverse = tied(basis)
            a = b.reshape(len(b), -1).T
            out = np.zeros((len(disp), len(b)))
            for f, frame in enumerate(disp.reshape(len(disp), -1)):
                ok = np.isfinite(frame)
                out[f] = nnls(a[ok], frame[ok])[0] if bounded else np.linalg.lstsq(a[ok], frame[ok], rcond=None)[0]
            return out[:, inverse]

        dense = np.concatenate([c.positions for c in solve_chunks(solver, layout_frames(solver, capture, "capture"))])
        return {"ours (ROM-calibrated, stretch; bounded, L1, smooth)": ours.weights,
                "ours, geometric correspondence only (before)": retarget_capture(
                    self.geometric, solver, capture, "capture", hold_unseen=False).weights,
                "ours, unseen shapes not held at 0": retarget_capture(
                    self.retargeter, solver, capture, "capture", hold_unseen=False).weights,
                **{f"ours, ROM extremes aligned (--rom-reach {q})": retarget_capture(r, solver, capture, "capture").weights
                   for q, r in self.reached.items()},
                "same solve without ROM calibration": same_solve.weights,
                "unconstrained least squares": per_frame(cal.basis[:, rows], d, False),
                "NNLS, raw displacements, no ROM (Zell)": per_frame(prior[:, rows], d, True),
                "solve -> dense -> NNLS": per_frame(prior, dense - cal.neutral, True),
                "solve -> dense -> ours on the calibrated dense basis": dense_calibrated(cal, dense)}


def dense_calibrated(cal, dense: np.ndarray) -> np.ndarray:
    """Weights (F, S) from ``solve``'s dense prediction (F, M, 3) with the calibrated dense basis."""
    from mocaptk.retarget.weight_solve import solve_weights

    basis, inverse = cal.tied_basis()
    return solve_weights(basis, dense - cal.neutral).weights[:, inverse]


def accuracy() -> None:
    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.retarget.character_files import load_character

    generic = load_character("arkit")
    other, factor = stylized(generic)
    print(f"stylized character: amplitude factors {np.round(factor, 2).tolist()}")
    sizes = [None, 20, 40] if len(sys.argv) < 3 else [None if s == "default" else int(s) for s in sys.argv[2].split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("BENCH_RETARGET_WORK", tmp))
        for name, session, performance, truth_path in datasets(work):
            truth, rom = truth_weights(truth_path), truth_weights(truth_path, rom=True)
            capture = read_c3d(performance)
            reached = rom.max(axis=0)[(rom > 0.1).any(axis=0)]
            print(f"\n## {name}: the ROM reaches {np.median(reached):.2f} of the rig's range (median over "
                  f"its shapes; {reached.min():.2f}-{reached.max():.2f})")
            characters = (generic, other) if os.environ.get("BENCH_RETARGET_CHARACTERS") != "generic" else (generic,)
            for rig in characters:
                actor = Actor(session, rig)
                print(f"\n### onto {rig.source}: fit + calibration {actor.fit_seconds[0]:.1f} s wall, "
                      f"{actor.fit_seconds[1]:.1f} s CPU")
                print("| layout markers | method | mean MAE | mean r | mesh RMSE mm |\n|---|---|---|---|---|")
                for size in sizes:
                    extra = os.environ.get("BENCH_RETARGET_CLUSTER", "").split()  # e.g. "--method set-cover --character arkit"
                    tag = "_".join(x.strip("-") for x in extra)
                    folder = work / f"layout_{session.parent.name}_{session.stem}_{size or 'default'}{'_' + tag if tag else ''}"
                    if not (folder / "layout.json").is_file():
                        mocaptk("cluster", session, "--out", folder, "--formats", "none", "--quiet", "--force",
                                *(("--markers", size) if size else ()), *extra)
                    results = actor.methods(folder / "layout.json", capture)
                    count = len(json.loads((folder / "layout.json").read_text())["layout"])
                    for method, weights in results.items():
                        s = scores(weights, truth, actor.rig)
                        print(f"| {count}{'' if size else ' (default)'} | {method} | {s['mae']:.3f} | "
                              f"{s['r']:.3f} | {s['mesh_rmse_mm']:.2f} |", flush=True)
                        if method.startswith("ours") and size is None:
                            worst = sorted(s["per_shape"].items(), key=lambda kv: kv[1][1])[:5]
                            print(f"|  | worst r: {', '.join(f'{k} {v[1]:.2f}' for k, v in worst)} | | | |")
                            if os.environ.get("BENCH_RETARGET_PER_SHAPE"):
                                print("|  | per shape (MAE, r): " + ", ".join(
                                    f"{k} {v[0]:.3f}/{v[1]:.2f}" for k, v in s["per_shape"].items()) + " | | | |")


def gain() -> None:
    """Where the ROM calibration's gain is: the range step alone (``calibrate(rounds=0)``) vs the
    learned shapes alone vs both, default layout, both characters; and each calibrated shape's
    amplitude at the dense markers against the actor's own motion (the generic rig through its
    correspondence) — median |log ratio|, and its correlation with the stylized factors."""
    from dataclasses import replace

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.character_files import load_character
    from mocaptk.retarget.retarget_outputs import fit_retargeter, retarget_capture
    from mocaptk.retarget.rom_calibration import Calibration, calibrate
    from mocaptk.retarget.solve import train_solver

    generic = load_character("arkit")
    other, factor = stylized(generic)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("BENCH_RETARGET_WORK", tmp))
        for name, session_path, performance, truth_path in datasets(work):
            truth, capture, session = truth_weights(truth_path), read_c3d(performance), read_c3d(session_path)
            folder = work / f"layout_{session_path.parent.name}_{session_path.stem}_default"
            if not (folder / "layout.json").is_file():
                mocaptk("cluster", session_path, "--out", folder, "--formats", "none", "--quiet", "--force")
            solver = train_solver(read_layout(folder / "layout.json"), session, {})
            own = fit_retargeter(generic, session).correspondence.shape_basis(generic)  # the actor's motion
            norm = np.linalg.norm(own.reshape(len(own), -1), axis=1)
            moving = norm > 0.5 * np.median(norm[norm > 0])
            characters = (generic, other) if os.environ.get("BENCH_RETARGET_CHARACTERS") != "generic" else (generic,)
            for rig in characters:
                fitted = fit_retargeter(rig, session)
                cal, prior, n = fitted.calibration, fitted.correspondence.shape_basis(rig), len(rig.names)
                variants = {"no calibration": Calibration(prior, cal.neutral, cal.ties, np.ones(n), np.ones(n)),
                            "range step only": calibrate(session.positions, cal.neutral, prior, cal.ties, rounds=0),
                            "learned shapes only": replace(cal, basis=cal.basis / cal.stretch[:, None, None],
                                                           stretch=np.ones(n)),
                            "both (default)": cal}
                print(f"\n## {name} onto {rig.source}\n| calibration | MAE | r | mesh mm | amplitude vs the actor's: "
                      f"median abs log ratio | corr with the stylized factors |\n|---|---|---|---|---|---|")
                for label, variant in variants.items():
                    s = scores(retarget_capture(replace(fitted, calibration=variant), solver, capture,
                                                "capture").weights, truth, rig)
                    ratio = (np.linalg.norm(variant.basis.reshape(n, -1), axis=1) / np.maximum(norm, 1e-12))[moving]
                    follows = f"{np.corrcoef(ratio, factor[moving])[0, 1]:.2f}" if rig is other else "-"
                    print(f"| {label} | {s['mae']:.3f} | {s['r']:.3f} | {s['mesh_rmse_mm']:.2f} | "
                          f"{np.median(np.abs(np.log(ratio))):.3f} | {follows} |", flush=True)


#: ``reach``: a shape "shows its extreme" when its 2nd-highest ROM peak is this close to the highest.
PEAK_AGREEMENT = 0.9


def reach() -> None:
    """Ribera's range alignment on our ROMs: each shape's ROM extreme as the calibration estimates
    it against the ROM's truth; alignment of only the shapes whose ROM repeats its peak; and an
    oracle aligning every shape with its true ROM reach (default layout, both characters)."""
    from dataclasses import replace

    from scipy.signal import find_peaks

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.character_files import load_character
    from mocaptk.retarget.retarget_outputs import fit_retargeter, retarget_capture
    from mocaptk.retarget.rom_calibration import MAX_FRAMES, MIN_PERFORMED, _rom_weights
    from mocaptk.retarget.solve import train_solver

    generic = load_character("arkit")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("BENCH_RETARGET_WORK", tmp))
        for name, session_path, performance, truth_path in datasets(work):
            truth, true_reach = truth_weights(truth_path), truth_weights(truth_path, rom=True).max(axis=0)
            capture, session = read_c3d(performance), read_c3d(session_path)
            folder = work / f"layout_{session_path.parent.name}_{session_path.stem}_default"
            if not (folder / "layout.json").is_file():
                mocaptk("cluster", session_path, "--out", folder, "--formats", "none", "--quiet", "--force")
            for rig in (generic, stylized(generic)[0]):
                retargeter = fit_retargeter(rig, session)
                cal = retargeter.calibration
                step = max(1, int(np.ceil(len(session.positions) / MAX_FRAMES)))
                rom = _rom_weights(cal, session.positions[::step] - cal.neutral, 1e-3)
                rom = rom * cal.stretch  # in the units the extremes were measured in
                performed = np.flatnonzero((cal.rom_extreme >= MIN_PERFORMED) & (true_reach >= MIN_PERFORMED)
                                           & (cal.ties == np.arange(len(cal.ties))))
                repeated = np.zeros(len(cal.ties), bool)
                for k in performed:
                    peaks = np.sort(rom[find_peaks(rom[:, k], prominence=0.5 * cal.rom_extreme[k])[0], k])[::-1]
                    repeated[k] = len(peaks) >= 2 and peaks[1] >= PEAK_AGREEMENT * peaks[0]
                est, true = cal.rom_extreme[performed], true_reach[performed]
                print(f"\n## {name} onto {rig.source}: {len(performed)} performed shapes; estimated vs true ROM "
                      f"extreme r {np.corrcoef(est, true)[0, 1]:.2f}, median |diff| {np.median(np.abs(est - true)):.2f}; "
                      f"true reach {true.min():.2f}-{true.max():.2f} (median {np.median(true):.2f}); repeated "
                      f"peaks: {', '.join(f'{rig.names[k]} (true {true_reach[k]:.2f})' for k in np.flatnonzero(repeated)) or 'none'}")
                solver = train_solver(read_layout(folder / "layout.json"), session, {})
                known = np.zeros(len(cal.ties), bool)
                known[performed] = True
                rules = {"default (keep the character's amplitude)": cal.stretch,
                         "--rom-reach 1 on the shapes with repeated peaks": np.where(repeated, cal.rom_extreme, cal.stretch),
                         "oracle: each shape aligned with its true ROM reach":
                             np.where(known, cal.rom_extreme / np.where(known, true_reach, 1.0), cal.stretch)}
                for rule, stretch in rules.items():
                    aligned = replace(cal, basis=cal.basis / cal.stretch[:, None, None] * stretch[:, None, None],
                                      stretch=stretch)
                    result = retarget_capture(replace(retargeter, calibration=aligned), solver, capture, "capture")
                    s = scores(result.weights, truth, rig)
                    print(f"| {rule} | {s['mae']:.3f} | {s['r']:.3f} | {s['mesh_rmse_mm']:.2f} |", flush=True)


def lost() -> None:
    """Weights error as layout markers are lost: 0/5/20 % per frame at random, lower lip 10 s."""
    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.character_files import load_character
    from mocaptk.retarget.retarget_outputs import retarget_capture
    from mocaptk.retarget.solve import train_solver

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(os.environ.get("BENCH_RETARGET_WORK", tmp))
        print("| actor | lost | mean MAE | mean r | mesh RMSE mm | NaN weights |\n|---|---|---|---|---|---|")
        for name, session, performance, truth_path in datasets(work):
            actor = Actor(session, load_character("arkit"))
            truth = truth_weights(truth_path)
            capture = read_c3d(performance)
            folder = work / f"layout_{session.parent.name}_{session.stem}_default"
            if not (folder / "layout.json").is_file():
                mocaptk("cluster", session, "--out", folder, "--formats", "none", "--quiet", "--force")
            solver = train_solver(read_layout(folder / "layout.json"), actor.session, {})
            labels = list(solver.layout_labels)
            columns = capture.index(labels)
            mouth = [i for i, label in enumerate(labels) if label.startswith("MOUTH")]
            heights = capture.positions[:, columns[mouth], 1]
            lower = [mouth[k] for k in np.flatnonzero(np.nanmedian(heights, axis=0) < np.nanmedian(heights))]
            rng = np.random.default_rng(0)
            cases = [(f"{p} % per frame", p) for p in (0, 5, 20)] + [(f"lower lip ({len(lower)}) 10 s", None)]
            for label, percent in cases:
                pos = capture.positions.copy()
                if percent is None:
                    pos[300:300 + int(10 * capture.rate), columns[lower]] = np.nan
                else:
                    gone = rng.random((capture.n_frames, len(labels))) < percent / 100
                    view = pos[:, columns]
                    view[gone] = np.nan
                    pos[:, columns] = view
                result = retarget_capture(actor.retargeter, solver, capture.replace(positions=pos), "capture")
                s = scores(result.weights, truth, actor.rig)
                print(f"| {name} | {label} | {s['mae']:.3f} | {s['r']:.3f} | {s['mesh_rmse_mm']:.2f} | "
                      f"{int(np.isnan(result.weights).sum())} |")


def speed() -> None:
    """Frames/s of the weight solve (the generic rig's 52 shapes at 50 of its moving vertices,
    the sample performance's true weights, 0.2 mm noise, 5 % lost) against scipy's lsq_linear."""
    from scipy.optimize import lsq_linear

    from mocaptk.retarget.weight_solve import solve_weights

    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.character_files import load_character

    rng = np.random.default_rng(1)
    rig = load_character("arkit")
    motion = np.linalg.norm(rig.deltas, axis=2).max(axis=0)
    moving = np.flatnonzero(motion > 1.0)  # mm: the face that moves
    basis = rig.deltas[:, rng.choice(moving, 50, replace=False)].astype(np.float64)  # 50 markers
    truth = np.tile(arkit_truth(load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")), (17, 1))[:20_000]
    d = np.einsum("fs,smc->fmc", truth, basis) + rng.normal(scale=0.2, size=(len(truth), 50, 3))
    d[rng.random(d.shape[:2]) < 0.05] = np.nan
    solve_weights(basis, d[:10])  # compile
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    solve_weights(basis, d)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    a = basis.reshape(52, -1).T
    n = 300
    w2, c2 = time.perf_counter(), time.process_time()
    for frame in d[:n].reshape(n, -1):
        ok = np.isfinite(frame)
        lsq_linear(a[ok], frame[ok], bounds=(0, 1))
    w2, c2 = time.perf_counter() - w2, time.process_time() - c2
    print(f"load {load:.1f}; ours: {len(d) / wall:,.0f} frames/s wall ({len(d) / cpu:,.0f} per CPU-s); "
          f"scipy lsq_linear (bounded, no L1/smoothness): {n / w2:,.0f} frames/s wall ({n / c2:,.0f} per CPU-s); "
          f"ratio {(len(d) / wall) / (n / w2):.0f}x")


def memory() -> None:
    """Peak RSS of a 72,000-frame retarget (the sample's performance tiled 60x, 48 layout markers)."""
    code = """
import resource, numpy as np, sys
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.clustering.layout import read_layout
from mocaptk.retarget.character_files import load_character
from mocaptk.retarget.retarget_outputs import fit_retargeter, retarget_capture
from mocaptk.retarget.solve import train_solver
session = read_c3d(sys.argv[1]); capture = read_c3d(sys.argv[2])
solver = train_solver(read_layout(sys.argv[3]), session, {})
r = fit_retargeter(load_character('arkit'), session)
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
long = capture.select(list(solver.layout_labels))
long = long.replace(positions=np.tile(long.positions, (60, 1, 1)), residuals=None)
result = retarget_capture(r, solver, long, 'long')
print(long.n_frames, 'frames; peak RSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 'MiB (after fit', base / 1024, 'MiB)')
"""
    with tempfile.TemporaryDirectory() as tmp:
        mocaptk("cluster", SAMPLES / "dense_halfface.c3d", "--out", Path(tmp) / "layout", "--formats", "none",
                "--quiet")
        done = subprocess.run([sys.executable, "-c", code, str(SAMPLES / "dense_halfface.c3d"),
                               str(SAMPLES / "dense_halfface_performance.c3d"), str(Path(tmp) / "layout" / "layout.json")],
                              capture_output=True, text=True)
        print(done.stdout or done.stderr[-2000:])


if __name__ == "__main__":
    {"accuracy": accuracy, "gain": gain, "reach": reach, "lost": lost, "speed": speed,
     "memory": memory}[sys.argv[1]]()
