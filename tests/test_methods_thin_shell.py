"""Thin-shell operators: cotangent Laplacian, mass matrix, operator and interpolation weights."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.errors import MocaptkError
from mocaptk.thin_shell import (cotangent_laplacian, interpolation_weights, mass_matrix,
                                thin_shell_operator)


def grid_mesh(n: int = 12, *, spacing: float = 5.0, jitter: float = 0.0, seed: int = 0):
    """A planar n×n vertex grid in mm (z = 0), two triangles per cell."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing, indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    interior = (xs.ravel() > 0) & (xs.ravel() < xs.max()) & (ys.ravel() > 0) & (ys.ravel() < ys.max())
    verts[interior, :2] += rng.uniform(-jitter, jitter, size=(interior.sum(), 2))
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces, idx


def sphere_mesh():
    import pyvista as pv
    mesh = pv.Sphere(radius=40.0, theta_resolution=24, phi_resolution=16).triangulate()
    return np.asarray(mesh.points, dtype=float), mesh.faces.reshape(-1, 4)[:, 1:]


def test_laplacian_matches_libigl_and_annihilates_constants():
    igl = pytest.importorskip("igl")
    verts, faces = sphere_mesh()
    lap = cotangent_laplacian(verts, faces)
    assert abs(lap - igl.cotmatrix(verts, faces)).max() < 1e-10
    assert np.abs(lap @ np.ones(len(verts))).max() < 1e-10
    assert abs(lap - lap.T).max() < 1e-12
    # negative semi-definite: xᵀLx ≤ 0 for random x
    x = np.random.default_rng(1).normal(size=len(verts))
    assert x @ (lap @ x) < 0


def test_mass_matrix_sums_to_surface_area_and_matches_libigl():
    igl = pytest.importorskip("igl")
    verts, faces, _ = grid_mesh(10, spacing=3.0, jitter=0.6)
    for kind, igl_kind in (("voronoi", igl.MASSMATRIX_TYPE_VORONOI),
                           ("barycentric", igl.MASSMATRIX_TYPE_BARYCENTRIC)):
        mass = mass_matrix(verts, faces, kind=kind)
        assert abs(mass - igl.massmatrix(verts, faces, igl_kind)).max() < 1e-9
        assert mass.diagonal().sum() == pytest.approx(27.0 * 27.0)
    with pytest.raises(MocaptkError):
        mass_matrix(verts, faces, kind="nope")


def test_operator_is_symmetric_psd_and_unit_free():
    verts, faces = sphere_mesh()
    op = thin_shell_operator(verts, faces)
    assert abs(op - op.T).max() < 1e-9
    assert np.abs(op @ np.ones(len(verts))).max() < 1e-9
    x = np.random.default_rng(2).normal(size=len(verts))
    assert x @ (op @ x) > 0
    # same operator in metres as in millimetres
    assert abs(thin_shell_operator(verts / 1000.0, faces) - op).max() < 1e-8 * abs(op).max()


def test_weights_interpolate_markers_and_rows_sum_to_one():
    verts, faces = sphere_mesh()
    markers = np.array([0, 17, 60, 130, 200, 251, 300])
    weights = interpolation_weights(thin_shell_operator(verts, faces), markers)
    assert weights.shape == (len(verts), len(markers))
    np.testing.assert_allclose(weights[markers], np.eye(len(markers)), atol=1e-12)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-9)
    # smooth, local interpolation: most vertices follow their nearest marker most
    nearest = np.argmin(np.linalg.norm(verts[:, None] - verts[markers][None], axis=2), axis=1)
    assert np.mean(np.argmax(weights, axis=1) == nearest) > 0.8


def test_linear_precision_on_a_plane():
    """With the boundary and its 1-ring pinned, a linear field is reproduced exactly."""
    verts, faces, idx = grid_mesh(12, jitter=0.0)
    ring = np.zeros_like(idx, dtype=bool)
    ring[:2], ring[-2:], ring[:, :2], ring[:, -2:] = True, True, True, True
    markers = np.concatenate([idx[ring], [idx[5, 6], idx[7, 4]]])
    weights = interpolation_weights(thin_shell_operator(verts, faces), markers)
    field = verts @ np.array([0.3, -1.7, 0.0]) + 2.5
    np.testing.assert_allclose(weights @ field[markers], field, atol=1e-8)


def test_weights_reject_bad_markers():
    verts, faces = sphere_mesh()
    op = thin_shell_operator(verts, faces)
    with pytest.raises(MocaptkError):
        interpolation_weights(op, [])
    with pytest.raises(MocaptkError):
        interpolation_weights(op, [3, 3])
    with pytest.raises(MocaptkError):
        interpolation_weights(op, [len(verts)])
