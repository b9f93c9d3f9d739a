"""Check a ``mocaptk retarget`` character file (.fbx, .glb, .usd) in Blender.

Runs in the bpy venv (see scripts/check_fbx_blender.py); mocaptk is not needed there:

    .tools/bpyvenv/bin/python scripts/check_character_blender.py expected.npz character.fbx [more files]

``expected.npz`` (written by the test) holds ``names`` (S,), ``rate``, ``frames`` (K,) capture frame
numbers and ``vertices`` (K, V, 3) mm: the product's own mesh at those frames (rig frame: Y up).
Prints a JSON list of reports, one per file; exits 0 when every check passes: one mesh with a shape key per shape,
the keys' values animated (one key per capture frame), the scene at the capture's rate (FBX, glTF;
Blender's USD importer keeps its scene rate whatever the stage's ``timeCodesPerSecond``: a USD's
keys are checked one per time code), and the
evaluated mesh at the K frames within ``TOLERANCE_MM`` of the product's.
"""

from __future__ import annotations

import json
import sys

import bpy
import numpy as np

TOLERANCE_MM = 0.01
# Blender is Z-up: its importers turn the file's Y-up axes into Blender's (x, -z, y).
BLENDER_TO_RIG = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def main(expected_path: str, *paths: str) -> int:
    expected = np.load(expected_path)
    reports = [check(path, expected) for path in paths]
    print(json.dumps(reports, indent=2))
    return 0 if all(r["ok"] for r in reports) else 1


def check(path: str, expected) -> dict:
    rate = float(expected["rate"])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if path.endswith((".glb", ".gltf")):
        scene.render.fps = int(round(rate))  # glTF keys seconds: import at the capture's rate
        bpy.ops.import_scene.gltf(filepath=path)
    elif path.endswith(".fbx"):
        bpy.ops.import_scene.fbx(filepath=path)
    else:
        bpy.ops.wm.usd_import(filepath=path)
    meshes = [o for o in scene.objects if o.type == "MESH" and o.data.shape_keys]
    report: dict = {"file": path, "meshes_with_shape_keys": len(meshes), "scene_fps": scene.render.fps / scene.render.fps_base}
    if len(meshes) != 1:
        report["ok"] = False
        return report
    obj = meshes[0]
    keys = obj.data.shape_keys
    names = [k.name for k in keys.key_blocks][1:]
    action = keys.animation_data.action if keys.animation_data else None
    curves = _fcurves(action) if action else []
    counts = sorted({len(fc.keyframe_points) for fc in curves})
    first = min(fc.keyframe_points[0].co[0] for fc in curves) if curves else 0.0
    rest = _positions(obj, scene, None)
    errors = []
    for frame, target in zip(expected["frames"], expected["vertices"]):
        moved = _positions(obj, scene, first + float(frame))
        errors.append(_matched_error(rest, moved, target, expected["rest"]))
    report.update(shape_keys=len(names), names_match=names == [str(n) for n in expected["names"]],
                  animated_keys=len(curves), keys_per_curve=counts, first_frame=first,
                  max_error_mm=max(errors))
    report["ok"] = bool(report["names_match"] and len(curves) >= len(names) - 1
                        and report["max_error_mm"] < TOLERANCE_MM
                        and (abs(report["scene_fps"] - rate) < 1e-6 or path.endswith((".usd", ".usda", ".usdc"))))
    return report


def _fcurves(action) -> list:
    try:
        return list(action.fcurves)
    except AttributeError:  # Blender 5 layered actions
        return [fc for layer in action.layers for strip in layer.strips
                for bag in strip.channelbags for fc in bag.fcurves]


def _positions(obj, scene, frame: float | None) -> np.ndarray:
    """World vertex positions (V, 3) mm in the rig frame at ``frame`` (None: the rest mesh)."""
    if frame is None:
        coords = np.array([v.co[:] for v in obj.data.vertices])
    else:
        scene.frame_set(int(np.floor(frame)), subframe=float(frame - np.floor(frame)))
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = evaluated.to_mesh()
        coords = np.array([v.co[:] for v in mesh.vertices])
        evaluated.to_mesh_clear()
    world = np.array(obj.matrix_world)
    coords = coords @ world[:3, :3].T + world[:3, 3]
    return coords @ BLENDER_TO_RIG.T * 1000.0


def _matched_error(rest: np.ndarray, moved: np.ndarray, target: np.ndarray, target_rest: np.ndarray) -> float:
    """Largest distance (mm) between Blender's vertices and ours, matched by rest position."""
    match = np.empty(len(rest), dtype=np.int64)
    for start in range(0, len(rest), 512):
        d = ((rest[start:start + 512, None] - target_rest[None]) ** 2).sum(axis=2)
        match[start:start + 512] = d.argmin(axis=1)
    return float(np.linalg.norm(moved - target[match], axis=1).max())


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
