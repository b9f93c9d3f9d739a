"""C3D bad input: one-line InputFileError naming the file; ezc3d failures contained in its child."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from conftest import shared_path
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaptk import Trajectories
from mocaptk.acquisition import c3d_ezc3d, c3d_raw
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.c3d_write import write_c3d
from mocaptk.errors import InputFileError


@pytest.fixture(scope="module")
def small_c3d(tmp_path_factory) -> bytes:
    """Bytes of a valid 3-marker, 40-frame C3D written by write_c3d."""
    rng = np.random.default_rng(1)
    traj = Trajectories(rng.normal(0, 100, (40, 3, 3)), ["A", "B", "C"], 100.0)
    path = write_c3d(traj, tmp_path_factory.mktemp("c3d") / "small.c3d")
    return path.read_bytes()


def _error(path) -> InputFileError:
    with pytest.raises(InputFileError) as info:
        read_c3d(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    return info.value


def _patch(data: bytes, name: bytes, skip: int, new: bytes) -> bytes:
    """Replace the bytes ``skip`` bytes after parameter ``name``'s name with ``new``."""
    at = data.index(name, 512) + len(name) + skip
    return data[:at] + new + data[at + len(new):]


def test_not_a_c3d(tmp_path):
    path = tmp_path / "notes.c3d"
    path.write_text("Frame,X,Y,Z\n" * 100)
    assert _error(path).problem.startswith("not a C3D file")


def test_empty(tmp_path):
    path = tmp_path / "empty.c3d"
    path.write_bytes(b"")
    assert _error(path).problem == "empty file (0 bytes)"


@pytest.mark.parametrize("keep", [100, 2048 + 16 * 3 * 10 + 7])
def test_truncated(tmp_path, small_c3d, keep):
    path = tmp_path / "cut.c3d"
    path.write_bytes(small_c3d[:keep])
    assert _error(path).problem.startswith("truncated C3D file")


def test_unknown_units(tmp_path, small_c3d):
    path = tmp_path / "units.c3d"
    path.write_bytes(_patch(small_c3d, b"UNITS", 5, b"zz"))  # offset, type, 1 dim, "mm"
    assert _error(path).problem == "unknown POINT:UNITS 'zz' (expected mm, cm or m)"


def test_absurd_frame_count_is_refused(tmp_path, small_c3d):
    """Header saturated + TRIAL:ACTUAL_END_FIELD = 2^30: refused before anything is allocated."""
    data = bytearray(_patch(small_c3d, b"ACTUAL_END_FIELD", 5, b"\xff\xff\x00\x40"))
    data[8:10] = b"\xff\xff"  # header last frame
    path = tmp_path / "huge.c3d"
    path.write_bytes(bytes(data))
    problem = _error(path).problem
    assert f"more than the {c3d_raw.MAX_POINT_SAMPLES:,} marker samples" in problem


def test_more_markers_than_the_file_holds(tmp_path, small_c3d):
    path = tmp_path / "used.c3d"
    path.write_bytes(_patch(small_c3d, b"USED", 4, b"\x30\x75"))  # POINT:USED = 30000
    assert _error(path).problem.startswith("truncated C3D file (declares 40 frames")


def test_zero_markers():
    path = shared_path("c3d", "ezc3d-testFiles", "Kistler.c3d")
    assert "no 3-D marker data" in _error(path).problem


def test_unreadable_paths(tmp_path):
    assert "No such file" in _error(tmp_path / "missing.c3d").problem
    assert "directory" in _error(tmp_path).problem.lower()


def test_bad_parameter_section():
    path = shared_path("c3d", "btkdata", "c3d.org", "sample18", "bad_parameter_section.c3d")
    assert _error(path).problem.startswith("bad parameter section")


def test_ezc3d_memory_blowup_is_contained():
    """ezc3d asks for ~12 GB on this 583 kB file; its child hits the limit, our reader reads it."""
    traj = read_c3d(shared_path("c3d", "btkdata", "c3d.org", "sample22", "BKINtechnologies.c3d"),
                    reader="ezc3d")
    assert traj.metadata["reader"] == "mocaptk" and traj.n_frames == 5065
    assert any("bad_alloc" in note or "needed more than" in note for note in traj.metadata["notes"])


def _crash(path):
    os.kill(os.getpid(), signal.SIGSEGV)


def _hang(path):
    time.sleep(60)


@pytest.mark.parametrize("behaviour, note", [(_crash, "ezc3d crashed (SIGSEGV)"),
                                             (_hang, "ezc3d did not finish within 1 s")])
def test_ezc3d_crash_or_hang_falls_back_to_own_reader(monkeypatch, tmp_path, small_c3d,
                                                      behaviour, note):
    """A native crash or hang in ezc3d (simulated in its child) never reaches the caller."""
    import ezc3d

    path = tmp_path / "ok.c3d"
    path.write_bytes(small_c3d)
    expected = read_c3d(path, reader="ezc3d")
    assert expected.metadata["reader"] == "ezc3d"
    monkeypatch.setattr(ezc3d, "c3d", behaviour)
    monkeypatch.setattr(c3d_ezc3d, "TIME_BASE", 1.0)
    traj = read_c3d(path, reader="ezc3d")
    assert traj.metadata["reader"] == "mocaptk"
    assert any(note in n for n in traj.metadata["notes"])
    np.testing.assert_array_equal(traj.positions, expected.positions)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_files_read_or_fail_cleanly(tmp_path, small_c3d, data):
    """Byte flips and truncations: a Trajectories or an InputFileError, nothing else."""
    raw = bytearray(small_c3d)
    for _ in range(data.draw(st.integers(1, 8))):
        at = data.draw(st.integers(0, len(raw) - 1))
        raw[at] = data.draw(st.integers(0, 255))
    raw = raw[:data.draw(st.integers(0, len(raw)))]
    path = tmp_path / "fuzz.c3d"
    path.write_bytes(bytes(raw))
    try:
        traj = read_c3d(path)
    except InputFileError as exc:
        assert "\n" not in str(exc)
    else:
        assert traj.positions.shape[1] == len(traj.labels)
