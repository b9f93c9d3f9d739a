"""With rigid head motion, the stabilized pipeline keeps the marker counts of the motion-free capture."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocaptk.clustering.pipeline import ClusterOptions, cluster_session


@pytest.fixture(scope="module")
def still_and_moving():
    """Three captures (seeds 2-4), each without and with rigid head motion."""
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.synth_layout import dense_layout
    from mocaptk.acquisition.synth_session import dense_session

    from mocaptk.errors import InputFileError

    try:
        model = load_face_model()
    except InputFileError as exc:  # ICT-FaceKit lives in ../shared/data
        pytest.skip(str(exc))
    layout = dense_layout(model, mode="half", spacing_mm=12)
    pairs = []
    for seed in (2, 3, 4):
        options = dict(seed=seed, expressions_per_take=3, rest_seconds=1.0, expression_seconds=1.0,
                       gaps_per_minute=0)
        pairs.append((dense_session(model, layout, **options).trajectories,
                      dense_session(model, layout, head_motion=True, **options).trajectories))
    return pairs


@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_stabilized_counts_match_motion_free_capture(still_and_moving, factor):
    # Summed over three captures: on one sparse capture (~17 clusters at factor 0.9) the count moves
    # by up to 25 % with the noise draw, even when stabilizing on the six truly least-moving markers
    # (the 0.3 mm noise of any rigid set becomes a small pose noise shared by all markers).
    n_ref = n_stab = 0
    for still, moving in still_and_moving:
        reference = cluster_session(still, options=ClusterOptions(method="paper", factor=factor, stabilize=False, mirror=False))
        stabilized = cluster_session(moving, options=ClusterOptions(method="paper", factor=factor, stabilize=True, mirror=False))
        raw = cluster_session(moving, options=ClusterOptions(method="paper", factor=factor, stabilize=False, mirror=False))
        n_ref += len(reference.layout.clusters)
        n_stab += len(stabilized.layout.clusters)
        assert len(stabilized.layout.extra["stabilization"]["rigid_labels"]) >= 3
        assert stabilized.layout.parameters["stabilized"] is True
        # unstabilized, head motion makes every region look highly correlated
        raw_means = [r.mean_correlation for r in raw.layout.regions]
        ref_means = [r.mean_correlation for r in reference.layout.regions]
        assert min(raw_means) > 2.0 and min(ref_means) < 1.0  # of at most 3 (x + y + z)
    assert abs(n_stab - n_ref) <= 0.15 * n_ref, (n_ref, n_stab)


def test_cli_stabilizes_on_the_given_rigid_markers(still_and_moving, run_cli, tmp_path):
    still, moving = still_and_moving[0]
    steady = np.nanpercentile(np.linalg.norm(still.positions - np.nanmedian(still.positions, axis=0), axis=2),
                              95, axis=0)
    rigid = sorted(still.labels[k] for k in np.argsort(steady)[:5])
    session = tmp_path / "moving.npz"
    np.savez(session, positions=moving.positions, labels=np.array(moving.labels), rate=moving.rate)
    result = run_cli("cluster", session, "--rigid", ",".join(rigid), "--out", tmp_path / "L", "--formats", "none")
    assert result.exit_code == 0, result.stderr
    layout = json.loads((tmp_path / "L" / "layout.json").read_text())
    assert layout["stabilization"]["rigid_labels"] == rigid
    assert layout["stabilization"]["applied"] is True
    evaluated = run_cli("evaluate", session, "--layout", tmp_path / "L" / "layout.json", "--seeds", "2", "--quiet")
    assert evaluated.exit_code == 0, evaluated.stderr
    for args, needle in [(("--rigid", "NOPE," + ",".join(rigid[:2])), "are not markers of moving.npz: NOPE"),
                         (("--rigid", ",".join(rigid[:2])), "at least 3"),
                         (("--rigid", ",".join(rigid), "--no-stabilize"), "--no-stabilize")]:
        bad = run_cli("cluster", session, *args, "--out", tmp_path / "bad", "--formats", "none")
        assert bad.exit_code == 2 and needle in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "bad").exists()


def test_head_relative_session_is_recognised_before_the_rigid_search(still_and_moving):
    """A still head gives a steady spread set at once (no search, no full-length fit); a moving
    head gives none; the pipeline reports the first as already head-relative."""
    from mocaptk.acquisition.stabilize import head_relative_markers
    from mocaptk.clustering.pipeline import HEAD_RELATIVE_RMS_MM, stabilize

    for still, moving in still_and_moving:
        found = head_relative_markers(still, tolerance_mm=HEAD_RELATIVE_RMS_MM)
        assert found is not None and 3 <= len(found[0]) <= 6 and found[1] < HEAD_RELATIVE_RMS_MM
        assert head_relative_markers(moving, tolerance_mm=HEAD_RELATIVE_RMS_MM) is None
        same, report = stabilize(still)
        assert same is still and report["applied"] is False
        assert report["rigid_labels"] == list(found[0])


def test_pruned_rigid_search_is_as_rigid_as_the_all_pairs_set(still_and_moving, monkeypatch):
    """The candidate pruning (here 40 of the markers, by distance changes to 12 probes) picks a
    set as rigid as the search over all pairs: the fitted rigid body's residual and the
    stabilized markers' distance to the motion-free capture are as small."""
    from mocaptk.acquisition import stabilize as stab

    for still, moving in still_and_moving:
        assert moving.n_markers > 40
        with monkeypatch.context() as patch:
            patch.setattr(stab, "AUTO_RIGID_CANDIDATES", 40)
            pruned = stab.detect_rigid_markers(moving)
        with monkeypatch.context() as patch:
            patch.setattr(stab, "AUTO_RIGID_CANDIDATES", 10**6)
            full = stab.detect_rigid_markers(moving)
        scores = []
        for labels in (pruned, full):
            result = stab.stabilize_head(moving, rigid_labels=labels)
            shape = result.trajectories.positions - np.nanmean(result.trajectories.positions, axis=0)
            truth = still.positions - np.nanmean(still.positions, axis=0)
            scores.append((float(np.nanmedian(result.rms_residual_mm)),
                           float(np.sqrt(np.nanmean((shape - truth) ** 2)))))
        assert scores[0][0] <= 1.25 * scores[1][0] + 0.05
        assert scores[0][1] <= 1.25 * scores[1][1] + 0.05


