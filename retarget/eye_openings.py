"""Eye apertures in the marker surface, from the ICT-FaceKit face fitted to the dense markers.

A dense session has no markers on the eyeball, but the marker surface is one sheet that spans
the eye openings (the marker holes there are no larger than the gaps elsewhere, so no size rule
finds them). The ICT-FaceKit face (MIT) has open eyes: fitted to the neutral markers
(:mod:`~mocaptk.retarget.face_template`), each of its eye boundary loops becomes a planar polygon, and a
marker-surface triangle whose centroid or edge midpoint falls inside an eye polygon (within
``depth_mm`` of its plane) is removed. No marker is peeled off the surface
(:func:`~mocaptk.surface_mesh.remove_triangles`); a mirrored layout's cut is made symmetric.
When the fit is poor (not a face), nothing is cut.
"""

from __future__ import annotations

import numpy as np

from mocaptk.surface_mesh import boundary_edges, remove_triangles

from .face_template import FittedTemplate, template_face

__all__ = ["boundary_loops", "cut_eye_openings", "eye_loops", "template_eye_loops"]


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Every boundary loop of a triangle mesh as ordered vertices (each (K,) int64), in the
    direction of its triangles' edges."""
    faces = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = {tuple(e) for e in boundary_edges(faces).tolist()}
    following = {int(a): int(b) for a, b in directed if tuple(sorted((int(a), int(b)))) in undirected}
    loops, seen = [], set()
    for start in sorted(following):
        if start in seen:
            continue
        loop = [start]
        while following.get(loop[-1], start) != start and len(loop) <= len(following):
            loop.append(following[loop[-1]])
        seen.update(loop)
        loops.append(np.array(loop, dtype=np.int64))
    return loops


def eye_loops(vertices: np.ndarray, faces: np.ndarray) -> list[np.ndarray]:
    """Ordered vertex loops (each (K,) int) of the openings above the nose tip: the eyes of a
    face mesh whose border is its longest boundary loop (Y up, nose tip = largest Z)."""
    loops = boundary_loops(faces)
    if len(loops) < 2:
        return []
    border = max(range(len(loops)), key=lambda i: len(loops[i]))
    used = np.unique(faces)  # the nose of these triangles, not of another part
    nose_y = vertices[used[int(np.argmax(vertices[used, 2]))], 1]
    return [loop for i, loop in enumerate(loops)
            if i != border and vertices[loop, 1].mean() > nose_y and len(loop) >= 4]


def template_eye_loops(template: FittedTemplate) -> list[np.ndarray]:
    """The fitted template face's eye loops as point polygons (each (K, 3) mm, markers' frame)."""
    face, triangles = template_face()
    return [template.vertices[loop] for loop in eye_loops(face, triangles)]


def cut_eye_openings(vertices: np.ndarray, faces: np.ndarray, polygons: list[np.ndarray], *,
                     depth_mm: float, vertex_mirror: np.ndarray | None = None) -> np.ndarray:
    """``faces`` (T, 3) without the triangles over the eye ``polygons`` (each (K, 3) mm, ordered
    around the opening); ``vertex_mirror`` (V,) makes the cut mirror-symmetric."""
    from matplotlib.path import Path

    faces = np.asarray(faces, dtype=np.int64)
    corners = np.asarray(vertices, dtype=float)[faces]  # (T, 3, 3)
    samples = np.concatenate([corners.mean(axis=1, keepdims=True),
                              (corners + np.roll(corners, -1, axis=1)) / 2], axis=1)  # (T, 4, 3)
    hits = np.zeros(faces.shape[0])
    for polygon in polygons:
        centre = polygon.mean(axis=0)
        basis = np.linalg.svd(polygon - centre)[2]  # rows: in-plane u, v, then the normal
        local = (samples - centre) @ basis.T
        inside = Path((polygon - centre) @ basis[:2].T).contains_points(local[..., :2].reshape(-1, 2))
        inside = inside.reshape(local.shape[:2]) & (np.abs(local[..., 2]) < depth_mm)
        hits += inside.sum(axis=1)
    drop = hits > 0
    if vertex_mirror is not None and drop.any():
        key = {tuple(sorted(f)): i for i, f in enumerate(faces.tolist())}
        for i in np.flatnonzero(drop):
            twin = key.get(tuple(sorted(np.asarray(vertex_mirror)[faces[i]].tolist())))
            if twin is not None:
                drop[twin] = True
                hits[twin] = max(hits[twin], hits[i])
    if not drop.any():
        return faces
    return remove_triangles(faces, drop, cost=hits, n_vertices=len(vertices))
