"""`mocaptk cluster`/`rig` bake the capture onto the rig: a head-moving capture plays in every
format with its head motion on face_root (world joints = raw markers), Blender imports and plays
FBX and GLB, and `rig` on the written layout reports the same numbers as `cluster`'s own rig.
Also: coincident markers and a coarse production mesh (MediaPipe) build a rig."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from readers import installed
from scipy.spatial.transform import Rotation

from conftest import SAMPLES, shared_path

FRAMES = 600


def _run(*args) -> None:
    from mocaptk.cli import main

    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        assert exc.code in (0, None), f"mocaptk {' '.join(map(str, args))} exited {exc.code}"


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """The sample performance (10 s) with a known rigid head motion (up to 14°, 30 mm), clustered
    with its own motion and a second copy (`--animate`) baked onto the rig."""
    from mocaptk.acquisition.formats import read_trajectories

    folder = tmp_path_factory.mktemp("moving")
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    positions = perf.positions[:FRAMES]
    t = np.arange(FRAMES) / perf.rate
    rotation = Rotation.from_euler("xyz", np.column_stack([
        0.25 * np.sin(0.7 * t), 0.2 * np.sin(0.4 * t), 0.1 * np.sin(0.9 * t)])).as_matrix()
    shift = np.column_stack([30 * np.sin(0.3 * t), 10 * np.sin(0.5 * t), 20 * np.sin(0.2 * t)])
    centre = np.nanmean(positions[0], axis=0)
    raw = np.einsum("fij,fmj->fmi", rotation, positions - centre) + centre + shift[:, None]
    session = folder / "moving.npz"
    np.savez(session, positions=raw, labels=np.array(perf.labels), rate=perf.rate)
    (folder / "again.npz").write_bytes(session.read_bytes())
    out = folder / "out"
    _run("cluster", session, "--out", out, "--animate", folder / "again.npz", "--quiet")
    motion = (rotation, shift, centre)  # the applied head motion, for checking face_root
    return folder, out, raw, list(perf.labels), motion


def _joint_of_marker(out) -> dict[str, int]:
    """rig.json joint index of each layout marker (the locators and structural joints apart)."""
    joints = json.loads((out / "rig.json").read_text())["joints"]
    return {j["marker"]: i for i, j in enumerate(joints)
            if j["marker"] and j["region"] != "stabilization"}


def test_cluster_bakes_the_head_motion_onto_the_head_joint(moving):
    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.export_json import read_rig_animation

    _, out, raw, labels, (head_rotation, head_shift, centre) = moving
    layout = read_layout(out / "layout.json")
    assert layout.parameters["stabilized"]
    report = json.loads((out / "rig_report.json").read_text())
    animation = report["animation"]
    assert [(t["name"], t["start"], t["end"]) for t in animation["takes"]] == [
        ("moving", 0, FRAMES), ("again", FRAMES, 2 * FRAMES)]
    assert animation["rate_hz"] == 60.0
    tracks = read_rig_animation(out / "rig_animation.npz")
    world = tracks.world_positions()
    rotation = np.array(report["frame_rotation"])
    joint_of = _joint_of_marker(out)
    errors = []
    for cluster in layout.clusters:
        joint = joint_of[cluster.representative]
        if cluster.mirrored_from is not None:
            continue  # no raw marker: it moves as its source's mirror image
        captured = raw[:, labels.index(cluster.representative)] @ rotation.T
        for take in (slice(0, FRAMES), slice(FRAMES, 2 * FRAMES)):
            seen = np.isfinite(captured).all(axis=1)
            errors.append(np.linalg.norm(world[take, joint][seen] - captured[seen], axis=1).max())
    print(f"world joints vs raw markers: max {max(errors):.2g} mm")
    assert max(errors) < 0.1
    # the head joint carries the applied head motion (not removed), to within the head-pose
    # estimate's error (stabilization: rotation p99 ~0.4 deg, about 1 mm at the head's lever arm)
    assert np.ptp(world[:, 0], axis=0).max() == 0.0  # face_root stays
    root_raw = world[:, 1] @ rotation  # the head, back to the capture's frame
    for take in (slice(0, FRAMES), slice(FRAMES, 2 * FRAMES)):
        expected = (np.einsum("fij,j->fi", head_rotation, root_raw[take][0] - centre) + centre
                    + head_shift)
        assert np.linalg.norm(root_raw[take] - expected, axis=1).max() < 2.0
    assert np.ptp(root_raw[:, 0]) > 20.0  # a 30 mm sideways sway, not a still root
    # the second capture has the dense markers: its per-region check and worst case are reported
    held = report["held_out"][0]
    assert held["capture"] == "again" and held["regions"]["mouth"]["markers"] > 0
    assert {"marker", "region", "frame", "error_mm"} <= set(held["max"])
    summary = (out / "summary.txt").read_text()  # and in the summary, as `mocaptk rig` prints it
    assert "held-out again: RMSE" in summary and "largest error on again:" in summary
    assert summary.count("  mouth            RMSE") == 2  # the session and the held-out capture
    assert summary.count("  mouth / mean of the other regions: ") == 2
    # renders at rest and at the last capture's widest jaw opening
    assert report["renders"]["jaw_open_frame"] >= FRAMES
    for name in ("rest_front", "rest_profile", "jaw_open_front", "jaw_open_profile"):
        assert (out / "renders" / f"{name}.png").stat().st_size > 10_000


def test_rig_on_the_written_layout_reports_the_same_numbers(moving):
    folder, out, *_ = moving
    again = folder / "rig_again"
    _run("rig", out / "layout.json", "--session", folder / "moving.npz", "--out", again,
         "--formats", "json", "--quiet")
    ours = json.loads((out / "rig_report.json").read_text())["skinning_check"]
    theirs = json.loads((again / "rig_report.json").read_text())["skinning_check"]
    assert ours == theirs


@pytest.fixture(scope="module")
def blender(moving):
    """Blender's check of rig.fbx and rig.glb: ``{name: (exit code, report)}`` (run once each)."""
    python = installed.blender_python()
    script = installed.REPO / "scripts" / "check_fbx_blender.py"
    out = moving[1]
    reports = {}
    for name in ("rig.fbx", "rig.glb"):
        done = subprocess.run([str(python), str(script), str(out / name), str(out / "rig.json")],
                              capture_output=True, text=True, timeout=600)
        reports[name] = (done.returncode, json.loads(done.stdout[done.stdout.index("{"):]))
    return reports


