"""Check a mocaptk rig FBX in Blender: import it and compare with the rig.json written beside it.

Runs in a separate Python 3.11 venv with PyPI ``bpy`` 5.0.1 (GPL, ~1.2 GB, pins numpy<2);
mocaptk itself is not needed there. Setup and use (see docs/rig-format.md):

    python3.11 -m venv .tools/bpyvenv && .tools/bpyvenv/bin/pip install bpy==5.0.1
    .tools/bpyvenv/bin/python scripts/check_fbx_blender.py rig.fbx rig.json

Prints one JSON report and exits 0 when every check passes, 1 otherwise. Checks: joint names
and hierarchy, bone heads (bind positions), vertex positions, per-vertex weights (vertex groups),
the rest-pose skinned mesh equals the mesh (bind matrices consistent), and moving one joint moves
each vertex by its weight times the joint's displacement.
"""

from __future__ import annotations

import argparse
import json
import sys

import bpy
import numpy as np
from mathutils import Matrix, Vector

WEIGHT_TOL = 1e-6
# Blender is Z-up: its importer turns the file's Y-up axes into Blender's (x, -z, y).
BLENDER_TO_RIG = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
POSITION_TOL_MM = 1e-3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fbx", help="rig.fbx written by mocaptk")
    parser.add_argument("rig_json", help="the rig.json written from the same rig")
    args = parser.parse_args()
    with open(args.rig_json, encoding="utf-8") as handle:
        rig = json.load(handle)
    report = check(args.fbx, rig)
    print(json.dumps(report, indent=2, sort_keys=True))
    return 0 if report["ok"] else 1


def check(fbx_path: str, rig: dict) -> dict:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.fbx(filepath=fbx_path)
    meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    armatures = [o for o in bpy.context.scene.objects if o.type == "ARMATURE"]
    if len(meshes) != 1 or len(armatures) != 1:
        return {"ok": False, "error": f"expected 1 mesh + 1 armature, got {len(meshes)} + "
                                      f"{len(armatures)}"}
    mesh_obj, arm_obj = meshes[0], armatures[0]
    to_mm = 1000.0 / bpy.context.scene.unit_settings.scale_length

    names = [j["name"] for j in rig["joints"]]
    bones = arm_obj.data.bones
    missing = [n for n in names if n not in bones]
    parents_ok = all((bones[j["name"]].parent.name if bones[j["name"]].parent else None)
                     == j["parent"] for j in rig["joints"] if j["name"] in bones)
    heads = np.array([list(arm_obj.matrix_world @ bones[n].head_local) if n in bones
                      else [np.nan] * 3 for n in names]) @ BLENDER_TO_RIG.T * to_mm
    bind = np.array([j["bind_position"] for j in rig["joints"]])
    head_error = float(np.nanmax(np.abs(heads - bind))) if not missing else float("inf")

    vertices = np.array(rig["mesh"]["vertices"])
    blender_vertices = _world_vertices(mesh_obj, evaluated=False) * to_mm
    same_count = len(blender_vertices) == len(vertices)
    vertex_error = (float(np.abs(blender_vertices - vertices).max()) if same_count
                    else float("inf"))

    expected = np.zeros((len(vertices), len(names)))
    for row, (index, value) in enumerate(zip(rig["weights"]["joint_index"],
                                             rig["weights"]["value"])):
        for joint, weight in zip(index, value):
            expected[row, joint] += weight
    got = np.zeros_like(expected)
    group_joint = {g.index: names.index(g.name) for g in mesh_obj.vertex_groups if g.name in names}
    for vertex in mesh_obj.data.vertices[:len(vertices)]:
        for group in vertex.groups:
            if group.group in group_joint and group.weight > 0:
                got[vertex.index, group_joint[group.group]] = group.weight
    weight_error = float(np.abs(got - expected).max()) if same_count else float("inf")

    rest_error = float(np.abs(_world_vertices(mesh_obj, evaluated=True) * to_mm
                              - vertices).max()) if same_count else float("inf")

    # Move the most influential leaf joint 10 mm along +X; vertices must follow by their weight.
    parents = {j["parent"] for j in rig["joints"]}
    leaves = [j for j, name in enumerate(names) if name not in parents]
    leaf = max(leaves, key=lambda j: expected[:, j].sum())
    move_mm = np.array([10.0, 0.0, 0.0])
    bpy.context.view_layer.objects.active = arm_obj
    pose_bone = arm_obj.pose.bones[names[leaf]]
    to_armature = arm_obj.matrix_world.inverted().to_3x3()
    offset = to_armature @ Vector(BLENDER_TO_RIG.T @ move_mm / to_mm)
    pose_bone.matrix = Matrix.Translation(offset) @ pose_bone.matrix
    bpy.context.view_layer.update()
    moved = _world_vertices(mesh_obj, evaluated=True) * to_mm
    pose_error = float(np.abs(moved - vertices - expected[:, [leaf]] * move_mm).max()) \
        if same_count else float("inf")

    report = {
        "reader": f"Blender {bpy.app.version_string}",
        "joints_missing": missing, "hierarchy_ok": parents_ok,
        "max_bone_head_error_mm": head_error,
        "vertex_count": len(blender_vertices), "max_vertex_error_mm": vertex_error,
        "mesh_object_scale": list(mesh_obj.matrix_world.to_scale()),
        "max_weight_error": weight_error,
        "max_rest_pose_skinning_error_mm": rest_error,
        "moved_joint": names[leaf], "max_moved_joint_error_mm": pose_error,
    }
    report["ok"] = bool(not missing and parents_ok and same_count
                        and head_error <= POSITION_TOL_MM and vertex_error <= POSITION_TOL_MM
                        and weight_error <= WEIGHT_TOL and rest_error <= POSITION_TOL_MM
                        and pose_error <= POSITION_TOL_MM)
    return report


def _world_vertices(obj: bpy.types.Object, *, evaluated: bool) -> np.ndarray:
    """World-space vertex positions in Blender units and the rig's Y-up axes, ``(V, 3)``."""
    source = obj.evaluated_get(bpy.context.evaluated_depsgraph_get()) if evaluated else obj
    mesh = source.to_mesh() if evaluated else source.data
    coords = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", coords)
    if evaluated:
        source.to_mesh_clear()
    coords = coords.reshape(-1, 3)
    world = np.array(obj.matrix_world)
    return (coords @ world[:3, :3].T + world[:3, 3]) @ BLENDER_TO_RIG.T


if __name__ == "__main__":
    sys.exit(main())
