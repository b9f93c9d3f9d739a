"""Render a mocaptk rig.fbx in Blender at rest, at the widest jaw opening and at the fullest blink
of its baked animation, front and three-quarter (what an animator sees after importing it).

Runs in the bpy venv (see scripts/check_fbx_blender.py); mocaptk is not needed there:

    .tools/bpyvenv/bin/python scripts/render_rig_blender.py OUT/rig.fbx OUT/rig.json RENDERS

The poses come from the baked tracks (rig_animation.npz beside rig.json): rest = the frame whose
joints are nearest their bind positions, widest jaw = the largest ``jaw`` rotation, blink = the
lowest ``upperLid`` joints. Writes ``<pose>_<view>.png`` (Cycles, CPU) and prints a JSON list of
what was rendered (take, clip frame, jaw angle).
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy
import numpy as np
from mathutils import Quaternion, Vector

VIEWS = {"front": 0.0, "three_quarter": 35.0}  # degrees about the vertical, towards the actor's left


def main(fbx: str, rig_json: str, out: str) -> None:
    with open(rig_json, encoding="utf-8") as handle:
        rig = json.load(handle)
    with np.load(os.path.join(os.path.dirname(os.path.abspath(rig_json)),
                              rig["animation"]["file"])) as data:
        tracks = {key: data[key] for key in data.files}
    names = [j["name"] for j in rig["joints"]]
    bind = np.array([j["bind_position"] for j in rig["joints"]])
    parents = [int(p) for p in tracks["joint_parents"]]
    local_bind = bind - np.array([bind[p] if p >= 0 else np.zeros(3) for p in parents])
    translations, rotations = tracks["translations"], tracks["rotations"]
    rotated = [int(j) for j in tracks["rotated_joints"]]
    jaw_track = rotations[:, rotated.index(names.index("jaw"))]
    jaw = np.array([Quaternion((q[3], *q[:3])).angle for q in jaw_track])
    markers = [i for i, j in enumerate(rig["joints"]) if j["marker"] and j["region"] != "stabilization"]
    lids = [i for i, n in enumerate(names) if n.startswith("upperLid")]
    still = np.linalg.norm(translations[:, markers] - local_bind[markers], axis=2).mean(axis=1)
    poses = {"rest": int(np.argmin(still + np.degrees(jaw) * 0.1)), "widest_jaw": int(np.argmax(jaw)),
             "blink": int(np.argmin((translations[:, lids, 1] - local_bind[lids, 1]).mean(axis=1)))}
    takes = [(str(n), int(a), int(b)) for n, (a, b) in zip(tracks["take_names"], tracks["take_frames"])]

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = int(round(float(tracks["rate"])))
    bpy.ops.import_scene.fbx(filepath=fbx, anim_offset=0.0)
    mesh = next(o for o in scene.objects if o.type == "MESH" and o.vertex_groups)
    arm = next(o for o in scene.objects if o.type == "ARMATURE")
    arm.hide_render = True
    for obj in scene.objects:
        if obj.type == "ARMATURE":
            obj.show_in_front = True
    corners = [mesh.matrix_world @ Vector(c) for c in mesh.bound_box]
    centre = sum(corners, Vector()) / 8.0
    size = max((a - b).length for a in corners for b in corners)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.lens = 85.0
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(60.0), 0.0, math.radians(-20.0))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("world")
    world.color = (0.25, 0.25, 0.28)
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.samples = 16
    scene.cycles.device = "CPU"
    scene.render.resolution_x = scene.render.resolution_y = 640
    actions = {a.name: a for a in bpy.data.actions}
    done = []
    for pose, frame in poses.items():
        name, start, _ = next(t for t in takes if t[1] <= frame < t[2])
        action = next(a for n, a in actions.items() if n == name or f"|{name}|" in n)
        arm.animation_data.action = action
        if hasattr(arm.animation_data, "action_suitable_slots") and \
                arm.animation_data.action_slot is None and arm.animation_data.action_suitable_slots:
            arm.animation_data.action_slot = arm.animation_data.action_suitable_slots[0]
        scene.frame_set(frame - start)
        for view, degrees in VIEWS.items():
            angle = math.radians(degrees)  # Blender: the face looks down -Y, its left is +X
            direction = Vector((math.sin(angle), -math.cos(angle), 0.05))
            camera.location = centre + direction.normalized() * size * 2.6
            camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
            scene.render.filepath = os.path.join(out, f"{pose}_{view}.png")
            bpy.ops.render.render(write_still=True)
        done.append({"pose": pose, "take": name, "clip_frame": frame - start,
                     "jaw_deg": float(np.degrees(jaw[frame]))})
    print(json.dumps(done))


if __name__ == "__main__":
    main(*sys.argv[1:4])
