"""Camera-aware layouts: --rig on cluster/compare, and the end-to-end score through a rig."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mocaptk.acquisition import cara_rig, load_ground_truth, read_trajectories, save_rig
from mocaptk.cli import main
from mocaptk.clustering.camera_cost import surface_normals
from mocaptk.clustering.compare import rig_aware
from mocaptk.clustering.end_to_end import capture_layout, end_to_end_errors, rmse
from mocaptk.clustering.methods import LayoutProblem, select_layout
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
from mocaptk.trajectories import Trajectories

SAMPLE = Path(__file__).resolve().parents[1] / "sample_c3d"


@pytest.fixture(scope="module")
def small_case(tmp_path_factory):
    """Every 4th frame of the sample session, 600 frames of its held-out performance (truth), and
    a badly placed rig: only the two Cara cameras on the subject's right (a rig file)."""
    session = read_trajectories(SAMPLE / "dense_halfface.c3d")
    session = Trajectories(session.positions[::4], session.labels, session.rate / 4)
    truth = load_ground_truth(SAMPLE / "dense_halfface_performance_truth.npz").positions[:600]
    rig_file = tmp_path_factory.mktemp("rig") / "cara_right.json"
    save_rig(cara_rig().subset([1, 3]), rig_file)
    return session, truth, rig_file


def test_camera_aware_layout_differs_and_wins_end_to_end(small_case):
    session, truth, rig_file = small_case
    neutral = neutral_pose(session.positions)
    blind = LayoutProblem(session.positions - neutral[None], neutral, labels=session.labels)
    aware = rig_aware(session, str(rig_file))(blind)
    assert aware.candidates.size < blind.n_points  # the markers the two cameras miss are out
    layouts = {name: select_layout(problem, 12, method="hybrid").layout
               for name, problem in (("blind", blind), ("aware", aware))}
    assert not np.array_equal(layouts["blind"], layouts["aware"])
    normals = surface_normals(truth, neutral_pose(truth))
    rig = cara_rig().subset([1, 3])
    scores = {name: rmse(end_to_end_errors(session.positions, layout,
                                           capture_layout(rig, truth, normals, layout, seed=0), truth))
              for name, layout in layouts.items()}
    exact = {name: rmse(end_to_end_errors(session.positions, layout, truth[:, layout], truth))
             for name, layout in layouts.items()}
    # the blind layout keeps markers this rig loses; measured exactly, both are about as good
    assert scores["aware"] < 0.9 * scores["blind"], scores
    assert abs(exact["aware"] - exact["blind"]) < 0.15 * exact["blind"], exact


def test_cluster_with_a_rig_records_it_and_moves_off_unseen_markers(small_case):
    session, _, rig_file = small_case
    options = ClusterOptions(markers=12, step=2, rig=str(rig_file))
    result = cluster_session(session, options=options)
    assert result.layout.parameters["rig"] == str(rig_file)
    blind = cluster_session(session, options=ClusterOptions(markers=12, step=2))
    assert "rig" not in blind.layout.parameters
    aware_labels = {c.representative for c in result.layout.clusters if c.mirrored_from is None}
    blind_labels = {c.representative for c in blind.layout.clusters if c.mirrored_from is None}
    assert aware_labels != blind_labels and len(aware_labels) == 12


@pytest.mark.parametrize("command", ["cluster", "compare"])
def test_a_bad_rig_is_one_line(command, tmp_path, capsys):
    session = SAMPLE / "dense_halfface_performance.c3d"
    cases = [(["--rig", "moon"], "--rig must be cara, room or a rig file")]
    if command == "cluster":
        cases.append((["--rig", "cara", "--method", "paper"], "--rig needs a layout method"))
    for args, message in cases:
        with pytest.raises(SystemExit) as exit_info:
            main([command, str(session), "--out", str(tmp_path / "out"), *args])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and message in err and err.count("\n") == 1, err
