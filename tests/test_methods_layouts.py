"""Layout methods: registry, reconstruction-aware selection, the paper wrapper, hybrid."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.clustering.evaluation import error_summary, heldout_errors, holdout_splits
from mocaptk.clustering.methods import LayoutProblem, method_names, select_layout
from mocaptk.clustering.methods.reconstruction import (CrossValidatedError, greedy_layout,
                                                       pivoted_qr_layout, swap_refine)
from mocaptk.errors import OptionError
from mocaptk.trajectories import Take


def driven_problem(*, n_points: int = 40, drivers: int = 5, frames: int = 320, noise: float = 0.05,
                   seed: int = 0) -> tuple[LayoutProblem, np.ndarray]:
    """Points on a 10 cm patch; every point moves as a linear mix of a few 'driver' points.

    Returns the problem (4 takes) and the driver indices (the ground-truth best layout).
    """
    rng = np.random.default_rng(seed)
    neutral = np.column_stack([rng.uniform(-50, 50, n_points), rng.uniform(-50, 50, n_points),
                               np.zeros(n_points)])
    t = np.linspace(0, 20, frames)
    driver_idx = np.sort(rng.choice(n_points, drivers, replace=False))
    motion = np.zeros((frames, n_points, 3))
    for k, d in enumerate(driver_idx):
        motion[:, d] = np.stack([np.sin((k + 1) * 0.7 * t + a) * (3 + k) for a in (0.0, 1.0, 2.0)], axis=1)
    others = np.setdiff1d(np.arange(n_points), driver_idx)
    for p in others:
        mix = rng.normal(size=(drivers, 3, 3)) * 0.4
        motion[:, p] = np.einsum("fkc,kcd->fd", motion[:, driver_idx], mix)
    motion += rng.normal(scale=noise, size=motion.shape)
    segments = tuple((i * frames // 4, (i + 1) * frames // 4) for i in range(4))
    return LayoutProblem(motion, neutral, segments=segments), driver_idx


def test_registry_names_and_bad_input():
    names = method_names()
    assert names[0] == "paper"
    for name in ("random", "farthest-point", "kmeans", "qr", "greedy", "thin-shell", "set-cover", "hybrid"):
        assert name in names
    problem, _ = driven_problem()
    with pytest.raises(OptionError, match="unknown layout method"):
        select_layout(problem, 5, method="nope")
    with pytest.raises(OptionError, match="between 1 and 40"):
        select_layout(problem, 41, method="qr")


@pytest.mark.parametrize("method", ["random", "farthest-point", "kmeans", "qr", "greedy", "paper", "hybrid"])
def test_every_method_returns_count_distinct_sorted_points(method):
    problem, _ = driven_problem()
    result = select_layout(problem, 7, method=method, seed=3)
    assert result.layout.size == 7
    assert np.array_equal(result.layout, np.unique(result.layout))
    assert result.layout.min() >= 0 and result.layout.max() < problem.n_points
    assert result.method == method and result.seconds >= 0


def test_cross_validated_error_matches_the_team_evaluation():
    problem, _ = driven_problem(noise=0.3)
    disp = problem.displacements
    takes = [Take(f"t{i}", a, b) for i, (a, b) in enumerate(problem.segments)]
    splits = holdout_splits(problem.n_frames, takes, split="takes")
    scorer = CrossValidatedError.from_displacements(disp, splits)
    positions = problem.positions
    for layout in ([0, 5, 9, 17], [1, 2, 3, 30, 31, 38]):
        expected = error_summary(heldout_errors(positions, layout, splits))["rmse_mm"]
        assert scorer.rmse(layout) == pytest.approx(expected, rel=1e-9)


def test_reconstruction_aware_layouts_find_the_drivers():
    problem, drivers = driven_problem()
    takes = [Take(f"t{i}", a, b) for i, (a, b) in enumerate(problem.segments)]
    scorer = CrossValidatedError.from_displacements(
        problem.displacements, holdout_splits(problem.n_frames, takes, split="takes"))
    truth = scorer.rmse(drivers)
    random_scores = [scorer.rmse(np.random.default_rng(s).choice(40, 5, replace=False)) for s in range(20)]
    for layout in (greedy_layout(problem, 5), pivoted_qr_layout(problem, 5)):
        # any 5 points span the drivers' motion up to noise, so all land near the truth; the
        # reconstruction-aware ones must be at least as good as the median random layout
        assert scorer.rmse(layout) <= np.median(random_scores) + 1e-9
        assert scorer.rmse(layout) < 5 * truth
    refined, cv = swap_refine(problem, greedy_layout(problem, 5))
    assert cv <= scorer.rmse(greedy_layout(problem, 5)) + 1e-12
    assert refined.size == 5


def test_greedy_keeps_fixed_points():
    problem, _ = driven_problem()
    layout = greedy_layout(problem, 6, fixed=[0, 1])
    assert {0, 1} <= set(layout.tolist()) and layout.size == 6


def test_greedy_and_qr_of_several_counts_are_each_counts_own_selection():
    # the pick orders are kept per problem and extended: counts in any order, then fixed points,
    # give what a problem of their own gives
    problem, _ = driven_problem(noise=0.3)
    for count, fixed in ((12, ()), (4, ()), (7, ()), (20, ()), (6, (0, 1)), (9, (0, 1)), (3, (5,))):
        fresh, _ = driven_problem(noise=0.3)
        assert np.array_equal(greedy_layout(problem, count, fixed=fixed), greedy_layout(fresh, count, fixed=fixed))
        if not fixed:
            assert np.array_equal(pivoted_qr_layout(problem, count), pivoted_qr_layout(fresh, count))


def test_paper_factor_bisection_hits_the_count():
    from mocaptk.clustering.methods.paper import paper_layout
    problem, _ = driven_problem()
    sizes = []
    for count in (4, 8, 15):
        result = paper_layout(problem, count)
        assert result.layout.size == count
        sizes.append(result.factor)
    assert sizes == sorted(sizes)  # more markers need a larger refinement factor
    with pytest.raises(OptionError):
        paper_layout(problem, 0)


def test_hybrid_reports_its_contenders():
    problem, _ = driven_problem()
    result = select_layout(problem, 8, method="hybrid")
    scores = result.details["local_rmse_mm"]
    assert set(scores) == {"clusters", "thin-shell", "qr", "greedy", "kmeans",
                           "thin-shell+local", "kmeans+local"}
    assert scores[result.details["winner"]] == min(scores.values())


def test_cluster_cli_method_option_keeps_the_papers_marker_count(tmp_path, run_cli):
    import json

    from mocaptk.acquisition.formats import write_trajectories
    from mocaptk.trajectories import Trajectories

    problem, _ = driven_problem(n_points=30)
    labels = [f"{'MOUTH' if i % 2 else 'CHEEK'}_{i:02d}_L" for i in range(30)]
    takes = [Take(f"t{i}", a, b) for i, (a, b) in enumerate(problem.segments)]
    session = write_trajectories(Trajectories(problem.positions, labels, 60.0, metadata={"takes": takes}),
                                 tmp_path / "s.c3d")
    counts = {}
    for method in ("paper", "qr"):
        out = tmp_path / method
        result = run_cli("cluster", session, "--method", method, "--no-stabilize", "--no-mirror",
                         "--formats", "none", "--out", out, "--quiet")
        assert result.exit_code == 0, result.stderr
        layout = json.loads((out / "layout.json").read_text())
        assert layout["parameters"]["method"] == method
        counts[method] = len(layout["layout"])
        members = [m for c in layout["clusters"] for m in c["members"]]
        assert sorted(members) == sorted(labels)  # every marker has one influence region
    assert counts["qr"] == counts["paper"]
    bad = run_cli("cluster", session, "--method", "magic", "--out", tmp_path / "bad")
    assert bad.exit_code == 2 and "unknown --method" in bad.stderr
