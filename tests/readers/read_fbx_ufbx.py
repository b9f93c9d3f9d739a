"""Load an FBX with ufbx and print what the rig tests compare, as JSON on stdout.

Run in a subprocess (the ufbx binding can crash the interpreter): python read_fbx_ufbx.py FILE
Matrices are 4x4 row-major lists (column vectors, translation in the last column), in file units.
"""

from __future__ import annotations

import json
import os
import sys

import ufbx


def matrix(m: ufbx.Matrix) -> list[list[float]]:
    cols = [m.c0, m.c1, m.c2, m.c3]
    return [[c.x for c in cols], [c.y for c in cols], [c.z for c in cols], [0.0, 0.0, 0.0, 1.0]]


# Every element wrapper the binding hands out is kept alive until exit: in ufbx 0.0.5, freeing a
# wrapper reached through another element (cluster.bone_node, node.parent...) corrupts the scene.
_HELD: list[object] = []


def held(value):
    _HELD.append(value)
    return value


def main(path: str) -> None:
    scene = held(ufbx.load_file(path))
    settings = held(scene.settings)
    axes = held(settings.axes)
    nodes = held(scene.nodes)
    mesh = held(held(scene.meshes)[0])
    flat = [int(i) for i in held(mesh.vertex_indices)]
    joints, mesh_to_world = {}, None
    for node in nodes:
        held(node)
        if held(node.mesh) is not None:
            mesh_to_world = matrix(held(node.node_to_world))
        if held(node.bone) is not None:
            parent = held(node.parent)
            joints[node.name] = {
                "parent": parent.name if held(parent.bone) is not None else None,
                "node_to_world": matrix(held(node.node_to_world))}
    clusters = {}
    for cluster in held(scene.skin_clusters):
        held(cluster)
        clusters[held(cluster.bone_node).name] = {
            "vertices": [int(v) for v in held(cluster.vertices)],
            "weights": [float(w) for w in held(cluster.weights)],
            "bind_to_world": matrix(held(cluster.bind_to_world)),
            "geometry_to_bone": matrix(held(cluster.geometry_to_bone)),
        }
    bind_pose = {}
    for pose in held(scene.poses):
        if held(pose).is_bind_pose:
            for bone_pose in held(pose.bone_poses):
                held(bone_pose)
                bind_pose[held(bone_pose.bone_node).name] = matrix(held(bone_pose.bone_to_world))
    stacks = []
    for stack in held(scene.anim_stacks):
        held(stack)
        curves = keys = 0
        for layer in held(stack.layers):
            for value in held(held(layer).anim_values):
                for curve in held(held(value).curves):
                    if held(curve) is not None:
                        curves += 1
                        keys += len(held(curve.keyframes))
        stacks.append({"name": stack.name, "time_begin": stack.time_begin,
                       "time_end": stack.time_end, "curves": curves, "keys": keys})
    out = {
        "version": held(scene.metadata).version,
        "frames_per_second": settings.frames_per_second,
        "anim_stacks": stacks,
        "unit_meters": settings.unit_meters,
        "axes": [axes.right.name, axes.up.name, axes.front.name],
        "vertices": [[p.x, p.y, p.z] for p in held(mesh.vertices)],
        "faces": [flat[f.index_begin:f.index_begin + f.num_indices] for f in held(mesh.faces)],
        "mesh_node_to_world": mesh_to_world,
        "joints": joints,
        "clusters": clusters,
        "bind_pose": bind_pose,
        "materials": [held(m).name for m in held(mesh.materials)],
        "face_material": [int(i) for i in held(mesh.face_material)],
    }
    json.dump(out, sys.stdout)
    sys.stdout.flush()
    os._exit(0)  # tearing the wrappers down at exit crashes ufbx 0.0.5 on large scenes


if __name__ == "__main__":
    main(sys.argv[1])
