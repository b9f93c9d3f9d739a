"""Cleaning with ground truth: head stabilization, gap filling, low-pass filtering, `mocaptk clean`."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import SAMPLES, shared_path
from scipy.spatial.transform import Rotation

from mocaptk import Take, Trajectories
from mocaptk.acquisition.filtering import lowpass
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.acquisition.gapfill import fill_gaps, held_out_errors, held_out_gaps
from mocaptk.acquisition.stabilize import detect_rigid_markers, kabsch, stabilize_head
from mocaptk.errors import MocaptkError, OptionError

RATE = 60.0


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) of the rotation taking each b to a, (F,)."""
    return np.degrees(Rotation.from_matrix(np.einsum("fij,fkj->fik", a, b)).magnitude())


def _head_motion(frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(frames) / RATE
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 6, 3)
    rotvec = np.stack([0.25 * np.sin(0.9 * t + phase[0]), 0.15 * np.sin(0.5 * t + phase[1]),
                       0.2 * np.sin(0.3 * t + phase[2])], axis=1)  # up to ~14 degrees
    trans = np.stack([40 * np.sin(0.4 * t), 20 * np.cos(0.7 * t), 8 * t], axis=1)
    return Rotation.from_rotvec(rotvec).as_matrix(), trans


def _face_like(frames=1200, markers=60, rigid=6, noise=0.1, dropout=0.1, seed=0):
    """Markers on a 'head': ``rigid`` of them fixed, the rest deforming (3-8 mm oscillations),
    moved by a known rigid motion; returns (session, local positions, R, t)."""
    rng = np.random.default_rng(seed)
    base = rng.normal(0, 40, (markers, 3))
    t = np.arange(frames) / RATE
    amp = rng.uniform(3, 8, (markers, 1)) * np.sin(2 * np.pi * rng.uniform(0.2, 1.5, (markers, 1)) * t
                                                   + rng.uniform(0, 6, (markers, 1)))
    dirs = rng.normal(size=(markers, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    local = base[None] + amp.T[:, :, None] * dirs[None]
    local[:, :rigid] = base[:rigid]
    rot, trans = _head_motion(frames, seed)
    world = np.einsum("fij,fmj->fmi", rot, local) + trans[:, None]
    world += rng.normal(0, noise, world.shape)
    world[rng.random((frames, markers)) < dropout] = np.nan
    labels = [f"HEAD_{i:02d}" for i in range(rigid)] + [f"FACE_{i:02d}" for i in range(markers - rigid)]
    return Trajectories(world, labels, RATE), local, rot, trans


def test_kabsch_exact_on_noise_free_points():
    rng = np.random.default_rng(4)
    ref = rng.normal(0, 50, (5, 3))
    rot = Rotation.random(20, random_state=5).as_matrix()
    trans = rng.normal(0, 100, (20, 3))
    moving = np.einsum("fij,mj->fmi", rot, ref) + trans[:, None]
    weights = np.ones((20, 5))
    weights[3, :3] = 0  # only 2 markers: no pose
    got_r, got_t = kabsch(ref, moving, weights)
    ok = np.arange(20) != 3
    np.testing.assert_allclose(got_r[ok], rot[ok], atol=1e-10)
    np.testing.assert_allclose(got_t[ok], trans[ok], atol=1e-8)
    assert np.isnan(got_r[3]).all() and np.isnan(got_t[3]).all()


@pytest.fixture(scope="module")
def face():
    return _face_like()


def test_rigid_markers_detected_automatically(face):
    session, *_ = face
    found = detect_rigid_markers(session)
    assert len(found) >= 3 and all(label.startswith("HEAD_") for label in found)


def test_stabilization_recovers_known_head_motion(face):
    session, local, rot, trans = face
    result = stabilize_head(session)
    ref = result.reference_frame
    assert len(result.rigid_labels) >= 3 and all(label.startswith("HEAD_") for label in result.rigid_labels)
    posed = np.isfinite(result.rotations[:, 0, 0])
    assert posed.mean() > 0.99  # 10 % dropout: < 3 of 6 rigid markers seen is rare
    # truth: pose relative to the reference frame, x_f = (R_f R_ref^T) x_ref + ...
    rel_rot = np.einsum("fij,kj->fik", rot, rot[ref])
    rel_trans = trans - np.einsum("fij,j->fi", rel_rot, trans[ref])
    angle = _angle_deg(result.rotations[posed], rel_rot[posed])
    shift = np.linalg.norm(result.translations[posed] - rel_trans[posed], axis=1)
    print(f"stabilization (0.1 mm noise, 10 % gaps, up to ~14 deg head rotation): rotation error "
          f"median {np.median(angle):.3f} deg, p99 {np.percentile(angle, 99):.3f} deg; "
          f"translation error median {np.median(shift):.3f} mm")
    assert np.median(angle) < 0.3 and np.percentile(angle, 99) < 1.0
    assert np.median(shift) < 1.0
    # head-relative positions equal the true local motion seen from the reference pose
    truth = np.einsum("ij,fmj->fmi", rot[ref], local) + trans[ref]
    err = np.linalg.norm(result.trajectories.positions - truth, axis=2)
    assert np.nanmedian(err) < 0.35 and np.nanpercentile(err, 99) < 1.5
    # ≈ √3 × the 0.1 mm per-axis noise: the pose, fitted to low-passed markers, no longer absorbs it
    assert np.nanmedian(result.rms_residual_mm) < 0.18
    np.testing.assert_allclose(result.rotations[ref], np.eye(3), atol=1e-12)
    assert result.trajectories.metadata["stabilized"]["rigid_labels"] == list(result.rigid_labels)


def test_stabilization_ignores_a_glitching_rigid_marker(face):
    session, _, rot, _ = face
    pos = session.positions.copy()
    pos[100:200, 2] += 15.0  # a rigid marker jumps (mislabel / slipping marker) for 100 frames
    result = stabilize_head(session.replace(positions=pos), rigid_labels=[f"HEAD_{i:02d}" for i in range(6)])
    ref = result.reference_frame
    rel_rot = np.einsum("fij,kj->fik", rot, rot[ref])
    window = np.arange(100, 200)
    window = window[np.isfinite(result.rotations[window, 0, 0])]
    angle = _angle_deg(result.rotations[window], rel_rot[window])
    print(f"15 mm glitch on 1 of 6 rigid markers: rotation error median {np.median(angle):.3f} deg, "
          f"max {angle.max():.3f} deg")
    assert np.median(angle) < 0.4 and angle.max() < 1.5  # without outlier rejection: up to ~10 deg


def test_short_pose_gaps_are_interpolated_long_ones_left(face):
    session, _, rot, _ = face
    pos = session.positions.copy()
    pos[300:306, :6] = np.nan  # all rigid markers lost for 6 frames ...
    pos[600:640, :6] = np.nan  # ... and for 40 frames
    result = stabilize_head(session.replace(positions=pos), rigid_labels=[f"HEAD_{i:02d}" for i in range(6)])
    assert np.isnan(result.rotations[600:640]).all() and np.isnan(result.trajectories.positions[600:640]).all()
    assert np.isnan(result.rms_residual_mm[300:306]).all()
    bridged = np.arange(300, 306)
    rel_rot = np.einsum("fij,kj->fik", rot, rot[result.reference_frame])
    angle = _angle_deg(result.rotations[bridged], rel_rot[bridged])
    assert angle.max() < 0.5
    assert not np.isnan(result.trajectories.positions[bridged, 6:]).all(axis=(1, 2)).any()


def test_stabilization_of_real_data_cancels_an_added_rigid_motion():
    """Real capture (pyomeca, Vicon): moving the whole marker cloud rigidly must not change the
    head-relative result beyond the reference frame's own change of coordinates."""
    real = read_trajectories(shared_path("csv_trc", "pyomeca", "markers.csv"))
    box = [label for label in real.labels if label.startswith("boite:")]
    rot, trans = _head_motion(real.n_frames, seed=3)
    moved = real.replace(positions=np.einsum("fij,fmj->fmi", rot, real.positions) + trans[:, None])
    for cutoff, atol in ((None, 1e-6), (12.0, 0.1)):  # raw fit: exact; low-passed rigid markers:
        a = stabilize_head(real, rigid_labels=box, pose_cutoff_hz=cutoff)  # filtering does not
        b = stabilize_head(moved, rigid_labels=box, pose_cutoff_hz=cutoff)  # commute with rotation
        assert a.reference_frame == b.reference_frame
        ref = a.reference_frame
        expected = np.einsum("ij,fmj->fmi", rot[ref], a.trajectories.positions) + trans[ref]
        np.testing.assert_allclose(b.trajectories.positions, expected, atol=atol)
        assert np.nanmedian(a.rms_residual_mm) < 0.5  # the box really is rigid


@pytest.fixture(scope="module")
def sample_face():
    """The bundled synthetic dense half-face performance (ICT-FaceKit, 139 markers, 0.27 mm noise)
    and its noise-free ground truth."""
    from mocaptk.acquisition.synth_session import load_ground_truth

    observed = read_trajectories(SAMPLES / "dense_halfface_performance.c3d")
    truth = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    assert observed.labels == truth.labels
    return observed, truth


def test_stabilization_of_a_facial_session_with_added_head_motion(sample_face):
    """No face marker is perfectly rigid (the model's most stable ones move 0.5-1.7 mm): the
    automatic set must still be spread over skull-like places and recover the head pose."""
    observed, truth = sample_face
    rot, trans = _head_motion(observed.n_frames, seed=2)
    moved = observed.replace(positions=np.einsum("fij,fmj->fmi", rot, observed.positions) + trans[:, None])
    result = stabilize_head(moved)
    assert 3 <= len(result.rigid_labels) <= 6
    assert not any(label.startswith(("MOUTH", "CHIN")) for label in result.rigid_labels)
    ref = result.reference_frame
    rel_rot = np.einsum("fij,kj->fik", rot, rot[ref])
    posed = np.isfinite(result.rotations[:, 0, 0])
    angle = _angle_deg(result.rotations[posed], rel_rot[posed])
    expected = np.einsum("ij,fmj->fmi", rot[ref], truth.positions) + trans[ref]
    err = np.linalg.norm(result.trajectories.positions - expected, axis=2)
    print(f"facial sample + head motion: rigid set {', '.join(result.rigid_labels)}; rotation error "
          f"median {np.median(angle):.3f} deg, p99 {np.percentile(angle, 99):.3f} deg; head-relative "
          f"position error vs truth median {np.nanmedian(err):.3f} mm, p99 {np.nanpercentile(err, 99):.3f} mm")
    assert posed.mean() > 0.99
    assert np.median(angle) < 0.6 and np.percentile(angle, 99) < 2.0
    assert np.nanmedian(err) < 0.6 and np.nanpercentile(err, 99) < 2.5


def test_stabilization_bad_options(face):
    session, *_ = face
    with pytest.raises(OptionError, match="at least 3"):
        stabilize_head(session, rigid_labels=["HEAD_00", "HEAD_01"])
    with pytest.raises(MocaptkError, match="rigid markers not in the session: NOSE"):
        stabilize_head(session, rigid_labels=["HEAD_00", "HEAD_01", "NOSE"])


# -- gap filling --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def complete_real():
    """The markers of pyomeca/markers.csv (real Vicon capture) that are never missing."""
    real = read_trajectories(shared_path("csv_trc", "pyomeca", "markers.csv"))
    complete = ~np.isnan(real.positions).any(axis=(0, 2))
    return real.select([label for label, ok in zip(real.labels, complete) if ok])


def _held_out(traj: Trajectories, length: int, seed: int):
    rng = np.random.default_rng(seed)
    cut = traj.positions.copy()
    holes = []
    for m in range(0, traj.n_markers, 3):
        start = int(rng.integers(20, traj.n_frames - length - 20))
        cut[start:start + length, m] = np.nan
        holes.append((m, start))
    return traj.replace(positions=cut), holes


def _rmse(filled: Trajectories, truth: Trajectories, holes, length) -> float:
    err = np.concatenate([np.linalg.norm(filled.positions[s:s + length, m] - truth.positions[s:s + length, m],
                                         axis=1) for m, s in holes])
    return float(np.sqrt(np.mean(err ** 2)))


@pytest.mark.parametrize("length", [5, 30, 60])
def test_gap_filling_error_on_held_out_real_gaps(complete_real, length):
    assert complete_real.n_markers >= 30
    cut, holes = _held_out(complete_real, length, seed=length)
    spline, spline_report = fill_gaps(cut, max_gap=1000, method="cubic")
    neigh, neigh_report = fill_gaps(cut, max_gap=10, method="neighbours")
    auto, _ = fill_gaps(cut, max_gap=10)
    assert spline_report.frames_filled("cubic") == neigh_report.frames_filled("neighbours") == length * len(holes)
    rmse = {name: _rmse(f, complete_real, holes, length) for name, f in
            (("cubic", spline), ("neighbours", neigh), ("auto", auto))}
    print(f"held-out {length}-frame gaps ({len(holes)} markers, 100 Hz Vicon): RMSE mm "
          + ", ".join(f"{k} {v:.3f}" for k, v in rmse.items()))
    if length <= 10:
        assert rmse["cubic"] < 0.5 and rmse["neighbours"] < 0.5
        assert rmse["auto"] == rmse["cubic"]
    else:
        assert rmse["neighbours"] < 3.0 and rmse["neighbours"] < 0.5 * rmse["cubic"]
        assert rmse["auto"] == rmse["neighbours"]
    assert not np.isnan(auto.positions).any()


def test_gap_filling_error_on_held_out_facial_gaps(sample_face):
    """Held-out 30-frame (0.5 s) gaps in the facial sample, error vs the noise-free truth."""
    observed, truth = sample_face
    observed, truth_positions = observed.frames(0, 600), truth.positions[:600]
    session, holes = held_out_gaps(observed, rng=np.random.default_rng(5))
    rmse = {}
    for method, max_gap in (("cubic", 1000), ("neighbours", 10)):
        filled, _ = fill_gaps(session, max_gap=max_gap, method=method)
        err = held_out_errors(filled.positions, truth_positions, holes)
        rmse[method] = float(np.sqrt(np.mean(err ** 2)))
    print(f"facial sample, {len(holes)} held-out 30-frame gaps, RMSE vs truth: cubic {rmse['cubic']:.3f} mm, "
          f"neighbours {rmse['neighbours']:.3f} mm (noise 0.27 mm)")
    assert len(holes) >= 25
    assert rmse["neighbours"] < 0.6 and rmse["neighbours"] < 0.3 * rmse["cubic"]


def test_leading_and_trailing_gaps_respect_the_limit(complete_real):
    pos = complete_real.positions.copy()
    pos[:25, 0] = np.nan   # leading gap longer than max_gap
    pos[:6, 1] = np.nan    # leading gap within max_gap
    pos[-8:, 2] = np.nan   # trailing gap within max_gap
    pos[-40:, 3] = np.nan  # trailing gap longer than max_gap
    filled, report = fill_gaps(complete_real.replace(positions=pos), max_gap=10)
    assert np.isnan(filled.positions[:25, 0]).all() and not np.isnan(filled.positions[25:, 0]).any()
    assert np.isnan(filled.positions[-40:, 3]).all()
    for m, frames in ((1, slice(0, 6)), (2, slice(-8, None))):
        err = np.linalg.norm(filled.positions[frames, m] - complete_real.positions[frames, m], axis=1)
        assert err.max() < 3.0
    by_marker = {r.marker: r for r in report.records}
    labels = complete_real.labels
    assert by_marker[labels[0]].method is None and "leading gap longer than max_gap 10" in by_marker[labels[0]].note
    assert (by_marker[labels[1]].position, by_marker[labels[1]].method) == ("leading", "neighbours")
    assert (by_marker[labels[2]].position, by_marker[labels[2]].method) == ("trailing", "neighbours")
    assert by_marker[labels[3]].method is None and by_marker[labels[3]].position == "trailing"
    # interpolation alone never extrapolates
    only_spline, spline_report = fill_gaps(complete_real.replace(positions=pos), max_gap=10, method="cubic")
    assert np.isnan(only_spline.positions[:6, 1]).all() and spline_report.frames_filled() == 0


def test_no_filling_across_take_cuts():
    frames = 100
    track = np.zeros((frames, 2, 3))
    track[50:, :, 0] = 100 + np.arange(50)[:, None]  # take b starts with a jump, then a ramp
    track[:, 1, 1] = 5.0
    gap = track.copy()
    gap[46:54, 0] = np.nan   # straddles the cut at 50: trailing gap of a + leading gap of b
    gap[56:59, 0] = np.nan   # interior gap of take b, near the cut
    takes = [Take("a", 0, 50), Take("b", 50, 100)]
    session = Trajectories(gap, ["A", "B"], RATE, metadata={"takes": takes})
    filled, report = fill_gaps(session, max_gap=3, method="cubic")
    assert np.isnan(filled.positions[46:54, 0]).all()  # 4-frame edge gaps > 3: not filled
    np.testing.assert_allclose(filled.positions[56:59, 0], track[56:59, 0], atol=1e-9)  # ramp of b only
    records = [(r.start, r.end, r.position, r.method) for r in report.records]
    assert records == [(46, 50, "trailing", None), (50, 54, "leading", None), (56, 59, "interior", "cubic")]
    # the same data without takes: the 8-frame gap is interior and gets filled
    no_takes, _ = fill_gaps(session.replace(metadata={}), max_gap=10, method="cubic")
    assert not np.isnan(no_takes.positions[46:54, 0]).any()


def test_gap_fill_options_are_checked(complete_real):
    with pytest.raises(OptionError, match="unknown gap-fill method"):
        fill_gaps(complete_real, method="magic")
    with pytest.raises(OptionError, match=">= 0"):
        fill_gaps(complete_real, max_gap=-1)


# -- low-pass -----------------------------------------------------------------------------

def test_lowpass_zero_phase_nan_aware_per_take():
    rate = 100.0
    t = np.arange(1000) / rate
    signal = 10 * np.sin(2 * np.pi * 1.0 * t)
    clean = np.stack([signal, -signal, 0.5 * signal], axis=1)[:, None]
    noisy = clean + np.random.default_rng(0).normal(0, 1, clean.shape)
    noisy[300:310] = np.nan
    takes = [Take("a", 0, 500), Take("b", 500, 1000)]
    session = Trajectories(noisy, ["M"], rate, metadata={"takes": takes})
    out = lowpass(session, cutoff_hz=6)
    assert np.isnan(out.positions[300:310]).all() and np.isnan(out.positions).sum() == 30
    inner = np.r_[20:290, 320:480, 520:980]  # away from run ends
    noise_before = np.std(noisy[inner] - clean[inner])
    noise_after = np.std(out.positions[inner] - clean[inner])
    print(f"low-pass 6 Hz on 1 Hz sine + 1 mm noise: error std {noise_before:.3f} -> {noise_after:.3f} mm")
    assert noise_after < 0.4 * noise_before
    # zero phase: a clean 1 Hz sine passes without lag or attenuation
    pure = lowpass(session.replace(positions=clean), cutoff_hz=6).positions
    np.testing.assert_allclose(pure[inner], clean[inner], atol=0.05)
    # take boundary = hard cut: take a filtered alone gives the same values
    alone = lowpass(session.frames(0, 500).replace(metadata={}), cutoff_hz=6).positions
    np.testing.assert_allclose(out.positions[:500], alone, atol=1e-12)
    with pytest.raises(OptionError, match="between 0 and 50"):
        lowpass(session, cutoff_hz=60)


# -- CLI ----------------------------------------------------------------------------------

def test_cli_clean_real_file(run_cli, tmp_path):
    source = shared_path("csv_trc", "pyomeca", "markers.csv")
    out, report = tmp_path / "clean.csv", tmp_path / "clean.json"
    result = run_cli("clean", source, out, "--lowpass", "10", "--report", report)
    assert result.exit_code == 0, result.stderr
    assert "stabilized on boite:" in result.stdout and "missing 1.03 % -> 0.00 %" in result.stdout
    cleaned = read_trajectories(out)
    assert cleaned.n_markers == 51 and not np.isnan(cleaned.positions).any()
    doc = json.loads(report.read_text())
    assert doc["format"] == "mocaptk-clean-report"
    assert all(label.startswith("boite:") for label in doc["stabilization"]["rigid_labels"])
    assert doc["gap_filling"]["unfilled_frames"] == 0 and doc["gap_filling"]["filled_frames"] > 0
    again = run_cli("clean", source, tmp_path / "second.csv", "--lowpass", "10", "--report", tmp_path / "2.json")
    assert again.exit_code == 0 and (tmp_path / "2.json").read_text() == report.read_text().replace(
        str(report), str(tmp_path / "2.json"))


@pytest.mark.parametrize("args, needle", [
    (["--rigid", "boite:gauche_ext,NOPE,X"], "rigid markers not in the session: NOPE"),
    (["--no-stabilize", "--rigid", "a,b,c"], "--rigid needs --stabilize"),
    (["--lowpass", "80"], "between 0 and 50"),
])
def test_cli_clean_bad_options(run_cli, tmp_path, args, needle):
    source = shared_path("csv_trc", "pyomeca", "markers.csv")
    result = run_cli("clean", source, tmp_path / "out.csv", *args)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in result.stderr
    assert not (tmp_path / "out.csv").exists()
