"""The optical pipeline measured against truth, each with its baseline in the same run.

1. ``calibrate`` intrinsics on the real Pose2Sim photos vs their Qualisys calibration.
2. Rig extrinsics from rendered ChArUco views of the Cara-like and room rigs: bundle adjustment
   vs OpenCV's chained stereoCalibrate (centre error mm, orientation error deg, vs truth).
3. Blob detection on rendered frames of a dense synthetic face session (139 markers, 8 mm):
   centre RMS, recall, false blobs, merged flags (merged blobs split in two), frames/s.
4. Unlabelled reconstruction on the same frames (dense) and on a sparse 20 mm layout, with
   labelled triangulation of the same detections (labels from the truth: today's path) beside.

Run: ``MOCAPTK_SHARED_DATA=../shared/data python benchmarks/bench_cameras.py [--frames 60]``.
Times are wall and CPU seconds with the 1-minute load average (the machine is shared);
reconstruction and its baseline: the fastest of 3 runs.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from mocaptk.acquisition.blob_detection import detect_blobs
from mocaptk.acquisition.boards import Board
from mocaptk.acquisition.calibration import (View, bundle_adjust, calibrate_intrinsics,
                                             chained_stereo, pairwise_errors, pose_errors,
                                             rig_from_poses)
from mocaptk.acquisition.cameras import cara_rig, load_rig, room_rig
from mocaptk.acquisition.correspondence import reconstruct
from mocaptk.acquisition.image_sequences import ImageSource
from mocaptk.acquisition.synth_board_views import (PRESET_BOARDS, board_poses, render_views,
                                                   texture_resolution)
from mocaptk.acquisition.synth_images import (marker_truth, render_markers, score_detections,
                                              skin_shading)
from mocaptk.acquisition.synth_wand import WAND_LENGTH_MM, wand_images, wand_positions
from mocaptk.acquisition.triangulate import triangulate
from mocaptk.acquisition.wand import wand_from_blobs

SHARED = Path(os.environ.get("MOCAPTK_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


class Clock:
    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall, self.cpu = time.perf_counter() - self.wall, time.process_time() - self.cpu

    def __str__(self):
        return f"wall {self.wall:.1f} s, CPU {self.cpu:.1f} s, load {os.getloadavg()[0]:.1f}"


def real_intrinsics() -> None:
    folder = SHARED / "multicam" / "pose2sim_demo" / "calibration"
    qualisys = load_rig(folder / "Calib.qca.txt")
    board = Board("checkerboard", (4, 7), 60.0)
    print("## 1. Intrinsics, real Pose2Sim photos (4x7, 60 mm) vs Qualisys")
    print("| camera | views kept | RMS px | fx err | fy err | cx, cy vs Qualisys px |")
    print("|---|---|---|---|---|---|")
    with Clock() as clock:
        for i, truth in enumerate(qualisys, start=1):
            source = ImageSource(folder / "intrinsics" / f"int_cam0{i}_img")
            views, size = [], None
            for name, image in source.frames():
                size = image.shape[1], image.shape[0]
                views.append(View(name, *board.detect(image)))
            fit = calibrate_intrinsics(board, views, size)
            fx, fy = fit.matrix[0, 0] / truth.matrix[0, 0] - 1, fit.matrix[1, 1] / truth.matrix[1, 1] - 1
            pp = fit.matrix[:2, 2] - truth.matrix[:2, 2]
            print(f"| {truth.name} | {len(fit.view_rms)}/{len(views)} | {fit.rms:.3f} | {fx:+.2%} | "
                  f"{fy:+.2%} | {pp[0]:+.1f}, {pp[1]:+.1f} |")
    print(f"\n({clock})\n")


def wand_observations(rig, estimate, n_frames: int, seed: int):
    """A wand (400 mm, 14 mm markers) waved ``n_frames`` times through ``rig``'s volume, rendered
    and detected (``detect_blobs``), its ends matched through the board calibration ``estimate``."""
    ends = wand_positions(rig, n_frames, seed=seed)
    found = [[detect_blobs(image).centres for image in wand_images(camera, ends, seed=seed + c)]
             for c, camera in enumerate(rig)]
    width = max(2, max(len(b) for row in found for b in row))
    blobs = np.full((len(rig), n_frames, width, 2), np.nan)
    for c, row in enumerate(found):
        for f, centres in enumerate(row):
            blobs[c, f, :len(centres)] = centres
    return wand_from_blobs(blobs, estimate, WAND_LENGTH_MM)


def rig_extrinsics(name: str, rig, board: Board, n_views: int, *, spread_mm: float | None = None,
                   seeds: tuple[int, ...] = (1,), wand_frames: int = 0) -> None:
    print(f"### {name}: {len(rig)} cameras, {n_views} board poses (centres within "
          f"+-{spread_mm or 0.3 * max(board.size_mm()):g} mm) ({board.corners[0]}x{board.corners[1]}, "
          f"{board.square:g} mm)")
    print("| seed | method | centre err mm, camera-1 frame (max / mean) | deg, camera-1 frame (max / mean) | "
          "centre err mm, aligned (max / mean) | deg, aligned (max / mean) | "
          "pairwise: centre distance err mm / relative rotation deg (max) | RMS px | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        poses = board_poses(rig, board, n_views, seed=seed, max_tilt_deg=30.0, spread_mm=spread_mm)
        resolution = texture_resolution(rig, board, poses)
        with Clock() as render:
            views = []
            for c, camera in enumerate(rig):
                views.append([View(f"v{v}", *board.detect(image)) if image is not None
                              else View(f"v{v}", np.zeros(0, int), np.zeros((0, 2)))
                              for v, image in enumerate(render_views(camera, board, poses,
                                                                     px_per_mm=resolution, seed=c + 10 * seed))])
        with Clock() as base_clock:
            fits = [calibrate_intrinsics(board, v, cam.image_size) for v, cam in zip(views, rig)]
            start = chained_stereo(board, views, fits)
        baseline = rig_from_poses(rig.names, [(f.matrix, f.distortion) for f in fits], start,
                                  [c.image_size for c in rig])
        with Clock() as ba_clock:
            result = bundle_adjust(board, views, fits, start)
        adjusted = rig_from_poses(rig.names, result.intrinsics, result.rig_poses, [c.image_size for c in rig])
        rows = [("OpenCV calibrateCamera + chained stereoCalibrate", baseline, result.initial_rms, base_clock),
                ("bundle adjustment (this)", adjusted, result.final_rms, ba_clock)]
        if wand_frames:
            with Clock() as wand_clock:
                wand = wand_observations(rig, baseline, wand_frames, seed=100 + seed)
                with_wand = bundle_adjust(board, views, fits, start, wand=wand)
            rows.append((f"bundle adjustment + wand ({wand.n_frames} of {wand_frames} frames kept; noise measured: "
                         f"corners {with_wand.corner_sd_px:.3f}, blobs {with_wand.wand_sd_px:.4f} px)",
                         rig_from_poses(rig.names, with_wand.intrinsics, with_wand.rig_poses,
                                        [c.image_size for c in rig]), with_wand.final_rms, wand_clock))
        for method, estimate, rms, clk in rows:
            mm, deg = pose_errors(estimate, rig)
            amm, adeg = pose_errors(estimate, rig, align=True)
            pmm, pdeg = pairwise_errors(estimate, rig)
            print(f"| {seed} | {method} | {mm.max():.3f} / {mm[1:].mean():.3f} | {deg.max():.3f} / "
                  f"{deg[1:].mean():.3f} | {amm.max():.3f} / {amm.mean():.3f} | {adeg.max():.3f} / "
                  f"{adeg.mean():.3f} | {pmm.max():.3f} / {pdeg.max():.3f} | {rms:.3f} | {clk.cpu:.1f} |",
                  flush=True)
    print(f"\n(last seed: render+detect {render}; views per camera {[len(f.view_rms) for f in fits]})\n")


def face_session(spacing: float, frames: int):
    from mocaptk.acquisition import synth_session as ss
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.synth_layout import dense_layout

    model = load_face_model(None)
    layout = dense_layout(model, mode="half", spacing_mm=spacing, seed=0)
    truth = ss.performance_session(model, layout, seed=0, seconds=frames / 60.0, rate=60.0,
                                   noise_mm=0.0, gaps_per_minute=0.0).truth
    normals = ss.marker_normals(model, truth)
    return truth.positions[:frames], normals


def _fastest(work, runs: int = 3):
    """``work()``'s result and the :class:`Clock` of its fastest (CPU) of ``runs`` runs."""
    clocks = []
    for _ in range(runs):
        with Clock() as clock:
            result = work()
        clocks.append(clock)
    return result, min(clocks, key=lambda c: c.cpu)


