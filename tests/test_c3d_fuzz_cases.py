"""The fuzz campaign's C3D reproducers (tests/data/fuzz/, made by make_c3d_cases.py from files our
own writer wrote): each reads cleanly or fails in one documented line, never a traceback or a
RuntimeWarning; and the rigid-set detection failure names the file and the way out."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.errors import InputFileError

FUZZ = Path(__file__).parent / "data" / "fuzz"


@pytest.mark.parametrize("name, problem", [
    ("c3d_units_numeric.c3d", "POINT:UNITS is a number (28013), not text such as 'mm'"),
    ("c3d_units_two_numbers.c3d", "POINT:UNITS is a number (109, 109), not text such as 'mm'"),
])
def test_numeric_units_are_refused_in_one_line(name, problem):
    with pytest.raises(InputFileError) as caught:
        read_c3d(FUZZ / name)
    assert caught.value.problem.startswith(problem) and caught.value.path == str(FUZZ / name)


def test_float_point_count_falls_back_to_the_header():
    traj = read_c3d(FUZZ / "c3d_used_float_minus_one.c3d")
    assert traj.n_markers == 2 and traj.labels == ("A", "B")
    assert "POINT:USED -1 is not a point count; used the header's 2" in traj.metadata["notes"]
    np.testing.assert_allclose(traj.positions.ravel(), np.arange(18) * 10.0)


def test_signalling_nan_header_scale_in_a_dec_file_warns_nothing():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        traj = read_c3d(FUZZ / "c3d_dec_header_scale_snan.c3d")
    assert traj.metadata["processor"] == "dec" and traj.rate == 100.0
    np.testing.assert_allclose(traj.positions.ravel(), np.arange(18) * 10.0)


def test_fuzz_cases_through_info(run_cli):
    for path in sorted(FUZZ.glob("c3d_*.c3d")):
        result = run_cli("info", path)
        assert "Traceback" not in result.stderr and "Warning" not in result.stderr, path
        assert result.exit_code in (0, 2), path
        if result.exit_code == 2:
            assert result.stderr.count("\n") == 1 and result.stderr.startswith(
                f"mocaptk: error: {path}: ")


def test_undetectable_rigid_set_names_the_file_and_the_fix(run_cli, tmp_path):
    """blenderFace read as mm (a 0.5 mm face) had 'cannot detect 3 rigid markers' with no file
    and no way out; this 24-marker copy of our sample in metres fails the same way."""
    path = FUZZ / "face_in_metres_read_as_mm.trc"
    result = run_cli("cluster", path, "--formats", "none", "--out", tmp_path / "out")
    assert result.exit_code == 2
    line = result.stderr.strip().splitlines()[-1]
    assert line.startswith(f"mocaptk: error: {path}: cannot detect 3 rigid head markers")
    assert "--rigid A,B,C" in line and "--no-stabilize" in line
    assert not (tmp_path / "out").exists()
    assert run_cli("cluster", path, "--formats", "none", "--no-stabilize",
                   "--out", tmp_path / "ok").exit_code == 0
