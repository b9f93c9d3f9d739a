"""Benchmark: rig export (rig.json, rig.fbx, rig.glb) vs an np.savez floor and Blender's exporters.

Rig: the ICT-FaceKit face (11,248 vertices) when the face model is available, else a
100 x 110 grid patch, with 60 farthest-point joints under a root and 4 Gaussian influences per
vertex. Times are the best of ``--repeat`` runs. Baselines, same rig, same run:
``np.savez`` of the raw arrays (the I/O floor), and, with ``--blender-python`` (a Python with
PyPI bpy 5.0.1, see docs/rig-format.md), Blender's own FBX and glTF exporters on the scene
Blender imports from our rig.fbx (import not timed).

Animation (``--frames``, default 72,000 = 20 min at 60 Hz; 0 skips it): the same face with 86
joints, smooth synthetic joint motion with 0.05 % of the marker-frames missing (runs of 1-30
frames) and a moving head; times the bake (gap filling included) and each writer with the
animation (wall and CPU seconds) against ``np.savez`` of the raw tracks (floor); prints file
sizes and bytes per frame.

    python benchmarks/bench_export.py [--repeat 3] [--frames 72000] [--blender-python .tools/bpyvenv/bin/python]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mocaptk.retarget import Rig, write_rig_fbx, write_rig_glb, write_rig_json
from mocaptk.retarget.export_fbx import rig_fbx_bytes

_BLENDER_EXPORT = """
import json, sys, time
import bpy
fbx, out = sys.argv[-2], sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.fbx(filepath=fbx)
best = {"fbx": float("inf"), "glb": float("inf")}
for _ in range(int(sys.argv[-3])):
    start = time.perf_counter()
    bpy.ops.export_scene.fbx(filepath=out + ".fbx", add_leaf_bones=False, bake_anim=False)
    best["fbx"] = min(best["fbx"], time.perf_counter() - start)
    start = time.perf_counter()
    bpy.ops.export_scene.gltf(filepath=out + ".glb", export_format="GLB", export_animations=False)
    best["glb"] = min(best["glb"], time.perf_counter() - start)
print("RESULT" + json.dumps(best))
"""


def benchmark_rig(joints: int = 60) -> tuple[Rig, str]:
    """The face (or grid) rig with ``joints`` joints and 4 Gaussian influences per vertex."""
    try:
        from mocaptk.acquisition.face_model import load_face_model
        model = load_face_model()
        vertices, faces, name = model.neutral, model.faces, "ICT-FaceKit face"
        candidates = vertices[:model.face_vertex_count]
    except Exception as exc:  # noqa: BLE001 - any missing-data problem: fall back to the grid
        print(f"face model unavailable ({exc}); using a grid patch")
        u, v = np.meshgrid(np.linspace(-70, 70, 110), np.linspace(-60, 60, 100))
        vertices = np.column_stack([u.ravel(), v.ravel(), 90 - (u.ravel() ** 2) / 200])
        quads = [(r * 110 + c, r * 110 + c + 1, (r + 1) * 110 + c + 1, (r + 1) * 110 + c)
                 for r in range(99) for c in range(109)]
        faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
        candidates, name = vertices, "grid patch"
    chosen = [int(np.argmax(candidates[:, 1]))]
    distance = np.linalg.norm(candidates - candidates[chosen[0]], axis=1)
    for _ in range(joints - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(candidates - candidates[chosen[-1]], axis=1))
    markers = candidates[chosen]
    falloff = np.exp(-0.5 * (np.linalg.norm(vertices[:, None] - markers[None], axis=2) / 25) ** 2)
    index = np.argsort(-(falloff + 1e-12), axis=1, kind="stable")[:, :4]
    value = np.take_along_axis(falloff + 1e-12, index, axis=1)
    value /= value.sum(axis=1, keepdims=True)
    sides = ["L" if x > 5 else "R" if x < -5 else "C" for x in markers[:, 0]]
    rig = Rig.from_markers(vertices, faces, marker_labels=[f"M{i:02d}" for i in range(joints)],
                           marker_positions=markers, marker_sides=sides,
                           marker_regions=["face"] * joints, weight_index=index,
                           weight_value=value)
    return rig, name


def best_time(action, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - start)
    return best


def benchmark_motion(rig: Rig, frames: int, *, seed: int = 0):
    """(F, J-1, 3) joint positions with gaps, head rotations (F, 3, 3), translations (F, 3)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 60.0
    joints = rig.joint_count - 1
    phase = rng.uniform(0, 2 * np.pi, (1, joints, 3))
    speed = rng.uniform(0.2, 2.0, (1, joints, 3))
    positions = rig.joint_positions[None, 1:] + 3.0 * np.sin(speed * t[:, None, None] + phase)
    for _ in range(int(frames * joints * 0.0005 / 15)):  # gaps of 1-30 frames, 0.05 %
        j, start = rng.integers(joints), rng.integers(1, frames - 31)
        positions[start:start + rng.integers(1, 31), j] = np.nan
    angles = np.column_stack([0.2 * np.sin(0.3 * t), 0.3 * np.sin(0.2 * t), 0.1 * np.sin(0.5 * t)])
    shift = np.column_stack([40 * np.sin(0.1 * t), 10 * np.sin(0.3 * t), 20 * np.sin(0.2 * t)])
    return positions, Rotation.from_euler("xyz", angles).as_matrix(), shift


