"""mocaptk plan: per layout marker visibility, triangulation error, lost-marker error and risk."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mocaptk.acquisition import cara_rig, save_rig
from mocaptk.cli import main
from mocaptk.clustering.camera_cost import capture_costs, captured_cloud, place_preset, resolve_rig

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_c3d"
PAPER_LAYOUT = ROOT / "tests" / "data" / "paper_layout_sample.json"


def run(args: list[str]) -> int:
    try:
        main(args)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


@pytest.fixture(scope="module")
def sample_copy(tmp_path_factory):
    """The sample's performance (the session's markers, 1,200 frames: quick) with the paper layout
    in ``dense_halfface_layout/`` beside it."""
    folder = tmp_path_factory.mktemp("plan")
    shutil.copy(SAMPLE / "dense_halfface_performance.c3d", folder)
    (folder / "dense_halfface_layout").mkdir()
    shutil.copy(PAPER_LAYOUT, folder / "dense_halfface_layout" / "layout.json")
    return folder


@pytest.fixture(scope="module")
def planned(sample_copy):
    layout = sample_copy / "dense_halfface_layout" / "layout.json"
    assert run(["plan", str(layout), "--rig", "cara", "-q", "--session",
                str(sample_copy / "dense_halfface_performance.c3d")]) == 0
    return sample_copy / "dense_halfface_layout_plan"


def test_plan_on_the_sample_reports_every_layout_marker(planned):
    plan = json.loads((planned / "plan.json").read_text())
    layout = json.loads(PAPER_LAYOUT.read_text())
    assert plan["format"] == "mocaptk.plan" and plan["version"] == 1
    assert [m["label"] for m in plan["markers"]] == layout["layout"]  # measured and mirrored
    seen = np.array([m["visibility_percent"] for m in plan["markers"]])
    error = np.array([m["triangulation_error_mm"] for m in plan["markers"]])
    lost = np.array([m["lost_rmse_mm"] for m in plan["markers"]])
    # the sample was made through this rig: everything is seen, at its 0.3 mm noise floor
    assert seen.min() > 95 and np.all(seen <= 100)
    assert 0.2 < np.median(error) < 0.6 and error.max() < 1.0
    # losing a marker mostly hurts the held-out fit; the cameras' geometry makes some markers noisier
    assert np.mean(lost > plan["intact_rmse_mm"]) > 0.5 and lost.max() > plan["intact_rmse_mm"] + 0.003
    assert error.max() > 1.5 * error.min()
    assert (planned / "plan.png").stat().st_size > 10_000


def test_plan_is_byte_identical_when_repeated(planned, sample_copy, tmp_path):
    layout = sample_copy / "dense_halfface_layout" / "layout.json"
    assert run(["plan", str(layout), "--rig", "cara", "-q", "--out", str(tmp_path), "--session",
                str(sample_copy / "dense_halfface_performance.c3d")]) == 0
    for name in ("plan.json", "plan.png"):
        assert (tmp_path / name).read_bytes() == (planned / name).read_bytes()


def test_preset_placed_on_the_synthetic_face_is_the_synth_rig():
    from mocaptk.acquisition import read_trajectories

    from mocaptk.clustering.layout import read_layout
    from mocaptk.clustering.plan import layout_plane

    traj = read_trajectories(SAMPLE / "dense_halfface_performance.c3d")
    cloud = captured_cloud(traj.positions, traj.labels, layout_plane(read_layout(PAPER_LAYOUT)))[0]  # the half face and its mirror image
    placed, preset = place_preset(cara_rig(), cloud), cara_rig()
    # the sample is in the face model's frame: the rig lands within a few mm of where synth put it
    for a, b in zip(placed, preset):
        assert np.linalg.norm(a.center - b.center) < 15.0
        assert np.allclose(a.rotation, b.rotation)


def test_a_two_camera_rig_leaves_the_far_side_unseen():
    from mocaptk.acquisition import read_trajectories

    from mocaptk.clustering.layout import read_layout
    from mocaptk.clustering.plan import layout_plane

    traj = read_trajectories(SAMPLE / "dense_halfface_performance.c3d")
    full = resolve_rig("cara", captured_cloud(traj.positions, traj.labels,
                                              layout_plane(read_layout(PAPER_LAYOUT)))[0])
    right = full.subset([1, 3])  # the cameras on the subject's right see the left half face badly
    costs = capture_costs(right, traj.positions, labels=traj.labels, frames=60)
    lateral = traj.positions[0, :, 0]
    assert costs.visibility[lateral > 40].mean() < 0.5 < costs.visibility[np.abs(lateral) < 10].mean()


def test_plan_errors_are_one_line(sample_copy, tmp_path, capsys):
    layout = sample_copy / "dense_halfface_layout" / "layout.json"
    bad_rig = tmp_path / "rig.json"
    save_rig(cara_rig().subset([0]), bad_rig)
    cases = [(["--rig", "moon"], "--rig must be cara, room or a rig file"),
             (["--rig", str(bad_rig)], "at least 2 cameras"),
             (["--rig", "cara", "--noise", "-1"], "--noise must be >= 0"),
             (["--rig", "cara", "--session", str(tmp_path / "none.c3d")], "no such file")]
    for args, message in cases:
        code = run(["plan", str(layout), "--out", str(tmp_path / "out"), *args])
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1, err
    lonely = tmp_path / "lonely" / "layout.json"
    lonely.parent.mkdir()
    shutil.copy(PAPER_LAYOUT, lonely)
    assert run(["plan", str(lonely), "--rig", "cara"]) == 2 and "give it with --session" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_plan_of_a_synthetic_full_face_with_head_motion_through_the_room_rig(tmp_path):
    from conftest import shared_path
    from mocaptk.acquisition import dense_layout, dense_session, load_face_model, write_trajectories
    from mocaptk.clustering.layout import write_layout
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session

    model = load_face_model(shared_path("face_mesh", "ict_facekit", "ict_facekit_FaceXModel_subset.tar.xz"))
    session = dense_session(model, dense_layout(model, mode="full", seed=1), seed=1, expressions_per_take=1,
                            rest_seconds=0.5, expression_seconds=1.0, head_motion=True).trajectories
    write_trajectories(session, tmp_path / "full.c3d")
    result = cluster_session(session, options=ClusterOptions(markers=10, method="kmeans", step=2),
                             source={"path": "full.c3d"})  # found beside the layout folder
    (tmp_path / "full_layout").mkdir()
    write_layout(result.layout, tmp_path / "full_layout" / "layout.json")
    assert run(["plan", str(tmp_path / "full_layout" / "layout.json"), "--rig", "room", "-q"]) == 0
    plan = json.loads((tmp_path / "full_layout_plan" / "plan.json").read_text())
    assert len(plan["markers"]) == 10 and all(m["mirrored_from"] is None for m in plan["markers"])
    assert plan["rig"]["cameras"][0] == "room_01" and len(plan["rig"]["cameras"]) == 10
    # ten cameras around the head see every frontal marker, through the head's motion too
    assert min(m["visibility_percent"] for m in plan["markers"]) > 95
    assert all(0.05 < m["triangulation_error_mm"] < 1.0 for m in plan["markers"])
