"""Where each marker sits on the character, refined by how it moves in the range of motion.

:mod:`.correspondence` puts each marker at the closest point of the character's face bent onto
the actor's neutral: right across the surface, not along it. A closest-point fit cannot see how
the actor's face slides against the character's (another mouth width, another lip height). On
``benchmarks/testbed``'s independent actor (an ICT-FaceKit identity; the generic rig is ICT's
face, so every marker's true place on it is known) a marker's surface point lies 2.1 mm from its
true one (median; 4.1 mm at the 90th percentile): enough to read a lip shape on the wrong side
of the lip (mouthRollUpper r 0.15 at the default layout).

The range of motion tells where a marker is: there, the character's shapes, driven by the ROM's
weights, move as the marker moved. Each of :data:`ROUNDS` rounds:

1. the ROM frames' weights from the current shapes at every marker (the calibration's solve,
   :func:`.rom_calibration.rom_weights`);
2. for each marker, the surface point within :data:`RADIUS_SPACINGS` marker spacings of its
   geometric point (the search stays local: a far point that happens to move alike is not the
   marker's) whose shapes best explain its ROM motion: least squares over the ROM frames, a
   quadratic in the barycentrics, minimised exactly over every candidate triangle;
3. each marker moves from its geometric point by the **median** of that offset over itself and
   its :data:`NEIGHBOURS` − 1 nearest markers (its ring), projected back onto the surface. Where
   the shapes' motion changes little along the surface (the nose, the forehead) a marker's own
   best point is ill-determined and slides with the noise (up to 6.7 mm on the sample, whose
   geometric places are already exact); the map between two faces is smooth, so the ring's
   median keeps what neighbours agree on.

Correspondence error against the true places (median / 90th percentile / largest, mm), by
geometry alone → by motion: the testbed actor 2.06 / 4.05 / 4.91 → 0.84 / 1.87 / 2.73; our
``synth --identity 1.5,-1.0,0.8`` actor 1.29 / 2.22 / 3.39 → 0.70 / 1.45 / 2.67; the sample
(the rig's own face: nothing to correct) 0.06 / 0.09 / 0.11 → 0.15 / 0.41 / 0.66. Cost: 2–5
CPU-s per fit (180 markers, 2,000 ROM frames).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from mocaptk.threads import one_thread

from .character import Character
from .align import SurfaceProximity
from .correspondence import Correspondence, barycentric_of
from .rom_calibration import Calibration, rom_frames, rom_weights, side_ties
from .weight_solve import DEFAULT_L1

__all__ = ["NEIGHBOURS", "RADIUS_SPACINGS", "ROUNDS", "refine_by_motion"]

#: The search radius around a marker's geometric point, in marker spacings (the median distance
#: of a marker to its nearest neighbour on the actor's neutral).
RADIUS_SPACINGS = 0.5
#: Alternations of ROM weights and marker places.
ROUNDS = 3
#: A marker's offset is the median over it and its nearest markers, this many in all (a marker
#: and its ring on a roughly even layout).
NEIGHBOURS = 9


def refine_by_motion(corr: Correspondence, character: Character, rom: np.ndarray, neutral: np.ndarray, *,
                     l1: float = DEFAULT_L1) -> Correspondence:
    """``corr`` with every seen marker moved to where the character's shapes explain its motion in
    the ROM ``rom`` (F, M, 3) mm (head-relative, NaN gaps); ``neutral`` (M, 3) mm the actor's."""
    seen = np.flatnonzero(corr.triangles >= 0)
    if seen.size < 2:
        return corr
    delta = rom_frames(rom, neutral)
    spacing = float(np.median(cKDTree(neutral[seen]).query(neutral[seen], k=2)[0][:, 1]))
    vertices = character.vertices.astype(np.float64)
    faces = np.asarray(character.faces)
    tree = cKDTree(vertices)
    triangles_of = _vertex_triangles(faces, len(vertices))
    start = corr.points(vertices, faces)  # the geometric points: the search stays around them
    radius = RADIUS_SPACINGS * spacing / corr.scale  # character units
    ring = cKDTree(start[seen]).query(start[seen], k=min(NEIGHBOURS, seen.size))[1]
    surface = SurfaceProximity(vertices, faces)
    with one_thread():  # hundreds of small products: BLAS threads only contend (5x the CPU, measured)
        for _ in range(ROUNDS):
            basis = corr.shape_basis(character)
            ones = np.ones(len(basis))
            weights = rom_weights(Calibration(basis, neutral, side_ties(character.names, basis), ones, ones),
                                  delta, l1)
            best = np.empty((seen.size, 3))
            for i, m in enumerate(seen):
                near = tree.query_ball_point(start[m], radius)
                candidates = np.unique(np.concatenate([triangles_of[v] for v in near] + [[corr.triangles[m]]]))
                frames = np.isfinite(delta[:, m]).all(axis=1)
                t, b = _best_point(delta[frames, m], weights[frames], character, corr, faces, candidates)
                best[i] = b @ vertices[faces[t]]
            offset = np.median(best[ring] - start[seen][ring], axis=1)  # the ring's consensus
            closest, _, triangle = surface.query(start[seen] + offset)
            triangles, barycentric = corr.triangles.copy(), corr.barycentric.copy()
            triangles[seen] = triangle
            barycentric[seen] = barycentric_of(closest, vertices[faces[triangle]])
            corr = dataclasses.replace(corr, triangles=triangles, barycentric=barycentric)
    return corr


