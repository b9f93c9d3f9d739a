"""Triangulate a dense neutral marker cloud into a clean face surface.

The markers of a dense facial session sample one skin surface (a cap that wraps around the
face). :func:`marker_surface_mesh` turns them into a triangle mesh whose vertices ARE the
markers (same order), so anything defined per dense marker is defined per vertex:

1. **Chart.** Unless the caller gives one, fit a sphere to the cloud (the face is a cap around a centre inside the head) and
   map every marker to its (azimuth, elevation) around that centre, scaled to mm; azimuth turns
   around the in-plane axis the face wraps least around (cheek to cheek wraps most). Unlike a flat
   PCA projection this keeps the sides of the face (cheeks, jaw line) from collapsing into
   slivers. A nearly flat cloud falls back to the PCA plane.
2. **Delaunay** (scipy) in the chart.
3. **Peel the rim.** The convex hull of the chart adds long, thin triangles along the border;
   boundary triangles with a 3-D edge longer than ``max_edge_factor`` x the local marker
   spacing (largest nearest-neighbour distance of its three markers), or flat slivers (angle
   facing the border > ``max_rim_angle_deg``), are removed, repeatedly, from the outside in.
   Interior triangles are kept (holes such as a missing marker stay filled); markers far from
   all others form separate small patches. Optionally (the rig's mesh), the notches the peel
   leaves (the border turning inwards by more than ``max_notch_deg`` at a marker, a zigzag top
   of the forehead) are then filled with the triangle across them.
4. **Flip** interior edges whose 3-D triangles are badly shaped (improves the smallest angle
   where the chart distorts), and **repair** vertices where two boundary loops touch (bow-ties),
   so the result is an edge-manifold disk.
5. **Orient** every triangle so its normal points out of the face (towards the viewer; +Z when
   the session looks down +Z).

A marker that ends up in no triangle (an isolated outlier) stays in ``vertices``, unreferenced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree

from .geometry import vector_lengths

__all__ = [
    "MeshQuality", "SurfaceMesh", "border_turns", "boundary_edges", "cut_openings", "face_normals",
    "front_direction", "marker_spacing",
    "marker_surface_mesh", "mesh_edges", "mesh_quality", "nanpercentile_rows", "remove_triangles",
    "triangle_angles",
    "vertex_normals",
]


@dataclass(frozen=True, eq=False)
class SurfaceMesh:
    """A triangle mesh in millimetres.

    ``vertices`` (V, 3) float64 mm; ``faces`` (T, 3) int64 vertex indices, counter-clockwise
    seen from outside (normals point out of the face).
    """

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


@dataclass(frozen=True)
class MeshQuality:
    """Shape statistics of a triangle mesh (angles in degrees, lengths in mm)."""

    min_angle_deg: float
    median_edge_mm: float
    max_edge_mm: float
    non_manifold_edges: int
    non_manifold_vertices: int
    boundary_loops: int
    unreferenced_vertices: int


def marker_spacing(points: np.ndarray) -> float:
    """Median distance (mm) from each marker to its nearest neighbour; ``points`` (M, 3)."""
    points = np.asarray(points, dtype=float)
    if points.shape[0] < 2:
        raise ValueError("need at least 2 points to measure marker spacing")
    dist, _ = cKDTree(points).query(points, k=2)
    return float(np.median(dist[:, 1]))


def mesh_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) (sorted pairs) and how many faces use each (E,)."""
    faces = np.asarray(faces, dtype=np.int64)
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges, counts = np.unique(np.sort(half, axis=1), axis=0, return_counts=True)
    return edges.reshape(-1, 2), counts


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Edges (B, 2) used by exactly one face (the mesh border)."""
    edges, counts = mesh_edges(faces)
    return edges[counts == 1]


def triangle_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Interior angles (T, 3) in degrees; column k is the angle at ``faces[:, k]``."""
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)]
    angles = np.empty(tri.shape[:2])
    for k in range(3):
        a = tri[:, (k + 1) % 3] - tri[:, k]
        b = tri[:, (k + 2) % 3] - tri[:, k]
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(
            np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        angles[:, k] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return angles


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit face normals (T, 3) from the counter-clockwise vertex order."""
    tri = np.asarray(vertices, dtype=float)[np.asarray(faces, dtype=np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V, 3); zero for unreferenced vertices."""
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 x area
    out = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, length, out=np.zeros_like(out), where=length > 0)


