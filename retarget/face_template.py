"""The ICT-FaceKit face region fitted to the dense neutral markers: a face prior for the surface.

A dense session's markers sample one skin surface, but not densely enough to show its shape
where the skin turns away from the viewer (the nostrils, under the nose tip). The ICT-FaceKit
face (MIT) is fitted to the neutral markers by the same similarity ICP as ``--mesh``; it gives

- a **fold-free chart**: a Tutte embedding of the face region (its eye and mouth holes filled,
  its border on a circle) is one-to-one, so the markers, placed in it through their closest
  points on the face, keep their order around the nose where a sphere chart folds over;
- its **eye loops** for :mod:`~mocaptk.retarget.eye_openings`.

The face region ships with the package (``data/ict_face_neutral.npz``, MIT, its licence beside
it; ``scripts/bundle_ict_face.py`` writes it), so the result is the same on every machine. When
the fit is poor (not a face), there is no template and the caller keeps its own chart.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

import numpy as np

from mocaptk.errors import MocaptkError

from .align import SurfaceProximity, align_mesh_to_markers

__all__ = ["FittedTemplate", "fit_template", "template_face"]

#: The ICT-FaceKit face region (MIT), packaged with mocaptk.retarget.
TEMPLATE_FILE = "data/ict_face_neutral.npz"

#: Largest fit residual (RMS, in dense marker spacings) for which the template is used.
MAX_FIT_SPACINGS = 0.5

#: Most markers the template's ICP fits (its cost is markers x iterations: 18 CPU-s for 10,000
#: markers); 1,000 evenly spread ones place a face as well (residual RMS within 1 % of the fit
#: on 3,200 markers of a synthetic face).
MAX_FIT_POINTS = 1000

#: Largest distance (in marker spacings) of any marker from the fitted face for the chart: a
#: marker beyond its border (hairline, neck) would land on the chart's rim among others.
MAX_CHART_SPACINGS = 1.0


def template_face() -> tuple[np.ndarray, np.ndarray]:
    """The bundled ICT-FaceKit neutral face region: vertices (9409, 3) mm, triangles (T, 3)."""
    with resources.files(__package__).joinpath(TEMPLATE_FILE).open("rb") as handle:
        with np.load(handle, allow_pickle=False) as data:
            return data["vertices"], data["triangles"].astype(np.int64)


@dataclass(frozen=True, eq=False)
class FittedTemplate:
    """The template face placed on the markers: ``vertices`` (V, 3) mm in the markers' frame,
    ``faces`` (T, 3) int64, and ``spacing`` the markers' median nearest-neighbour distance, mm."""

    vertices: np.ndarray
    faces: np.ndarray
    spacing: float

    def chart(self, points: np.ndarray, *, mirror: np.ndarray | None = None) -> np.ndarray | None:
        """2-D chart coordinates (M, 2) of ``points`` (M, 3) mm: their closest points on the
        face, in its Tutte embedding scaled to mm; None if a point is off the face.

        ``mirror`` (M,) gives each point's mirror image (itself on the midline): the chart is
        then made mirror-symmetric, so a mirrored layout gets a mirror-symmetric mesh.
        """
        import igl

        points = np.asarray(points, dtype=float)
        closest, distance, triangle = SurfaceProximity(self.vertices, self.faces).query(points)
        if distance.max() > MAX_CHART_SPACINGS * self.spacing:
            return None
        corners = self.vertices[self.faces[triangle]]
        bary = np.asarray(igl.barycentric_coordinates(
            np.ascontiguousarray(closest), *(np.ascontiguousarray(corners[:, k]) for k in range(3))))
        embedding = _tutte_embedding(self.vertices, self.faces)
        chart = np.einsum("ij,ijk->ik", bary, embedding[self.faces[triangle]])
        if mirror is not None:
            chart = _symmetric(chart, np.asarray(mirror, dtype=np.int64))
        if len(np.unique(chart, axis=0)) < len(chart):
            return None  # two markers on one closest point: the chart cannot tell them apart
        return chart


def fit_template(points: np.ndarray, *, spacing: float) -> FittedTemplate | None:
    """The template fitted to the neutral dense markers ``points`` (N, 3) mm, or None when the
    fit residual RMS (over every marker) is above :data:`MAX_FIT_SPACINGS` x ``spacing`` (mm).
    Past :data:`MAX_FIT_POINTS` markers the ICP fits that many, evenly spread in marker order."""
    face, triangles = template_face()
    points = np.asarray(points, dtype=float)
    fitted = points
    if len(points) > MAX_FIT_POINTS:
        fitted = points[np.linspace(0, len(points) - 1, MAX_FIT_POINTS).round().astype(np.int64)]
    try:
        fit = align_mesh_to_markers(face, triangles, fitted)
    except MocaptkError:
        return None
    vertices = fit.transform.apply(face)
    rms = fit.rms_mm
    if fitted is not points:
        _, distance, _ = SurfaceProximity(vertices, triangles).query(points)
        rms = float(np.sqrt(np.mean(distance ** 2)))
    if not rms <= MAX_FIT_SPACINGS * spacing:
        return None
    return FittedTemplate(vertices=vertices, faces=triangles, spacing=spacing)


def _symmetric(chart: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """``chart`` (M, 2) averaged with the reflected chart of each point's ``mirror`` (M,): the
    2-D reflection that best maps the points onto their images (least squares) is the axis."""
    centre = chart.mean(axis=0)
    source, image = chart - centre, chart[mirror] - centre
    u, _, vt = np.linalg.svd(source.T @ image)
    flip = np.diag([1.0, -1.0 if np.linalg.det(u @ vt) > 0 else 1.0])
    reflection = u @ flip @ vt  # orthogonal, det -1: a reflection
    return centre + (source + image @ reflection.T) / 2


def _tutte_embedding(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Planar coordinates (V, 2) in mm: the border loop on a circle of the face's perimeter,
    every other vertex at the mean of its neighbours (holes fan-filled first), one-to-one."""
    import igl
    from scipy.sparse import coo_matrix, diags
    from scipy.sparse.linalg import splu

    loops = [np.asarray(loop, dtype=np.int64) for loop in igl.boundary_loop_all(faces)]
    border = max(loops, key=len)
    n = len(vertices)
    fans = [faces]
    for k, loop in enumerate(lp for lp in loops if lp is not border):
        centre = np.full(len(loop), n + k)
        fans.append(np.column_stack([np.roll(loop, -1), loop, centre]))
    filled = np.concatenate(fans)
    size = n + len(loops) - 1
    edges = np.concatenate([filled[:, [0, 1]], filled[:, [1, 2]], filled[:, [2, 0]]])
    adjacency = coo_matrix((np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())),
                           shape=(size, size)).tocsr()
    adjacency.data[:] = 1.0  # each edge once, however many triangles share it
    laplacian = (diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()
    perimeter = np.linalg.norm(vertices[border] - vertices[np.roll(border, -1)], axis=1).sum()
    rim = np.asarray(igl.map_vertices_to_circle(vertices, border)) * perimeter / (2 * np.pi)
    inner = np.setdiff1d(np.arange(size), border)
    coords = np.zeros((size, 2))
    coords[border] = rim
    solve = splu(laplacian[inner][:, inner].tocsc())
    coords[inner] = solve.solve(-(laplacian[inner][:, border] @ rim))
    return coords[:n]
