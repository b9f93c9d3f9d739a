"""Align a character mesh to the session's neutral markers: similarity transform, ICP with scale.

Both the mesh and the markers are expected in the rig frame (Y up, face looking down +Z; the
usual convention of DCC tools and glTF), so the rotation starts at identity. Without landmark
pairs, the coarse start puts the mesh's most forward point (nose tip) on the markers' most
forward point and tries a few scales around the ratio of their frontal extents; each start is
refined by ICP (markers to their closest points on the mesh surface, similarity with scale),
and the start with the smallest residual wins.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.geometry import Similarity, similarity_transform

__all__ = ["Alignment", "Similarity", "align_mesh_to_markers", "SurfaceProximity",
           "similarity_transform"]


@dataclass(frozen=True)
class Alignment:
    """A mesh aligned to markers.

    ``transform`` maps the mesh file's coordinates into the session (rig) frame, mm;
    ``residuals`` (M,) distance of each marker to the aligned mesh surface, mm.
    """

    transform: Similarity
    residuals: np.ndarray
    method: str

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))

    @property
    def max_mm(self) -> float:
        return float(self.residuals.max())


def align_mesh_to_markers(vertices: np.ndarray, faces: np.ndarray, markers: np.ndarray, *,
                          landmarks: Mapping[int, int] | None = None,
                          iterations: int = 200, trim: float = 0.9) -> Alignment:
    """Similarity transform bringing a mesh onto neutral markers.

    Parameters
    ----------
    vertices, faces : (V, 3) float, (T, 3) int
        The mesh, any unit, Y up, facing +Z.
    markers : (M, 3) float
        Neutral marker positions, mm, rig frame.
    landmarks : {marker index: vertex index}, optional
        Known correspondences (>= 3); used as the start (and alone if ``iterations`` is 0).
    iterations : int
        ICP iterations after the start.
    trim : float
        Fraction of markers (closest first) used in each ICP step, so markers off the mesh
        (e.g. beyond its border) do not pull it.
    """
    verts = np.asarray(vertices, dtype=float)
    pts = np.asarray(markers, dtype=float)
    mesh = SurfaceProximity(verts, faces)
    if landmarks:
        if len(landmarks) < 3:
            raise OptionError("landmark alignment needs at least 3 marker/vertex pairs")
        m_idx = np.array(list(landmarks.keys()))
        v_idx = np.array(list(landmarks.values()))
        if v_idx.min() < 0 or v_idx.max() >= len(verts):
            raise OptionError(f"landmark vertex indices must be in 0..{len(verts) - 1}")
        starts = [similarity_transform(verts[v_idx], pts[m_idx])]
        method = "landmarks" + ("+icp" if iterations else "")
    else:
        starts = _coarse_starts(verts, pts)
        method = "icp"
    keep = max(3, int(trim * len(pts)))

    def score(t: Similarity) -> float:
        return float(np.sqrt(np.mean(np.sort(_surface_distance(mesh, pts, t))[:keep] ** 2)))

    # a few ICP steps from each start, then the best one to convergence
    rough = [_icp(mesh, pts, s, iterations=min(iterations, 8), trim=trim) for s in starts]
    transform = _icp(mesh, pts, min(rough, key=score), iterations=iterations, trim=trim)
    return Alignment(transform, _surface_distance(mesh, pts, transform), method)


def _coarse_starts(verts: np.ndarray, pts: np.ndarray) -> list[Similarity]:
    """Identity rotation, nose tip on nose tip, scales from the extents' ratio upwards.

    The markers cover at most the mesh's face (a half face, no neck or scalp), so the ratio of
    extents underestimates the scale: the starts go from it to twice it.
    """
    front = verts[verts[:, 2] > np.percentile(verts[:, 2], 30)]  # skip the back of a head
    ratio = float(np.max(np.ptp(pts[:, :2], axis=0) / np.maximum(np.ptp(front[:, :2], axis=0),
                                                                 1e-12)))
    tip_v = verts[np.argmax(verts[:, 2])]
    tip_p = pts[np.argmax(pts[:, 2])]
    out = []
    for f in (0.9, 1.15, 1.45, 1.85):
        s = ratio * f
        out.append(Similarity(s, np.eye(3), tip_p - s * tip_v))
    return out


def _icp(mesh: SurfaceProximity, pts: np.ndarray, start: Similarity, *, iterations: int,
         trim: float) -> Similarity:
    """Refine ``start`` (mesh -> markers) by ICP with scale on the trimmed closest pairs."""
    transform = start
    keep = max(3, int(round(trim * len(pts))))
    for _ in range(iterations):
        inverse = _inverse(transform)
        local = inverse.apply(pts)  # markers in mesh coordinates
        closest, dist, _ = mesh.query(local)
        order = np.argsort(dist, kind="stable")[:keep]
        step = similarity_transform(closest[order], pts[order])
        moved = np.abs(step.apply(closest[order]) - transform.apply(closest[order])).max()
        transform = step
        if moved < 1e-4:  # mm
            break
    return transform


def _inverse(t: Similarity) -> Similarity:
    rot = t.rotation.T
    return Similarity(1.0 / t.scale, rot, -(rot @ t.translation) / t.scale)


def _surface_distance(mesh: SurfaceProximity, pts: np.ndarray,
                      transform: Similarity) -> np.ndarray:
    """Distance (mm) from each marker to the transformed mesh surface."""
    _, dist, _ = mesh.query(_inverse(transform).apply(pts))
    return dist * transform.scale


class SurfaceProximity:
    """Closest points on a fixed triangle mesh (libigl AABB tree, built once)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import igl

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self._tree = igl.AABB()
        self._tree.init(self.vertices, self.faces)

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points (N, 3), distances (N,) and triangle indices (N,)."""
        sq, tri, closest = self._tree.squared_distance(
            self.vertices, self.faces, np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3))
        return np.asarray(closest), np.sqrt(np.asarray(sq)), np.asarray(tri, dtype=np.int64)
