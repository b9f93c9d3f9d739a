"""The animation bake (retarget/bake.py) and its keys in rig.fbx, rig.glb and rig.json/.npz:
head pose on face_root, gaps filled and listed, one clip per take, the capture's frame rate;
read back by ufbx, the Autodesk FBX SDK (FBX2glTF) and the Khronos glTF validator."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from readers import installed
from readers.fbx_dom import parse_fbx
from readers.sample_rig import sample_rig
from scipy.spatial.transform import Rotation

from mocaptk.retarget import write_rig_fbx, write_rig_glb, write_rig_json
from mocaptk.retarget.bake import HEAD_POSE, bake_animation, concatenate_animations
from mocaptk.retarget.export_fbx import KTIME_PER_SECOND, rig_fbx_bytes
from mocaptk.retarget.export_json import read_rig_animation, rig_animation_bytes
from mocaptk.trajectories import Take

FRAMES = 90


def _motion(rig, frames: int = FRAMES, seed: int = 3):
    """Smooth joint motion (mm, head-relative) and a head pose (rotation up to ~25°, 40 mm)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, frames)[:, None, None]
    amplitude = rng.normal(0.0, 3.0, (1, rig.joint_count - 1, 3))
    relative = rig.joint_positions[None, 1:] + amplitude * np.sin(2 * np.pi * t)
    angles = np.column_stack([0.4 * np.sin(3 * t[:, 0, 0]), 0.2 * t[:, 0, 0], 0.1 * t[:, 0, 0]])
    rotations = Rotation.from_euler("xyz", angles).as_matrix()
    translations = np.column_stack([40 * t[:, 0, 0], -10 * t[:, 0, 0], 5 * t[:, 0, 0]])
    return relative, rotations, translations


@pytest.fixture(scope="module")
def baked():
    rig = sample_rig(silent_joints=("face_root",))
    relative, rotations, translations = _motion(rig)
    holes = relative.copy()
    holes[10:14, 1] = np.nan  # short interior gap: spline
    holes[0:20, 2] = np.nan  # leading gap longer than max_gap: held from frame 20
    rotations[50:52] = np.nan  # frames without a head pose: held
    takes = (Take("neutral", 0, 40), Take("smile", 40, FRAMES))
    anim = bake_animation(rig, holes, rate=60.0, head_rotations=rotations,
                          head_translations=translations, takes=takes, name="session")
    return rig, anim, relative, rotations, translations


def test_world_joints_follow_the_raw_capture(baked):
    rig, anim, relative, rotations, translations = baked
    assert np.isfinite(anim.translations).all() and np.isfinite(anim.root_rotations).all()
    raw = np.einsum("fij,fkj->fki", rotations, relative) + translations[:, None]
    world = anim.world_positions()
    posed = np.isfinite(rotations).all(axis=(1, 2))
    seen = np.ones(relative.shape[:2], bool)
    seen[10:14, 1] = seen[0:20, 2] = False
    error = np.linalg.norm(world[:, 1:] - raw, axis=2)[posed[:, None] & seen]
    assert error.max() < 1e-9
    # the root carries the head: at the bind position, moved by the pose
    expected_root = np.einsum("fij,j->fi", rotations, rig.joint_positions[0]) + translations
    np.testing.assert_allclose(world[posed, 0], expected_root[posed], atol=1e-9)
    # continuous quaternions (no sign flips between consecutive keys)
    assert np.all(np.einsum("fi,fi->f", anim.root_rotations[1:], anim.root_rotations[:-1]) > 0)


