"""Worst-case single lost marker: the evaluation's ridge model refitted without the marker."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.clustering.evaluation import error_summary, heldout_errors, holdout_splits
from mocaptk.clustering.lost_marker import heldout_folds, lost_marker_rmse, worst_lost_marker


def driven_positions(*, frames: int = 200, markers: int = 12, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    neutral = rng.uniform(-40, 40, size=(markers, 3))
    drivers = rng.normal(size=(frames, 3)).cumsum(axis=0)
    mix = rng.normal(size=(3, markers, 3))
    return neutral[None] + np.einsum("fk,kmc->fmc", drivers, mix) + rng.normal(scale=0.1, size=(frames, markers, 3))


def test_lost_marker_error_is_the_evaluation_of_the_layout_without_it():
    positions = driven_positions()
    train, test = positions[:150], positions[150:]
    layout = np.array([1, 4, 7, 10])
    folds = heldout_folds(train, test=test)
    lost = lost_marker_rmse(folds, layout)
    for i, marker in enumerate(layout):
        rest = np.delete(layout, i)
        expected = error_summary(heldout_errors(train, rest, [], test=test))["rmse_mm"]
        assert lost[i] == pytest.approx(expected, rel=1e-6)
    worst = worst_lost_marker(folds, layout)
    assert worst.lost_rmse_mm == pytest.approx(lost.max()) and worst.marker == layout[np.argmax(lost)]
    assert worst.intact_rmse_mm == pytest.approx(
        error_summary(heldout_errors(train, layout, [], test=test))["rmse_mm"], rel=1e-6)
    assert worst.lost_rmse_mm > worst.intact_rmse_mm


def test_lost_marker_follows_the_held_out_splits_on_gap_free_frames():
    positions = driven_positions(seed=1)
    positions[20:23, 5] = np.nan  # frames with a gap are left out
    splits = holdout_splits(positions.shape[0], split="blocks", folds=4)
    layout = np.array([0, 3, 8])
    folds = heldout_folds(positions, splits)
    keep = np.isfinite(positions).all(axis=(1, 2))
    clean = [(tr[keep[tr]], te[keep[te]]) for tr, te in splits]
    errors = heldout_errors(positions, np.array([3, 8]), clean)
    errors[~keep] = np.nan
    assert lost_marker_rmse(folds, layout)[0] == pytest.approx(error_summary(errors)["rmse_mm"], rel=1e-6)


def test_robust_method_lowers_the_worst_single_lost_marker_of_the_hybrid():
    from test_methods_hybrid import wave_problem

    from mocaptk.clustering.methods import select_layout
    from mocaptk.clustering.methods.hybrid import local_error
    from mocaptk.clustering.methods.robust import worst_lost

    problem = wave_problem(seed=4)
    hybrid = select_layout(problem, 7, method="hybrid").layout
    robust = select_layout(problem, 7, method="robust")
    assert robust.layout.size == 7
    score = local_error(problem, scales=(1, 2))
    before, after = worst_lost(score, hybrid)[0], worst_lost(score, robust.layout)[0]
    assert robust.details["worst_lost_local_rmse_mm"] == {"hybrid": pytest.approx(before),
                                                          "robust": pytest.approx(after)}
    assert after <= before
    np.testing.assert_array_equal(robust.layout, select_layout(wave_problem(seed=4), 7, method="robust").layout)


def test_lost_marker_downdate_equals_refits_on_the_sample():
    """The rank-3 downdates give each reduced layout's refit (real data, a take held out)."""
    from pathlib import Path

    from mocaptk.acquisition.c3d_read import read_c3d

    sample = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"
    if not sample.exists():
        pytest.skip("sample_c3d/dense_halfface.c3d not available")
    session = read_c3d(sample)
    positions = session.positions[::4]
    splits = holdout_splits(positions.shape[0], split="blocks", folds=3)
    folds = heldout_folds(positions, splits[:1])
    layout = np.sort(np.random.default_rng(2).choice(positions.shape[1], 30, replace=False))
    refits = np.array([folds.rmse(np.delete(layout, i)) for i in range(layout.size)])
    np.testing.assert_allclose(lost_marker_rmse(folds, layout), refits, rtol=1e-9)
    assert worst_lost_marker(folds, layout).marker == layout[np.argmax(refits)]
