"""Check a mocaptk rig FBX (or GLB) in Blender: import it and compare with the rig.json beside it.

Runs in a separate Python 3.11 venv with PyPI ``bpy`` 5.0.1 (GPL, ~1.2 GB, pins numpy<2);
mocaptk itself is not needed there. Setup and use (see docs/rig-format.md):

    python3.11 -m venv .tools/bpyvenv && .tools/bpyvenv/bin/pip install bpy==5.0.1
    .tools/bpyvenv/bin/python scripts/check_fbx_blender.py rig.fbx rig.json

Prints one JSON report and exits 0 when every check passes, 1 otherwise. Checks: joint names
and hierarchy, bone heads (bind positions), vertex positions, per-vertex weights (vertex groups),
the rest-pose skinned mesh equals the mesh (bind matrices consistent), and moving one joint moves
each vertex by its weight times the joint's displacement. When rig.json names an animation
(rig_animation.npz): one action per take spanning frames 0 .. its length - 1 (every take its
own clip from 0), the scene at the capture's frame rate, and at 5 frames and the widest jaw
opening the armature-deformed mesh against the rig's own skinning of the baked tracks (forward
kinematics over the hierarchy, linear blend skinning), with the ``jaw`` bone's rotation there; the world joint positions at those frames are reported (``joint_world_mm``)
for the caller to compare with the raw capture, and the bones whose ``bpy.utils.flip_name``
names no bone (``flip_name_unmatched``: empty when Blender's mirror tools pair every bone).
"""

from __future__ import annotations

import argparse
import json
import sys

import bpy
import numpy as np
from mathutils import Matrix, Quaternion, Vector

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
    tracks = _tracks(rig, fbx_path)
    if fbx_path.lower().endswith((".glb", ".gltf")):
        if tracks is not None:  # glTF keys seconds: import at the capture's rate
            bpy.context.scene.render.fps = int(round(float(tracks["rate"])))
        bpy.ops.import_scene.gltf(filepath=fbx_path)
    else:  # Blender's importer shifts FBX keys by its "Animation Offset" (default 1 frame): 0
        # keeps the file's frames, clip frame 0 at Blender frame 0 as with the glTF
        bpy.ops.import_scene.fbx(filepath=fbx_path, anim_offset=0.0)
    bpy.context.scene.frame_set(0)  # every clip's first key (the static checks below start there)
    # skinned meshes only (the glTF importer adds an unskinned bone-shape icosphere)
    meshes = [o for o in bpy.context.scene.objects if o.type == "MESH" and o.vertex_groups]
    armatures = [o for o in bpy.context.scene.objects if o.type == "ARMATURE"]
    if len(meshes) != 1 or len(armatures) != 1:
        return {"ok": False, "error": f"expected 1 mesh + 1 armature, got {len(meshes)} + "
                                      f"{len(armatures)}"}
    mesh_obj, arm_obj = meshes[0], armatures[0]
    to_mm = 1000.0 / bpy.context.scene.unit_settings.scale_length

    names = [j["name"] for j in rig["joints"]]
    bones = arm_obj.data.bones
    if arm_obj.animation_data is not None:  # the static checks below need the rest pose
        arm_obj.animation_data.action = None
        for bone in arm_obj.pose.bones:
            bone.matrix_basis = Matrix.Identity(4)
        if arm_obj.name in names and arm_obj.name not in bones:  # the root: back to its bind
            rest = mesh_obj.matrix_world.copy()
            bind_root = np.array(rig["joints"][names.index(arm_obj.name)]["bind_position"])
            rest.translation = Vector(BLENDER_TO_RIG.T @ bind_root / to_mm)
            arm_obj.matrix_world = rest
        bpy.context.view_layer.update()
    # an unweighted root is written as the skeleton's Root: Blender makes it the armature object
    root_object = arm_obj.name if arm_obj.name in names and arm_obj.name not in bones else None
    missing = [n for n in names if n not in bones and n != root_object]
    parents_ok = all((bones[j["name"]].parent.name if bones[j["name"]].parent else root_object)
                     == j["parent"] for j in rig["joints"] if j["name"] in bones)
    heads = np.array([list(arm_obj.matrix_world @ bones[n].head_local) if n in bones
                      else list(arm_obj.matrix_world.translation) if n == root_object
                      else [np.nan] * 3 for n in names]) @ BLENDER_TO_RIG.T * to_mm
    lengths = {b.name: arm_obj.matrix_world.to_scale()[0] * b.length * to_mm for b in bones}
    bone_length_mm = max(lengths.values(), default=0.0)
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
        "max_bone_length_mm": bone_length_mm, "root_is_armature_object": root_object is not None,
        "bone_length_mm": {n: lengths[n] for n in ("head", "jaw") if n in lengths},
        "max_leaf_bone_length_mm": max((lengths[b.name] for b in bones if not b.children),
                                       default=0.0),
        # Blender's mirror tools pair bones by flip_name: imported names with no partner
        "flip_name_unmatched": [b.name for b in bones
                                if bpy.utils.flip_name(b.name) not in bones],
    }
    if tracks is not None:
        report.update(_check_animation(rig, tracks, mesh_obj, arm_obj, names, expected, to_mm))
    report["ok"] = bool(report.get("animation_ok", True) and not missing and parents_ok and same_count
                        and head_error <= POSITION_TOL_MM and vertex_error <= POSITION_TOL_MM
                        and weight_error <= WEIGHT_TOL and rest_error <= POSITION_TOL_MM
                        and pose_error <= POSITION_TOL_MM)
    return report