def test_fbx_and_gltf_play_the_same_frames(blender):
    """Clip frame k is the same pose in Blender from the FBX and from the glTF (issue 30: they
    differed by one): joints and jaw agree at every checked frame."""
    fbx, glb = blender["rig.fbx"][1], blender["rig.glb"][1]
    assert fbx["frames_checked"] == glb["frames_checked"]
    assert fbx["action_frame_ranges"] == glb["action_frame_ranges"]
    gap = np.abs(np.array(fbx["joint_world_mm"]) - np.array(glb["joint_world_mm"])).max()
    print(f"FBX vs glTF in Blender: world joints differ by at most {gap:.2g} mm")
    assert gap < 1e-3
    np.testing.assert_allclose(fbx["jaw_rotation_deg"], glb["jaw_rotation_deg"], atol=1e-3)


@pytest.mark.parametrize("name", ["rig.fbx", "rig.glb"])
def test_blender_plays_the_baked_animation(moving, blender, name):
    """Blender imports FBX and GLB: one action per take at 60 fps, each its own clip from frame 0
    (FBX and glTF alike; issue 30: they started at the take's place in the whole animation, and
    differed by one), the deformed mesh at 5 frames equals the rig's own skinning (< 0.01 mm),
    world joints equal the raw capture (< 0.1 mm), bpy.utils.flip_name maps every bone to a bone."""
    from mocaptk.clustering.layout import read_layout

    _, out, raw, labels, _ = moving
    returncode, report = blender[name]
    report = dict(report)
    world = np.array(report.pop("joint_world_mm"))
    print("Blender:", json.dumps(report, sort_keys=True))
    assert returncode == 0 and report["ok"], report
    assert report["scene_fps"] == 60.0 and report["max_animated_mesh_error_mm"] < 0.01
    takes = json.loads((out / "rig_report.json").read_text())["animation"]["takes"]
    assert report["action_frame_ranges"] == {t["name"]: [0.0, t["end"] - t["start"] - 1.0]
                                             for t in takes}
    assert report["flip_name_unmatched"] == []  # Blender's mirror tools pair every bone
    if name == "rig.fbx":  # Blender: a bone as long as the mean distance to its children, a
        # marker bone (no children) as long as its parent (docs/rig-format.md)
        rig = json.loads((out / "rig.json").read_text())
        bind = {j["name"]: np.array(j["bind_position"]) for j in rig["joints"]}
        for bone in ("head", "jaw"):
            children = [j["name"] for j in rig["joints"] if j["parent"] == bone]
            mean = np.mean([np.linalg.norm(bind[c] - bind[bone]) for c in children])
            assert report["bone_length_mm"][bone] == pytest.approx(mean, abs=1e-3)
        assert report["max_leaf_bone_length_mm"] <= max(report["bone_length_mm"].values()) + 1e-3
    # the jaw bone rotates: at the widest opening as keyed (issue 30)
    assert max(report["jaw_rotation_deg"]) > 10.0
    np.testing.assert_allclose(report["jaw_rotation_deg"], report["jaw_track_deg"], atol=0.01)
    layout = read_layout(out / "layout.json")
    rotation = np.array(json.loads((out / "rig_report.json").read_text())["frame_rotation"])
    errors = []
    for row, frame in enumerate(report["frames_checked"]):
        for cluster in layout.clusters:
            joint = _joint_of_marker(out)[cluster.representative]
            if cluster.mirrored_from is None:
                captured = raw[frame % FRAMES, labels.index(cluster.representative)] @ rotation.T
                if np.isfinite(captured).all():
                    errors.append(np.linalg.norm(world[row, joint] - captured))
    print(f"{name}: Blender's world joints vs the raw capture: max {max(errors):.2g} mm")
    assert max(errors) < 0.1