def test_every_gap_is_filled_and_listed(baked):
    rig, anim, relative, *_ = baked
    gaps = {(g.marker, g.start, g.end): g.method for g in anim.gaps}
    label1, label2 = rig.joint_markers[2], rig.joint_markers[3]
    assert gaps[(label1, 10, 14)] == "cubic"
    assert gaps[(label2, 0, 20)] in ("neighbours", "hold")
    assert gaps[(HEAD_POSE, 50, 52)] == "hold"
    assert anim.filled_frames() == 4 + 20
    assert np.abs(anim.translations[10:14, 2] + rig.joint_positions[0]
                  - relative[10:14, 1]).max() < 0.5  # a smooth spline through a sine
    report = anim.report()
    assert report["filled_marker_frames"] == 24 and report["head_pose_frames_held"] == 2
    assert [t["name"] for t in report["takes"]] == ["neutral", "smile"]


def test_concatenated_captures_keep_their_clips(baked):
    rig, anim, *_ = baked
    both = concatenate_animations([anim, anim])
    assert both.frame_count == 2 * FRAMES
    assert [(t.name, t.start, t.end) for t in both.takes] == [
        ("neutral", 0, 40), ("smile", 40, 90), ("session_neutral", 90, 130),
        ("session_smile", 130, 180)]
    assert both.gaps[-1].start >= FRAMES


