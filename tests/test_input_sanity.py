"""Input sanity before clustering (issue 14 items 4, 5): a face read in the wrong units gets one
warning naming the ``--units`` that fit; a body capture is refused (a warning with ``--regions``)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import SAMPLES, shared_path

from mocaptk import Trajectories
from mocaptk.acquisition.formats import write_trajectories
from mocaptk.clustering.sanity import body_labels, check_face, face_span


def _face(scale: float = 1.0) -> np.ndarray:
    """A 24-marker half-ellipsoid face ~150 mm tall, ~120 mm wide, times ``scale``."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-1, 1, 24), rng.uniform(-1, 1, 24)
    return np.column_stack([60 * u, 75 * v, 30 * np.sqrt(np.clip(1 - u**2 / 2 - v**2 / 2, 0, 1))]) * scale


@pytest.mark.parametrize("unit, mm", [("m", 1000.0), ("cm", 10.0), ("in", 25.4)])
def test_face_in_other_units_names_the_unit(unit, mm):
    check = check_face([f"M{i}" for i in range(24)], _face(1 / mm), assumed=True)
    assert check.not_a_face is None
    assert check.units_warning.endswith(f"the file is probably in {unit} (give --units {unit})"), check
    assert "read as mm, assumed" in check.units_warning


def test_face_in_mm_passes_and_a_stray_marker_does_not_count():
    face = _face()
    assert 100 <= face_span(face) <= 250
    with_stray = np.vstack([face, [[3000.0, 0, 0]]])  # a calibration wand in the volume
    check = check_face([f"M{i}" for i in range(25)], with_stray)
    assert check.units_warning is None and check.not_a_face is None


def test_body_vocabulary():
    body, face = body_labels(["LASI", "RKNE", "R.Shoulder", "genou1_NewMarker", "Foot_Marker2", "C7", "ASISr",
                              "MOUTH_01_L", "FOREHEAD_BROW_02_C", "CL4", "BL7", "A8", "LFHD"])
    assert body == ["LASI", "RKNE", "R.Shoulder", "genou1_NewMarker", "Foot_Marker2", "C7", "ASISr"]
    assert face == 2


def test_blenderface_without_units_warns_with_the_mm_per_unit(run_cli, tmp_path):
    """blenderFace (Blender units, read as mm): a 0.58 mm face; no standard unit fits, so the
    warning gives the range of mm per unit (the true scale, ~188 mm per unit from its pupil
    distance of 0.336 units, lies in it)."""
    session = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    result = run_cli("cluster", session, "--rate", "25", "--no-stabilize", "--out", tmp_path / "o",
                     "--formats", "none", "--quiet")
    warning = [line for line in result.stderr.splitlines() if line.startswith(f"mocaptk: warning: {session}")]
    assert len(warning) == 1, result.stderr
    assert "the face spans 0.579 mm (read as mm, assumed), but a face is 100-250 mm across" in warning[0]
    assert "--units N (here N = 173 to 432)" in warning[0]
    again = run_cli("cluster", session, "--rate", "25", "--no-stabilize", "--units", "188",
                    "--out", tmp_path / "o2", "--formats", "none", "--quiet")
    assert again.exit_code == 0 and "face spans" not in again.stderr


def test_sample_face_has_no_sanity_warning(run_cli, tmp_path):
    result = run_cli("cluster", SAMPLES / "dense_halfface.c3d", "--out", tmp_path / "o", "--formats", "none",
                     "--quiet")
    assert result.exit_code == 0 and "face spans" not in result.stderr and "not a face" not in result.stderr


def test_metres_trc_read_as_mm_names_units_m(run_cli, tmp_path):
    traj = Trajectories(np.repeat(_face(1e-3)[None], 30, axis=0), [f"M{i:02d}" for i in range(24)], 100.0)
    path = write_trajectories(traj, tmp_path / "face.trc")
    result = run_cli("cluster", path, "--no-stabilize", "--out", tmp_path / "o", "--formats", "none", "--quiet")
    assert f"mocaptk: warning: {path}: the face spans 0.1" in result.stderr
    assert "the file is probably in m (give --units m)" in result.stderr


@pytest.mark.parametrize("parts", [("c3d", "ezc3d-testFiles", "Vicon.c3d"), ("csv_trc", "btkdata", "Knee.trc")])
def test_body_capture_is_refused_with_the_fix(run_cli, tmp_path, parts):
    session = shared_path(*parts)
    result = run_cli("cluster", session, "--out", tmp_path / "o", "--formats", "none")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"mocaptk: error: {session}: not a face capture: ")
    assert "labels name body landmarks" in lines[0] and "--regions FILE" in lines[0]
    if parts[-1] == "Vicon.c3d":
        assert "it spans 0.912 m" in lines[0]
    assert not (tmp_path / "o").exists()


def test_body_capture_with_regions_is_clustered_with_a_warning(run_cli, tmp_path):
    from mocaptk.acquisition.formats import read_trajectories

    session = shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d")
    labels = read_trajectories(session, strip_prefixes=True).labels
    regions = tmp_path / "regions.json"
    regions.write_text(json.dumps({"trunk": list(labels[8:30]), "legs": list(labels[30:])}))
    result = run_cli("cluster", session, "--regions", regions, "--no-stabilize", "--out", tmp_path / "o",
                     "--formats", "none", "--quiet")
    assert result.exit_code == 0, result.stderr
    assert f"mocaptk: warning: {session}: not a face capture" in result.stderr
