"""The session's reading (rate, units, first frame) is remembered in layout.json and reused by
evaluate, solve and rig: a column CSV needs --rate/--units once, at cluster (real blenderFace
files: 25 Hz video, 187.6 mm per file unit)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA
from mocaptk.clustering.layout import Layout, read_layout
from mocaptk.cli.options import recorded_reading
from mocaptk.errors import InputFileError

BLENDERFACE = SHARED_DATA / "facial_mocap" / "blenderface"  # each test skips where it is absent


@pytest.fixture(scope="module")
def csv_layout(tmp_path_factory) -> Path:
    """Subject_01/02.csv copied into a folder and Subject_01's layout (--formats none) beside them."""
    if not (BLENDERFACE / "Subject_01.csv").is_file():
        pytest.skip("blenderFace data not available")
    from mocaptk.cli import main

    folder = tmp_path_factory.mktemp("csv")
    for name in ("Subject_01.csv", "Subject_02.csv"):
        shutil.copy(BLENDERFACE / name, folder / name)
    main(["cluster", str(folder / "Subject_01.csv"), "--rate", "25", "--units", "187.6", "--no-stabilize",
          "--formats", "none", "--out", str(folder / "layout"), "--quiet"])
    return folder


def test_cluster_records_the_reading(csv_layout):
    layout = read_layout(csv_layout / "layout" / "layout.json")
    assert layout.source["reading"] == {"rate": 25.0, "units": "187.6", "first_frame": 1}
    assert layout.source["rate"] == 25.0


@pytest.mark.slow
def test_solve_evaluate_and_rig_read_the_csv_session_without_repeating(csv_layout, run_cli):
    lay = csv_layout / "layout" / "layout.json"
    solved = run_cli("solve", lay, csv_layout / "Subject_02.csv", "--out", csv_layout / "solved",
                     "--formats", "npz", "--surface", "markers", "--quiet")  # the markers' own size
    assert solved.exit_code == 0, solved.stderr
    capture = json.loads((csv_layout / "solved" / "solve.json").read_text())["capture"]
    assert capture["frames"] == 1692 and capture["rate"] == 25.0  # read as the layout's session was
    frames = np.load(csv_layout / "solved" / "mesh_frames.npy")
    first = frames[np.isfinite(frames).all(axis=(1, 2))][0]  # the first solved frame
    height = first[:, 1].max() - first[:, 1].min()
    assert 80 < height < 160  # mm: a face (187.6 mm per file unit), not 0.6 file units
    evaluated = run_cli("evaluate", csv_layout / "Subject_01.csv", "--layout", lay, "--test",
                        csv_layout / "Subject_02.csv", "--seeds", "1", "--quiet")
    assert evaluated.exit_code == 0, evaluated.stderr
    rig = run_cli("rig", lay, "--session", csv_layout / "Subject_01.csv", "--formats", "json",
                  "--out", csv_layout / "rig", "--quiet")
    assert rig.exit_code == 0, rig.stderr
    joints = json.loads((csv_layout / "rig" / "rig.json").read_text())["joints"]
    heights = [j["bind_position"][1] for j in joints]
    assert 80 < max(heights) - min(heights) < 160  # mm, a face's size


@pytest.mark.slow
def test_a_head_relative_capture_is_not_posed_on_facial_stabilization_markers(csv_layout, run_cli):
    """blenderFace is head-relative, so Subject_01's layout took facial markers (lids, cheek,
    brow) as its stabilization set. Posing a capture frame by frame on them turned expressions
    into head motion: Subject_01 solved with its own layout was 6.6 mm off at the markers outside
    the layout (0.13 mm without poses). They move as much as in the session: the head is still
    (Subject_01), or one fixed pose lays another recording's frame onto the session's (Subject_02)."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.clustering.pipeline import load_session

    lay = csv_layout / "layout" / "layout.json"
    in_layout = set(read_layout(lay).labels)
    summaries = {}
    for subject in ("Subject_01", "Subject_02"):
        out = csv_layout / f"posed_{subject}"
        done = run_cli("solve", lay, csv_layout / f"{subject}.csv", "--out", out, "--formats", "npz",
                       "--surface", "markers", "--quiet")
        assert done.exit_code == 0, done.stderr
        summaries[subject] = json.loads((out / "solve.json").read_text())
        assert summaries[subject]["head_motion"]["still"]
    own, _ = load_session(str(csv_layout / "Subject_01.csv"), rate=25.0, units="187.6")
    dense = read_trajectories(csv_layout / "posed_Subject_01" / "dense.c3d")
    other = [label for label in dense.labels if label not in in_layout]
    err = np.linalg.norm(dense.positions[:, dense.index(other)] - own.positions[:, own.index(other)], axis=2)
    assert np.sqrt(np.nanmean(err ** 2)) < 0.5  # mm (measured 0.13; posed per frame: 6.6)
    assert any("already in the session's head frame" in n for n in summaries["Subject_01"]["notes"])
    assert any("one fixed pose" in n for n in summaries["Subject_02"]["notes"])


def test_given_options_win_and_other_kinds_are_read_as_they_are():
    layout = Layout({"path": "s.csv", "reading": {"rate": 25.0, "units": "cm", "first_frame": 1}}, {}, (), ())
    assert recorded_reading(layout, Path("take.csv"), rate=None, units=None) == (25.0, "cm")
    assert recorded_reading(layout, Path("take.CSV"), rate=50.0, units=None) == (50.0, "cm")
    assert recorded_reading(layout, Path("take.c3d"), rate=None, units=None) == (None, None)
    old = Layout({"path": "s.csv"}, {}, (), ())  # a layout written before the reading was recorded
    assert recorded_reading(old, Path("take.csv"), rate=None, units="mm") == (None, "mm")


@pytest.mark.parametrize("reading", [{"rate": -1}, {"rate": "fast"}, {"units": 10}, {"first_frame": 1.5}, []])
def test_read_layout_names_a_damaged_reading(tmp_path, reading):
    layout = json.loads((Path(__file__).parent / "data" / "paper_layout_sample.json").read_text())
    layout["source"]["reading"] = reading
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(layout))
    with pytest.raises(InputFileError, match="source.reading"):
        read_layout(path)
