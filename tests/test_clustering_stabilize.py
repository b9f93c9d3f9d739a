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

    model = load_face_model()
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
        reference = cluster_session(still, options=ClusterOptions(factor=factor, stabilize=False, mirror=False))
        stabilized = cluster_session(moving, options=ClusterOptions(factor=factor, stabilize=True, mirror=False))
        raw = cluster_session(moving, options=ClusterOptions(factor=factor, stabilize=False, mirror=False))
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
    for args, needle in [(("--rigid", "NOPE," + ",".join(rigid[:2])), "not in the session: NOPE"),
                         (("--rigid", ",".join(rigid[:2])), "at least 3"),
                         (("--rigid", ",".join(rigid), "--no-stabilize"), "--no-stabilize")]:
        bad = run_cli("cluster", session, *args, "--out", tmp_path / "bad", "--formats", "none")
        assert bad.exit_code == 2 and needle in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "bad").exists()
