"""Property tests (hypothesis, bounded example counts): clustering partitions markers for any valid
correlation matrix and reassignment never lowers a member's correlation to its representative; rig
weights stay normalized after capping; triangulation does not depend on camera order; every marker
writer's output reads back as the same session.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mocaptk import Take, Trajectories
from mocaptk.acquisition.cameras import FACE_CENTER_MM, CameraRig, cara_rig
from mocaptk.acquisition.formats import read_trajectories, write_trajectories
from mocaptk.acquisition.projection import project_markers
from mocaptk.acquisition.triangulate import triangulate
from mocaptk.clustering.threshold import cluster_region
from mocaptk.retarget.weights import cap_weights

FAST = settings(max_examples=40, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


@st.composite
def correlation_matrices(draw) -> tuple[np.ndarray, np.ndarray]:
    """A valid correlation matrix (symmetric PSD, unit diagonal; from random signals, possibly
    with identical or anti-correlated markers) and displacements with ties."""
    n = draw(st.integers(1, 12))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    signals = rng.normal(size=(draw(st.integers(2, 4)), 30))
    mix = rng.normal(size=(n, signals.shape[0]))
    if draw(st.booleans()):
        mix[rng.integers(n)] = mix[0]  # two markers moving identically
    if draw(st.booleans()):
        mix[rng.integers(n)] = -mix[0]
    data = mix @ signals + 1e-3 * rng.normal(size=(n, 30))
    matrix = np.corrcoef(data) if n > 1 else np.ones((1, 1))
    displacement = rng.integers(1, 4, size=n).astype(float)  # ties on purpose
    return matrix, displacement


@FAST
@given(correlation_matrices(), st.floats(0.3, 2.5))
def test_clusters_partition_markers_and_reassignment_never_lowers_correlation(data, factor):
    matrix, displacement = data
    n = len(matrix)
    result = cluster_region(matrix, displacement, factor=factor)
    reps = result.representatives
    # a partition: every marker in exactly one cluster, each cluster has its representative
    assert result.assignment.shape == (n,)
    assert np.all((0 <= result.assignment) & (result.assignment < len(reps)))
    assert len(set(reps.tolist())) == len(reps)
    assert np.array_equal(result.assignment[reps], np.arange(len(reps)))
    members = np.bincount(result.assignment, minlength=len(reps))
    assert members.sum() == n and np.all(members >= 1)
    # reassignment: a member's correlation to its representative never drops, and is the best
    before = matrix[reps[result.first_assignment], np.arange(n)]
    after = matrix[reps[result.assignment], np.arange(n)]
    assert np.all(after >= before - 1e-12)
    non_reps = np.setdiff1d(np.arange(n), reps)
    if non_reps.size:
        best = matrix[np.ix_(reps, non_reps)].max(axis=0)
        assert np.allclose(after[non_reps], best)
    assert np.array_equal(result.member_correlation, after)


@FAST
@given(st.integers(1, 30), st.integers(1, 9), st.integers(1, 8), st.integers(0, 2**32 - 1),
       st.sampled_from(["dense", "sparse", "tiny"]))
def test_capped_weights_are_normalized(n_vertices, n_joints, max_influences, seed, kind):
    rng = np.random.default_rng(seed)
    weights = rng.random((n_vertices, n_joints))
    if kind == "sparse":
        weights[weights < 0.7] = 0.0
    elif kind == "tiny":
        weights *= 1e-4  # everything under min_weight: the fallback joint takes the vertex
    index, value = cap_weights(weights, max_influences=max_influences)
    assert index.shape == value.shape == (n_vertices, max_influences)
    assert np.allclose(value.sum(axis=1), 1.0)
    assert np.all(value >= 0) and np.all((value == 0) | (value >= 1e-3))
    assert np.all((index >= 0) & (index < n_joints))
    assert np.all(np.diff(value, axis=1) <= 1e-12)  # strongest first
    used = value > 0
    for row in range(n_vertices):  # no joint twice in a row
        assert len(set(index[row, used[row]].tolist())) == used[row].sum()


@pytest.fixture(scope="module")
def capture():
    """A Cara rig and 2-D detections of face-like points (noise, dropouts)."""
    rig = cara_rig()
    rng = np.random.default_rng(4)
    points = rng.normal(FACE_CENTER_MM, [40.0, 50.0, 15.0], (3, 25, 3))
    obs = project_markers(rig, points, pixel_noise=0.5, dropout=0.1, rng=5)
    return rig, obs


@FAST
@given(st.permutations(range(4)))
def test_triangulation_does_not_depend_on_camera_order(capture, order):
    rig, obs = capture
    base = triangulate(rig, obs, rate=60.0)
    assert np.isfinite(base.positions).all(axis=2).mean() > 0.8
    shuffled = CameraRig(tuple(rig.cameras[i] for i in order), name=rig.name, rate=rig.rate)
    again = triangulate(shuffled, obs[list(order)], rate=60.0)
    np.testing.assert_allclose(again.positions, base.positions, rtol=0, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(again.residuals, base.residuals, rtol=0, atol=1e-6, equal_nan=True)
    assert np.array_equal(again.metadata["view_counts"], base.metadata["view_counts"])


LABEL = st.text(alphabet=st.sampled_from("ABCXYZabcxyz0123456789_"), min_size=1, max_size=8)


@st.composite
def sessions(draw) -> Trajectories:
    """Small sessions: any labels, gaps, rates, first frames, takes; mm values of any sign."""
    n_frames = draw(st.integers(2, 12))
    labels = draw(st.lists(LABEL, min_size=1, max_size=5, unique=True))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    positions = rng.normal(0, 10 ** draw(st.integers(0, 3)), (n_frames, len(labels), 3))
    positions[rng.random((n_frames, len(labels))) < 0.2] = np.nan
    rate = draw(st.sampled_from([50.0, 60.0, 100.0, 119.88, 240.0]))
    first = draw(st.integers(0, 5000))
    takes = []
    if draw(st.booleans()) and n_frames >= 4:
        cut = draw(st.integers(1, n_frames - 1))
        takes = [Take("first", 0, cut, "mouth"), Take("second", cut, n_frames, None)]
    return Trajectories(positions, labels, rate, first_frame=first, metadata={"takes": takes})


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(sessions(), st.sampled_from([".c3d", ".csv", ".trc"]))
def test_reader_of_writer_is_identity(tmp_path_factory, traj, suffix):
    path = tmp_path_factory.mktemp("rw") / f"s{suffix}"
    write_trajectories(traj, path)
    back = read_trajectories(path)
    assert back.labels == traj.labels
    assert back.n_frames == traj.n_frames and back.first_frame == traj.first_frame
    assert back.rate == pytest.approx(traj.rate, rel=1e-6)
    assert np.array_equal(np.isnan(back.positions), np.isnan(traj.positions))
    # text: 10 significant digits; C3D: float32
    rel = 2e-7 if suffix == ".c3d" else 1e-9
    scale = np.nanmax(np.abs(traj.positions), initial=1.0)
    np.testing.assert_allclose(back.positions, traj.positions, rtol=rel, atol=rel * scale, equal_nan=True)
    if suffix != ".trc":  # TRC has no place for takes
        assert back.takes == traj.takes
