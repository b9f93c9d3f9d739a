"""Markers anchored on the mesh and each vertex's main influence region (geodesic).

A layout marker becomes a joint pinned at one mesh vertex: the vertex nearest to the marker's
closest surface point. Every dense marker of the session (the clusters' members) is anchored
the same way; a vertex belongs to the **main influence region** of the cluster whose member is
nearest *along the surface* (Dijkstra on the mesh edges with their 3-D lengths), so regions do
not leak across the lips or eyelids the way straight-line distances would.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from mocaptk.surface_mesh import mesh_edges

from .align import SurfaceProximity

__all__ = ["anchor_vertices", "distinct_vertices", "edge_graph", "geodesic_distance",
           "main_influence_regions"]


def edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Symmetric (V, V) sparse graph of mesh edges weighted by their length (mm)."""
    edges, _ = mesh_edges(faces)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    length = np.maximum(length, 1e-9)  # coincident vertices must stay connected
    n = len(vertices)
    graph = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(n, n))
    return (graph + graph.T).tocsr()


def anchor_vertices(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, *,
                    proximity: SurfaceProximity | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Anchor points (N, 3) mm on the mesh.

    Returns the vertex of each point (N,) int64 - the corner of its closest triangle nearest
    to the closest surface point - and the point's distance to the surface (N,) mm.
    """
    proximity = proximity or SurfaceProximity(vertices, faces)
    closest, dist, tri = proximity.query(points)
    corners = np.asarray(faces)[tri]  # (N, 3)
    gap = np.linalg.norm(np.asarray(vertices)[corners] - closest[:, None, :], axis=2)
    return corners[np.arange(len(corners)), np.argmin(gap, axis=1)], dist


def distinct_vertices(vertices: np.ndarray, points: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """One vertex per point (N,) int64, all different: ``anchors`` where unshared, else (for all
    but the point nearest to a shared vertex) the nearest vertex no other point holds.

    Points at the very same position keep their shared vertex (they are one surface point).
    """
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, dtype=float)
    points = np.asarray(points, dtype=float)
    out = np.asarray(anchors, dtype=np.int64).copy()
    gap = np.linalg.norm(vertices[out] - points, axis=1)
    taken: dict[int, int] = {}
    tree = None
    for i in np.argsort(gap, kind="stable"):
        holder = taken.get(int(out[i]))
        if holder is None or np.array_equal(points[holder], points[i]):
            taken.setdefault(int(out[i]), int(i))
            continue
        tree = tree or cKDTree(vertices)
        k = min(len(vertices), len(points) + 1)
        _, near = tree.query(points[i], k=k)
        free = [int(v) for v in np.atleast_1d(near) if int(v) not in taken]
        if free:
            out[i] = free[0]
            taken[free[0]] = int(i)
    return out


def geodesic_distance(graph: sp.csr_matrix, sources: np.ndarray, *,
                      limit: float = np.inf) -> np.ndarray:
    """Shortest surface-path distance (V,) mm from the nearest of ``sources`` (vertex indices).

    ``inf`` beyond ``limit`` and on mesh parts the sources do not reach.
    """
    return dijkstra(graph, directed=False, indices=np.asarray(sources, dtype=np.int64),
                    min_only=True, limit=limit)


def main_influence_regions(graph: sp.csr_matrix, member_vertices: list[np.ndarray]) -> np.ndarray:
    """Cluster index (V,) whose member vertex is geodesically nearest to each vertex.

    ``member_vertices[c]``: anchor vertices of cluster ``c``'s members. Vertices no member
    reaches (a separate mesh part) get -1. Ties go to the lower cluster index.
    """
    owner = np.concatenate([np.full(len(m), c) for c, m in enumerate(member_vertices)])
    sources = np.concatenate([np.asarray(m, dtype=np.int64) for m in member_vertices])
    # a vertex shared by several clusters' members keeps the first cluster
    sources, first = np.unique(sources, return_index=True)
    owner = owner[first]
    _, _, nearest = dijkstra(graph, directed=False, indices=sources, min_only=True,
                             return_predecessors=True)
    region = np.full(graph.shape[0], -1, dtype=np.int64)
    reached = nearest >= 0
    lookup = np.full(graph.shape[0], -1, dtype=np.int64)
    lookup[sources] = owner
    region[reached] = lookup[nearest[reached]]
    return region
