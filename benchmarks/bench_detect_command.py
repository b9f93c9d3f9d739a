"""``mocaptk detect`` end to end (decode + detect + write) against detection alone and OpenCV's
SimpleBlobDetector, frames of four 1280x720 cameras per second, wall and CPU, in one run.

    python benchmarks/bench_detect_command.py [--frames 200] [--repeat 2]

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
from mocaptk.acquisition.image_sequences import ImageSource
from mocaptk.acquisition.projection import ellipsoid_markers
from mocaptk.acquisition.synth_images import marker_truth, png_bytes, render_markers, skin_shading


def render(frames: int) -> list[list[np.ndarray]]:
    rig = cara_rig()
    points, normals = ellipsoid_markers(frames, 139, max_yaw=1.1, seed=1)
    truth = marker_truth(rig, points, normals)
    rng = np.random.default_rng(0)
    return [[render_markers(skin_shading(cam, c), truth.pixels[c, f], truth.radius[c, f], rng=rng)[0]
             for f in range(frames)] for c, cam in enumerate(rig)]


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


def command(folder: Path, out: Path) -> tuple[float, float]:
    """Wall and CPU seconds (the child's, all its threads) of one ``mocaptk detect`` run."""
    inputs = sorted(folder.iterdir()) if any(p.suffix == ".avi" for p in folder.iterdir()) else [folder]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mocaptk", "detect", *map(str, inputs), "--out", str(out),
                    "--force", "--quiet"], check=True, capture_output=True)
    wall = time.perf_counter() - wall
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    frames = args.frames
    images = render(frames)
    flat = [image for row in images for image in row]
    detect_blobs(flat[0])  # compiled pass loaded from numba's cache, not timed
    params = cv2.SimpleBlobDetector_Params()  # as benchmarks/bench_cameras.py
    params.blobColor, params.minArea, params.maxArea = 255, 6, 2000
    params.filterByCircularity = params.filterByConvexity = params.filterByInertia = False
    params.minThreshold, params.maxThreshold, params.thresholdStep = 120, 240, 20
    detector = cv2.SimpleBlobDetector_create(params)
    rows = []

    def row(name: str, wall: float, cpu: float) -> None:
        rows.append(f"| {name} | {frames / wall:.0f} | {frames / cpu:.0f} | {os.getloadavg()[0]:.1f} |")

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
            name = f"`mocaptk detect` command, {label} ({size / 1024:.0f} KiB per image)"
            for _ in range(args.repeat):
                best[name] = min(best.get(name, (np.inf, np.inf)), command(folder, temp / f"{kind}.npz"),
                                 key=lambda t: t[1])
            row(name, *best[name])
    print(f"{frames} frames of 4 cameras (1280x720 grey, 139 markers); {os.cpu_count()} CPUs; "
          f"fastest (CPU) of {args.repeat} rounds\n")
    print("| what | frames/s (wall) | frames per CPU-s | load |")
    print("|---|---:|---:|---:|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