def _score(truth, frames, found):
    """Summed :func:`score_detections` of ``found[c][f] = (centres, merged)``."""
    score = None
    for c, row in enumerate(found):
        for f in range(frames):
            one = score_detections(truth.pixels[c, f], truth.radius[c, f], truth.merged[c, f], *row[f])
            score = one if score is None else score + one
    return score


def detection_and_reconstruction(label: str, spacing: float, frames: int) -> None:
    rig = cara_rig()
    points, normals = face_session(spacing, frames)
    truth = marker_truth(rig, points, normals)
    rng = np.random.default_rng(0)
    backgrounds = [skin_shading(cam, c) for c, cam in enumerate(rig)]
    images = [[render_markers(backgrounds[c], truth.pixels[c, f], truth.radius[c, f], rng=rng)[0]
               for f in range(frames)] for c in range(len(rig))]
    n_markers = points.shape[1]
    detect_blobs(images[0][0])  # compiled kernel loaded from numba's cache, not timed
    with Clock() as clock:
        found = [[detect_blobs(image, split=True) for image in row] for row in images]
    score = _score(truth, frames, [[(b.centres, b.merged) for b in row] for row in found])
    # baseline: OpenCV's SimpleBlobDetector (bright blobs, same area limits, no shape filters)
    params = cv2.SimpleBlobDetector_Params()
    params.blobColor, params.minArea, params.maxArea = 255, 6, 2000
    params.filterByCircularity = params.filterByConvexity = params.filterByInertia = False
    params.minThreshold, params.maxThreshold, params.thresholdStep = 120, 240, 20
    detector = cv2.SimpleBlobDetector_create(params)
    with Clock() as base_clock:
        keypoints = [[detector.detect(image) for image in row] for row in images]
    base_score = _score(truth, frames, [[(np.array([k.pt for k in kp]).reshape(-1, 2), np.zeros(len(kp), bool))
                                         for kp in row] for row in keypoints])
    # two threads over the images (OpenCV and the compiled pass release the GIL)
    with Clock() as threaded, ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda image: detect_blobs(image, split=True), [i for row in images for i in row]))
    print(f"## {label}: {n_markers} markers ({spacing:g} mm layout), {frames} frames, Cara rig 4 x 720x1280")
    print("| detector | isolated-marker centre RMS px | recall of visible unmerged | false blobs | "
          "frames of 4 cameras per CPU-s | wall frames/s |")
    print("|---|---|---|---|---|---|")
    for name, sc, clk in (("OpenCV SimpleBlobDetector (baseline)", base_score, base_clock),
                          ("detect_blobs (this), 1 thread", score, clock)):
        print(f"| {name} | {sc.rms_px:.3f} | {sc.recall:.2%} of {sc.isolated} | {sc.false_rate:.2%} of {sc.blobs} | "
              f"{frames / clk.cpu:.0f} | {frames / clk.wall:.0f} |")
    print(f"| detect_blobs (this), 2 threads | | | | {frames / threaded.cpu:.0f} | {frames / threaded.wall:.0f} |")
    print(f"\nspeed ratio vs baseline (CPU) {base_clock.cpu / clock.cpu:.1f}x; merged-blob halves "
          f"{score.merged_blobs} ({score.merged_flagged} on truly merged markers; "
          f"{truth.merged[np.isfinite(truth.pixels[..., 0])].mean():.1%} of visible marker views merge). "
          f"(this: {clock}; baseline: {base_clock}; 2 threads: {threaded})\n")
    width = max(len(b.centres) for row in found for b in row)
    blobs = np.full((len(rig), frames, width, 2), np.nan)
    for c in range(len(rig)):
        for f in range(frames):
            k = len(found[c][f].centres)
            blobs[c, f, :k] = found[c][f].centres
    reconstruct(rig, blobs[:, :2])  # compiled kernels loaded from numba's cache, not timed
    # split halves of merged blobs used; bad ones are outliers; fastest of 3 runs (shared box)
    result, rec_clock = _fastest(lambda: reconstruct(rig, blobs))
    # baseline: the same detections labelled by the truth (unmerged blob within 1 px of its marker)
    labelled = np.full((len(rig), frames, n_markers, 2), np.nan)
    for c in range(len(rig)):
        for f in range(frames):
            keep = ~found[c][f].merged
            centres = found[c][f].centres[keep]
            if len(centres):
                distance, index = cKDTree(centres).query(np.nan_to_num(truth.pixels[c, f], nan=-1e6))
                hit = distance < 1.0
                labelled[c, f, hit] = centres[index[hit]]
    triangulate(rig, labelled[:, :2])
    baseline, tri_clock = _fastest(lambda: triangulate(rig, labelled).positions)
    seen2 = np.isfinite(truth.pixels[..., 0]).sum(axis=0) >= 2
    rows = []
    for name, per_frame, clk in (("labelled triangulation (truth labels; today's path)",
                                  lambda f: baseline[f], tri_clock),
                                 ("unlabelled reconstruct (this)", lambda f: result.points[f], rec_clock)):
        good = ghosts = total = 0
        for f in range(frames):
            present = per_frame(f)[np.isfinite(per_frame(f)[:, 0])]
            if len(present):
                good += int((cKDTree(present).query(points[f])[0][seen2[f]] < 1.0).sum())
                ghosts += int((cKDTree(points[f]).query(present)[0] > 2.0).sum())
                total += len(present)
        rows.append(f"| {name} | {good / seen2.sum():.2%} | {ghosts / max(total, 1):.2%} | "
                    f"{frames / clk.wall:.0f} wall, {frames / clk.cpu:.0f} per CPU-s ({clk}) |")
    print("| method | marker-frames seen by >= 2 cameras within 1 mm | ghost points (> 2 mm from every marker) | frames/s |")
    print("|---|---|---|---|")
    print("\n".join(rows))
    lengths = result.fragment_lengths()
    unmerged = (np.isfinite(truth.pixels[..., 0]) & ~truth.merged).sum(axis=0)
    print(f"\nfragments: {len(lengths)} for {n_markers} markers; length median {np.median(lengths):.0f}, "
          f"p10 {np.percentile(lengths, 10):.0f}, max {lengths.max()} of {frames} frames. Marker-frames "
          f"by unmerged views: 2: {(unmerged == 2).sum()}, >=3: {(unmerged >= 3).sum()}, <2 (lost to "
          f"merging/occlusion though seen by >= 2): {(seen2 & (unmerged < 2)).sum()}\n")


