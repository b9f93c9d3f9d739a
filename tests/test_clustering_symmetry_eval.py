"""Mirroring across the sagittal plane; baseline layouts and held-out reconstruction."""

from __future__ import annotations

import numpy as np
import pytest
from clustering_synthetic import planted_session

from mocaptk import OptionError
from mocaptk.clustering.baselines import farthest_point_layout, kmeans_layout, random_layout
from mocaptk.clustering.evaluation import (
    error_summary, evaluate_layout, fit_reconstruction, heldout_errors, holdout_splits, reconstruction_errors,
)
from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
from mocaptk.clustering.symmetry import (
    SagittalPlane, fit_sagittal_plane, is_half_capture, mirror_label, side_tag,
)


@pytest.fixture(scope="module")
def mirrored_layout():
    traj, _ = planted_session(seed=11)
    return traj, cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False))


def test_half_capture_is_detected_and_mirrored_symmetrically(mirrored_layout):
    traj, result = mirrored_layout
    layout = result.layout
    assert is_half_capture(traj.labels) and layout.parameters["mirror"] is True
    plane = SagittalPlane(np.array(layout.extra["sagittal_plane"]["point"]),
                          np.array(layout.extra["sagittal_plane"]["normal"]))
    assert abs(plane.normal @ [1.0, 0.0, 0.0]) == pytest.approx(1.0, abs=1e-6)  # midline markers at x = 0
    by_label = {c.representative: c for c in layout.clusters}
    originals = [c for c in layout.clusters if c.mirrored_from is None]
    mirrored = [c for c in layout.clusters if c.mirrored_from is not None]
    assert len(mirrored) == sum(c.side != "C" for c in originals)
    for copy in mirrored:
        source = by_label[copy.mirrored_from]
        assert copy.representative == mirror_label(source.representative)
        assert {copy.side, source.side} == {"L", "R"} and side_tag(copy.representative) == copy.side
        assert np.allclose(plane.mirror(np.array(copy.position)), source.position)  # reflection
        assert plane.signed_distance(np.array(copy.position)) == pytest.approx(
            -plane.signed_distance(np.array(source.position)))
        assert copy.region == source.region
        assert all(side_tag(m) == copy.side for m in copy.members)  # midline members stay put
        assert [mirror_label(m) for m in source.members if side_tag(m) != "C"] == list(copy.members)


def test_no_mirror_and_full_faces_are_left_alone(mirrored_layout):
    traj, _ = mirrored_layout
    plain = cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False, mirror=False)).layout
    assert all(c.mirrored_from is None for c in plain.clusters)
    assert not is_half_capture(["A_01_L", "A_01_R", "A_02_C"])
    assert mirror_label("NOSE_02_L") == "NOSE_02_R" and mirror_label("X7") == "X7_mirror"


def test_sagittal_plane_fit_and_collinear_midline():
    rng = np.random.default_rng(12)
    normal = np.array([0.96, 0.2, 0.2]) / np.linalg.norm([0.96, 0.2, 0.2])
    basis = np.linalg.svd(normal[None])[2][1:]  # two in-plane directions
    pts = rng.normal(size=(10, 2)) * 30 @ basis + 5.0
    plane = fit_sagittal_plane(pts, np.array([1.0, 0, 0]))
    assert plane.normal @ normal == pytest.approx(1.0, abs=1e-9)
    line = np.outer(np.linspace(-50, 50, 6), [0, 1.0, 0])
    plane = fit_sagittal_plane(line, np.array([1.0, 0.1, 0]))
    assert np.allclose(plane.normal, [1, 0, 0])
    with pytest.raises(OptionError):
        fit_sagittal_plane(line[:1], np.array([1.0, 0, 0]))


def test_baselines_have_the_requested_size_and_are_deterministic():
    rng = np.random.default_rng(13)
    neutral = rng.normal(size=(40, 3)) * 30
    a = random_layout(40, 7, seed=1)
    assert a.size == 7 and np.unique(a).size == 7 and np.array_equal(a, random_layout(40, 7, seed=1))
    fps = farthest_point_layout(neutral, 5)
    assert fps.size == 5 and np.unique(fps).size == 5
    dist = np.linalg.norm(neutral - neutral.mean(axis=0), axis=1)
    assert int(np.argmax(dist)) in fps
    with pytest.raises(OptionError):
        random_layout(5, 6, seed=0)


def test_kmeans_layout_picks_one_marker_per_planted_group():
    traj, group_of = planted_session(seed=14, takes=False)
    disp = traj.positions - np.median(traj.positions, axis=0)
    idx = kmeans_layout(disp, len(set(group_of.values())), seed=0)
    assert sorted(group_of[traj.labels[i]] for i in idx) == sorted(set(group_of.values()))


