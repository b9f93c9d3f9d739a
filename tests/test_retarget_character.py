"""``mocaptk retarget`` on the bundled sample: the generic ARKit rig, Live Link Face CSV read back
by its documented columns, weights against the held-out performance's truth, bad input."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
from conftest import SAMPLES
from readers import installed

from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.c3d_write import write_c3d
from mocaptk.acquisition.synth_session import load_ground_truth
from mocaptk.retarget.character import ARKIT_NAMES, arkit_name
from mocaptk.retarget.character_files import load_character
from mocaptk.retarget.livelink_csv import LIVELINK_COLUMNS, timecode
from mocaptk.retarget.weight_solve import solve_weights


def arkit_truth(truth) -> np.ndarray:
    """The truth's ICT weights (F, 53) as ARKit's 52 (split L/R shapes averaged, tongueOut 0)."""
    out = np.zeros((len(truth.weights), 52))
    for j, name in enumerate(truth.blendshape_names):
        target = arkit_name(name) or arkit_name(name[:-2])
        split = arkit_name(name) is None
        out[:, ARKIT_NAMES.index(target)] += truth.weights[:, j] * (0.5 if split else 1.0)
    return out


@pytest.fixture(scope="module")
def workspace(tmp_path_factory, run_cli_module):
    root = tmp_path_factory.mktemp("retarget")
    shutil.copy(SAMPLES / "dense_halfface.c3d", root)
    assert run_cli_module("cluster", root / "dense_halfface.c3d", "--out", root / "layout",
                          "--formats", "none", "--quiet").exit_code == 0
    layout = json.loads((root / "layout" / "layout.json").read_text())
    performance = read_c3d(SAMPLES / "dense_halfface_performance.c3d")
    capture = performance.select([label for label in layout["layout"] if label in set(performance.labels)])
    write_c3d(capture.replace(residuals=None, metadata={"takes": []}), root / "perf_layout.c3d")
    done = run_cli_module("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d",
                          "--character", "arkit", "--out", root / "out", "--quiet")
    assert done.exit_code == 0, done.stderr
    return root, done


@pytest.fixture(scope="module")
def run_cli_module():
    from mocaptk.cli import main
    from conftest import CliResult

    def run(*args):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
        return CliResult(code, "", "")
    return run


def test_generic_rig_has_the_52_arkit_shapes_on_the_bundled_face():
    rig = load_character("arkit")
    assert rig.names == ARKIT_NAMES and rig.deltas.shape == (52, len(rig.vertices), 3)
    motion = np.abs(rig.deltas).max(axis=(1, 2))
    assert motion[ARKIT_NAMES.index("tongueOut")] == 0  # ICT has none: a zero shape
    assert (np.delete(motion, ARKIT_NAMES.index("tongueOut")) > 1.0).all()  # mm, every other moves
    assert motion[ARKIT_NAMES.index("jawOpen")] > 20  # the jaw drops centimetres
    # ICT's browInnerUp_L/_R are summed: the combined shape moves both brows
    brow = np.linalg.norm(rig.deltas[ARKIT_NAMES.index("browInnerUp")], axis=1)
    x = rig.vertices[:, 0]
    assert brow[x > 5].max() > 3 and brow[x < -5].max() > 3


def test_arkit_names_match_across_spellings():
    assert arkit_name("mouthSmile_L") == arkit_name("MouthSmileLeft") == "mouthSmileLeft"
    assert arkit_name("eye_blink_right") == "eyeBlinkRight" and arkit_name("JawOpen") == "jawOpen"
    assert arkit_name("smile") is None


def test_timecode_counts_frames_within_the_second():
    assert timecode(0, 60.0) == "00:00:00:00.000"
    assert timecode(61, 60.0) == "00:00:01:01.000"
    assert timecode(60 * 3661 + 59, 60.0) == "01:01:01:59.000"


def test_solve_is_zero_at_the_neutral_and_recovers_known_weights():
    rng = np.random.default_rng(3)
    basis = rng.normal(size=(6, 20, 3))
    truth = np.clip(rng.normal(0.3, 0.3, size=(50, 6)), 0, 1)
    d = np.einsum("fs,smc->fmc", truth, basis)
    d[5, :4] = np.nan  # lost markers are dropped, never filled
    solved = solve_weights(basis, d, l1=0.0, smooth=0.0)
    assert np.abs(solved.weights - truth).max() < 1e-4 and solved.lost[5] == 4
    assert np.abs(solve_weights(basis, np.zeros((3, 20, 3))).weights).max() == 0


@pytest.mark.slow
def test_blendshapes_csv_reads_back_by_its_documented_columns(workspace):
    root, _ = workspace
    with open(root / "out" / "blendshapes.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0].keys()) == LIVELINK_COLUMNS and len(LIVELINK_COLUMNS) == 2 + 52 + 9
    assert len(rows) == 1200 and rows[61]["Timecode"] == "00:00:01:01.000"
    assert {r["BlendShapeCount"] for r in rows} == {"61"}
    weights = np.load(root / "out" / "weights.npz")
    jaw = np.array([float(r["JawOpen"]) for r in rows])
    assert np.allclose(jaw, weights["weights"][:, list(weights["names"]).index("jawOpen")], atol=1e-6)
    assert max(float(r["HeadYaw"]) for r in rows) == 0.0  # the sample has no head motion


@pytest.mark.slow
def test_weights_recover_the_held_out_performance_truth(workspace):
    root, _ = workspace
    truth = arkit_truth(load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz"))
    solved = np.load(root / "out" / "weights.npz")["weights"]
    assert solved.shape == truth.shape and np.isfinite(solved).all()
    assert solved.min() >= 0 and solved.max() <= 1
    moving = (truth > 0.1).any(axis=0)
    mae = np.abs(solved - truth).mean(axis=0)[moving]
    r = np.array([np.corrcoef(solved[:, k], truth[:, k])[0, 1] for k in np.flatnonzero(moving)])
    assert mae.mean() <= 0.05 and r.mean() >= 0.9  # the targets
    summary = json.loads((root / "out" / "retarget.json").read_text())
    assert summary["format"] == "mocaptk.retarget" and summary["version"] == 1
    assert len(summary["frames"]["residual_mm"]) == 1200
    follows = {s["name"]: s["follows"] for s in summary["shapes"]}
    assert follows["eyeBlinkRight"] == "eyeBlinkLeft"  # a half face: the unseen side mirrors


@pytest.mark.slow
def test_shapes_no_layout_marker_sees_are_named(workspace):
    """The default layout sees every shape; the same layout without its eye markers cannot see
    the lids' shapes (the identity actor's 20-marker layout: blinks r 0), and says so."""
    from mocaptk.retarget.retarget_outputs import RetargetResult, unseen_shapes
    from mocaptk.retarget.rom_calibration import Calibration

    root, _ = workspace
    summary = json.loads((root / "out" / "retarget.json").read_text())
    assert min(s["layout_motion_mm"] for s in summary["shapes"] if s["max_weight"] > 0.1) >= 0.5
    assert not any("move no layout marker" in note for note in summary["notes"])

    with np.load(root / "out" / "calibration.npz") as data:
        labels = json.loads(bytes(data["header"]).decode())["labels"]
        cal = Calibration(*(data[k] for k in ("basis", "neutral", "ties", "rom_extreme", "stretch")))
    names = [s["name"] for s in summary["shapes"]]
    rows = [labels.index(label) for label in summary["layout_markers"] if not label.startswith("EYE")]
    (seen, inverse), (dense, _) = cal.tied_basis(np.array(rows)), cal.tied_basis()
    motion = [np.nan_to_num(np.linalg.norm(b, axis=2)).max(axis=1)[inverse] for b in (seen, dense)]
    result = RetargetResult(*(None,) * 7, *motion)
    named = set(unseen_shapes(names, result))
    assert {"eyeBlinkLeft", "eyeWideLeft"} <= named and not any(n.startswith(("mouth", "jaw")) for n in named)
    assert all(motion[0][names.index(n)] < 0.5 <= motion[1][names.index(n)] for n in named)


@pytest.mark.slow
def test_saved_calibration_for_another_rig_is_refused(workspace, tmp_path, run_cli):
    root, _ = workspace
    cal = np.load(root / "out" / "calibration.npz")
    arrays = {k: cal[k] for k in cal.files}
    header = json.loads(bytes(arrays["header"]).decode())
    header["shapes"] = header["shapes"][:40]
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    np.savez(tmp_path / "other.npz", **arrays)
    done = run_cli("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d",
                   "--character", "arkit", "--calibration", tmp_path / "other.npz",
                   "--out", tmp_path / "o", "--formats", "none")
    assert done.exit_code == 2 and not (tmp_path / "o").exists()
    assert done.stderr.strip() == (f"mocaptk: error: {tmp_path / 'other.npz'}: calibrated for 40 "
                                   "shapes, the character has 52")
    from mocaptk.atomic import write_bytes
    from mocaptk.retarget.export_character import character_glb_bytes
    rig = load_character("arkit")  # a real rig with 40 shapes, given the 52-shape calibration
    write_bytes(tmp_path / "forty.glb", character_glb_bytes(
        rig.replace(names=rig.names[:40], deltas=rig.deltas[:40]), np.zeros((0, 40)), 60.0))
    done = run_cli("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d",
                   "--character", tmp_path / "forty.glb", "--calibration", root / "out" / "calibration.npz",
                   "--out", tmp_path / "o", "--formats", "none")
    assert done.exit_code == 2 and not (tmp_path / "o").exists()
    assert done.stderr.strip() == (f"mocaptk: error: {root / 'out' / 'calibration.npz'}: calibrated for 52 "
                                   "shapes, the character has 40")


def test_capture_lacking_layout_markers_and_character_without_shapes(workspace, tmp_path, run_cli):
    root, _ = workspace
    capture = read_c3d(root / "perf_layout.c3d")
    write_c3d(capture.select(list(capture.labels[3:])), tmp_path / "short.c3d")
    done = run_cli("retarget", root / "layout" / "layout.json", tmp_path / "short.c3d",
                   "--character", "arkit", "--out", tmp_path / "o", "--formats", "none")
    assert done.exit_code == 2 and "lacks 3 of the layout's" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
    import trimesh
    trimesh.creation.icosphere().export(tmp_path / "plain.glb")
    done = run_cli("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d",
                   "--character", tmp_path / "plain.glb", "--out", tmp_path / "o", "--formats", "none")
    assert done.exit_code == 2 and not (tmp_path / "o").exists()
    assert done.stderr.strip().endswith("the character has no blend shapes (morph targets)")
    from mocaptk.atomic import write_bytes
    from mocaptk.retarget.character import Character
    from mocaptk.retarget.export_character import character_glb_bytes
    ball = trimesh.creation.icosphere(subdivisions=3, radius=120.0)
    bump = np.zeros((1, len(ball.vertices), 3), np.float32)
    bump[0, :, 1] = 5.0
    write_bytes(tmp_path / "ball.glb", character_glb_bytes(
        Character(np.asarray(ball.vertices), np.asarray(ball.faces), ("puff",), bump, "ball"), np.zeros((0, 1)), 60.0))
    done = run_cli("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d",
                   "--character", tmp_path / "ball.glb", "--out", tmp_path / "o", "--formats", "none")
    assert done.exit_code == 2 and not (tmp_path / "o").exists()
    assert "the markers do not fit the character's face" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_character_files_are_valid_and_byte_identical(workspace):
    from pxr import Usd, UsdSkel, UsdValidation

    from mocaptk.retarget.export_character import character_glb_bytes
    from mocaptk.retarget.export_character_fbx import character_fbx_bytes

    root, _ = workspace
    out, rig = root / "out", load_character("arkit")
    weights = np.load(out / "weights.npz")["weights"]
    assert (out / "character.glb").read_bytes() == character_glb_bytes(rig, weights, 60.0)
    assert (out / "character.fbx").read_bytes() == character_fbx_bytes(rig, weights, 60.0)
    stage = Usd.Stage.Open(str(out / "character.usd"))
    assert stage.GetTimeCodesPerSecond() == 60.0 and stage.GetEndTimeCode() == 1199
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Skeleton/Animation"))
    assert list(anim.GetBlendShapesAttr().Get()) == list(ARKIT_NAMES)
    np.testing.assert_allclose(np.array(anim.GetBlendShapeWeightsAttr().Get(700)), weights[700], atol=1e-7)
    registry = UsdValidation.ValidationRegistry()  # what usdchecker runs
    errors = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators()).Validate(stage)
    assert not errors, [e.GetMessage() for e in errors]
    report = installed.run_validator(out / "character.glb")
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:5]


@pytest.mark.slow
def test_blender_imports_animated_shape_keys_matching_our_mesh(workspace, tmp_path):
    import subprocess

    from conftest import REPO

    python = installed.blender_python()
    root, _ = workspace
    rig = load_character("arkit")
    weights = np.load(root / "out" / "weights.npz")["weights"]
    frames = np.array([0, 250, 500, 800, 1199])
    expected = rig.vertices + np.tensordot(weights[frames].astype(np.float64),
                                           rig.deltas.astype(np.float64), axes=(1, 0))
    np.savez(tmp_path / "expected.npz", names=np.array(rig.names), rate=np.array(60.0), frames=frames,
             vertices=expected, rest=rig.vertices)
    files = [root / "out" / name for name in ("character.fbx", "character.glb", "character.usd")]
    done = subprocess.run([str(python), str(REPO / "scripts" / "check_character_blender.py"),
                           str(tmp_path / "expected.npz"), *map(str, files)],
                          capture_output=True, text=True, timeout=900)
    reports = json.loads(done.stdout[done.stdout.index("["):])
    for report in reports:
        assert report["names_match"] and report["animated_keys"] == 52, report
        assert report["keys_per_curve"] == [1200] and report["max_error_mm"] < 0.01, report
        assert report["ok"], report
    assert [r["scene_fps"] for r in reports[:2]] == [60.0, 60.0]  # FBX TimeMode, glTF at the rate


def deformed_character(path):
    """The generic rig with a 20 % wider jaw and an 8 mm longer nose, its shapes renamed
    (``cc_<name>``: no ARKit name matches), written as a GLB with morph targets."""
    from mocaptk.atomic import write_bytes
    from mocaptk.retarget.export_character import character_glb_bytes

    rig = load_character("arkit")
    v = rig.vertices.copy()
    low = np.clip((-40.0 - v[:, 1]) / 40.0, 0, 1)  # below the mouth: the jaw widens
    v[:, 0] *= 1 + 0.2 * low
    tip = v[np.argmax(v[:, 2])]
    near = np.exp(-np.sum((v - tip) ** 2, axis=1) / (2 * 15.0 ** 2))
    v[:, 2] += 8.0 * near  # the nose grows forward
    other = rig.replace(vertices=v, names=tuple(f"cc_{n}" for n in rig.names))
    write_bytes(path, character_glb_bytes(other, np.zeros((0, 52)), 60.0))
    return other


@pytest.mark.slow
def test_another_character_with_its_own_names_follows_the_same_performance(workspace, run_cli):
    root, _ = workspace
    other = deformed_character(root / "other.glb")
    done = run_cli("retarget", root / "layout" / "layout.json", root / "perf_layout.c3d", "--character",
                   root / "other.glb", "--out", root / "other", "--formats", "glb")
    assert done.exit_code == 0, done.stderr
    ours = np.load(root / "other" / "weights.npz")
    assert list(ours["names"]) == list(other.names)  # its own names kept
    generic = np.load(root / "out" / "weights.npz")["weights"]
    moving = (generic > 0.1).any(axis=0)
    r = [np.corrcoef(ours["weights"][:, k], generic[:, k])[0, 1] for k in np.flatnonzero(moving)]
    assert np.mean(r) > 0.9 and np.abs(ours["weights"] - generic).mean() < 0.03
    csv_text = (root / "other" / "blendshapes.csv").read_text().splitlines()
    assert all(float(x) == 0 for x in csv_text[700].split(",")[2:54])  # no ARKit name: zero columns
    assert (root / "other" / "retarget_frames.png").is_file()
    from mocaptk.retarget.retarget_renders import pick_frames
    assert len(set(pick_frames(other.names, ours["weights"]).values())) == 4  # its names still found
    generic_picks = pick_frames(ARKIT_NAMES, generic)
    for title, name in (("widest jaw", "jawOpen"), ("strongest smile", "mouthSmileLeft"),
                        ("blink", "eyeBlinkLeft")):  # the generic rig's moments are the other's too
        column = ours["weights"][:, ARKIT_NAMES.index(name)]
        assert column[generic_picks[title]] >= 0.7 * column.max(), title


@pytest.mark.slow
def test_fbx_characters_read_back_ours_and_blenders(workspace, tmp_path):
    import subprocess

    root, _ = workspace
    rig = load_character("arkit")
    ours = load_character(root / "out" / "character.fbx")
    assert ours.names == rig.names and np.abs(ours.vertices - rig.vertices).max() < 1e-9
    assert np.abs(ours.deltas - rig.deltas).max() < 1e-5
    python = installed.blender_python()  # Blender's own FBX writer: object scale 100, -90 deg X
    script = ("import bpy, sys; bpy.ops.wm.read_factory_settings(use_empty=True); "
              "bpy.ops.import_scene.gltf(filepath=sys.argv[-2]); "
              "bpy.ops.export_scene.fbx(filepath=sys.argv[-1], bake_anim=False)")
    subprocess.run([str(python), "-c", script, str(root / "out" / "character.glb"), str(tmp_path / "b.fbx")],
                   capture_output=True, timeout=600, check=True)
    theirs = load_character(tmp_path / "b.fbx")
    assert theirs.names == rig.names
    assert np.abs(theirs.vertices - rig.vertices).max() < 1e-3  # mm
    assert np.abs(theirs.deltas - rig.deltas).max() < 1e-3


def test_eye_markers_are_found_by_their_whole_label_only():
    from mocaptk.retarget.gaze import eye_labels

    assert eye_labels(["EYE_01", "EYE_L", "LEFT_EYE", "PUPIL_L", "R_Pupil", "cornea.r"]) == \
        {"left": "PUPIL_L", "right": "R_Pupil"}  # lid/socket markers (EYE_01, EYE_L) never taken
    assert eye_labels(["LeftIris", "GAZE_R", "pupils_L"]) == {"left": "LeftIris", "right": "GAZE_R"}


def test_gaze_angles_recover_known_yaw_and_pitch_in_the_characters_axes():
    from mocaptk.retarget.gaze import EYE_RADIUS_MM, gaze_angles

    rng = np.random.default_rng(2)
    axes = np.linalg.qr(rng.normal(size=(3, 3)))[0]  # left, up, forward columns in the head frame
    axes[:, 2] *= np.sign(np.linalg.det(axes))
    truth = np.zeros((300, 2))
    truth[100:] = rng.uniform(-0.4, 0.4, size=(200, 2))  # mostly ahead, as the median assumes
    yaw, pitch = truth.T
    d = np.stack([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)], axis=1)
    eye = np.array([30.0, 40.0, 80.0]) + EYE_RADIUS_MM * d @ axes.T
    eye[7] = np.nan  # lost: 0
    got = gaze_angles(eye, axes)
    ok = np.isfinite(eye).all(axis=1)
    assert np.abs(got[ok] - truth[ok]).max() < 1e-9 and np.all(got[7] == 0)
    assert np.all(gaze_angles(np.full((4, 3), np.nan), axes) == 0)


@pytest.mark.slow
def test_gaze_from_pupil_markers_reaches_the_livelink_columns(workspace, tmp_path, run_cli):
    root, _ = workspace
    capture = read_c3d(root / "perf_layout.c3d")
    axes = np.load(root / "out" / "calibration.npz")["axes"]  # the character's axes, head frame
    t = np.arange(capture.n_frames) / capture.rate
    yaw = np.where(t > 5, 0.3 * np.sin(2 * np.pi * 0.5 * t), 0.0)  # 5 s ahead, then looking around
    pitch = np.where(t > 5, 0.2 * np.sin(2 * np.pi * 0.3 * t), 0.0)
    d = np.stack([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)], axis=1)
    eyes = [label for label in capture.labels if label.startswith("EYE_")]
    centre = np.nanmean(capture.positions[0, capture.index(eyes)], axis=0) - 10 * axes[:, 2]
    pupil = centre + 12.0 * d @ axes.T
    pupil[100:110] = np.nan
    positions = np.concatenate([capture.positions, pupil[:, None]], axis=1)
    write_c3d(capture.replace(labels=(*capture.labels, "PUPIL_L"), positions=positions, residuals=None),
              tmp_path / "eyes.c3d")
    done = run_cli("retarget", root / "layout" / "layout.json", tmp_path / "eyes.c3d", "--character", "arkit",
                   "--out", tmp_path / "o", "--formats", "none", "--no-renders")
    assert done.exit_code == 0, done.stderr
    with open(tmp_path / "o" / "blendshapes.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    got = np.array([[float(r[c]) for c in ("LeftEyeYaw", "LeftEyePitch", "RightEyeYaw")] for r in rows])
    ok = np.isfinite(pupil).all(axis=1)
    assert np.abs(got[ok, 0] - yaw[ok]).max() < 0.01 and np.abs(got[ok, 1] - pitch[ok]).max() < 0.01
    assert np.all(got[~ok, :2] == 0) and np.all(got[:, 2] == 0)  # lost: 0; no right eye marker: 0
    assert json.loads((tmp_path / "o" / "retarget.json").read_text())["eye_markers"] == {"left": "PUPIL_L"}
    assert np.all(np.array([float(r["LeftEyeYaw"]) for r in
                            csv.DictReader(open(root / "out" / "blendshapes.csv"))]) == 0)  # none: 0


@pytest.mark.slow
def test_report_shows_the_character_driven_by_the_weights_beside_the_actor(workspace):
    import base64
    import re

    root, _ = workspace
    text = (root / "out" / "report.html").read_text(encoding="utf-8")
    block = re.search(r'<script id="report-data" type="application/json">(.*?)</script>', text, re.S)
    data = json.loads(block.group(1))
    assert data["kind"] == "retarget" and data["format"] == "mocaptk.report"
    clip, character = data["clips"][0], data["character"]
    weights = np.load(root / "out" / "weights.npz")["weights"]
    assert clip["source_frames"] == len(weights) and len(character["weights"]) == clip["frames"]
    assert np.allclose(character["weights"], weights[::clip["step"]], atol=6e-4)  # the replayed frames
    rig = load_character("arkit")
    assert character["names"] == list(rig.names) and len(character["vertices"]) == len(rig.vertices)
    shapes = np.frombuffer(base64.b64decode(character["shapes"]), "<i2").reshape(rig.deltas.shape)
    jaw = ARKIT_NAMES.index("jawOpen")
    assert np.corrcoef(shapes[jaw].ravel(), rig.deltas[jaw].ravel())[0, 1] > 0.999
    assert jaw in character["curves"] and ARKIT_NAMES.index("tongueOut") not in character["curves"]
    actor = np.array(data["markers"]["neutral"], dtype=float)
    assert np.min(np.array(character["vertices"])[:, 0]) > np.nanmax(actor[:, 0])  # beside, not on top


@pytest.mark.slow
def test_few_marker_poses_leave_a_still_head_unposed_and_follow_a_moving_one(workspace, tmp_path, run_cli):
    """A 20-marker layout has no stabilization markers: its least-moving markers move with the
    expression. The still performance must not get false head motion (it cost r 0.98 -> 0.83);
    the same performance with added head motion must still be posed."""
    from scipy.spatial.transform import Rotation

    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.retarget_outputs import fit_retargeter, retarget_capture
    from mocaptk.retarget.solve import train_solver

    root, _ = workspace
    assert run_cli("cluster", root / "dense_halfface.c3d", "--markers", "20", "--out", tmp_path / "l20",
                   "--formats", "none", "--quiet").exit_code == 0
    session = read_c3d(root / "dense_halfface.c3d")
    solver = train_solver(read_layout(tmp_path / "l20" / "layout.json"), session, {})
    assert not solver.rigid_labels  # poses from the least-moving layout markers
    retargeter = fit_retargeter(load_character("arkit"), session)
    capture = read_c3d(SAMPLES / "dense_halfface_performance.c3d")
    truth = arkit_truth(load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz"))
    moving = (truth > 0.1).any(axis=0)

    def mean_r(weights):
        return np.mean([np.corrcoef(weights[:, k], truth[:, k])[0, 1] for k in np.flatnonzero(moving)])

    still = retarget_capture(retargeter, solver, capture, "still")
    assert np.all(still.head == 0) and mean_r(still.weights) > 0.95
    t = np.arange(capture.n_frames) / capture.rate
    yaw = 8 * np.sin(2 * np.pi * 0.2 * t)
    rot = Rotation.from_euler("YXZ", np.stack([yaw, 5 * np.sin(2 * np.pi * 0.13 * t), 0 * t], 1),
                              degrees=True).as_matrix()
    centre = np.nanmean(capture.positions[0], axis=0)
    turned = capture.replace(positions=np.einsum("fij,fmj->fmi", rot, capture.positions - centre) + centre)
    posed = retarget_capture(retargeter, solver, turned, "turned")
    assert np.abs(np.degrees(posed.head[:, 0]) - yaw).max() < 1.5 and mean_r(posed.weights) > 0.8


@pytest.mark.slow
def test_rom_reach_scales_each_performed_shape_so_its_rom_extreme_is_q():
    """``--rom-reach Q`` (off by default): the learned shapes are the default's; every shape the
    ROM performs (extreme >= 0.2) is scaled so its ROM extreme is Q, others keep the default rule.
    On the sample's ROM, which takes its shapes to 0.47-1.00 of their range, that overshoots:
    mouthFunnel (taken to 0.52 of its range) gets 1 / 0.52 times its weight at Q = 1."""
    from mocaptk.retarget.retarget_outputs import fit_retargeter
    from mocaptk.retarget.rom_calibration import MIN_PERFORMED

    session, rig = read_c3d(SAMPLES / "dense_halfface.c3d"), load_character("arkit")
    default, reached = (fit_retargeter(rig, session, reach=q).calibration for q in (None, 1.0))
    np.testing.assert_allclose(reached.rom_extreme, default.rom_extreme)
    performed = default.rom_extreme >= MIN_PERFORMED
    assert performed.sum() >= 20
    np.testing.assert_allclose(reached.stretch[performed], default.rom_extreme[performed])
    np.testing.assert_array_equal(reached.stretch[~performed], default.stretch[~performed])
    unscaled = default.basis / default.stretch[:, None, None]
    np.testing.assert_allclose(reached.basis, unscaled * reached.stretch[:, None, None])
    funnel = rig.names.index("mouthFunnel")
    assert 0.4 < default.rom_extreme[funnel] < 0.65  # the ROM's funnel: about half the rig's


@pytest.mark.slow
def test_shapes_no_layout_marker_sees_are_held_at_0_and_counted(workspace, tmp_path):
    """The sample's default layout without its eye markers: the lid shapes move no layout marker
    by 0.5 mm. They come out exactly 0 (held: solved freely, the L1 term also keeps them at 0 on
    this capture, but nothing guaranteed it), retarget.json marks them unobserved and the
    summary line counts them (neither did before)."""
    import dataclasses

    from mocaptk.cli.retarget import summary_text
    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.retarget_outputs import fit_retargeter, retarget_capture, unseen_shapes, write_retarget_outputs
    from mocaptk.retarget.solve import train_solver

    root, _ = workspace
    layout = read_layout(root / "layout" / "layout.json")
    eyes = {c.representative for c in layout.clusters if c.region == "eye"}
    layout = dataclasses.replace(layout, clusters=tuple(c for c in layout.clusters if c.representative not in eyes))
    session = read_c3d(root / "dense_halfface.c3d")
    solver = train_solver(layout, session, {"path": None, "sha256": None})
    assert not eyes & set(solver.layout_labels)
    capture = read_c3d(SAMPLES / "dense_halfface_performance.c3d")
    retargeter = fit_retargeter(load_character("arkit"), session)
    held = retarget_capture(retargeter, solver, capture, "capture")
    names = retargeter.character.names
    blind = [names.index(n) for n in unseen_shapes(names, held)]
    assert names.index("eyeBlinkLeft") in blind and not any(names[k].startswith(("mouth", "jaw")) for k in blind)
    assert len(blind) >= 4 and (held.weights[:, blind] == 0).all()
    summary = write_retarget_outputs(retargeter, held, capture, {}, {}, tmp_path, options={}, formats=())
    observed = {s["name"]: s["observed"] for s in summary["shapes"]}
    assert {n for n, seen in observed.items() if not seen} == {names[k] for k in blind}
    assert observed["jawOpen"] and observed["tongueOut"]  # a zero shape is no blind channel
    first = summary_text(summary).splitlines()[0]
    assert f", {len(blind)} unobserved by the layout, held at 0)" in first