def _tracks(rig: dict, path: str) -> dict | None:
    """The baked tracks rig.json names (arrays of rig_animation.npz), or None."""
    import os

    animation = rig.get("animation")
    if not animation:
        return None
    with np.load(os.path.join(os.path.dirname(os.path.abspath(path)), animation["file"])) as data:
        return {key: data[key] for key in data.files}


ANIMATION_TOL_MM = 0.01
FRAMES_CHECKED = 5


def _check_animation(rig: dict, tracks: dict, mesh_obj, arm_obj, names: list[str],
                     weights: np.ndarray, to_mm: float) -> dict:
    """Actions, frame rate, and the deformed mesh at a few frames against the baked tracks."""
    scene = bpy.context.scene
    rate = float(tracks["rate"])
    takes = [(str(n), int(a), int(b)) for n, (a, b) in zip(tracks["take_names"],
                                                           tracks["take_frames"])]
    actions = {a.name: a for a in bpy.data.actions}

    def action_of(take: str):
        found = [a for name, a in actions.items() if name == take or f"|{take}|" in name]
        return found[0] if found else None

    ranges = {}
    for name, start, end in takes:
        action = action_of(name)
        ranges[name] = None if action is None else [float(v) for v in action.frame_range]
    # every take is its own clip from frame 0: its action spans 0 .. its length - 1
    offset = 0.0
    ranges_ok = all(r is not None and abs(r[0]) < 1e-3 and abs(r[1] - (b - a - 1)) < 1e-3
                    for (n, a, b), r in zip(takes, ranges.values()))

    vertices = np.array(rig["mesh"]["vertices"])
    bind = np.array([j["bind_position"] for j in rig["joints"]])
    translations = tracks["translations"].astype(float)
    quaternions = tracks["rotations"].astype(float)
    rotated = [int(j) for j in tracks["rotated_joints"]]
    parents = [int(p) for p in tracks["joint_parents"]]
    total = len(translations)
    jaw = rotated.index(names.index("jaw")) if "jaw" in names else None
    jaw_track = (np.array([Quaternion((q[3], *q[:3])).angle for q in quaternions[:, jaw]])
                 if jaw is not None else np.zeros(total))
    frames = np.unique(np.append(np.linspace(0, total - 1, FRAMES_CHECKED).round().astype(int),
                                 int(np.argmax(np.degrees(jaw_track)))))  # + the widest jaw
    mesh_errors, joints_world, jaw_deg = [], [], []
    for frame in frames:
        take = next(t for t in takes if t[1] <= frame < t[2])
        action = action_of(take[0])
        if action is None:
            mesh_errors.append(float("inf"))
            continue
        arm_obj.animation_data.action = action
        if hasattr(arm_obj.animation_data, "action_suitable_slots") and \
                arm_obj.animation_data.action_slot is None and arm_obj.animation_data.action_suitable_slots:
            arm_obj.animation_data.action_slot = arm_obj.animation_data.action_suitable_slots[0]
        for bone in arm_obj.pose.bones:  # the keys, not the earlier test pose
            bone.matrix_basis = Matrix.Identity(4)
        scene.frame_set(int(round(frame - take[1] + offset)))  # the clip's own frame
        bpy.context.view_layer.update()
        got = _world_vertices(mesh_obj, evaluated=True) * to_mm
        rotations, positions = _forward_kinematics(translations[frame], quaternions[frame],
                                                   rotated, parents)
        want = np.zeros_like(vertices)
        for joint in np.flatnonzero(weights.any(axis=0)):  # linear blend skinning, bind = identity
            want += weights[:, [joint]] * ((vertices - bind[joint]) @ rotations[joint].T
                                           + positions[joint])
        mesh_errors.append(float(np.abs(got - want).max()) if got.shape == want.shape
                           else float("inf"))
        if "jaw" in arm_obj.pose.bones:
            jaw_deg.append(float(np.degrees(arm_obj.pose.bones["jaw"].matrix_basis
                                            .to_quaternion().angle)))
        world = []
        for name in names:
            if name in arm_obj.pose.bones:
                head = arm_obj.matrix_world @ arm_obj.pose.bones[name].head
            else:  # the root as the armature object
                head = arm_obj.matrix_world.translation
            world.append(list(np.array(head) @ BLENDER_TO_RIG.T * to_mm))
        joints_world.append(world)
    fps = scene.render.fps / scene.render.fps_base
    ok = (ranges_ok and abs(fps - rate) < 1e-6 and len(actions) >= len(takes)
          and max(mesh_errors) <= ANIMATION_TOL_MM)
    return {"animation_ok": bool(ok), "actions": sorted(actions), "action_frame_ranges": ranges,
            "scene_fps": fps, "frames_checked": [int(f) for f in frames],
            "max_animated_mesh_error_mm": max(mesh_errors), "joint_world_mm": joints_world,
            "jaw_rotation_deg": jaw_deg,
            "jaw_track_deg": [float(np.degrees(jaw_track[f])) for f in frames]}


def _forward_kinematics(local: np.ndarray, quaternions: np.ndarray, rotated: list[int],
                        parents: list[int]) -> tuple[list[np.ndarray], np.ndarray]:
    """World rotations (3x3 each) and positions (J, 3) mm of the joints from one frame's local
    translations (J, 3), the rotating joints' quaternions (R, 4) (x, y, z, w) and the parents."""
    rotations, positions = [], np.zeros_like(local)
    for joint, parent in enumerate(parents):
        own = (np.array(Quaternion((quaternions[rotated.index(joint)][3],
                                    *quaternions[rotated.index(joint)][:3])).to_matrix())
               if joint in rotated else np.eye(3))
        if parent < 0:
            rotations.append(own)
            positions[joint] = local[joint]
        else:
            rotations.append(rotations[parent] @ own)
            positions[joint] = rotations[parent] @ local[joint] + positions[parent]
    return rotations, positions


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