def animation_benchmark(frames: int) -> None:
    """Bake + write a long capture on an 86-joint face rig; times, sizes, bytes per frame."""
    from mocaptk.retarget.bake import bake_animation

    rig, name = benchmark_rig(joints=86)
    positions, rotations, shift = benchmark_motion(rig, frames)
    print(f"\nanimation: {frames} frames x {rig.joint_count - 1} joints (+ face_root) on the {name}, "
          f"{int(np.isnan(positions[..., 0]).sum())} missing marker-frames")
    start, cpu = time.perf_counter(), time.process_time()
    anim = bake_animation(rig, positions, rate=60.0, head_rotations=rotations,
                          head_translations=shift)
    bake = time.perf_counter() - start, time.process_time() - cpu
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        start, cpu = time.perf_counter(), time.process_time()
        np.savez(out / "floor.npz", translations=anim.translations, rotations=anim.root_rotations)
        floor = time.perf_counter() - start, time.process_time() - cpu
        rows = [("bake_animation (gap fill + head pose)", bake, None)]
        for fmt, writer in (("json", write_rig_json), ("fbx", write_rig_fbx),
                            ("glb", write_rig_glb)):
            start, cpu = time.perf_counter(), time.process_time()
            writer(rig, out / f"rig.{fmt}", animation=anim)
            seconds = time.perf_counter() - start, time.process_time() - cpu
            size = (out / f"rig.{fmt}").stat().st_size
            if fmt == "json":
                size += (out / "rig_animation.npz").stat().st_size
            rows.append((f"write_rig_{fmt} with animation", seconds, size))
        rig_only = len(rig_fbx_bytes(rig))
    # CPU seconds beside wall: on a loaded machine the wall time mostly measures the queue
    print(f"{'step':40s} {'wall s':>8s} {'CPU s':>7s} {'CPU x np.savez':>15s} {'size MB':>9s} "
          f"{'bytes/frame':>12s}")
    for label, (wall, cpu), size in [("np.savez of the tracks (floor)", floor, None)] + rows:
        extra = "" if size is None else f" {size / 1e6:9.1f} {size / frames:12.0f}"
        print(f"{label:40s} {wall:8.2f} {cpu:7.2f} {cpu / floor[1]:15.1f}{extra}")
    fbx_size = next(size for label, _, size in rows if "fbx" in label)
    print(f"FBX animation alone: {(fbx_size - rig_only) / frames:.0f} bytes/frame "
          f"({(fbx_size - rig_only) / frames / rig.joint_count:.1f} per joint-frame)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per writer (best is kept)")
    parser.add_argument("--frames", type=int, default=72_000,
                        help="frames of the animation benchmark (0: skip it)")
    parser.add_argument("--blender-python", type=Path, default=None,
                        help="Python with bpy 5.0.1 for the Blender exporter baselines")
    args = parser.parse_args()
    rig, name = benchmark_rig()
    print(f"rig: {name}, {rig.vertex_count} vertices, {len(rig.faces)} triangles, "
          f"{rig.joint_count} joints, {rig.max_influences} influences")
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        floor = best_time(lambda: np.savez(out / "floor.npz", vertices=rig.vertices,
                                           faces=rig.faces, index=rig.weight_index,
                                           value=rig.weight_value), args.repeat)
        ours = {fmt: best_time(lambda w=writer, f=fmt: w(rig, out / f"rig.{f}"), args.repeat)
                for fmt, writer in (("json", write_rig_json), ("fbx", write_rig_fbx),
                                    ("glb", write_rig_glb))}
        sizes = {fmt: (out / f"rig.{fmt}").stat().st_size for fmt in ours}
        blender = {}
        if args.blender_python is not None:
            done = subprocess.run([str(args.blender_python), "-c", _BLENDER_EXPORT,
                                   str(args.repeat), str(out / "rig.fbx"), str(out / "blender")],
                                  capture_output=True, text=True, check=True)
            blender = json.loads(done.stdout.split("RESULT", 1)[1])
    print(f"{'writer':32s} {'seconds':>9s} {'size MB':>8s} {'x np.savez':>11s} {'x Blender':>10s}")
    print(f"{'np.savez (floor)':32s} {floor:9.3f} {'':>8s} {1.0:11.1f}")
    for fmt, seconds in ours.items():
        versus = f"{seconds / blender[fmt]:10.2f}" if fmt in blender else f"{'-':>10s}"
        print(f"{'mocaptk write_rig_' + fmt:32s} {seconds:9.3f} {sizes[fmt] / 1e6:8.2f} "
              f"{seconds / floor:11.1f} {versus}")
    for fmt, seconds in blender.items():
        print(f"{'Blender export_scene.' + fmt:32s} {seconds:9.3f} {'':>8s} {seconds / floor:11.1f}")
    if args.frames > 0:
        animation_benchmark(args.frames)


if __name__ == "__main__":
    sys.exit(main())