def mesh_quality(vertices: np.ndarray, faces: np.ndarray) -> MeshQuality:
    """Smallest angle, edge lengths, manifoldness and boundary loops of a mesh."""
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    edges, counts = mesh_edges(faces)
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    border = edges[counts == 1]
    bad_vertices = np.flatnonzero(np.bincount(border.ravel(), minlength=len(vertices)) > 2)
    loops = 0
    if len(border):
        n = len(vertices)
        graph = coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])), shape=(n, n))
        _, comp = connected_components(graph, directed=False)
        loops = len(np.unique(comp[np.unique(border)]))
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    return MeshQuality(
        min_angle_deg=float(triangle_angles(vertices, faces).min()) if len(faces) else 0.0,
        median_edge_mm=float(np.median(lengths)) if len(lengths) else 0.0,
        max_edge_mm=float(lengths.max()) if len(lengths) else 0.0,
        non_manifold_edges=int(np.sum(counts > 2)),
        non_manifold_vertices=int(len(bad_vertices)),
        boundary_loops=int(loops),
        unreferenced_vertices=int(np.sum(~used)),
    )


def marker_surface_mesh(points: np.ndarray, *, max_edge_factor: float = 2.5,
                        max_rim_angle_deg: float = 120.0, max_notch_deg: float | None = None,
                        chart: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a dense neutral marker cloud as one face surface.

    Parameters
    ----------
    points : (M, 3) float
        Neutral marker positions in mm (no NaN, M >= 3, not all on a line).
    max_edge_factor : float
        Border triangles with an edge longer than this x the local marker spacing (largest
        nearest-neighbour distance among their three markers) are peeled.
    max_rim_angle_deg : float
        Border triangles whose angle facing the border is wider than this (degrees) are peeled
        (flat slivers between rim markers).
    max_notch_deg : float
        The border turns inwards by at most this much (degrees, in the tangent plane) at a
        marker: a deeper notch left by the peel is filled with the triangle across it when its
        new edge is short enough (``max_edge_factor``), so the border (top of the forehead) is
        smooth rather than a zigzag. None (default): no fill (the layouts' and solve's mesh).
    chart : (M, 2) float, optional
        One-to-one 2-D coordinates of the points (mm) to triangulate in, e.g. from a face
        template (:mod:`mocaptk.retarget.face_template`); default: the sphere chart.

    Returns
    -------
    vertices : (M, 3) float64
        The input points, same order (vertex i = marker i).
    faces : (T, 3) int64
        Triangles, counter-clockwise seen from the front of the face.

    Raises
    ------
    ValueError
        NaN/inf in ``points``, fewer than 3 points, duplicate points, or a degenerate cloud.
    """
    vertices = np.array(points, dtype=float)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < 3:
        raise ValueError(f"expected (M >= 3, 3) points, got shape {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("points contain NaN or inf (a marker missing in the neutral pose?)")
    if len(np.unique(vertices, axis=0)) < len(vertices):
        raise ValueError("points contain duplicates (two markers at the same position)")
    nearest = cKDTree(vertices).query(vertices, k=2)[0][:, 1]
    own_chart, front = _face_chart(vertices)
    chart = own_chart if chart is None else np.asarray(chart, dtype=float)
    try:
        faces = Delaunay(chart).simplices.astype(np.int64)
    except Exception as exc:  # scipy raises QhullError for collinear clouds
        raise ValueError(f"cannot triangulate the marker cloud: {exc}") from None
    faces = _orient_in_chart(chart, faces)
    faces = _peel_border(vertices, faces, max_edge=max_edge_factor * nearest,
                         max_rim_angle=max_rim_angle_deg)
    if max_notch_deg is not None:
        faces = _fill_notches(vertices, faces, max_edge=max_edge_factor * nearest,
                              max_turn=max_notch_deg)
    faces = _flip_bad_edges(vertices, faces, chart)
    faces = _repair_bowties(faces, len(vertices))
    faces = _orient_outward(vertices, faces, front)
    order = np.lexsort(faces.T[::-1])
    return vertices, faces[order]


#: An edge whose length (99th percentile over the session) exceeds this x its neutral length
#: spans an opening: on the sample, edges across the lips stretch 2.1-3.7x, every other edge at
#: most 1.65x (docs/rig-weights.md).
OPENING_STRETCH = 2.0

#: :func:`cut_openings` measures the stretch on at most this many frames, evenly spaced (every
#: k-th, the smallest k that fits): they span a session's expressions, and the (edges, frames)
#: lengths stay ~70 MB instead of 0.6 GB at 72,000 frames.
OPENING_MAX_FRAMES = 8192


def cut_openings(faces: np.ndarray, trajectories: np.ndarray, neutral: np.ndarray, *,
                 max_stretch: float = OPENING_STRETCH, columns: np.ndarray | None = None,
                 max_frames: int = OPENING_MAX_FRAMES) -> tuple[np.ndarray, np.ndarray]:
    """Remove the triangles that span an opening of the face (the lips), found from the motion.

    An edge between two markers that stretches more than ``max_stretch`` x its neutral length
    (99th percentile of its length over the frames where both are seen) joins the two sides of
    an opening: an upper and a lower lip marker part when the jaw drops, skin neighbours do not.
    Every triangle holding such an edge is removed, except that a marker keeps its least
    stretched triangle so it stays on the surface; bow-ties are then repaired.

    Parameters
    ----------
    faces : (T, 3) int
        Triangles over the markers (vertex i = marker i).
    trajectories : (F, M, 3) float mm
        The markers' motion, NaN gaps allowed.
    neutral : (M, 3) float mm
    max_stretch : float
    columns : (M,) int, optional
        The ``trajectories`` column of each marker (default: marker i = column i); a caller's
        wider session array then needs no (F, M, 3) copy.
    max_frames : int
        Frames the stretch is measured on (every k-th frame of a longer session).

    Returns
    -------
    faces : (T', 3) int64
        The kept triangles (same order).
    cut_edges : (C, 2) int64
        The edges found to span an opening.
    """
    faces = np.asarray(faces, dtype=np.int64)
    edges, _ = mesh_edges(faces)
    if len(edges) == 0:
        return faces, edges
    rest = np.linalg.norm(neutral[edges[:, 0]] - neutral[edges[:, 1]], axis=1)
    step = -(-len(trajectories) // max_frames)
    by_edge = edge_lengths(trajectories[::step],
                           edges if columns is None else np.asarray(columns)[edges]).T
    seen = np.isfinite(by_edge).any(axis=1)
    stretch = np.ones(len(edges))
    stretch[seen] = (nanpercentile_rows(by_edge, 99)[seen]  # by_edge is consumed
                     / np.maximum(rest[seen], 1e-9))
    cut = stretch > max_stretch
    if not cut.any():
        return faces, edges[:0]
    n = int(faces.max()) + 1
    key = {int(a) * n + int(b): i for i, (a, b) in enumerate(edges)}
    corners = np.sort(np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1),
                      axis=2)
    index = np.vectorize(lambda a, b: key[int(a) * n + int(b)])(corners[..., 0], corners[..., 1])
    return remove_triangles(faces, cut[index].any(axis=1), cost=stretch[index].max(axis=1),
                            n_vertices=n), edges[cut]


#: Frames per block of :func:`edge_lengths` (its marker-major block and gathers stay in cache).
EDGE_BLOCK_FRAMES = 32


def edge_lengths(trajectories: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Length (F, E) mm of each edge ``edges`` (E, 2) in each frame of ``trajectories`` (F, M, 3)
    mm (NaN where an end is missing); the values of ``np.linalg.norm`` (same sum order).
    Edge-major in memory (the transpose of a C-ordered (E, F) array: a row per edge)."""
    traj = np.asarray(trajectories, dtype=float)
    by_edge = np.empty((len(edges), traj.shape[0]))
    length = by_edge.T
    for start in range(0, traj.shape[0], EDGE_BLOCK_FRAMES):
        # marker-major (M, 3, B): an edge end is one contiguous row to gather, not 3 scattered values
        block = traj[start:start + EDGE_BLOCK_FRAMES].transpose(1, 2, 0).copy()
        length[start:start + EDGE_BLOCK_FRAMES] = vector_lengths(
            block[edges[:, 0]] - block[edges[:, 1]], axis=1).T
    return length


def nanpercentile_rows(values: np.ndarray, q: float) -> np.ndarray:
    """``np.nanpercentile(values, q, axis=1)`` (method ``linear``) of a C-ordered (R, F) float
    array, bit for bit (up to the sign of a zero), fast for high ``q``: one partition of the
    whole array instead of one per row (numpy drops each row's NaNs and partitions it alone).
    ``values`` is overwritten. A row with no finite-or-inf value gives NaN (no warning)."""
    quantile = np.true_divide(q, 100)
    count = values.shape[1] - np.count_nonzero(np.isnan(values), axis=1)  # n per row
    virtual = (count - 1) * quantile  # numpy's virtual index, its ranks and weight (gamma)
    previous = np.floor(virtual)
    following = previous + 1
    last = virtual >= count - 1
    previous[last] = following[last] = -1
    gamma = virtual - previous
    # rank among a row's values counted from its largest (0 = the maximum)
    from_top = [np.where(r < 0, 0, count - 1 - r).astype(np.intp) for r in (previous, following)]
    result = np.full(len(values), np.nan)
    rows = np.flatnonzero(count > 0)
    if rows.size == 0:
        return result
    keep = min(values.shape[1], int(max(t[rows].max() for t in from_top)) + 1)
    np.negative(values, out=values)  # the largest values first; NaN still sorts last
    if keep < values.shape[1]:
        values.partition(keep - 1, axis=1)
    top = np.sort(values[rows, :keep], axis=1)
    a, b = (-top[np.arange(len(rows)), t[rows]] for t in from_top)
    t = gamma[rows]
    with np.errstate(invalid="ignore"):  # inf - inf: NaN, as numpy gives
        diff = b - a  # numpy's _lerp, elementwise in the same order
        lerp = a + diff * t
        np.subtract(b, diff * (1 - t), out=lerp, where=t >= 0.5)
    result[rows] = lerp
    return result


def remove_triangles(faces: np.ndarray, drop: np.ndarray, *, cost: np.ndarray,
                     n_vertices: int) -> np.ndarray:
    """``faces`` (T, 3) without the ``drop`` (T,) ones, except that a vertex losing all its
    triangles keeps its dropped one of least ``cost`` (T,) (no marker is peeled off the
    surface); bow-ties are then repaired. Returns the kept triangles (same order)."""
    drop = np.asarray(drop, bool).copy()
    kept = np.zeros(n_vertices, bool)
    kept[faces[~drop].ravel()] = True
    for v in np.unique(faces[drop].ravel()):
        if not kept[v]:
            around = np.flatnonzero(drop & (faces == v).any(axis=1))
            best = around[np.argmin(cost[around])]
            drop[best] = False
            kept[faces[best]] = True
    return _repair_bowties(faces[~drop], n_vertices)


def front_direction(points: np.ndarray) -> np.ndarray:
    """Unit direction (3,) the face in ``points`` (M, 3) looks towards.

    The least-spread principal axis, signed so the cloud bulges that way: a face is a cap
    whose rim (forehead top, cheeks, jaw line) lies behind its centre (nose). A flat cloud
    looks towards +Z.
    """
    points = np.asarray(points, dtype=float)
    centred = points - points.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    return _front_direction(centred, *axes)


def _face_chart(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2-D chart coordinates (M, 2) in mm and the unit front direction (3,).

    Azimuth is measured around the in-plane axis the face wraps least around (ear to ear is
    the strongly curved direction), so points on the far sides of the cheeks - even behind the
    fitted sphere's centre - do not fold over; elevation along the other axis stays within
    ±90°.
    """
    centre = vertices.mean(axis=0)
    _, sing, axes = np.linalg.svd(vertices - centre, full_matrices=False)
    if sing[1] <= 1e-9 * max(sing[0], 1e-300):
        raise ValueError("the marker cloud is degenerate (all markers on a line)")
    e1, e2, normal = axes  # largest spread first; normal = least spread = face depth
    front = _front_direction(vertices - centre, e1, e2, normal)
    d = vertices - centre
    u, v, depth = d @ e1, d @ e2, d @ front
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones_like(u), u, v, u * u, v * v]), depth,
                               rcond=None)
    if coef[3] * np.ptp(u) ** 2 > coef[4] * np.ptp(v) ** 2:  # depth drops more along v
        e1, e2 = e2, e1
    if np.dot(np.cross(e1, e2), front) < 0:
        e2 = -e2
    extent = float(np.ptp(d @ np.stack([e1, e2]).T, axis=0).max())
    sphere = _fit_sphere(vertices)
    if sphere is not None:
        c, radius = sphere
        behind = np.dot(centre - c, front)
        if extent * 0.25 < radius < extent * 5.0 and behind > 0:
            d = vertices - c
            x, y, z = d @ e1, d @ e2, d @ front
            azimuth = np.arctan2(x, z)
            elevation = np.arctan2(y, np.hypot(x, z))
            return np.column_stack([azimuth, elevation]) * radius, front
    return np.column_stack([d @ e1, d @ e2]), front


def _front_direction(centred: np.ndarray, e1: np.ndarray, e2: np.ndarray,
                     normal: np.ndarray) -> np.ndarray:
    """The side of the PCA plane the face bulges towards (tie: +Z)."""
    u, v, depth = centred @ e1, centred @ e2, centred @ normal
    design = np.column_stack([np.ones_like(u), u, v, u * u + v * v])
    coef, *_ = np.linalg.lstsq(design, depth, rcond=None)
    curvature = coef[3] * float(np.mean(u * u + v * v))
    if abs(curvature) > 1e-6 * max(float(np.ptp(depth)), 1e-300) and abs(curvature) > 1e-9:
        return -normal if curvature > 0 else normal  # rim behind centre => bulge = front
    return normal if normal[2] >= 0 else -normal


def _fit_sphere(vertices: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Algebraic least-squares sphere (centre (3,), radius mm); None when ill-posed."""
    design = np.column_stack([2 * vertices, np.ones(len(vertices))])
    rhs = np.einsum("ij,ij->i", vertices, vertices)
    sol, _, rank, _ = np.linalg.lstsq(design, rhs, rcond=None)
    if rank < 4:
        return None
    centre = sol[:3]
    r2 = sol[3] + centre @ centre
    return (centre, float(np.sqrt(r2))) if r2 > 0 else None


def _orient_in_chart(chart: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Make every triangle counter-clockwise in the chart."""
    area = _ccw(chart, faces)
    faces = faces.copy()
    flip = area < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces[area != 0]


def _peel_border(vertices: np.ndarray, faces: np.ndarray, *, max_edge: np.ndarray,
                 max_rim_angle: float) -> np.ndarray:
    """Remove bad triangles that lie on the border, from the outside in.

    Bad = an edge longer than the largest ``max_edge`` (V,) mm of its three vertices, or a
    flat rim sliver: the angle facing one of its border edges is wider than ``max_rim_angle``
    (degrees) - the long thin triangles the convex hull adds between rim markers. A marker is
    never peeled off the surface: of the bad triangles that would leave a vertex without any, the
    one with the shortest longest edge stays.
    """
    n = len(vertices)
    keys = np.sort(np.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], axis=1),
                   axis=2)
    keys = keys[:, :, 0] * n + keys[:, :, 1]  # (T, 3) edge facing vertex k, as one integer
    edge_keys, edge = np.unique(keys, return_inverse=True)
    edge = edge.reshape(keys.shape)  # (T, 3) edge index: counts are updated, not re-sorted
    tri = vertices[faces]
    longest = np.max(np.stack([np.linalg.norm(tri[:, (k + 1) % 3] - tri[:, k], axis=1)
                               for k in range(3)]), axis=0)
    too_long = longest > max_edge[faces].max(axis=1)
    wide = triangle_angles(vertices, faces) > max_rim_angle  # (T, 3) angle facing edge k
    keep = np.ones(len(faces), bool)
    kept_for_marker = np.zeros(len(faces), bool)
    uses = np.bincount(edge.ravel(), minlength=len(edge_keys))  # kept triangles on each edge
    while True:
        on_border = uses[edge] == 1  # (T, 3)
        drop = keep & ~kept_for_marker & ((on_border.any(axis=1) & too_long) | (on_border & wide).any(axis=1))
        if not drop.any():
            return faces[keep]
        referenced = np.zeros(n, bool)
        referenced[faces[keep & ~drop].ravel()] = True
        owner, starts = _vertex_triangles(faces, n, np.flatnonzero(drop))
        for v in np.flatnonzero(np.diff(starts)):  # every vertex of a dropped triangle
            if not referenced[v]:
                candidates = owner[starts[v]:starts[v + 1]]
                candidates = candidates[drop[candidates]]
                best = candidates[np.argmin(longest[candidates])]
                drop[best], kept_for_marker[best] = False, True
                referenced[faces[best]] = True
        keep &= ~drop
        uses -= np.bincount(edge[drop].ravel(), minlength=len(edge_keys))


def _vertex_triangles(faces: np.ndarray, n_vertices: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Incidence of the triangles ``faces[rows]`` (``rows`` ascending): those holding vertex v
    are ``owner[starts[v]:starts[v + 1]]``, ascending (one sort instead of a scan per vertex)."""
    corner = faces[rows].ravel()
    by_vertex = np.argsort(corner, kind="stable")
    starts = np.searchsorted(corner[by_vertex], np.arange(n_vertices + 1))
    return np.repeat(rows, 3)[by_vertex], starts


def border_turns(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary vertices (B,) and the border's turn at each (B,) degrees, in the vertex's
    tangent plane: > 0 turns round the mesh (convex), < 0 into it (a notch). ``faces`` must be
    an edge-manifold mesh (one border edge in and one out of each boundary vertex)."""
    faces = np.asarray(faces, dtype=np.int64)
    vertices = np.asarray(vertices, dtype=float)
    _, ahead, behind = _border_links(faces, len(vertices))
    return _turns(vertices, faces, ahead, behind)


def _turns(vertices: np.ndarray, faces: np.ndarray, ahead: dict[int, int],
           behind: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`border_turns` from the border's links (next / previous boundary vertex)."""
    at = np.array(sorted(ahead), dtype=np.int64)
    prev = np.array([behind[int(b)] for b in at], dtype=np.int64)
    nxt = np.array([ahead[int(b)] for b in at], dtype=np.int64)
    normal = vertex_normals(vertices, faces)[at]
    e1 = vertices[at] - vertices[prev]
    e2 = vertices[nxt] - vertices[at]
    e1 -= normal * np.einsum("ij,ij->i", e1, normal)[:, None]
    e2 -= normal * np.einsum("ij,ij->i", e2, normal)[:, None]
    turn = np.degrees(np.arctan2(np.einsum("ij,ij->i", np.cross(e1, e2), normal),
                                 np.einsum("ij,ij->i", e1, e2)))
    return at, turn


def _border_half_edges(faces: np.ndarray, n: int) -> np.ndarray:
    """Directed border edges (B, 2) ``a -> b`` as in their triangle (the mesh on their left)."""
    half = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return half[~np.isin(half[:, 0] * n + half[:, 1], half[:, 1] * n + half[:, 0])]


def _border_links(faces: np.ndarray, n: int) -> tuple[np.ndarray, dict[int, int], dict[int, int]]:
    """The directed border edges (B, 2) and, per boundary vertex, the next and previous one."""
    border = _border_half_edges(faces, n)
    return (border, dict(zip(border[:, 0].tolist(), border[:, 1].tolist())),
            dict(zip(border[:, 1].tolist(), border[:, 0].tolist())))


def _fill_notches(vertices: np.ndarray, faces: np.ndarray, *, max_edge: np.ndarray,
                  max_turn: float, max_passes: int = 10) -> np.ndarray:
    """Close border notches deeper than ``max_turn`` degrees with the triangle across them, if
    its new edge is no longer than the larger ``max_edge`` (V,) mm of its ends and not an edge
    yet. A pass fills all its notches at once (none beside another): a symmetric mesh stays so."""
    n = len(vertices)
    for _ in range(max_passes):
        if len(faces) == 0:
            return faces
        border, ahead, behind = _border_links(faces, n)
        if np.bincount(border[:, 0], minlength=n).max() > 1:
            return faces  # two border loops touch at a vertex (no single turn)
        at, turn = _turns(vertices, faces, ahead, behind)
        edges, _ = mesh_edges(faces)
        existing = set((edges[:, 0] * n + edges[:, 1]).tolist())
        notch = {int(b) for b, t in zip(at, turn) if t < -max_turn}
        new = []
        for b in sorted(notch):
            a, c = behind[b], ahead[b]
            if a in notch or c in notch or a == c or min(a, c) * n + max(a, c) in existing:
                continue
            if np.linalg.norm(vertices[a] - vertices[c]) <= max(max_edge[a], max_edge[c]):
                new.append((a, c, b))  # holds the reverses of a -> b and b -> c
        if not new:
            return faces
        faces = np.concatenate([faces, np.array(new, dtype=np.int64)])
    return faces


def _flip_bad_edges(vertices: np.ndarray, faces: np.ndarray, chart: np.ndarray,
                    max_passes: int = 20) -> np.ndarray:
    """Flip interior edges when that raises the smaller 3-D angle of the two triangles.

    A flip is only taken where the quad is strictly convex in the chart, so the mesh stays an
    embedded disk (both new triangles remain counter-clockwise there).
    """
    faces = faces.copy()
    for _ in range(max_passes):
        t0, t1, a, b, c, d = _interior_edge_quads(faces)
        new0 = np.column_stack([a, d, c])
        new1 = np.column_stack([b, c, d])
        convex = (_ccw(chart, new0) > 0) & (_ccw(chart, new1) > 0)
        old = np.minimum(triangle_angles(vertices, faces[t0]).min(axis=1),
                         triangle_angles(vertices, faces[t1]).min(axis=1))
        new = np.minimum(triangle_angles(vertices, new0).min(axis=1),
                         triangle_angles(vertices, new1).min(axis=1))
        gain = np.where(convex, new - old, 0.0)
        touched = np.zeros(len(faces), bool)
        flipped = False
        for i in np.flatnonzero(gain > 1e-6)[np.argsort(-gain[gain > 1e-6], kind="stable")]:
            if touched[t0[i]] or touched[t1[i]]:
                continue  # one flip per triangle per pass keeps the quads valid
            faces[t0[i]], faces[t1[i]] = new0[i], new1[i]
            touched[[t0[i], t1[i]]] = True
            flipped = True
        if not flipped:
            break
    return faces


def _interior_edge_quads(faces: np.ndarray) -> tuple[np.ndarray, ...]:
    """For each edge shared by two faces: the faces t0, t1, the edge a->b (as in t0) and the
    opposite vertices c (in t0) and d (in t1)."""
    n_faces = len(faces)
    a = faces.ravel()
    b = faces[:, [1, 2, 0]].ravel()
    c = faces[:, [2, 0, 1]].ravel()
    tri = np.repeat(np.arange(n_faces), 3)
    n = int(faces.max()) + 1 if n_faces else 0
    directed = a * n + b
    reverse = b * n + a
    order = np.argsort(directed)
    pos = np.searchsorted(directed[order], reverse)
    pos = np.minimum(pos, len(order) - 1)
    found = directed[order][pos] == reverse
    twin = order[pos]
    first = found & (a < b)  # each interior edge once
    return tri[first], tri[twin[first]], a[first], b[first], c[first], c[twin[first]]


def _ccw(chart: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Twice the signed chart area (T,) of triangles (T, 3); > 0 = counter-clockwise."""
    p0, p1, p2 = chart[faces[:, 0]], chart[faces[:, 1]], chart[faces[:, 2]]
    return ((p1[:, 0] - p0[:, 0]) * (p2[:, 1] - p0[:, 1])
            - (p2[:, 0] - p0[:, 0]) * (p1[:, 1] - p0[:, 1]))


def _repair_bowties(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Where several triangle fans meet at one vertex, keep only the largest fan."""
    while True:
        degree = np.bincount(boundary_edges(faces).ravel(), minlength=n_vertices)
        bad = np.flatnonzero(degree > 2)
        if len(bad) == 0:
            return faces
        drop = np.zeros(len(faces), bool)
        owner, starts = _vertex_triangles(faces, n_vertices, np.arange(len(faces)))
        for v in bad:
            around = owner[starts[v]:starts[v + 1]]
            around = around[~drop[around]]
            if len(around) == 0:  # every fan went with an earlier vertex's small fans
                continue
            fans = _fans_around(faces[around], int(v))
            largest = np.argmax(np.bincount(fans))
            drop[around[fans != largest]] = True
        faces = faces[~drop]


def _fans_around(ring: np.ndarray, v: int) -> np.ndarray:
    """Label (K,) the fans of triangles ``ring`` (K, 3) around vertex ``v``: triangles sharing
    an edge through ``v`` are in the same fan."""
    label = np.arange(len(ring))
    others = [set(pair) for pair in ring[ring != v].reshape(len(ring), 2).tolist()]
    changed = True
    while changed:  # propagate the smallest label across shared neighbours (tiny K)
        changed = False
        for i in range(len(ring)):
            for j in range(i + 1, len(ring)):
                if label[i] != label[j] and others[i] & others[j]:
                    label[i] = label[j] = min(label[i], label[j])
                    changed = True
    return np.unique(label, return_inverse=True)[1]


def _orient_outward(vertices: np.ndarray, faces: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Flip the whole mesh if its normals point into the head rather than out of the face."""
    if len(faces) == 0:
        return faces
    tri = vertices[faces]
    total = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
    return faces[:, [0, 2, 1]] if np.dot(total, front) < 0 else faces