def end_to_end(step: int, folder: Path) -> None:
    """images -> detect -> reconstruct -> label -> cluster vs cluster of the labelled truth.

    The synthetic session (``mocaptk synth``, Cara rig, 139 markers, 6 takes) is rendered every
    ``step``-th frame (all of it would be ~50 000 images); each image is detected as it is
    rendered (``detect_blobs``, as ``mocaptk detect`` does after decoding a PNG). The fragments
    break at the 100 ms steps, so ``label`` sees per-frame clouds. Both layouts are scored by
    ``mocaptk evaluate`` on the same truth capture (held-out blocks of every take)."""
    import json
    import subprocess
    import sys

    from mocaptk.acquisition import synth_session as ss
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.formats import write_trajectories
    from mocaptk.trajectories import Trajectories

    folder.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "mocaptk"]

    def run(*args) -> str:
        done = subprocess.run([*cli, *map(str, args)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout

    session = folder / "session.c3d"
    if not session.exists():
        run("synth", session, "--rig", "cara", "--seed", "0", "--quiet")
    truth = ss.load_ground_truth(folder / "session_truth.npz")
    rig = cara_rig()
    frames = np.arange(0, truth.n_frames, step)
    rate = truth.rate / step
    positions = truth.positions[frames]
    normals = ss.marker_normals(load_face_model(None), truth)
    takes = json.loads((folder / "session_takes.json").read_text())
    for take in takes["takes"]:
        take["start"], take["end"] = int(np.searchsorted(frames, take["start"])), int(np.searchsorted(frames, take["end"]))
    (folder / "takes_sub.json").write_text(json.dumps(takes))
    write_trajectories(Trajectories(positions=positions, labels=list(truth.labels), rate=rate),
                       folder / "truth.c3d", force=True)
    rng = np.random.default_rng(0)
    backgrounds = [skin_shading(cam, c) for c, cam in enumerate(rig)]
    found, detect_cpu = [[] for _ in rig], 0.0
    with Clock() as render:
        for f in frames:
            seen = marker_truth(rig, truth.positions_between(f, f + 1), normals(f, f + 1))
            for c in range(len(rig)):
                image = render_markers(backgrounds[c], seen.pixels[c, 0], seen.radius[c, 0], rng=rng)[0]
                start = time.process_time()
                found[c].append(detect_blobs(image, split=True).centres)
                detect_cpu += time.process_time() - start
    width = max(len(b) for row in found for b in row)
    blobs = np.full((len(rig), len(frames), width, 2), np.nan)
    for c, row in enumerate(found):
        for f, centres in enumerate(row):
            blobs[c, f, :len(centres)] = centres
    with Clock() as rec_clock:
        result = reconstruct(rig, blobs)
    raw = result.trajectories_array()
    write_trajectories(Trajectories(positions=raw, labels=[f"*{i + 1}" for i in range(raw.shape[1])], rate=rate),
                       folder / "raw.c3d", force=True)
    labelled = run("label", folder / "raw.c3d", "--template", folder / "session_performance.c3d",
                   "--out", folder / "labelled.c3d", "--drop-unlabelled", "--force").strip().splitlines()[0]
    rows = []
    # gaps move the paper's rule's count, so the last two rows take the truth layout's count (like for like)
    for name, capture, extra in (("labelled truth capture (baseline)", "truth.c3d", ()),
                                 ("images -> detect -> reconstruct -> label", "labelled.c3d", ()),
                                 ("the same, cluster --fill-gaps", "labelled.c3d", ("--fill-gaps",)),
                                 ("the same at the truth layout's count", "labelled.c3d", ("--markers",)),
                                 ("the same, --fill-gaps, at the truth layout's count", "labelled.c3d",
                                  ("--fill-gaps", "--markers"))):
        if "--markers" in extra:
            truth_layout = json.loads((folder / "layout_truth" / "layout.json").read_text())
            measured = sum(c["mirrored_from"] is None for c in truth_layout["clusters"])
            extra = tuple(a for a in extra if a != "--markers") + ("--markers", str(measured))
        out = folder / "_".join([f"layout_{Path(capture).stem}", *(a.strip('-').replace('-', '_') for a in extra)])
        run("cluster", folder / capture, "--regions", folder / "session_regions.json", "--takes",
            folder / "takes_sub.json", "--step", "1", "--formats", "none", "--out", out, "--force", "--quiet",
            *extra)
        run("evaluate", folder / "truth.c3d", "--layout", out / "layout.json", "--takes", folder / "takes_sub.json",
            "--out", out / "evaluation.json", "--force")
        evaluation = json.loads((out / "evaluation.json").read_text())
        method = json.loads((out / "layout.json").read_text())["parameters"]["method"]
        rows.append((name, evaluation["count"], evaluation["methods"][method]["rmse_mm"],
                     evaluation["methods"]["random"]["rmse_mm"]))
    print(f"## 5. End to end: {truth.n_frames} frames of the synthetic session, every {step}th rendered "
          f"({len(frames)} frames x 4 cameras, {rate:g} Hz)")
    print(f"render+detect {render}; detection alone {detect_cpu:.1f} CPU-s "
          f"({len(frames) / detect_cpu:.0f} frames of 4 cameras per CPU-s); reconstruct {rec_clock} "
          f"({len(frames) / rec_clock.cpu:.0f} frames per CPU-s); label: {labelled}")
    print("| layout from | layout markers | held-out RMSE mm (evaluate on the truth capture) | "
          "random layouts of that size |")
    print("|---|---|---|---|")
    for name, count, rmse, random in rows:
        print(f"| {name} | {count} | {rmse:.4f} | {random:.4f} |")
    print(f"\nratio {rows[1][2] / rows[0][2]:.3f}, with --fill-gaps {rows[2][2] / rows[0][2]:.3f} (each at its own "
          f"count); at the truth layout's count {rows[3][2] / rows[0][2]:.3f}, with --fill-gaps "
          f"{rows[4][2] / rows[0][2]:.3f} (target <= 1.05)\n")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--views", type=int, default=24, help="Cara board poses (room: x2)")
    parser.add_argument("--room-spread", type=float, default=None,
                        help="Board centres within +-this of the aim point, mm (default 0.3 x board)")
    parser.add_argument("--e2e-step", type=int, default=10, help="End to end: render every Nth frame")
    parser.add_argument("--e2e-dir", type=Path, default=Path("bench_cameras_e2e"),
                        help="End to end: working folder (the synthetic session is kept there)")
    parser.add_argument("--wand", type=int, default=0,
                        help="Room rig: also calibrate with this many rendered wand frames (render+detect CPU included)")
    parser.add_argument("--seeds", default="1", help="Comma-separated board-pose seeds (rig sections)")
    parser.add_argument("--only", default="real,cara,room,images",
                        help="Comma-separated sections: real, cara, room, images, e2e")
    args = parser.parse_args()
    only = args.only.split(",")
    seeds = tuple(int(seed) for seed in args.seeds.split(","))
    if "real" in only:
        real_intrinsics()
    if "cara" in only or "room" in only:
        print("## 2. Rig extrinsics from rendered ChArUco views (errors relative to camera 1)")
    if "cara" in only:
        rig_extrinsics("Cara-like", cara_rig(), PRESET_BOARDS["cara"], args.views, seeds=seeds)
    if "room" in only:
        rig_extrinsics("room", room_rig(), PRESET_BOARDS["room"], 2 * args.views,
                       spread_mm=args.room_spread, seeds=seeds, wand_frames=args.wand)
    if "images" in only:
        detection_and_reconstruction("3-4. Dense session", 8.0, args.frames)
        detection_and_reconstruction("3-4. Sparse layout", 20.0, args.frames)
    if "e2e" in only:
        end_to_end(args.e2e_step, args.e2e_dir)


if __name__ == "__main__":
    main()
