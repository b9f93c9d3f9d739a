"""Thin-shell layout optimizer (Le, Zhu & Deng 2013): factorization reuse and planted-marker recovery."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.clustering.methods import LayoutProblem, select_layout
from mocaptk.clustering.methods.thin_shell_layout import (ThinShellWeights, border_vertices,
                                                          mesh_neighbours, optimize_thin_shell,
                                                          thin_shell_layout)
from mocaptk.thin_shell import interpolation_weights, thin_shell_operator


def wavy_grid(n: int = 22, size: float = 100.0):
    """A wavy square patch in mm: (vertices, faces), symmetric about x = 0."""
    xs, ys = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n),
                         indexing="ij")
    zs = 8.0 * np.cos(xs / 25.0) * np.cos(ys / 30.0)
    verts = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def planted_markers(verts: np.ndarray, count: int, *, min_distance: float, seed: int) -> np.ndarray:
    """Random vertices at least ``min_distance`` mm apart (Poisson-disk-like)."""
    rng = np.random.default_rng(seed)
    chosen: list[int] = []
    for v in rng.permutation(len(verts)):
        if all(np.linalg.norm(verts[v] - verts[c]) > min_distance for c in chosen):
            chosen.append(int(v))
        if len(chosen) == count:
            break
    return np.sort(np.array(chosen))


@pytest.fixture(scope="module")
def grid():
    verts, faces = wavy_grid()
    return verts, faces, thin_shell_operator(verts, faces)


def test_factorized_weights_equal_direct_solves_without_refactoring(grid):
    verts, faces, op = grid
    solver = ThinShellWeights(op)
    rng = np.random.default_rng(0)
    for _ in range(3):
        markers = rng.choice(len(verts), 9, replace=False)
        np.testing.assert_allclose(solver.weights(markers), interpolation_weights(op, markers), atol=1e-9)
    # one factorization; one triangular solve pair per distinct marker vertex (+1 anchor column)
    assert solver.solves <= 3 * 9 + 1



def two_grids():
    """A wavy 12 x 12 grid, the mesh of it and a copy 150 mm away (two components), and that
    mesh's thin-shell operator."""
    verts, faces = wavy_grid(12)
    verts2 = np.concatenate([verts, verts + [150.0, 0.0, 0.0]])
    faces2 = np.concatenate([faces, faces + len(verts)])
    return verts, verts2, thin_shell_operator(verts2, faces2)


def test_trial_errors_equal_direct_reconstruction_and_tried_vertices_cost_no_solve():
    """error() of trial layouts (one or two non-resident markers) from cached entries and row
    lookups equals ‖X − W·X_H‖² with W from direct solves; on a mesh of two components."""
    verts, verts2, op = two_grids()
    rng = np.random.default_rng(3)
    data = rng.normal(size=(len(verts2), 7))
    solver = ThinShellWeights(op)
    solver.bind(data)
    layout = [int(v) for v in rng.choice(len(verts2), 8, replace=False)]

    def direct(markers):
        return float(np.sum((data - interpolation_weights(op, markers) @ data[markers]) ** 2))

    assert solver.error(layout) == pytest.approx(direct(layout), rel=1e-9)
    solver.expected_trajectories(layout, [0])  # layout markers become resident
    free = [v for v in range(len(verts2)) if v not in layout]
    singles = [(v,) for v in free[:5]]
    pair = (free[7], free[9])
    solver.prepare(singles + [pair])
    solved = solver.solves
    for unit in singles + [pair]:
        trial = layout[:-len(unit)] + list(unit)
        assert solver.error(trial) == pytest.approx(direct(trial), rel=1e-9)
    solver.forget(layout)
    for unit in singles + [pair]:  # tried again later: cached entries, no solve
        solver.error(layout[:-len(unit)] + list(unit))
    assert solver.solves == solved
    np.testing.assert_allclose(solver.fitted(layout), interpolation_weights(op, layout) @ data[layout],
                               atol=1e-9)


def test_le_et_al_validation_recovers_planted_markers(grid):
    """Plant markers, generate motion with the thin-shell model, recover the layout."""
    verts, faces, op = grid
    planted = planted_markers(verts, 10, min_distance=18.0, seed=4)
    rng = np.random.default_rng(1)
    motion = rng.normal(scale=4.0, size=(planted.size, 3 * 30))  # 30 frames of marker motion, mm
    data = interpolation_weights(op, planted) @ motion  # (V, 3F) every vertex's trajectory
    result = optimize_thin_shell(data, ThinShellWeights(op), planted.size, restarts=1, iterations=10,
                                 neighbours=mesh_neighbours(faces, len(verts)), seed=0)
    found = np.intersect1d(result.layout, planted).size
    print(f"planted {planted.size}, found {found}, RMSE {result.rmse_mm:.2e} mm")
    assert found >= planted.size - 1
    if found == planted.size:
        assert result.rmse_mm < 1e-6
    # the paper's step as written (no verification) does clearly worse on the same data
    plain = optimize_thin_shell(data, ThinShellWeights(op), planted.size, restarts=1, iterations=10,
                                verify=False, seed=0)
    assert plain.rmse_mm > result.rmse_mm