def _moved(positions: np.ndarray, *, seed: int, offset_deg: float, shift_mm: float) -> np.ndarray:
    """``positions`` (F, M, 3) under a slow rigid head motion starting ``offset_deg`` / ``shift_mm``
    away from the capture's own pose."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    t = np.arange(len(positions)) / 60.0
    phase = rng.uniform(0, 2 * np.pi, 3)
    angles = np.radians(offset_deg + 3 * np.sin(0.5 * t[:, None] + phase))
    rotation = Rotation.from_euler("xyz", angles).as_matrix()
    shift = shift_mm + 5 * np.sin(0.3 * t[:, None] + phase)
    centre = np.nanmean(positions[0], axis=0)
    return np.einsum("fij,fmj->fmi", rotation, positions - centre) + centre + shift[:, None]


def _best_frame(original: tuple[np.ndarray, list[str]], stabilized):
    """The rigid map (Similarity) from a capture's motion-free coordinates to its stabilized
    ones, and the motion-free positions in the stabilized marker order (F, M, 3)."""
    from mocaptk.geometry import similarity_transform

    positions, labels = original
    positions = positions[:, [labels.index(label) for label in stabilized.labels]]
    seen = np.isfinite(positions).all(axis=2) & np.isfinite(stabilized.positions).all(axis=2)
    return similarity_transform(positions[seen], stabilized.positions[seen], with_scale=False), positions


def test_a_test_capture_is_stabilized_into_the_sessions_head_frame(tmp_path):
    """Session and held-out performance under different head poses (6 degrees, 25 mm apart): the
    performance lands in the session's head frame, as close to it as to its own best frame (the
    performance moves the sample's rigid set too: 2.1 mm). Before, each file was stabilized into
    its own reference frame: 47 mm RMS off here, and on `synth --rig room --head-motion` 3 degrees
    apart, which made every held-out error in docs/layout-methods.md 3-5 mm."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.clustering.pipeline import load_session_and_test

    from conftest import SAMPLES

    files = {}
    for name, frames, seed, offset, shift in (("session", 2400, 1, 0.0, 0.0),
                                              ("performance", 1200, 2, 6.0, 25.0)):
        traj = read_trajectories(SAMPLES / f"dense_halfface{'_performance' * (name != 'session')}.c3d",
                                 strip_prefixes=True)
        files[name] = (traj.positions[:frames], list(traj.labels))
        np.savez(tmp_path / f"{name}.npz", labels=np.array(traj.labels), rate=traj.rate,
                 positions=_moved(traj.positions[:frames], seed=seed, offset_deg=offset, shift_mm=shift))
    session, test, _ = load_session_and_test(tmp_path / "session.npz", tmp_path / "performance.npz",
                                             stabilized=True)
    session_frame, _ = _best_frame(files["session"], session)
    own_frame, truth = _best_frame(files["performance"], test)
    rmse = lambda frame: float(np.sqrt(np.nanmean(  # noqa: E731
        np.sum((test.positions - frame.apply(truth)) ** 2, axis=2))))
    assert rmse(session_frame) < rmse(own_frame) + 0.5 < 3.0
