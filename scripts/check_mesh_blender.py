"""Check ``mocaptk solve``'s animated mesh (mesh.usd or mesh.glb) in Blender against mesh_frames.npy.

Runs in the separate Blender venv (PyPI ``bpy`` 5.0.1, see scripts/check_fbx_blender.py); mocaptk
itself is not needed there:

    .tools/bpyvenv/bin/python scripts/check_mesh_blender.py OUT/mesh.usd OUT/mesh_frames.npy RATE

Imports the file with Blender's own USD or glTF importer (the scene at the capture's rate, so a
glTF key at ``f / rate`` seconds lands on frame ``f``), then at a few frames compares the evaluated
mesh (Mesh Sequence Cache for USD, shape keys driven by the animation for glTF), in world
coordinates, with the frame written by mocaptk (USD: at time code ``--first-frame`` + the
frame; glTF: the first clip, from time 0). Prints one JSON report; exits 0 when the vertex
count matches, every checked frame is within ``POSITION_TOL_MM`` and the mesh moves, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys

import bpy
import numpy as np

# Blender is Z-up: both importers turn the file's Y-up axes into Blender's (x, -z, y).
BLENDER_TO_FILE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: mesh_frames.npy is float32 mm; glTF stores float32 offsets from the neutral.
POSITION_TOL_MM = 1e-2


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", help="mesh.usd or mesh.glb written by mocaptk solve")
    parser.add_argument("frames", help="mesh_frames.npy of the same solve")
    parser.add_argument("rate", type=float, help="the capture's frame rate (Hz)")
    parser.add_argument("--first-frame", type=int, default=0,
                        help="the capture's first frame number (USD time codes start there)")
    args = parser.parse_args()
    report = check(args.mesh, np.load(args.frames), args.rate, first_frame=args.first_frame)
    print(json.dumps(report, indent=2, sort_keys=True))
    return 0 if report["ok"] else 1


def check(path: str, frames: np.ndarray, rate: float, *, first_frame: int = 0) -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = int(round(rate))  # glTF keys seconds (USD time codes are frames already)
    gltf = path.lower().endswith((".glb", ".gltf"))
    if gltf:  # glTF time 0 lands on Blender frame 0, USD time code t on frame t
        bpy.ops.import_scene.gltf(filepath=path)
    else:
        bpy.ops.wm.usd_import(filepath=path)
    # the mesh (glTF: the skinned one; the importer adds an unskinned bone-shape icosphere)
    meshes = [o for o in scene.objects if o.type == "MESH" and (o.vertex_groups or not gltf)]
    if len(meshes) != 1:
        return {"ok": False, "error": f"expected 1 mesh, got {len(meshes)}"}
    obj = meshes[0]
    n_frames, n_verts = frames.shape[:2]
    report: dict = {"importer": "gltf" if gltf else "usd", "shape_keys": (
                        len(obj.data.shape_keys.key_blocks) - 1 if obj.data.shape_keys else 0),
                    "fps": scene.render.fps / scene.render.fps_base,
                    "vertices": len(obj.data.vertices), "expected_vertices": int(n_verts),
                    "frame_range": [scene.frame_start, scene.frame_end]}
    if len(obj.data.vertices) != n_verts:
        report["ok"] = False
        return report
    checked = sorted({0, n_frames // 3, n_frames // 2, n_frames - 1})
    errors, positions = {}, {}
    offset = 0 if gltf else first_frame  # USD time codes are the capture's frame numbers
    for f in checked:
        positions[f] = _evaluated_mm(obj, f + offset)
        errors[str(f)] = float(np.abs(positions[f] - frames[f]).max())
    # the largest vertex displacement from the first checked frame: the mesh plays, not just loads
    motion = max(float(np.linalg.norm(positions[f] - positions[0], axis=1).max()) for f in checked)
    expected = max(float(np.linalg.norm(frames[f] - frames[0], axis=1).max()) for f in checked)
    report.update(max_error_mm=errors, motion_mm=motion, expected_motion_mm=expected)
    report["ok"] = max(errors.values()) <= POSITION_TOL_MM and motion > 0.1
    return report


def _evaluated_mm(obj, frame: int) -> np.ndarray:
    """The object's evaluated vertices (V, 3) at ``frame``, world space, in the file's frame (mm)."""
    scene = bpy.context.scene
    scene.frame_set(frame)
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    co = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", co)
    evaluated.to_mesh_clear()
    world = np.array(obj.matrix_world)
    co = co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3]
    to_mm = 1000.0 * scene.unit_settings.scale_length
    return to_mm * co @ BLENDER_TO_FILE.T


if __name__ == "__main__":
    sys.exit(main())
