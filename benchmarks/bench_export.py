"""Benchmark: rig export (rig.json, rig.fbx, rig.glb) vs an np.savez floor and Blender's exporters.

Rig: the ICT-FaceKit face (11,248 vertices) when the face model is available, else a
100 x 110 grid patch, with 60 farthest-point joints under a root and 4 Gaussian influences per
vertex. Times are the best of ``--repeat`` runs. Baselines, same rig, same run:
``np.savez`` of the raw arrays (the I/O floor), and, with ``--blender-python`` (a Python with
PyPI bpy 5.0.1, see docs/rig-format.md), Blender's own FBX and glTF exporters on the scene
Blender imports from our rig.fbx (import not timed).

    python benchmarks/bench_export.py [--repeat 3] [--blender-python .tools/bpyvenv/bin/python]
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


def benchmark_rig() -> tuple[Rig, str]:
    """The face (or grid) rig with 60 joints and 4 Gaussian influences per vertex."""
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
    for _ in range(59):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(candidates - candidates[chosen[-1]], axis=1))
    markers = candidates[chosen]
    falloff = np.exp(-0.5 * (np.linalg.norm(vertices[:, None] - markers[None], axis=2) / 25) ** 2)
    index = np.argsort(-(falloff + 1e-12), axis=1, kind="stable")[:, :4]
    value = np.take_along_axis(falloff + 1e-12, index, axis=1)
    value /= value.sum(axis=1, keepdims=True)
    sides = ["L" if x > 5 else "R" if x < -5 else "C" for x in markers[:, 0]]
    rig = Rig.from_markers(vertices, faces, marker_labels=[f"M{i:02d}" for i in range(60)],
                           marker_positions=markers, marker_sides=sides,
                           marker_regions=["face"] * 60, weight_index=index, weight_value=value)
    return rig, name


def best_time(action, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per writer (best is kept)")
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


if __name__ == "__main__":
    sys.exit(main())