def test_coincident_markers_build_a_rig(tmp_path):
    """Two markers at the same place (pyomeca's STER/STERr) no longer crash the surface step."""
    from mocaptk.acquisition.formats import read_trajectories

    trc = shared_path("csv_trc", "pyomeca", "markers.trc")
    regions = tmp_path / "regions.json"  # a body capture: clustered only with explicit regions
    regions.write_text(json.dumps({"body": list(read_trajectories(trc, strip_prefixes=True).labels)}))
    _run("cluster", trc, "--regions", regions, "--out", tmp_path / "o", "--formats", "json", "--quiet")
    report = json.loads((tmp_path / "o" / "rig_report.json").read_text())
    assert np.isfinite(report["skinning_check"]["rmse_mm"])


def test_mutated_c3d_with_coincident_markers_builds_a_rig(tmp_path):
    """The fuzz campaign's case: pc_real.c3d with its data-start byte changed 13 -> 2 reads
    frames of parameter bytes, markers coincide; the rig step used to raise a traceback."""
    data = bytearray(shared_path("c3d", "btkdata", "c3d.org", "sample02", "pc_real.c3d")
                     .read_bytes())
    assert data[16] == 13
    data[16] = 2
    mutated = tmp_path / "mutated.c3d"
    mutated.write_bytes(bytes(data))
    # it spans 1.4 m: refused as no face in one line, and clustered with explicit regions
    done = subprocess.run(["mocaptk", "cluster", str(mutated), "--out", str(tmp_path / "n")],
                          capture_output=True, text=True)
    assert done.returncode == 2 and "not a face capture" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "n").exists()
    from mocaptk.acquisition.formats import read_trajectories
    regions = tmp_path / "regions.json"
    regions.write_text(json.dumps({"body": list(read_trajectories(mutated).labels)}))
    _run("cluster", mutated, "--regions", regions, "--out", tmp_path / "o", "--formats", "json",
         "--quiet")
    assert (tmp_path / "o" / "rig.json").stat().st_size > 0


def test_coincident_joint_vertices_share_their_weight():
    from mocaptk.retarget.influence import edge_graph
    from mocaptk.retarget.weights import thin_shell_weights
    from readers.sample_rig import sample_rig

    rig = sample_rig()
    graph = edge_graph(rig.vertices, rig.faces)
    single = thin_shell_weights(rig.vertices, rig.faces, np.array([5, 40, 90]), graph=graph)
    shared = thin_shell_weights(rig.vertices, rig.faces, np.array([5, 40, 40, 90]), graph=graph)
    np.testing.assert_allclose(shared[:, [0, 3]], single[:, [0, 2]])
    np.testing.assert_allclose(shared[:, 1], single[:, 1] / 2)
    np.testing.assert_allclose(shared[:, 1], shared[:, 2])