def test_kmeans_two_member_tie_goes_to_the_member_that_moves_most():
    # two pairs of markers, each pair's members exactly equidistant from its mean: which one is
    # kept must not depend on a BLAS kernel's rounding (it did: CPU-dependent layouts)
    rng = np.random.default_rng(3)
    base = rng.normal(size=(2, 6841, 3)) * 5.0
    spread = rng.normal(size=(2, 6841, 3)) * 0.2
    disp = np.stack([base[0] + spread[0], base[0] - 1.05 * spread[0],
                     base[1] - 1.1 * spread[1], base[1] + spread[1]], axis=1)
    energy = (disp ** 2).sum(axis=(0, 2))
    expected = [int(np.argmax(energy[:2])), 2 + int(np.argmax(energy[2:]))]
    assert kmeans_layout(disp, 2, seed=0).tolist() == expected
    assert kmeans_layout(disp[:, ::-1], 2, seed=0).tolist() == [3 - i for i in expected[::-1]]



@pytest.mark.parametrize("tile_values", [1, 1000, None])
def test_kmeans_gaps_count_as_rest_in_any_tiles(monkeypatch, tile_values):
    """Gaps are 0 displacement whatever the feature tiles (1 frame, a few, the default)."""
    from mocaptk.clustering import baselines

    traj, _ = planted_session(seed=16, takes=False)
    disp = traj.positions - np.median(traj.positions, axis=0)
    gappy = disp.copy()
    gappy[np.random.default_rng(4).random(disp.shape[:2]) < 0.05] = np.nan
    filled = np.nan_to_num(gappy, nan=0.0)
    expected = kmeans_layout(filled, 6, seed=1)
    if tile_values is not None:
        monkeypatch.setattr(baselines, "FEATURE_TILE_VALUES", tile_values)
    assert kmeans_layout(gappy, 6, seed=1).tolist() == expected.tolist()
    assert np.isnan(gappy).any()  # the caller's array is left as it was


def test_reconstruction_is_exact_for_linear_data_and_handles_gaps():
    rng = np.random.default_rng(15)
    drivers = rng.normal(size=(300, 3, 3)).cumsum(axis=0)
    mix = rng.normal(size=(3, 12))
    pos = np.einsum("fka,km->fma", drivers, mix) + rng.normal(size=(12, 3)) * 40  # linear in 3 markers
    model = fit_reconstruction(pos[:200], [0, 1, 2], ridge=0.0)
    err = reconstruction_errors(model, pos[200:])
    assert np.nanmax(err) < 1e-6
    gappy = pos.copy()
    gappy[rng.random((300, 12)) < 0.1] = np.nan
    err = reconstruction_errors(fit_reconstruction(gappy[:200], [0, 1, 2, 3], ridge=0.0), gappy[200:])
    truth_missing = np.isnan(gappy[200:]).any(axis=2)
    assert np.all(np.isnan(err[truth_missing]))
    enough = np.isfinite(gappy[200:, :4, 0]).sum(axis=1) >= 3  # 3 markers determine the 3 drivers
    assert (~enough).any() and (enough & np.isnan(gappy[200:, :4, 0]).any(axis=1)).any()
    assert np.nanmax(err[enough]) < 1e-6  # frames missing a layout marker use the ones present
    summary = error_summary(err[enough], regions={"a": [0, 1], "b": [5]})
    assert summary["rmse_mm"] < 1e-6 and set(summary["regions"]) == {"a", "b"}


def test_holdout_splits_cover_every_take():
    from mocaptk import Take

    splits = holdout_splits(100, [Take("a", 0, 50), Take("b", 50, 100)], folds=5)
    assert len(splits) == 5
    tested = np.concatenate([test for _, test in splits])
    assert np.array_equal(np.sort(tested), np.arange(100))
    for train, test in splits:
        assert np.intersect1d(train, test).size == 0
        assert (test < 50).any() and (test >= 50).any()
    assert len(holdout_splits(100, [Take("a", 0, 50), Take("b", 50, 100)], split="takes")) == 2
    with pytest.raises(OptionError):
        holdout_splits(100, [], split="takes")


def test_evaluate_layout_reports_baselines_of_equal_size(mirrored_layout):
    traj, result = mirrored_layout
    index = {label: i for i, label in enumerate(traj.labels)}
    idx = [index[c.representative] for c in result.layout.clusters if c.mirrored_from is None]
    out = evaluate_layout(traj.positions, idx, takes=traj.takes, n_random=3, regions={"all": range(traj.n_markers)})
    methods = out["methods"]
    assert set(methods) == {"layout", "random", "farthest-point", "kmeans"}
    assert all(m["count"] == len(idx) for m in methods.values())
    assert methods["random"]["layouts"] == 3 and "rmse_sd_mm" in methods["random"]
    # the planted layout (one marker per driving signal) reconstructs far better than random
    assert methods["layout"]["rmse_mm"] < 0.5 * methods["random"]["rmse_mm"]
    errors = heldout_errors(traj.positions, idx, holdout_splits(traj.n_frames, traj.takes))
    assert np.isfinite(errors).all()
