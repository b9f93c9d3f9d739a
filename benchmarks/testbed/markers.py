"""Marker placement on the ICT face: farthest-point sampling by geodesic (mesh-edge) distance.

Not the project's placement (``synth_layout``): candidates are the narrow face area's front-facing
vertices off the eyelids; the first marker is a random candidate, each next one the candidate
farthest (Dijkstra along mesh edges) from those placed. A half face first places a midline chain
(|x| < 0.5 mm) and then fills the actor's left (+x). Labels ``m017_L`` / ``m017_R`` / ``m017_C``:
a side suffix, no region prefix (so ``cluster`` finds regions from the geometry).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from mocaptk.surface_mesh import vertex_normals

from .ict import NARROW_VERTICES, IctFace

#: Eyelid vertices (moved more than this by a blink, mm) take no marker: a studio never puts one there.
EYELID_MM = 1.0
#: Within this distance of x = 0 (mm) a marker is on the midline (``_C``).
MIDLINE_MM = 1.5


def edge_graph(points: np.ndarray, faces: np.ndarray):
    """Sparse (V, V) matrix of mesh edge lengths (mm)."""
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    length = np.linalg.norm(points[a] - points[b], axis=1)
    n = len(points)
    return coo_matrix((np.r_[length, length], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()


def candidates(face: IctFace, rest: np.ndarray) -> np.ndarray:
    """(V,) bool: narrow face area, facing forward-ish, off the eyelids."""
    blink = np.maximum(np.linalg.norm(face.delta("eyeBlink_L"), axis=1),
                       np.linalg.norm(face.delta("eyeBlink_R"), axis=1))
    normals = vertex_normals(rest, face.faces)
    ok = np.zeros(len(rest), dtype=bool)
    ok[:NARROW_VERTICES] = True
    return ok & (blink < EYELID_MM) & (normals[:, 2] > -0.1)


def farthest_points(graph, allowed: np.ndarray, count: int, start: list[int], rng: np.random.Generator
                    ) -> list[int]:
    """Add ``count`` vertices among ``allowed`` to ``start`` (or a random allowed one), each the
    farthest by graph distance from those chosen so far."""
    chosen = list(start) or [int(rng.choice(np.flatnonzero(allowed)))]
    dist = dijkstra(graph, indices=chosen, min_only=True)
    target = len(chosen) + count - (0 if start else 1)
    while len(chosen) < target:
        score = np.where(allowed & np.isfinite(dist), dist, -1.0)
        nxt = int(np.argmax(score))
        chosen.append(nxt)
        dist = np.minimum(dist, dijkstra(graph, indices=nxt, limit=float(score[nxt]) * 1.01))
    return chosen


def place_markers(face: IctFace, rest: np.ndarray, *, count: int, half: bool, seed: int
                  ) -> tuple[np.ndarray, list[str]]:
    """Vertex indices (count,) and labels of a dense marker set on the face ``rest`` (V, 3) mm."""
    rng = np.random.default_rng([seed, 9173])  # a seed scheme of its own
    graph = edge_graph(rest, face.faces)
    allowed = candidates(face, rest)
    x = face.neutral[:, 0]  # the generic face is symmetric: sides from it, not from the identity
    if half:
        midline = allowed & (np.abs(x) < 0.5)
        chain = farthest_points(graph, midline, max(6, count // 10), [], rng)
        chosen = farthest_points(graph, allowed & (x > -0.5), count - len(chain), chain, rng)
    else:
        chosen = farthest_points(graph, allowed, count, [], rng)
    idx = np.array(sorted(set(chosen)), dtype=np.intp)
    sides = np.where(np.abs(x[idx]) <= MIDLINE_MM, "C", np.where(x[idx] > 0, "L", "R"))
    return idx, [f"m{i:03d}_{s}" for i, s in enumerate(sides)]


def headband(face: IctFace, rest: np.ndarray, *, count: int = 4, offset_mm: float = 6.0) -> np.ndarray:
    """(count, 3) mm: a headband's markers, ``offset_mm`` out of the skin at the top of the face
    area, spread across it. No shape moves them (the face area has no still vertex: even the
    hairline moves ≥ 0.4 mm with some shape, so they ride the band, not the skin)."""
    y = rest[:, 1]
    top = np.flatnonzero(y > np.percentile(y[:NARROW_VERTICES], 97))
    normals = vertex_normals(rest, face.faces)
    order = top[np.argsort(rest[top, 0])]
    picks = order[np.linspace(0, len(order) - 1, count).round().astype(int)]
    return rest[picks] + offset_mm * normals[picks]
