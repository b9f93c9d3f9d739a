"""Up, forward and the actor's left from a face's geometry (acquisition/orientation.py), on the
bundled sample (upright, its labels right), the sample turned by random rotations (upside down
among them) and with its L/R names swapped, and on the real blenderFace files (Y up, their L
the viewer's left)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.orientation import UNDECIDED_SCORE, infer_orientation, labels_warning, marker_motion
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.trajectories import Trajectories

from conftest import SHARED_DATA

SAMPLE = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"
BLENDERFACE = SHARED_DATA / "facial_mocap" / "blenderface"  # each test skips where it is absent


@pytest.fixture(scope="module")
def sample():
    traj = read_c3d(SAMPLE)
    neutral = neutral_pose(traj.positions)
    return traj, neutral, marker_motion(traj.positions, neutral)


def _rotations(seed: int = 7, count: int = 6) -> list[np.ndarray]:
    """Random rotations plus two upside-down ones (180° about the file's X and Z axes)."""
    rng = np.random.default_rng(seed)
    out = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for _ in range(count):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        out.append(q if np.linalg.det(q) > 0 else -q)
    return out


def test_sample_is_upright_and_its_labels_agree(sample):
    traj, neutral, motion = sample
    found = infer_orientation(traj.labels, neutral, motion)
    left, up, forward = found.frame
    assert found.labels == "agree" and labels_warning(found) is None
    assert up[1] > 0.95  # the sample is written Y up, looking down +Z, X = the subject's left
    assert forward[2] > 0.75 and left[0] > 0.75
    assert np.allclose(found.frame @ found.frame.T, np.eye(3), atol=1e-12) and np.linalg.det(found.frame) > 0
    chin = [traj.labels.index(label) for label in traj.labels if label.startswith("CHIN")]
    brow = [traj.labels.index(label) for label in traj.labels if label.startswith("FOREHEAD")]
    assert (neutral[chin] @ up).max() < (neutral[brow] @ up).min()


@pytest.mark.parametrize("turn", range(8))
def test_the_frame_turns_with_the_face(sample, turn):
    """Any rotation of the file (upside down included): the same face axes, turned alike."""
    traj, neutral, motion = sample
    rotation = _rotations()[turn]
    upright = infer_orientation(traj.labels, neutral, motion).frame
    turned = infer_orientation(traj.labels, neutral @ rotation.T, motion)
    assert turned.labels == "agree"
    assert np.allclose(turned.frame, upright @ rotation.T, atol=1e-9)


def test_swapped_labels_are_overruled_with_a_warning(sample):
    traj, neutral, motion = sample
    swapped = [re.sub(r"_([LR])$", lambda m: "_" + {"L": "R", "R": "L"}[m.group(1)], label)
               for label in traj.labels]
    upright = infer_orientation(traj.labels, neutral, motion)
    found = infer_orientation(swapped, neutral @ _rotations()[0].T, motion)
    assert found.labels == "contradict"
    assert np.allclose(found.frame, upright.frame @ _rotations()[0].T, atol=1e-9)
    assert "contradict" in labels_warning(found)


def test_labels_decide_only_what_the_geometry_cannot():
    """A cap symmetric top to bottom that does not move: the labels' sides choose up."""
    u, v = np.meshgrid(np.linspace(-1, 1, 7), np.linspace(-1, 1, 9))
    cloud = np.column_stack([60 * u.ravel(), 80 * v.ravel(), -20 * (u.ravel() ** 2 + v.ravel() ** 2)])
    labels = [f"M{i}_{'L' if x > 0 else 'R' if x < 0 else 'C'}" for i, x in enumerate(cloud[:, 0])]
    found = infer_orientation(labels, cloud, np.zeros(len(cloud)))
    assert found.labels in ("agree", "decided")
    assert found.frame[0][0] > 0.99 and found.frame[2][2] > 0.99  # left = +X (the labels), forward +Z


def _blenderface(name: str) -> Trajectories:
    from mocaptk.acquisition.formats import read_trajectories
    path = BLENDERFACE / name
    if not path.is_file():
        pytest.skip("blenderFace data not available")
    return read_trajectories(path, strip_prefixes=True, rate=25, units="187.6")


@pytest.mark.parametrize("name", ["Subject_01.csv", "Subject_02.csv"])
@pytest.mark.parametrize("stabilized", [False, True])
def test_blenderface_up_from_geometry_and_its_labels_named_from_the_viewer(name, stabilized):
    """As read (cluster --no-stabilize) and with head motion removed on the rigid set cluster
    detects (Subject_02's holds mouth markers: its motion vote turns negative, the taper holds)."""
    from mocaptk.clustering.pipeline import stabilize

    traj = _blenderface(name)
    if stabilized:
        traj = stabilize(traj)[0]
    neutral = neutral_pose(traj.positions)
    found = infer_orientation(traj.labels, neutral, marker_motion(traj.positions, neutral))
    left, up, forward = found.frame
    # the file is Y up (chin A8 lowest, brow row 2 highest), the face looks down +Z, and CL7 (the
    # labels' "L") lies at -X: the viewer's left
    assert up[1] > 0.95 and forward[2] > 0.95 and left[0] > 0.95
    assert found.labels == "contradict"
    height = neutral @ up
    assert height[traj.labels.index("A8")] < height[traj.labels.index("A7")] < height[traj.labels.index("DL2")]
    assert sum(found.up_votes.values()) > UNDECIDED_SCORE and found.up_votes["shape"] > 0.4  # not "decided"


def test_blenderface_layout_and_rig_frame_upright():
    """cluster's layout of Subject_01: the plane's normal and the rig frame put the actor's left
    at +X and the chin below the brows; the layout records the orientation and the warning."""
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import dense_cloud, guide_reference

    traj = _blenderface("Subject_01.csv")
    result = cluster_session(traj, options=ClusterOptions(stabilize=False, method="paper"))
    layout = result.layout
    assert layout.extra["orientation"]["labels"] == "contradict"
    assert any("contradict" in note for note in result.notes)
    assert layout.extra["sagittal_plane"]["normal"][0] > 0.95
    cloud = dense_cloud(layout, traj)
    y = dict(zip(cloud.labels, cloud.neutral[:, 1]))
    x = dict(zip(cloud.labels, cloud.neutral[:, 0]))
    assert y["A8"] < y["A7"] < min(y["DL2"], y["DR2"])
    assert x["CR7"] > x["CL7"]  # the labels' R is the actor's left: +X in the rig
    # no nose marker: the guide measures from the most forward marker (upper lip), not a "nose tip"
    assert guide_reference(cloud.neutral)[1] == "front marker"
    assert result.frame[1][1] > 0.95  # pictures: up is up
    sides = {c.representative: c.side for c in layout.clusters}
    assert all(sides[label] == "R" for label in sides if re.fullmatch(r"[A-D]L\d", label))


@pytest.mark.parametrize("orientation", [
    {"frame": [[1, 0, 0], [0, 1, 0]], "labels": "agree"},
    {"frame": [[1, 0, 0], [0, 1, 0], [0, 0, "z"]], "labels": "agree"},
    {"frame": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "labels": "maybe"},
    "up"])
def test_read_layout_names_a_damaged_orientation(tmp_path, orientation):
    import json

    from mocaptk.clustering.layout import read_layout
    from mocaptk.errors import InputFileError

    layout = json.loads((Path(__file__).parent / "data" / "paper_layout_sample.json").read_text())
    path = tmp_path / "layout.json"
    path.write_text(json.dumps({**layout, "orientation": orientation}))
    with pytest.raises(InputFileError, match="orientation"):
        read_layout(path)
    path.write_text(json.dumps({**layout, "orientation": {"frame": np.eye(3).tolist(), "labels": "agree"}}))
    assert read_layout(path).extra["orientation"]["labels"] == "agree"
