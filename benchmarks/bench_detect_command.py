"""``mocaptk detect`` end to end (decode + detect + write) against detection alone, OpenCV's
SimpleBlobDetector and (``--baseline``) another tree's command, frames of four 1280x720 cameras
per second, wall and CPU, in one run; each command output scored against the truth.

    python benchmarks/bench_detect_command.py [--frames 200] [--repeat 2] [--baseline OLD_TREE]

``OLD_TREE``: a checkout of the code to compare with (``git archive 88d4272 | tar -x -C
OLD_TREE``); its ``mocaptk detect`` runs from it (PYTHONPATH) in this environment, alternating
with this tree's, and the outputs are compared byte for byte.

Renders ``--frames`` frames of 139 markers on a face-sized ellipsoid through the Cara rig
(as ``mocaptk synth --images`` renders them) and writes them three ways: PNG as ``synth
--images`` writes it (uncompressed), PNG deflated (OpenCV's default, as a camera's software
may write it) and an MJPG video per camera (lossy; video input). Then, in this process on the
images held in memory: OpenCV's SimpleBlobDetector (baseline, 1 thread) and ``detect_blobs``
(1 thread: the detection-only figure); and ``mocaptk detect`` as a user runs it, in a child
process (its CPU time from ``getrusage``), with the command's own in-process time beside it
(start-up excluded). The fastest of ``--repeat`` rounds counts; the 1-minute load average is
printed beside each row (the machine is shared: CPU time is the steadier measure).
"""

from __future__ import annotations

import argparse
import filecmp
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from mocaptk.acquisition.blob_detection import detect_blobs
from mocaptk.acquisition.cameras import cara_rig
from mocaptk.acquisition.detect_images import detect_sources
from mocaptk.acquisition.detections_file import load_detections
from mocaptk.acquisition.image_sequences import ImageSource
from mocaptk.acquisition.projection import ellipsoid_markers
from mocaptk.acquisition.synth_images import (MarkerTruth, marker_truth, png_bytes, render_markers,
                                              score_detections, skin_shading)


def render(frames: int) -> tuple[list[list[np.ndarray]], MarkerTruth]:
    rig = cara_rig()
    points, normals = ellipsoid_markers(frames, 139, max_yaw=1.1, seed=1)
    truth = marker_truth(rig, points, normals)
    rng = np.random.default_rng(0)
    return [[render_markers(skin_shading(cam, c), truth.pixels[c, f], truth.radius[c, f], rng=rng)[0]
             for f in range(frames)] for c, cam in enumerate(rig)], truth


def scored(out: Path, truth: MarkerTruth) -> str:
    """``RMS px / recall / false blobs`` of a detections file against the truth."""
    found, score = load_detections(out), None
    for c in range(found.points2d.shape[0]):
        for f in range(found.points2d.shape[1]):
            keep = np.isfinite(found.points2d[c, f, :, 0])
            one = score_detections(truth.pixels[c, f], truth.radius[c, f], truth.merged[c, f],
                                   found.points2d[c, f, keep], found.merged[c, f, keep])
            score = one if score is None else score + one
    return f"{score.rms_px:.3f} px / {100 * score.recall:.2f} % / {100 * score.false_rate:.2f} %"