def _vertex_triangles(faces: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Per vertex, the triangles around it."""
    order = np.argsort(faces.ravel(), kind="stable")
    bounds = np.searchsorted(faces.ravel()[order], np.arange(n_vertices + 1))
    return [order[bounds[v]:bounds[v + 1]] // 3 for v in range(n_vertices)]


def _best_point(y: np.ndarray, weights: np.ndarray, character: Character, corr: Correspondence,
                faces: np.ndarray, candidates: np.ndarray) -> tuple[int, np.ndarray]:
    """The triangle among ``candidates`` and barycentrics (3,) where the character's shapes, driven
    by ``weights`` (F, S), best fit the marker's motion ``y`` (F, 3) mm (least squares)."""
    corners = faces[candidates]  # (T, 3)
    verts, local = np.unique(corners, return_inverse=True)
    local = local.reshape(corners.shape)
    shapes = corr.scale * character.deltas[:, verts].astype(np.float64) @ corr.rotation.T  # (S, V, 3)
    motion = (weights @ shapes.reshape(len(shapes), -1)).reshape(len(weights), len(verts), 3)
    motion = motion.transpose(1, 0, 2).reshape(len(verts), -1)  # (V, F·3): each vertex's ROM motion
    gram, cross = motion @ motion.T, motion @ y.ravel()
    g = gram[local[:, :, None], local[:, None, :]]  # (T, 3, 3)
    c = cross[local]  # (T, 3)
    best_cost, best = np.full(len(candidates), np.inf), np.zeros((len(candidates), 3))
    for b in _simplex_minima(g, c):  # interior, edge and corner minima, each feasible or inf
        cost = np.einsum("ti,tij,tj->t", b, g, b) - 2 * np.einsum("ti,ti->t", b, c)
        cost = np.where(np.isfinite(b).all(axis=1), cost, np.inf)
        better = cost < best_cost
        best_cost[better], best[better] = cost[better], b[better]
    k = int(np.argmin(best_cost))
    return int(candidates[k]), best[k]


def _simplex_minima(g: np.ndarray, c: np.ndarray) -> list[np.ndarray]:
    """Candidate minimisers (T, 3) of ``bᵀ g b − 2 bᵀ c`` over the simplex (b ≥ 0, Σ b = 1): the
    stationary point inside (NaN when outside), on each edge (clipped) and the corners."""
    out = []
    e = np.array([[-1.0, 1.0, 0.0], [-1.0, 0.0, 1.0]])  # b = corner 0 + u e0 + v e1
    h = np.einsum("ai,tij,bj->tab", e, g, e)
    r = np.einsum("ai,ti->ta", e, c) - np.einsum("ai,ti->ta", e, g[:, :, 0])
    det = h[:, 0, 0] * h[:, 1, 1] - h[:, 0, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (r[:, 0] * h[:, 1, 1] - r[:, 1] * h[:, 0, 1]) / det
        v = (r[:, 1] * h[:, 0, 0] - r[:, 0] * h[:, 0, 1]) / det
    inside = (u >= 0) & (v >= 0) & (u + v <= 1) & (np.abs(det) > 0)
    interior = np.stack([1 - u - v, u, v], axis=1)
    interior[~inside] = np.nan
    out.append(interior)
    for i, j in ((0, 1), (1, 2), (0, 2)):  # b_i = 1 − t, b_j = t
        a = g[:, i, i] - 2 * g[:, i, j] + g[:, j, j]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.clip((c[:, j] - c[:, i] - g[:, i, j] + g[:, i, i]) / a, 0.0, 1.0)
        t = np.where(a > 0, t, 0.0)
        b = np.zeros((len(g), 3))
        b[:, i], b[:, j] = 1 - t, t
        out.append(b)
    return out