def grid_problem(verts, faces, *, frames: int = 40, seed: int = 2) -> LayoutProblem:
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 6, frames)
    # two smooth bumps moving the patch up/down and sideways
    bump1 = np.exp(-np.sum((verts[:, :2] - [20, 10]) ** 2, axis=1) / 400.0)
    bump2 = np.exp(-np.sum((verts[:, :2] - [-25, -15]) ** 2, axis=1) / 300.0)
    disp = (np.sin(t)[:, None, None] * bump1[None, :, None] * [0, 0, 5]
            + np.cos(1.7 * t)[:, None, None] * bump2[None, :, None] * [3, 0, 2])
    disp += rng.normal(scale=0.01, size=disp.shape)
    mirror = np.array([int(np.argmin(np.linalg.norm(verts - v * [-1, 1, 1], axis=1))) for v in verts])
    return LayoutProblem(disp, verts, faces=faces, mirror=mirror)


def test_constraints_symmetry_boundary_multiresolution():
    verts, faces = wavy_grid(13)
    problem = grid_problem(verts, faces)
    sym = thin_shell_layout(problem, 7, symmetric=True, restarts=1, iterations=3)
    assert sym.layout.size == 7
    assert set(problem.mirror[sym.layout].tolist()) == set(sym.layout.tolist())
    border = border_vertices(faces, 4, verts)
    bounded = thin_shell_layout(problem, 8, border_markers=4, restarts=1, iterations=3)
    assert set(border.tolist()) <= set(bounded.layout.tolist())
    coarse = select_layout(problem, 4, method="thin-shell", restarts=1, iterations=3).layout
    fine = thin_shell_layout(problem, 9, fixed=coarse, restarts=1, iterations=3)
    assert set(coarse.tolist()) <= set(fine.layout.tolist()) and fine.layout.size == 9


def test_one_factorization_per_problem_gives_the_same_layouts():
    """compare runs the optimizer at several counts on one problem: the second and later runs
    reuse the problem's factorization (``ThinShellWeights.fresh``) and must find exactly what a
    run on a problem of their own finds, with the same solve counts."""
    verts, faces = wavy_grid(11)
    shared = grid_problem(verts, faces)
    runs = [thin_shell_layout(shared, count, restarts=2, iterations=3) for count in (6, 9, 6)]
    assert len([k for k in shared.cache if k[0] == "thin-shell-solver"]) == 1
    for count, run in zip((6, 9, 6), runs):
        alone = thin_shell_layout(grid_problem(verts, faces), count, restarts=2, iterations=3)
        assert np.array_equal(run.layout, alone.layout) and run.rmse_mm == alone.rmse_mm
        assert run.solves == alone.solves and run.evaluations == alone.evaluations


def test_move_errors_equal_error_of_each_moved_layout():
    """move_errors (the base layout solved once, each move a bordered k×k Schur step) equals
    error() of every moved layout: single and paired units, first and last positions, and moves
    into the mesh component without a base marker (evaluated directly)."""
    verts, verts2, op = two_grids()
    rng = np.random.default_rng(5)
    data = rng.normal(size=(len(verts2), 7))
    for case in range(8):
        solver = ThinShellWeights(op)
        solver.bind(data)
        k = 1 + case % 2
        layout = [int(v) for v in rng.choice(len(verts), 9, replace=False)]  # first component only
        cols = list(range(k)) if case < 4 else list(range(9 - k, 9))
        solver.expected_trajectories(layout, cols)  # as the optimizer: layout markers resident
        free = [v for v in range(len(verts2)) if v not in layout]
        units = [tuple(int(v) for v in rng.choice(free, k, replace=False)) for _ in range(8)]
        units.append(tuple(len(verts) + np.arange(k)))  # into the second component
        solver.prepare(units)
        errors = solver.move_errors(layout, cols, units)
        for unit, err in zip(units, errors):
            trial = np.array(layout)
            trial[cols] = unit
            assert err == pytest.approx(solver.error(trial), rel=1e-9)


def test_expected_trajectories_kept_per_layout_follow_the_bound_data(grid):
    """expected_trajectories (WᵀX, WᵀW kept per layout) equals Le et al.'s H̄j from direct
    weights, asked twice, and again after bind() with other data (the kept products dropped)."""
    verts, faces, op = grid
    rng = np.random.default_rng(7)
    layout = [int(v) for v in rng.choice(len(verts), 10, replace=False)]
    weights = interpolation_weights(op, layout)
    solver = ThinShellWeights(op)
    for data in (rng.normal(size=(len(verts), 6)), rng.normal(size=(len(verts), 6))):
        solver.bind(data)
        for cols in ([0], [3, 4], [0]):
            others = [k for k in range(len(layout)) if k not in cols]
            rest = data - weights[:, others] @ data[np.array(layout)[others]]
            direct = np.stack([weights[:, j] @ rest / (weights[:, j] @ weights[:, j]) for j in cols])
            np.testing.assert_allclose(solver.expected_trajectories(layout, cols), direct, rtol=1e-9, atol=1e-9)
