"""Low-rank gap filling (``cluster --fill-gaps``): gaps that follow the expression, as the
lips' and chin's do in captures reconstructed from images, filled from the session's own motion."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.acquisition.gapfill import fill_low_rank

SAMPLE = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"


def test_expression_gaps_filled_from_the_session_motion():
    truth = read_c3d(SAMPLE).positions[::40]
    rest = np.median(truth, axis=0)
    moving = np.linalg.norm(truth - rest, axis=2)
    # the markers that move most are lost in their 20 % widest frames (merged blobs, hidden lips)
    busy = np.argsort(moving.max(axis=0))[-20:]
    gaps = np.zeros(moving.shape, bool)
    gaps[:, busy] = moving[:, busy] > np.percentile(moving[:, busy], 80, axis=0)
    gappy = truth.copy()
    gappy[gaps] = np.nan
    filled = fill_low_rank(gappy)
    assert np.isfinite(filled).all()
    assert np.array_equal(filled[~gaps], truth[~gaps])  # seen points untouched
    error = np.linalg.norm(filled - truth, axis=2)[gaps]
    mean_fill = np.linalg.norm(np.nanmean(gappy, axis=0)[None] - truth, axis=2)[gaps]
    # the gaps are the markers' widest frames: their mean misses by millimetres
    assert np.sqrt(np.mean(error ** 2)) < 0.25 * np.sqrt(np.mean(mean_fill ** 2)), (
        np.sqrt(np.mean(error ** 2)), np.sqrt(np.mean(mean_fill ** 2)))


def test_never_seen_markers_stay_gaps_and_complete_sessions_unchanged():
    truth = read_c3d(SAMPLE).positions[::50]
    assert np.array_equal(fill_low_rank(truth), truth)
    gappy = truth.copy()
    gappy[:, 3] = np.nan
    gappy[::4, 7] = np.nan
    filled = fill_low_rank(gappy)
    assert np.isnan(filled[:, 3]).all() and np.isfinite(filled[:, 7]).all()


def test_fill_gaps_takes_one_session(run_cli, tmp_path):
    result = run_cli("cluster", SAMPLE, SAMPLE, "--fill-gaps", "--out", tmp_path / "out")
    assert result.exit_code == 2 and "--fill-gaps takes one session" in result.stderr, result.stderr
