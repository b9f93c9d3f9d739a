"""The layout markers' outlier test has one home (`retarget.consistency.outlier_threshold`): the
capture screen and the solve's measured error on the stabilization markers use the same rule."""

from __future__ import annotations

import numpy as np
from conftest import SAMPLES

from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.retarget.consistency import (OUTLIER_FLOOR_MM, LayoutGaussian, capture_screen, outlier_threshold,
                                          stabilization_residuals)

GHOST_MM = 40.0


def sample_markers(count: int) -> np.ndarray:
    """(frames, count, 3) mm: every 15th marker of the bundled sample, from the first."""
    return read_c3d(SAMPLES / "dense_halfface.c3d").positions[:, ::15][:, :count]


def test_the_capture_screen_and_the_measured_error_share_one_outlier_rule():
    x = sample_markers(8)
    half = len(x) // 2
    gauss = LayoutGaussian.fit(x[:half])
    capture = x[half:].copy()
    capture[100, 3] += GHOST_MM  # a ghost: drawn 40 mm off
    capture[:, 5] = np.nan  # a marker never seen
    screen = capture_screen(gauss, capture, training_mm=1.0)
    median, threshold = outlier_threshold(gauss.loo_residuals(capture))
    np.testing.assert_array_equal(screen.median, median)
    np.testing.assert_array_equal(screen.threshold_mm, threshold)
    assert threshold[5] == OUTLIER_FLOOR_MM and not median[5].any()

    # the solve's error on markers it did not see: a frame later stands in for the solve (real motion)
    solved, captured = x[1:, :3], x[:-1, :3].copy()
    captured[200, 1] += GHOST_MM
    distance = stabilization_residuals(solved, captured)
    r = solved - captured
    median, threshold = outlier_threshold(r)
    dropped = np.linalg.norm(r - median, axis=2) > threshold
    assert dropped[200, 1] and dropped.sum() < 0.01 * dropped.size
    np.testing.assert_array_equal(np.isnan(distance), dropped | np.isnan(r).any(axis=2))