def test_fbx_stacks_curves_and_frame_rate(baked, tmp_path):
    rig, anim, *_ = baked
    path = write_rig_fbx(rig, tmp_path / "rig.fbx", animation=anim)
    _, root = parse_fbx(path.read_bytes())
    settings = {p.props[0]: p.props[4:] for p in
                root.first("GlobalSettings").first("Properties70").find("P")}
    assert settings["TimeMode"] == [3] and settings["CustomFrameRate"] == [60.0]  # 60 fps
    objects = root.first("Objects")
    stacks = objects.find("AnimationStack")
    assert [s.props[1].split("\x00")[0] for s in stacks] == ["neutral", "smile"]
    curves = objects.find("AnimationCurve")
    per_stack = 3 * rig.joint_count + 3  # translation of every joint + the root's rotation
    assert len(curves) == 2 * per_stack
    times = curves[0].first("KeyTime").props[0]
    np.testing.assert_array_equal(times, np.arange(40) * (KTIME_PER_SECOND // 60))
    # the second take is its own clip from 0 too (it started at frame 40: issue 30)
    later = curves[per_stack].first("KeyTime").props[0]
    np.testing.assert_array_equal(later, np.arange(50) * (KTIME_PER_SECOND // 60))
    assert all(np.isfinite(c.first("KeyValueFloat").props[0]).all() for c in curves)
    assert [t.props[0] for t in root.first("Takes").find("Take")] == ["neutral", "smile"]
    # another rate: custom time mode
    odd = bake_animation(rig, anim.translations[:, 1:] + rig.joint_positions[0], rate=119.0)
    _, odd_root = parse_fbx(rig_fbx_bytes(rig, animation=odd))
    odd_settings = {p.props[0]: p.props[4:] for p in
                    odd_root.first("GlobalSettings").first("Properties70").find("P")}
    assert odd_settings["TimeMode"] == [14] and odd_settings["CustomFrameRate"] == [119.0]


def test_ufbx_and_fbx_sdk_read_the_same_stacks_and_keys(baked, tmp_path):
    rig, anim, *_ = baked
    path = write_rig_fbx(rig, tmp_path / "rig.fbx", animation=anim)
    scene = installed.run_ufbx(path)
    assert scene["frames_per_second"] == 60.0
    stacks = scene["anim_stacks"]
    assert [s["name"] for s in stacks] == ["neutral", "smile"]
    curves = 3 * rig.joint_count + 3
    assert [(s["curves"], s["keys"]) for s in stacks] == [(curves, 40 * curves),
                                                          (curves, 50 * curves)]
    binary = installed.fbx2gltf()
    done = subprocess.run([str(binary), "-b", "--anim-framerate", "bake60", "-i", str(path),
                           "-o", str(tmp_path / "sdk")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "zero channels" not in done.stdout
    import pygltflib

    sdk = pygltflib.GLTF2().load(str(tmp_path / "sdk.glb"))
    assert [a.name for a in sdk.animations] == ["neutral", "smile"]
    # the SDK keys every joint (translation) and the root (rotation) at every frame
    for animation, frames in zip(sdk.animations, (40, 50)):
        assert {sdk.accessors[s.input].count for s in animation.samplers} == {frames}
        animated = {sdk.nodes[c.target.node].name for c in animation.channels}
        assert animated == set(rig.joint_names)


def test_gltf_animations_validate(baked, tmp_path):
    rig, anim, *_ = baked
    path = write_rig_glb(rig, tmp_path / "rig.glb", animation=anim)
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(path))
    assert [a.name for a in gltf.animations] == ["neutral", "smile"]
    for animation, frames in zip(gltf.animations, (40, 50)):
        assert {s.interpolation for s in animation.samplers} == {"LINEAR"}
        times = gltf.accessors[animation.samplers[0].input]  # every clip from time 0
        assert times.min == [0.0] and times.max == [pytest.approx((frames - 1) / 60)]
        paths = [c.target.path for c in animation.channels]
        assert paths.count("translation") == rig.joint_count and paths.count("rotation") == 1
    assert gltf.nodes[1].extras == {"side": "C"}  # the root: no marker, no region
    assert gltf.nodes[2].extras == {"marker": "LBrow", "side": "L", "region": "brow"}
    report = installed.run_validator(path)
    issues = report["issues"]
    assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), \
        issues["messages"]
    assert report["info"]["animationCount"] == 2


def test_rig_json_names_its_tracks(baked, tmp_path):
    rig, anim, *_ = baked
    write_rig_json(rig, tmp_path / "rig.json", animation=anim)
    import json

    doc = json.loads((tmp_path / "rig.json").read_text())
    assert doc["animation"]["file"] == "rig_animation.npz"
    assert doc["animation"]["filled_marker_frames"] == 24
    back = read_rig_animation(tmp_path / "rig_animation.npz")
    assert back.joint_names == rig.joint_names and back.rate == 60.0
    assert [(t.name, t.start, t.end) for t in back.takes] == [("neutral", 0, 40),
                                                            ("smile", 40, 90)]
    np.testing.assert_allclose(back.translations, anim.translations, atol=1e-3)
    assert rig_animation_bytes(anim) == rig_animation_bytes(anim)  # deterministic bytes


def test_bad_shapes_are_refused():
    rig = sample_rig()
    with pytest.raises(ValueError, match="joint_positions must have shape"):
        bake_animation(rig, np.zeros((5, 2, 3)), rate=60.0)
    with pytest.raises(ValueError, match="rate must be > 0"):
        bake_animation(rig, np.zeros((5, rig.joint_count - 1, 3)), rate=0.0)


def test_an_excerpt_keeps_its_first_frame_in_every_clip(baked, tmp_path):
    """A capture cut at frame 700: its clips still play from 0, and rig.json, the .npz and each
    glTF animation's extras name the capture frame each clip starts at (issue 30)."""
    import json

    import pygltflib

    rig, _, relative, rotations, translations = baked
    takes = (Take("neutral", 0, 40), Take("smile", 40, FRAMES))
    anim = bake_animation(rig, relative, rate=60.0, takes=takes, first_frame=700)
    both = concatenate_animations([anim, bake_animation(rig, relative, rate=60.0)])
    assert [both.first_frame(k) for k in range(3)] == [700, 740, 0]
    write_rig_json(rig, tmp_path / "rig.json", animation=both)
    doc = json.loads((tmp_path / "rig.json").read_text())
    assert [t["first_frame"] for t in doc["animation"]["takes"]] == [700, 740, 0]
    assert read_rig_animation(tmp_path / "rig_animation.npz").first_frames == (700, 740, 0)
    gltf = pygltflib.GLTF2().load(str(write_rig_glb(rig, tmp_path / "rig.glb", animation=both)))
    assert [a.extras["first_frame"] for a in gltf.animations] == [700, 740, 0]
    assert [gltf.accessors[a.samplers[0].input].min for a in gltf.animations] == [[0.0]] * 3