def write(images: list[list[np.ndarray]], folder: Path, kind: str) -> Path:
    folder.mkdir()
    for c, row in enumerate(images):
        if kind == "mjpg":
            height, width = row[0].shape
            video = cv2.VideoWriter(str(folder / f"cam{c + 1}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 60,
                                    (width, height), isColor=False)
            for image in row:
                video.write(image)
            video.release()
            continue
        (folder / f"cam{c + 1}").mkdir()
        for f, image in enumerate(row):
            data = png_bytes(image) if kind == "png" else cv2.imencode(".png", image)[1].tobytes()
            (folder / f"cam{c + 1}" / f"frame_{f:05d}.png").write_bytes(data)
    return folder


def clocked(work):
    wall, cpu = time.perf_counter(), time.process_time()
    result = work()
    return result, time.perf_counter() - wall, time.process_time() - cpu


def command(folder: Path, out: Path, tree: Path | None = None) -> tuple[float, float]:
    """Wall and CPU seconds (the child's, all its threads) of one ``mocaptk detect`` run, of
    this tree or (``tree``: a folder holding ``mocaptk`` as installed) another."""
    inputs = sorted(folder.iterdir()) if any(p.suffix == ".avi" for p in folder.iterdir()) else [folder]
    env = dict(os.environ, **({"PYTHONPATH": str(tree)} if tree else {}))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.perf_counter()
    # cwd: not the repository (``python -m`` puts it first on sys.path, before PYTHONPATH)
    subprocess.run([sys.executable, "-m", "mocaptk", "detect", *map(str, inputs), "--out", str(out),
                    "--force", "--quiet"], check=True, capture_output=True, env=env, cwd=out.parent)
    wall = time.perf_counter() - wall
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def installed_layout(tree: Path, folder: Path) -> Path:
    """``folder/mocaptk``: the source ``tree``'s ``mocaptk`` with its stage folders inside, as
    pyproject's package-dir installs them (links, not copies)."""
    package = folder / "mocaptk"
    package.mkdir(parents=True)
    for entry in (tree / "mocaptk").iterdir():
        (package / entry.name).symlink_to(entry.resolve())
    for stage in ("acquisition", "clustering", "retarget"):
        (package / stage).symlink_to((tree / stage).resolve())
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--baseline", type=Path, help="source tree of the code to compare with")
    args = parser.parse_args()
    frames = args.frames
    images, truth = render(frames)
    flat = [image for camera in images for image in camera]
    detect_blobs(flat[0])  # compiled pass loaded from numba's cache, not timed
    params = cv2.SimpleBlobDetector_Params()  # as benchmarks/bench_cameras.py
    params.blobColor, params.minArea, params.maxArea = 255, 6, 2000
    params.filterByCircularity = params.filterByConvexity = params.filterByInertia = False
    params.minThreshold, params.maxThreshold, params.thresholdStep = 120, 240, 20
    detector = cv2.SimpleBlobDetector_create(params)
    rows = []

    def row(name: str, wall: float, cpu: float, score: str = "") -> None:
        rows.append(f"| {name} | {frames / wall:.0f} | {frames / cpu:.0f} | {os.getloadavg()[0]:.1f} | {score} |")

    best = {}
    for _ in range(args.repeat):
        for name, work in (("OpenCV SimpleBlobDetector, images in memory, 1 thread (baseline)",
                            lambda: [detector.detect(image) for image in flat]),
                           ("detect_blobs, images in memory, 1 thread (detection only)",
                            lambda: [detect_blobs(image, split=True) for image in flat])):
            _, wall, cpu = clocked(work)
            best[name] = min(best.get(name, (np.inf, np.inf)), (wall, cpu), key=lambda t: t[1])
    for name, (wall, cpu) in best.items():
        row(name, wall, cpu)
    with tempfile.TemporaryDirectory(prefix="bench-detect-") as temp:
        temp = Path(temp)
        old = installed_layout(args.baseline, temp / "baseline") if args.baseline else None
        for kind, label in (("png", "PNG as synth --images writes it (uncompressed)"),
                            ("deflate", "PNG deflated (OpenCV's default level)"),
                            ("mjpg", "MJPG video per camera (lossy)")):
            folder = write(images, temp / kind, kind)
            size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / (4 * frames)
            sources = [ImageSource(p) for p in sorted(folder.iterdir())]
            for threads in (1, None):
                name = f"detect_sources, {label}, {threads or os.cpu_count()} thread(s), in process"
                for _ in range(args.repeat):
                    _, wall, cpu = clocked(lambda: detect_sources(sources, min_area=6, max_area=2000,
                                                                  threads=threads))
                    best[name] = min(best.get(name, (np.inf, np.inf)), (wall, cpu), key=lambda t: t[1])
                row(name, *best[name])
            runs = [("`mocaptk detect` (this tree)", None, temp / f"{kind}.npz")]
            if old:
                runs.append((f"`mocaptk detect` ({args.baseline.name}, baseline)", old, temp / f"{kind}-old.npz"))
            for _ in range(args.repeat):  # this tree and the baseline alternate
                for who, tree, out in runs:
                    name = f"{who}, {label} ({size / 1024:.0f} KiB per image)"
                    best[name] = min(best.get(name, (np.inf, np.inf)), command(folder, out, tree),
                                     key=lambda t: t[1])
            for who, tree, out in runs:
                name = f"{who}, {label} ({size / 1024:.0f} KiB per image)"
                row(name, *best[name], scored(out, truth))
            if kind == "png":  # the fixed part: start-up, compiled-kernel load, output, teardown
                single = write([camera[:1] for camera in images], temp / "png-1", kind)
                for who, tree, out in runs:
                    cpu = min(command(single, out.with_name("single.npz"), tree)[1] for _ in range(args.repeat))
                    rows.append(f"| {who} on 1 frame (fixed cost) | | {cpu:.2f} CPU-s | "
                                f"{os.getloadavg()[0]:.1f} | |")
            if old:
                same = all(filecmp.cmp(temp / f"{kind}{end}", temp / f"{kind}-old{end}", shallow=False)
                           for end in (".npz", "_overlay.png"))
                rows.append(f"| outputs (npz, overlay) of the two trees byte-identical: {same} | | | | |")
    print(f"{frames} frames of 4 cameras (1280x720 grey, 139 markers); {os.cpu_count()} CPUs; "
          f"fastest (CPU) of {args.repeat} rounds\n")
    print("| what | frames/s (wall) | frames per CPU-s | load | RMS / recall / false blobs |")
    print("|---|---:|---:|---:|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
