"""The ICT-FaceKit template fitted to dense markers: placed right, refused off a face, also past
MAX_FIT_POINTS markers (where the ICP fits an even subset and the residual is over all)."""

from __future__ import annotations

import numpy as np

from mocaptk.retarget.face_template import MAX_FIT_POINTS, fit_template, template_face
from mocaptk.surface_mesh import marker_spacing


def _dense_face(count: int, *, seed: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
    """``count`` noisy markers on the template's front scaled 1.1 and moved: (points, scale, shift)."""
    face, _ = template_face()
    rng = np.random.default_rng(seed)
    front = face[face[:, 2] > np.percentile(face[:, 2], 20)]
    shift = np.array([3.0, -2.0, 5.0])
    points = front[rng.choice(len(front), count, replace=False)] * 1.1 + shift
    return points + rng.normal(scale=0.2, size=points.shape), 1.1, shift


def test_many_markers_place_the_template_where_the_face_is():
    points, scale, shift = _dense_face(3 * MAX_FIT_POINTS)
    fitted = fit_template(points, spacing=marker_spacing(points))
    assert fitted is not None
    face, _ = template_face()
    error = np.linalg.norm(fitted.vertices - (face * scale + shift), axis=1)
    assert np.sqrt(np.mean(error ** 2)) < 0.3  # mm; the markers' noise is 0.2 mm per axis


def test_the_residual_counts_every_marker_not_only_the_fitted_ones():
    """Every marker the even subset skips sits 20 mm off the face: refused."""
    points, _, _ = _dense_face(3 * MAX_FIT_POINTS)
    fitted = np.linspace(0, len(points) - 1, MAX_FIT_POINTS).round().astype(int)
    off = np.setdiff1d(np.arange(len(points)), fitted)
    points[off, 2] += 20.0
    spacing = marker_spacing(points[fitted])
    assert fit_template(points[fitted], spacing=spacing) is not None  # the subset alone fits
    assert fit_template(points, spacing=spacing) is None
