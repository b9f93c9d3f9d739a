"""`mocaptk info` and `mocaptk convert` on real files: output, JSON determinism, errors (exit 2, one line)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import shared_path

from mocaptk.acquisition.formats import read_trajectories


def _one_line_error(result, *needles):
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mocaptk: error: ")
    assert "Traceback" not in result.stderr + result.stdout
    for needle in needles:
        assert needle in lines[0]


def test_info_human_output(run_cli):
    path = shared_path("csv_trc", "pyomeca", "markers.csv")
    result = run_cli("info", path)
    assert result.exit_code == 0, result.stderr
    out = result.stdout
    for expected in ("format       vicon_csv", "markers      51", "frames       580 (first frame 1)",
                     "rate         100 Hz", "duration     5.800 s", "units        mm",
                     "longest gap  71 frames (0.710 s), marker Daphnee:SCAP_CP", "takes        none"):
        assert expected in out


def test_info_json_is_deterministic_and_complete(run_cli):
    csv_path = shared_path("csv_trc", "pyomeca", "markers.csv")
    face = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    first = run_cli("info", "--json", csv_path)
    second = run_cli("info", "--json", csv_path)
    assert first.exit_code == 0 and first.stdout == second.stdout
    doc = json.loads(first.stdout)
    assert doc["format"] == "mocaptk-info" and doc["version"] == 1
    nexus, = doc["files"]
    blender, = json.loads(run_cli("info", "--json", "--rate", "50", face).stdout)["files"]
    traj = read_trajectories(csv_path)
    stats = traj.gap_stats()
    assert nexus["missing_percent"] == pytest.approx(100 * stats.total_missing_fraction, abs=1e-6)
    assert nexus["longest_gap_frames"] == int(stats.longest_gap.max()) == 71
    assert (nexus["markers"], nexus["frames"], nexus["rate_hz"]) == (51, 580, 100.0)
    assert blender["units"] == "mm (assumed)" and blender["markers"] == 16
    assert [t["name"] for t in blender["takes"]] == ["posed_neutral", "posed_disgust", "posed_happy",
                                                      "posed_fear"]


def test_info_reports_each_bad_file_and_exits_2(run_cli, tmp_path):
    good = shared_path("csv_trc", "btkdata", "Anto.trc")
    empty = shared_path("csv_trc", "btkdata", "Empty.trc")
    truncated = shared_path("csv_trc", "btkdata", "Truncated.trc")
    result = run_cli("info", good, empty, truncated)
    assert result.exit_code == 2
    assert "markers      34" in result.stdout
    errors = result.stderr.strip().splitlines()
    assert errors == [f"mocaptk: error: {empty}: file is empty",
                      f"mocaptk: error: {truncated}: truncated TRC header (2 of 5 header lines)"]
    as_json = run_cli("info", "--json", good, empty)
    assert as_json.exit_code == 2
    assert json.loads(as_json.stdout)["files"][1] == {"path": str(empty), "error": f"{empty}: file is empty"}


@pytest.mark.parametrize("case", ["missing", "folder", "empty", "truncated", "devices_only", "not_mocap",
                                  "latin1", "duplicates", "units", "zero_markers"])
def test_convert_bad_input_one_line_and_no_output(case, run_cli, tmp_path):
    bad = {
        "missing": tmp_path / "nope.c3d",
        "folder": tmp_path,
        "empty": shared_path("csv_trc", "btkdata", "Empty.trc"),
        "truncated": shared_path("csv_trc", "btkdata", "Truncated.trc"),
        "devices_only": shared_path("csv_trc", "pyomeca", "analogs.csv"),
        "not_mocap": shared_path("csv_trc", "pyomeca", "LICENSE.md"),
    }.get(case)
    contents = {
        "latin1": "Trajectories\n100\n,,Épaule,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1,2,3\n".encode("latin-1"),
        "duplicates": b"frame,time,A_x,A_y,A_z,A_x,A_y,A_z\n1,0,1,2,3,4,5,6\n2,0.01,1,2,3,4,5,6\n",
        "units": b"Trajectories\n100\n,,A,,\nFrame,Sub Frame,X,Y,Z\n,,ft,ft,ft\n1,0,1,2,3\n",
        "zero_markers": b"frame,time,comment\n1,0,a\n2,0.01,b\n",
    }
    if case in contents:
        bad = tmp_path / f"{case}.csv"
        bad.write_bytes(contents[case])
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    result = run_cli("convert", bad, out_dir / "x.trc")
    _one_line_error(result, str(bad))
    assert list(out_dir.iterdir()) == []


def test_convert_round_trip_and_overwrite_protection(run_cli, tmp_path):
    source = shared_path("csv_trc", "pyomeca", "markers.csv")
    trc = tmp_path / "m.trc"
    back = tmp_path / "m.csv"
    assert run_cli("convert", source, trc).exit_code == 0
    result = run_cli("convert", trc, back)
    assert result.exit_code == 0 and "51 markers, 580 frames, 100 Hz" in result.stdout
    a, b = read_trajectories(source), read_trajectories(back)
    assert a.labels == b.labels
    np.testing.assert_array_equal(a.positions, b.positions)  # 6 decimals hold the file's 6 digits
    before = trc.read_bytes()
    refused = run_cli("convert", back, trc)
    _one_line_error(refused, "already exists", "--force")
    assert trc.read_bytes() == before
    assert run_cli("convert", back, trc, "--force").exit_code == 0
    _one_line_error(run_cli("convert", source, tmp_path / "m.xlsx"), "unknown output extension")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv", "m.trc"]


def test_convert_to_c3d_equals_source(run_cli, tmp_path):
    source = shared_path("csv_trc", "btkdata", "Knee.trc")
    target = tmp_path / "knee.c3d"
    assert run_cli("convert", source, target).exit_code == 0
    a, b = read_trajectories(source), read_trajectories(target)
    assert a.labels == b.labels and a.rate == b.rate and b.metadata["format"] == "c3d"
    np.testing.assert_array_equal(np.isnan(a.positions), np.isnan(b.positions))
    np.testing.assert_allclose(a.positions, b.positions, rtol=1e-6, atol=1e-4)  # float32 storage


def test_units_and_rate_are_refused_for_files_that_declare_their_own(run_cli, tmp_path):
    """Every command reads marker files the same way: an explicit --units on a C3D (which declares
    POINT:UNITS) or --rate on a file that stores its rate is a one-line error, never ignored."""
    from mocaptk import Trajectories
    from mocaptk.acquisition.formats import write_trajectories

    traj = Trajectories(np.arange(60.0).reshape(5, 4, 3), ["A", "B", "C", "D"], 100.0)
    c3d = write_trajectories(traj, tmp_path / "s.c3d")
    trc = write_trajectories(traj, tmp_path / "s.trc")
    out = tmp_path / "out"
    out.mkdir()
    for argv in (["info", c3d, "--units", "cm"], ["info", "--json", c3d, "--units", "cm"],
                 ["convert", c3d, out / "x.trc", "--units", "cm"],
                 ["cluster", c3d, "--units", "cm", "--out", out / "L", "--no-stabilize"]):
        result = run_cli(*argv)
        if "--json" in argv:
            assert result.exit_code == 2 and "declares its units" in json.loads(result.stdout)["files"][0]["error"]
            continue
        _one_line_error(result, "--units applies to text files only", str(c3d), "declares its units (POINT:UNITS)")
    for argv in (["info", trc, "--rate", "50"], ["convert", c3d, out / "x.trc", "--rate", "50"]):
        _one_line_error(run_cli(*argv), "--rate applies to column CSV files only")
    assert list(out.iterdir()) == []
    # where the option applies it is used: a TRC's numbers read as cm are 10x the mm
    scaled = run_cli("convert", trc, out / "cm.c3d", "--units", "cm")
    assert scaled.exit_code == 0, scaled.stderr
    np.testing.assert_allclose(read_trajectories(out / "cm.c3d").positions, 10 * traj.positions, rtol=1e-6)
