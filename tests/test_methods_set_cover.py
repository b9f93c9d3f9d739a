"""Blendshape set cover (Zell & McDonnell): certified-optimal ILP, cover constraints, statistics."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mocaptk.clustering.methods import LayoutProblem, select_layout
from mocaptk.clustering.methods.set_cover import (cover_costs, facing_direction, layout_statistics,
                                                  problem_visibility, relative_displacement,
                                                  representative_shapes, set_cover_layout, solve_cover,
                                                  visibility)
from mocaptk.surface_mesh import marker_spacing, vertex_normals

from conftest import SAMPLES


def bump_model(n: int = 9, shapes: int = 7, seed: int = 0):
    """A flat n×n patch (mm) with ``shapes`` blendshapes, each a smooth bump at a random spot."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(-40, 40, n), np.linspace(-40, 40, n), indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    centres = rng.uniform(-35, 35, size=(shapes, 2))
    widths = rng.uniform(8, 20, size=shapes)
    deltas = np.zeros((shapes, n * n, 3))
    for k in range(shapes):
        g = np.exp(-np.sum((verts[:, :2] - centres[k]) ** 2, axis=1) / (2 * widths[k] ** 2))
        deltas[k, :, 2] = 6.0 * g
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces, deltas


def test_ilp_is_certified_optimal_and_covers_every_shape():
    verts, _, deltas = bump_model(n=5, shapes=6)
    rel = relative_displacement(deltas)
    candidate = rel >= 0.5
    costs = cover_costs(rel, candidate, None)
    solution = solve_cover(candidate, costs)
    assert solution.status == "Optimal"
    assert candidate[solution.chosen].any(axis=0).all()  # every cover constraint holds
    # brute force over all subsets of the 25 points up to the solution's size + 1
    best = np.inf
    useful = np.flatnonzero(candidate.any(axis=1))
    for size in range(1, solution.chosen.size + 2):
        for subset in itertools.combinations(useful, size):
            if candidate[list(subset)].any(axis=0).all():
                best = min(best, costs[list(subset)].sum())
    assert solution.objective == pytest.approx(best)


def test_multi_cover_reaches_the_count_and_statistics():
    verts, faces, deltas = bump_model()
    problem = LayoutProblem(deltas, verts, faces=faces)
    minimal = set_cover_layout(problem, epsilon=0.7)
    assert minimal.status == ["Optimal"]
    rel = relative_displacement(deltas)
    assert (rel[minimal.layout] >= 0.7).any(axis=0).all()
    stats = layout_statistics(deltas, minimal.layout)
    assert stats["0.7"]["unseen_shapes"] == 0
    assert stats["0.3"]["idle_markers_percent"] == 0.0
    result = select_layout(problem, 15, method="set-cover", epsilon=0.3)
    assert result.layout.size == 15
    assert all(s == "Optimal" for s in result.details["status"])
    # a random layout of the same size typically leaves shapes unseen at ε = 0.7
    random_unseen = [layout_statistics(deltas, np.random.default_rng(s).choice(81, 3, replace=False))
                     ["0.7"]["unseen_shapes"] for s in range(10)]
    assert max(random_unseen) > 0


def test_symmetric_cover_is_mirror_closed():
    verts, faces, deltas = bump_model()
    mirror = np.array([int(np.argmin(np.linalg.norm(verts - v * [-1, 1, 1], axis=1))) for v in verts])
    problem = LayoutProblem(deltas, verts, faces=faces, mirror=mirror)
    result = set_cover_layout(problem, 10, symmetric=True)
    assert result.layout.size == 10
    assert set(mirror[result.layout].tolist()) == set(result.layout.tolist())


def test_visibility_is_lower_inside_a_pit():
    verts, faces, _ = bump_model(n=21)
    radius = np.linalg.norm(verts[:, :2], axis=1)
    verts = verts.copy()
    verts[:, 2] = -25.0 * np.exp(-radius ** 2 / 150.0)  # a deep, narrow pit at the centre
    vis = visibility(verts, faces, np.zeros((1, len(verts), 3)), directions=16)
    centre = int(np.argmin(radius))
    flat = int(np.argmin(np.abs(radius - 30.0)))  # far from the pit
    assert vis[flat] > 0.8 and vis[flat] > vis[centre] + 0.2
    assert ((vis >= 0) & (vis <= 1)).all()


def test_visibility_sees_a_pit_on_a_sparse_mesh_too():
    # the same pit sampled ~1 cm apart (like markers): occlusion comes from the triangles between them
    verts, faces, _ = bump_model(n=11)
    radius = np.linalg.norm(verts[:, :2], axis=1)
    verts = verts.copy()
    verts[:, 2] = -30.0 * np.exp(-radius ** 2 / 200.0)
    vis = visibility(verts, faces, np.zeros((1, len(verts), 3)), directions=16, resolution=2.0)
    assert vis[int(np.argmin(radius))] < 0.5 < vis[int(np.argmax(radius))]


@pytest.fixture(scope="module")
def sample_problem():
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.clustering.methods import layout_problem

    path = SAMPLES / "dense_halfface.c3d"
    if not path.exists():
        pytest.skip("sample_c3d/ has no session")
    return layout_problem(read_trajectories(path))


def test_marker_session_visibility_on_the_marker_surface_mesh(sample_problem):
    problem = sample_problem
    front = facing_direction(problem)
    assert front[2] > 0.9  # the sample's face looks down +Z (sample_c3d/README.md), half face or not
    shapes = representative_shapes(problem.displacements)
    vis = problem_visibility(problem)
    assert vis.shape == (problem.n_points,) and ((vis >= 0) & (vis <= 1)).all()
    # markers whose skin turns away from the frontal view are seen from fewer directions
    facing = vertex_normals(problem.neutral, problem.surface_faces()) @ front
    assert vis[facing < 0.5].mean() < vis[facing > 0.9].mean() - 0.1
    lateral = problem.neutral[:, 0]  # the half face is on +X; the far side of the cheek vs midline
    assert vis[lateral > np.percentile(lateral, 85)].mean() < vis[lateral < np.percentile(lateral, 30)].mean()
    # a deformed shape can only hide markers: worst case over neutral + shapes ≤ neutral alone
    neutral_only = visibility(problem.neutral, problem.surface_faces(), shapes[:0], front=front,
                              resolution=max(1.5, marker_spacing(problem.neutral) / 4))
    assert (vis <= neutral_only).all() and (vis < neutral_only).any()


def test_set_cover_on_a_marker_session_uses_visibility_and_stays_optimal(sample_problem):
    problem = sample_problem
    shapes = representative_shapes(problem.displacements)
    vis = problem_visibility(problem)
    relative = relative_displacement(shapes)
    candidate = relative >= 0.3
    minimal = set_cover_layout(problem)  # the registry's path: visibility computed on the marker mesh
    assert minimal.status == ["Optimal"]
    assert candidate[minimal.layout].any(axis=0)[candidate.any(axis=0)].all()  # every cover constraint
    blind = set_cover_layout(problem, visibility_weights=np.ones(problem.n_points))
    costs = cover_costs(relative, candidate, vis)
    assert costs[minimal.layout].sum() <= costs[blind.layout].sum() + 1e-9  # optimal for ω with l_n
    assert not np.array_equal(minimal.layout, blind.layout)  # visibility changes the choice here
    result = select_layout(problem, 20, method="set-cover")
    assert result.layout.size == 20 and all(s == "Optimal" for s in result.details["status"])
