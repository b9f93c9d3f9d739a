"""Skin weights: thin-shell interpolation, region shaping, capping - on meshes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.errors import OptionError
from mocaptk.retarget.animate import skin_vertices, skinning_error
from mocaptk.retarget.influence import (anchor_vertices, edge_graph, geodesic_distance,
                                        main_influence_regions)
from mocaptk.retarget.weights import cap_weights, region_masks, shape_by_regions, thin_shell_weights
from mocaptk.surface_mesh import marker_surface_mesh


@pytest.fixture(scope="module")
def sheet():
    """A gently curved 15 x 12 sheet of vertices 5 mm apart, joints on a coarse sub-grid."""
    g = np.stack(np.meshgrid(np.arange(15.0), np.arange(12.0)), -1).reshape(-1, 2) * 5.0
    rng = np.random.default_rng(1)
    g += rng.normal(0, 0.4, g.shape)
    pts = np.column_stack([g, -0.004 * ((g - g.mean(axis=0)) ** 2).sum(axis=1)])
    vertices, faces = marker_surface_mesh(pts)
    joints = np.array([i for i in range(len(pts)) if (i % 15) % 4 == 1 and (i // 15) % 4 == 1])
    graph = edge_graph(vertices, faces)
    return vertices, faces, joints, graph


def test_thin_shell_weights_interpolate_and_partition_unity(sheet):
    vertices, faces, joints, graph = sheet
    w = thin_shell_weights(vertices, faces, joints, graph=graph)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(w[joints], np.eye(len(joints)), atol=1e-12)
    # a linear field is reproduced closely between the joints (smooth interpolant)
    field = vertices[:, :2] @ np.array([0.3, -0.2])
    lo, hi = vertices[joints, :2].min(axis=0), vertices[joints, :2].max(axis=0)
    inside = np.all((vertices[:, :2] >= lo) & (vertices[:, :2] <= hi), axis=1)
    assert np.abs(w @ field[joints] - field)[inside].max() < 0.05 * np.ptp(field)


def test_weights_are_smooth_between_markers(sheet):
    vertices, faces, joints, graph = sheet
    w = thin_shell_weights(vertices, faces, joints, graph=graph)
    edges = graph.tocoo()
    jump = np.abs(w[edges.row] - w[edges.col]).max()
    assert jump < 0.5  # neighbours 5 mm apart never switch joints abruptly


def test_region_shaping_keeps_markers_exact_and_limits_reach(sheet):
    vertices, faces, joints, graph = sheet
    members = [np.array([j]) for j in joints]
    regions = main_influence_regions(graph, members)
    assert np.all(regions[joints] == np.arange(len(joints)))
    w = thin_shell_weights(vertices, faces, joints, graph=graph)
    shaped = shape_by_regions(w, region_masks(graph, regions, len(joints), falloff_mm=6.0))
    np.testing.assert_allclose(shaped.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(shaped[joints], np.eye(len(joints)), atol=1e-12)
    assert shaped.min() >= 0
    # a joint has no weight farther than the falloff outside its region
    for j in range(len(joints)):
        dist = geodesic_distance(graph, np.flatnonzero(regions == j))
        assert np.all(shaped[dist > 6.0 + 1e-9, j] == 0)
    # inside its own region a vertex's own joint is the strongest
    own = shaped[np.arange(len(vertices)), regions]
    assert np.mean(own >= shaped.max(axis=1) - 1e-12) > 0.9


@pytest.mark.parametrize("k", [1, 4, 8])
def test_cap_weights_top_k_sum_one(sheet, k):
    vertices, faces, joints, graph = sheet
    w = thin_shell_weights(vertices, faces, joints, graph=graph)
    index, value = cap_weights(w, max_influences=k)
    assert index.shape == value.shape == (len(vertices), k)
    np.testing.assert_allclose(value.sum(axis=1), 1.0, atol=1e-12)
    assert np.all((value > 0).sum(axis=1) >= 1)
    assert np.all((value == 0) | (value >= 1e-3))
    assert np.all(index[joints, 0] == np.arange(len(joints))) and np.all(value[joints, 0] == 1)
    # the kept joints are the largest ones
    kept = np.take_along_axis(w, index, axis=1)[:, 0]
    np.testing.assert_allclose(kept, w.max(axis=1))


def test_cap_weights_fallback_and_bad_option():
    w = np.array([[0.0, 0.0, 0.0], [-0.2, 0.5, 0.7], [0.0005, 0.0002, 0.0]])
    index, value = cap_weights(w, max_influences=2, fallback=np.array([2, 0, 1]))
    assert index[0, 0] == 2 and value[0, 0] == 1.0  # nothing positive: fallback joint
    np.testing.assert_allclose(value[1], [0.7 / 1.2, 0.5 / 1.2])
    assert index[2, 0] == 1 and value[2, 0] == 1.0  # all below 1e-3: fallback
    with pytest.raises(OptionError):
        cap_weights(w, max_influences=0)


def test_parts_without_joints_follow_the_nearest_joint(sheet):
    vertices, faces, joints, _ = sheet
    island = vertices[:3] + np.array([0.0, -30.0, 0.0])
    v2 = np.vstack([vertices, island])
    f2 = np.vstack([faces, [[len(vertices), len(vertices) + 1, len(vertices) + 2]]])
    w = thin_shell_weights(v2, f2, joints, graph=edge_graph(v2, f2))
    assert np.all(w[len(vertices):].max(axis=1) == 1.0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)


def test_anchor_vertices_and_skinning_translation(sheet):
    vertices, faces, joints, _ = sheet
    idx, dist = anchor_vertices(vertices, faces, vertices[joints] + [0.1, -0.1, 0.5])
    assert np.array_equal(idx, joints) and np.all(dist < 0.6)
    index, value = cap_weights(np.full((len(vertices), 3), 1 / 3), max_influences=4)
    disp = np.tile(np.array([1.0, 2.0, 3.0]), (5, 3, 1))  # every joint moves the same
    moved = skin_vertices(vertices, index, value, disp)
    np.testing.assert_allclose(moved - vertices, np.broadcast_to([1.0, 2.0, 3.0], moved.shape))
    err = skinning_error(moved, moved + [0.0, 0.0, 2.0])
    assert err.rmse_mm == pytest.approx(2.0) and err.frames == 5
