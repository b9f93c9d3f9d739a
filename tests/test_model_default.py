"""The default solve model on data our code did not make: never more than 2 % worse than plain
ridge (issue #27; the whole bed: benchmarks/bench_model_choice.py, docs/testbed.md)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mocaptk.clustering.baselines import kmeans_layout
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.clustering.reconstruction_models import CV_RIDGES, DEFAULT_KIND, fit_model

from conftest import REPO, shared_path

TOLERANCE = 1.02


def _outside_rmse(model, test: np.ndarray, truth: np.ndarray) -> float:
    """RMSE (mm) over the dense markers outside the layout, held-out frames."""
    pred = model.predict(test[:, model.layout]).positions
    outside = np.setdiff1d(np.arange(truth.shape[1]), model.layout)
    err = np.sum((pred[:, outside] - truth[:, outside]) ** 2, axis=2)
    return float(np.sqrt(np.nanmean(err)))


def _layout(train: np.ndarray, count: int) -> np.ndarray:
    return np.unique(kmeans_layout(train[::5] - neutral_pose(train)[None], count, seed=0))


@pytest.fixture(scope="module")
def independent():
    """A half face (60 markers) of the independent generator: ROM -> 20 s held-out performance."""
    tarball = shared_path("face_mesh", "ict_facekit", "ict_facekit_FaceXModel_subset.tar.xz")
    sys.path.insert(0, str(REPO / "benchmarks"))
    from testbed import load_ict, make_actor, performance_session, rom_session

    face = load_ict(tarball)
    actor = make_actor(face, identity_seed=11, count=60, half=True, marker_seed=5)
    rom = rom_session(face, actor, seed=1)
    perf = performance_session(face, actor, seed=2, seconds=20.0)
    return rom.capture.positions, perf.capture.positions, perf.truth


def test_default_is_within_2_percent_of_ridge_on_the_independent_generator(independent):
    train, test, truth = independent
    layout = _layout(train, 20)
    ridge = _outside_rmse(fit_model(train, layout, kind="ridge", expected_error=False), test, truth)
    default = _outside_rmse(fit_model(train, layout, kind=DEFAULT_KIND, expected_error=False), test, truth)
    assert default <= TOLERANCE * ridge, (default, ridge)
    assert 0.05 < ridge < 1.0  # mm: a real solve, not a degenerate one


def test_default_is_within_2_percent_of_ridge_on_real_blenderface_leave_one_take_out():
    from mocaptk.clustering.pipeline import load_session

    traj, _ = load_session(str(shared_path("facial_mocap", "blenderface", "Subject_01.csv")), rate=25,
                           units="187.6")
    layout = _layout(traj.positions, 6)
    scores = {}
    for kind in ("ridge", DEFAULT_KIND):
        squared, count = 0.0, 0
        for take in traj.takes:  # leave one take out, scored on the measured markers
            held = np.zeros(traj.n_frames, dtype=bool)
            held[take.start:take.end] = True
            model = fit_model(traj.positions[~held], layout, kind=kind, expected_error=False)
            rmse = _outside_rmse(model, traj.positions[held], traj.positions[held])
            points = np.isfinite(traj.positions[held][:, np.setdiff1d(np.arange(traj.n_markers), layout), 0]).sum()
            squared, count = squared + rmse ** 2 * points, count + points
        scores[kind] = np.sqrt(squared / count)
    assert scores[DEFAULT_KIND] <= TOLERANCE * scores["ridge"], scores


def test_ridge_cv_chooses_its_strength_on_the_training_frames(independent):
    train, _, _ = independent
    model = fit_model(train, _layout(train, 20), kind="ridge-cv", expected_error=False)
    assert model.ridge == CV_RIDGES[int(np.argmin(model.cv_rmse_mm))]
    assert model.cv_rmse_mm.shape == (len(CV_RIDGES),) and np.all(np.isfinite(model.cv_rmse_mm))
    # the scores are a real choice: the strengths tried do not all score alike
    assert model.cv_rmse_mm.max() > 1.05 * model.cv_rmse_mm.min()