def test_mediapipe_canonical_face_as_the_rig_mesh(moving):
    """A coarse production mesh (468 vertices): layout markers get distinct vertices."""
    from mocaptk.clustering.layout import read_layout
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.retarget.build import build_rig
    from mocaptk.retarget.mesh_io import load_mesh

    mesh = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    folder, out, *_ = moving
    layout = read_layout(out / "layout.json")
    session, _ = load_session(str(folder / "moving.npz"))
    session, _ = stabilize(session, rigid=layout.extra["stabilization"]["rigid_labels"])
    build = build_rig(layout, session, mesh=mesh)
    assert len(set(build.joint_vertices.tolist())) == len(layout.clusters)
    assert build.check.rmse_mm < 1.5


def test_rig_files_have_the_head_jaw_hierarchy_and_the_stabilization_locators(moving):
    """rig.json, rig.fbx and rig.glb: face_root -> head -> jaw -> chin and lower-lip joints, the
    upper face and one unweighted locator per layout stabilization marker under head (issues 27
    and 30); the jaw's pivot fitted behind the chin from the session's opening."""
    import pygltflib

    from mocaptk.clustering.layout import read_layout
    from mocaptk.retarget.export_json import read_rig_json

    _, out, *_ = moving
    rig = read_rig_json(out / "rig.json")
    names, parents = rig.joint_names, rig.joint_parents
    parent = {n: (names[p] if p >= 0 else None) for n, p in zip(names, parents)}
    assert names[:3] == ("face_root", "head", "jaw")
    assert parent["head"] == "face_root" and parent["jaw"] == "head"
    by_region = {}
    for name, region in zip(names[3:], rig.joint_regions[3:]):
        by_region.setdefault(region, set()).add(parent[name])
    assert by_region["chin"] == {"jaw"} and by_region["forehead_brow"] == {"head"}
    assert by_region["eye"] == {"head"} and by_region["nose"] == {"head"}
    assert by_region["mouth"] == {"head", "jaw"}  # upper lip on the head, lower lip on the jaw
    layout = read_layout(out / "layout.json")
    rigid = layout.extra["stabilization"]["rigid_labels"]
    locators = [n for n, r in zip(names, rig.joint_regions) if r == "stabilization"]
    assert locators == [f"stabilization_H{k + 1}" for k in range(len(rigid))] and len(rigid) >= 3
    assert [rig.joint_markers[names.index(n)] for n in locators] == rigid
    assert {parent[n] for n in locators} == {"head"}
    weighted = set(np.unique(rig.weight_index[rig.weight_value > 0]))
    assert not weighted & {names.index(n) for n in ("face_root", "head", "jaw", *locators)}
    report = json.loads((out / "rig_report.json").read_text())["hierarchy"]
    pivot, chin = np.array(report["jaw"]["pivot_mm"]), rig.joint_positions[names.index("jaw")]
    np.testing.assert_allclose(pivot, chin)
    lowest = rig.joint_positions[[names.index(n) for n in report["jaw"]["children"]]]
    assert report["jaw"]["method"] == "fitted"
    assert pivot[2] < lowest[:, 2].max() - 30.0 and pivot[1] > lowest[:, 1].min()
    gltf = pygltflib.GLTF2().load(str(out / "rig.glb"))
    nodes = {n.name: n for n in gltf.nodes}
    assert [gltf.nodes[c].name for c in nodes["face_root"].children] == ["head"]
    assert "jaw" in [gltf.nodes[c].name for c in nodes["head"].children]
    assert {gltf.nodes[c].name for c in nodes["jaw"].children} == set(report["jaw"]["children"])
    assert nodes["stabilization_H1"].extras["marker"] == rigid[0]
    report = installed.run_validator(out / "rig.glb")["issues"]  # the hierarchy and its clips
    assert (report["numErrors"], report["numWarnings"], report["numInfos"]) == (0, 0, 0), \
        report["messages"][:5]
