"""``mocaptk compare`` and the comparison protocol (methods see training frames only)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocaptk import Take, Trajectories
from mocaptk.clustering.compare import compare_methods, rows_as_markdown
from mocaptk.clustering.evaluation import error_summary, heldout_errors
from mocaptk.clustering.methods import select_layout
from mocaptk.clustering.methods.set_cover import representative_shapes, set_cover_layout
from mocaptk.clustering.compare import _gap_free, _problem


def small_session(*, frames: int = 240, markers: int = 24, seed: int = 0) -> Trajectories:
    """A face-like patch whose markers follow 4 hidden drivers; 3 takes; a few gaps."""
    rng = np.random.default_rng(seed)
    neutral = np.column_stack([rng.uniform(-40, 40, markers), rng.uniform(-50, 50, markers),
                               rng.uniform(0, 10, markers)])
    t = np.linspace(0, 12, frames)
    drivers = np.stack([np.sin((k + 1) * 0.9 * t + k) for k in range(4)], axis=1)  # (F, 4)
    mix = rng.normal(size=(4, markers, 3)) * 2.0
    pos = neutral[None] + np.einsum("fk,kmc->fmc", drivers, mix)
    pos += rng.normal(scale=0.05, size=pos.shape)
    pos[50:53, 3] = np.nan
    takes = [Take("a", 0, 80), Take("b", 80, 160), Take("c", 160, 240)]
    return Trajectories(pos, [f"M{i:02d}" for i in range(markers)], 60.0, metadata={"takes": takes})


def test_protocol_scores_layouts_chosen_without_the_test_take():
    session = small_session()
    rows = compare_methods(session, counts=[4, 6], methods=["qr", "random"])
    assert [(r.method, r.count) for r in rows] == [("qr", 4), ("qr", 6), ("random", 4), ("random", 6)]
    # recompute the qr row by hand: choose on two takes, score on the third
    errors = np.full(session.positions.shape[:2], np.nan)
    for take in session.takes:
        held = np.arange(take.start, take.end)
        train = np.setdiff1d(np.arange(session.n_frames), held)
        layout = select_layout(_problem(session.positions, session, train, {}), 4, method="qr").layout
        errors[held] = heldout_errors(_gap_free(session.positions[train]), layout, [],
                                      test=session.positions[held])
    assert rows[0].rmse_mm == pytest.approx(error_summary(errors)["rmse_mm"])
    assert rows[0].rmse_mm < rows[2].rmse_mm  # pivoted QR beats the mean of random layouts here
    assert "**" in rows_as_markdown(rows)


def test_rows_carry_the_worst_single_lost_marker_of_each_folds_layout():
    from mocaptk.clustering.lost_marker import heldout_folds

    session = small_session()
    rows = compare_methods(session, counts=[2], methods=["qr"])
    # by hand: per left-out take, the fold's layout without each marker, refitted on gap-free frames
    sse = points = 0.0
    for take in session.takes:
        held = np.arange(take.start, take.end)
        train = np.setdiff1d(np.arange(session.n_frames), held)
        layout = select_layout(_problem(session.positions, session, train, {}), 2, method="qr").layout
        fold = heldout_folds(session.positions, [(train, held)])
        worst = max(fold.rmse(np.delete(layout, i)) for i in range(layout.size))
        sse, points = sse + worst ** 2 * fold.n_test_points, points + fold.n_test_points
    assert rows[0].lost_rmse_mm == pytest.approx(np.sqrt(sse / points))
    assert rows[0].lost_rmse_mm > 1.5 * rows[0].rmse_mm  # one marker (3 coordinates) cannot follow 4 drivers
    table = rows_as_markdown(rows)
    assert "1 lost" in table and f"{rows[0].lost_rmse_mm:.3f}" in table


def test_every_row_carries_zell_layout_statistics_over_the_set_cover_shapes():
    session = small_session()
    rows = compare_methods(session, counts=[3, 8], methods=["kmeans", "set-cover"])
    shapes = representative_shapes(_problem(session.positions, session, None, {}).displacements)
    magnitude = np.linalg.norm(shapes, axis=2)  # (K, N)
    relative = magnitude / magnitude.max(axis=1, keepdims=True)
    for row in rows:
        assert set(row.statistics) == {"0.3", "0.7"}
        for eps, stats in row.statistics.items():
            moves = relative[:, row.layout] >= float(eps)  # (K, count)
            assert stats["idle_markers_percent"] == pytest.approx(100 * np.mean(~moves.any(axis=0)))
            assert stats["unseen_shapes"] == int(np.sum(~moves.any(axis=1)))
    # set cover (ε = 0.3) sees every shape at 0.3 once the count reaches its minimal cover
    minimal = set_cover_layout(_problem(session.positions, session, None, {})).layout.size
    assert minimal <= 8
    assert all(r.statistics["0.3"]["unseen_shapes"] == 0 for r in rows
               if r.method == "set-cover" and r.count >= minimal)
    table = rows_as_markdown(rows)
    assert "Layout statistics" in table and table.count("| set-cover |") == 2


def test_compare_cli_writes_table_json_plot_and_gallery(tmp_path, run_cli):
    from mocaptk.acquisition.formats import write_trajectories

    session = write_trajectories(small_session(), tmp_path / "session.c3d")
    test = write_trajectories(small_session(seed=0).frames(0, 120), tmp_path / "perf.c3d")
    out = tmp_path / "cmp"
    result = run_cli("compare", session, "--test", test, "--counts", "4,6,99", "--methods",
                     "kmeans,qr,hybrid", "--out", out, "--no-stabilize", "--quiet")
    assert result.exit_code == 0, result.stderr
    data = json.loads((out / "compare.json").read_text())
    assert data["format"] == "mocaptk-compare"
    assert {(r["method"], r["count"]) for r in data["rows"]} == {
        (m, c) for m in ("kmeans", "qr", "hybrid") for c in (4, 6)}
    assert all(len(r["layout"]) == r["count"] for r in data["rows"] if r["error"] is None)
    assert all(r["lost_marker_rmse_mm"] > r["rmse_mm"] for r in data["rows"])
    for r in data["rows"]:
        assert set(r["layout_statistics"]) == {"0.3", "0.7"}
        assert 0 <= r["layout_statistics"]["0.7"]["idle_markers_percent"] <= 100
    markdown = (out / "compare.md").read_text()
    assert markdown.count("| hybrid |") == 2 and "idle %" in markdown
    for png in ("rmse_vs_markers.png", "layouts.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # same input, same options: byte-identical JSON except the run times
    again = run_cli("compare", session, "--test", test, "--counts", "4,6", "--methods", "kmeans,qr",
                    "--out", out, "--no-stabilize", "--quiet", "--force")
    assert again.exit_code == 0
    rows2 = json.loads((out / "compare.json").read_text())["rows"]
    assert [(r["layout"], r["rmse_mm"]) for r in rows2] == [
        (r["layout"], r["rmse_mm"]) for r in data["rows"] if r["method"] in ("kmeans", "qr")]


@pytest.mark.parametrize("args, message", [
    (["--counts", "4,x"], "--counts"),
    (["--methods", "qr,magic"], "unknown method"),
    (["--restarts", "0"], "--restarts"),
])
def test_compare_cli_rejects_bad_options(tmp_path, run_cli, args, message):
    from mocaptk.acquisition.formats import write_trajectories

    session = write_trajectories(small_session(), tmp_path / "session.c3d")
    result = run_cli("compare", session, "--out", tmp_path / "o", "--no-stabilize", *args)
    assert result.exit_code == 2
    assert result.stderr.startswith("mocaptk: error:") and message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_compare_cli_missing_file(tmp_path, run_cli):
    result = run_cli("compare", tmp_path / "nope.c3d", "--out", tmp_path / "o")
    assert result.exit_code == 2 and "nope.c3d" in result.stderr


def test_gap_free_ridge_scores_as_the_per_pattern_fits_on_the_sample():
    """compare's one-Gram-per-fold scorer gives heldout_errors' errors (test frames with gaps)."""
    from pathlib import Path

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.evaluation import GapFreeRidge

    sample = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"
    if not sample.exists():
        pytest.skip("sample_c3d/dense_halfface.c3d not available")
    positions = read_c3d(sample).positions[::3]
    train, test = _gap_free(positions[:1500]), positions[1500:].copy()
    layout = np.sort(np.random.default_rng(1).choice(positions.shape[1], 40, replace=False))
    test[10:40, layout[:3]] = np.nan  # lost layout markers: other presence patterns
    expected = heldout_errors(train, layout, [], test=test)
    errors = GapFreeRidge.fit(train).errors(layout, test)
    np.testing.assert_array_equal(np.isnan(errors), np.isnan(expected))
    np.testing.assert_allclose(errors, expected, rtol=0, atol=1e-8, equal_nan=True)
    intact = GapFreeRidge.fit(train).errors(layout, positions[1500:])
    assert (errors[:, layout[3:]] == 0).all() and not np.allclose(errors[10:40], intact[10:40], equal_nan=True)


def test_ridge_moments_give_heldout_errors_per_pattern_fits_on_the_sample():
    """The report's held-out errors from one RidgeMoments per training set equal heldout_errors'
    per-pattern fits on frames with gaps: lost layout markers in training and test frames, a
    target missing in most frames (few complete frames left), and a layout holding every marker
    with gaps (its full pattern fitted on the complete frames alone)."""
    from pathlib import Path

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.evaluation import heldout_errors_of_layouts, holdout_splits

    sample = Path(__file__).resolve().parents[1] / "sample_c3d" / "dense_halfface.c3d"
    if not sample.exists():
        pytest.skip("sample_c3d/dense_halfface.c3d not available")
    positions = read_c3d(sample).positions[::4].copy()
    rng = np.random.default_rng(2)
    layouts = [np.sort(rng.choice(positions.shape[1], n, replace=False)) for n in (20, 40)]
    positions[100:160, layouts[1][:2]] = np.nan  # lost layout markers, in training and test frames
    spare = np.setdiff1d(np.arange(positions.shape[1]), np.concatenate(layouts))[0]
    positions[rng.random(positions.shape[0]) < 0.6, spare] = np.nan  # a target mostly missing
    gappy = np.flatnonzero(~np.isfinite(positions).all(axis=(0, 2)))
    layouts.append(np.union1d(gappy, layouts[0][:10]))  # every frame with a gap loses one of these
    splits = holdout_splits(positions.shape[0], split="blocks", folds=4)
    many = list(heldout_errors_of_layouts(positions, layouts, splits))
    tested = list(heldout_errors_of_layouts(positions[:1000], layouts, [], test=positions[1000:]))
    for layout, errors, on_test in zip(layouts, many, tested):
        for got, expected in ((errors, heldout_errors(positions, layout, splits)),
                              (on_test, heldout_errors(positions[:1000], layout, [], test=positions[1000:]))):
            np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-8, equal_nan=True)
            assert np.nanmax(expected) > 1.0  # real errors, not a trivial fit
