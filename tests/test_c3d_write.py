"""write_c3d: round trips (NaN pattern exact, values to float32 precision), large files, takes,
atomic output; files checked with our own reader, ezc3d and py-c3d."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_path
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaptk import Take, Trajectories
from mocaptk.acquisition import c3d_raw
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.c3d_write import write_c3d
from mocaptk.errors import OutputError

F32 = 2.0 ** -23  # float32 relative precision (round to nearest: half of this)


def session(frames: int, markers: int, *, seed: int = 0, gaps: float = 0.1,
            prefix: str = "Anna:") -> Trajectories:
    rng = np.random.default_rng(seed)
    pos = rng.normal(0, 400, (frames, markers, 3))
    pos[rng.random((frames, markers)) < gaps] = np.nan
    return Trajectories(pos, [f"{prefix}M{k:03d}" for k in range(markers)], 120.0, first_frame=7)


def assert_same(got: Trajectories, want: Trajectories) -> None:
    assert got.labels == want.labels and got.rate == want.rate
    assert got.first_frame == want.first_frame
    np.testing.assert_array_equal(np.isnan(got.positions), np.isnan(want.positions))
    np.testing.assert_allclose(got.positions, want.positions, rtol=F32, atol=0)
    assert got.takes == want.takes


def test_round_trip_with_gaps_takes_and_prefixes(tmp_path):
    traj = session(500, 20)
    traj = traj.replace(metadata={"takes": [Take("brows", 0, 200, "brow"), Take("jaw", 200, 500)]})
    back = read_c3d(write_c3d(traj, tmp_path / "s.c3d"))
    assert_same(back, traj)
    assert back.metadata["reader"] == "mocaptk" and back.metadata["subjects"] == ["Anna"]
    assert back.metadata["original_units"] == "mm"
    assert back.takes[0].region == "brow" and back.takes[1].region is None


def test_gaps_are_invalid_points_not_zeros(tmp_path):
    traj = session(50, 4, gaps=0.3)
    structure = c3d_raw.read_structure(write_c3d(traj, tmp_path / "g.c3d"))
    xyz, residual = c3d_raw.read_points(structure)
    gaps = np.isnan(traj.positions[..., 0])
    assert (residual[gaps] == -1).all() and (residual[~gaps] >= 0).all()
    assert not np.isnan(xyz).any()  # NaN is never written


def test_more_than_255_markers_use_labels2(tmp_path):
    traj = session(30, 300)
    path = write_c3d(traj, tmp_path / "wide.c3d")
    structure = c3d_raw.read_structure(path)
    assert len(structure.param("POINT", "LABELS")) == 255
    assert len(structure.param("POINT", "LABELS2")) == 45
    assert_same(read_c3d(path), traj)


def test_more_than_65535_frames(tmp_path):
    traj = session(70_000, 2, gaps=0.02, prefix="")
    traj = traj.replace(metadata={"takes": [Take("all", 0, 70_000), Take("end", 69_000, 70_000)]})
    path = write_c3d(traj, tmp_path / "long.c3d")
    structure = c3d_raw.read_structure(path)
    assert structure.header_saturated and structure.n_frames == 70_000
    back = read_c3d(path)
    assert_same(back, traj)
    theirs = read_c3d(path, reader="ezc3d")
    assert theirs.metadata["reader"] == "mocaptk"  # ezc3d stops at 65,535 frames
    assert any("at most 65535 frames" in note for note in theirs.metadata["notes"])


def test_residuals_round_trip_to_the_c3d_step(tmp_path):
    traj = session(40, 3, gaps=0.2)
    residuals = np.where(np.isnan(traj.positions[..., 0]), np.nan, 2.0)
    traj = traj.replace(residuals=residuals)
    back = read_c3d(write_c3d(traj, tmp_path / "r.c3d"))
    np.testing.assert_array_equal(back.residuals, residuals)


def test_peers_read_what_we_write(tmp_path):
    import c3d
    import ezc3d

    traj = session(100, 12, gaps=0.15, prefix="")
    path = write_c3d(traj, tmp_path / "peer.c3d")
    points = ezc3d.c3d(str(path))["data"]["points"][:3].transpose(2, 1, 0)
    np.testing.assert_allclose(points, traj.positions, rtol=F32)  # gaps: NaN in both
    with open(path, "rb") as handle, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = [p.copy() for _, p, _ in c3d.Reader(handle).read_frames()]
    values = np.array(frames)
    np.testing.assert_array_equal(values[..., 3] < 0, np.isnan(traj.positions[..., 0]))


def test_real_file_round_trip(tmp_path):
    traj = read_c3d(shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d"))
    back = read_c3d(write_c3d(traj, tmp_path / "vicon.c3d"))
    assert_same(back, traj)
    assert back.metadata["descriptions"] == traj.metadata["descriptions"]


def test_atomic_and_force(tmp_path):
    traj = session(10, 2)
    path = write_c3d(traj, tmp_path / "out.c3d")
    before = path.read_bytes()
    with pytest.raises(OutputError, match="already exists"):
        write_c3d(session(10, 2, seed=5), path, force=False)
    assert path.read_bytes() == before
    other = write_c3d(traj, tmp_path / "OUT.C3D")  # ezc3d would append ".c3d" to this name
    assert other.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["OUT.C3D", "out.c3d"]


@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.integers(1, 40), markers=st.integers(1, 6), gaps=st.floats(0, 1),
       scale=st.sampled_from([1e-3, 1.0, 1e4]), seed=st.integers(0, 2**16))
def test_read_of_write_is_identity(tmp_path, frames, markers, gaps, scale, seed):
    traj = session(frames, markers, seed=seed, gaps=gaps)
    traj = traj.replace(positions=traj.positions * scale)
    assert_same(read_c3d(write_c3d(traj, tmp_path / "h.c3d")), traj)


def test_non_ascii_labels_round_trip(tmp_path):
    traj = Trajectories(np.ones((3, 3, 3)), ["Ánna:nez_é", "Ωmega", "plain"], 60.0)
    back = read_c3d(write_c3d(traj, tmp_path / "utf8.c3d"))
    assert back.labels == traj.labels and back.metadata["subjects"] == ["Ánna"]


def test_nothing_to_write_is_refused(tmp_path):
    with pytest.raises(OutputError, match="nothing to write"):
        write_c3d(Trajectories(np.zeros((0, 2, 3)), ["a", "b"], 100.0), tmp_path / "e.c3d")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("markers", [10_000, 32_767, 65_535])
def test_label_table_round_trips_to_65535_markers(tmp_path, markers):
    """LABELS, LABELS2, ... LABELS257 (a 250+ block parameter section): every label read back,
    by our reader and, up to its limit of 32,767 points, by ezc3d."""
    import ezc3d

    traj = session(2, markers, gaps=0.01, prefix="Face:")
    path = write_c3d(traj, tmp_path / "wide.c3d")
    back = read_c3d(path)
    assert_same(back, traj)
    assert back.metadata["reader"] == "mocaptk" and back.metadata["notes"] == []
    if markers > 32_767:  # ezc3d 1.7 reads POINT:USED as signed 16-bit
        with pytest.raises(RuntimeError):
            ezc3d.c3d(str(path))
        return
    c3d = ezc3d.c3d(str(path))
    params = c3d["parameters"]["POINT"]
    keys = ["LABELS"] + [f"LABELS{k}" for k in range(2, 300) if f"LABELS{k}" in params]
    assert [lab.strip() for key in keys for lab in params[key]["value"]] == list(traj.labels)
    np.testing.assert_allclose(c3d["data"]["points"][:3].transpose(2, 1, 0), traj.positions,
                               rtol=F32)


def test_writer_memory_is_bounded_by_its_block(tmp_path, monkeypatch):
    """The point block is encoded a block of frames at a time: peak extra memory is about one
    block (here 1 MB), not the session's size (200 markers x 4,000 frames, 19 MB of float64)."""
    import tracemalloc

    from mocaptk.acquisition import c3d_write

    monkeypatch.setattr(c3d_write, "BLOCK_BYTES", 2**20)
    traj = session(4_000, 200, gaps=0.02, prefix="")
    tracemalloc.start()
    path = write_c3d(traj, tmp_path / "long.c3d")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 0.25 * traj.positions.nbytes, peak
    assert_same(read_c3d(path), traj)
