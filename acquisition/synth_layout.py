"""Dense facial marker layouts on the ICT-FaceKit face: ≈1 cm apart, with regions and sides.

Where markers may go (the *marker zone*), on the face region of the neutral mesh:

- inside the face outline seen from the front: the Multi-PIE jaw-contour landmarks (0–16) closed
  over the forehead by an arc ``FOREHEAD_HEIGHT_MM`` above the brows, and in front of the
  outermost contour landmarks (0, 16, at the tragus): no ears, neck or scalp;
- on skin that faces the front (vertex normal ``z`` ≥ ``MIN_FORWARD_NORMAL``: no nostril
  interior, no under-nose or under-chin skin);
- not on the eyelids or the inner lips: mesh-graph distance to the eye openings ≥
  ``EYELID_MARGIN_MM``, and to the mouth opening farther than the inner-lip landmarks (60–67)
  plus ``INNER_LIP_MARGIN_MM``.

The *wide* zone (``wide=True``, ``mocaptk synth --wide-zone``) also takes the skin a rig sees badly:
under the nose and chin and the jaw's underside (normal ``z`` ≥ ``WIDE_MIN_FORWARD_NORMAL``), the
eyelids (≥ ``WIDE_EYELID_MARGIN_MM`` from the eye openings) and the inner lips (up to
``-WIDE_INNER_LIP_MARGIN_MM`` inside the inner-lip landmarks) — the test case of camera-aware layouts.

Markers are picked among zone vertices by farthest-point sampling (Euclidean, mm) until every
zone vertex is closer than ``spacing`` to a marker, so neighbours are ≥ ``spacing`` apart (the
default 8 mm gives a median nearest neighbour ≈ 9.3 mm, ≈ 1 cm nominal, and ≈ 140 markers on half
a face). The midline (x = 0) is sampled first; the character's left side (+X) follows; ``full``
mirrors the left side onto the right (the ICT mesh is left/right symmetric), so full layouts are
symmetric — a left marker closer than ``spacing / 2`` to the midline is closer than ``spacing`` to
its own mirror twin (one pair, ≈ 4 mm, at the default spacing).

Regions (:func:`face_regions`) are rules on the frontal projection (x, y) measured from the
landmarks of the +X side, applied to ``|x|``; first match wins:

- **mouth**: ellipse around the outer-lip landmarks widened by 10 mm;
- **eye** (the orbit: lids' surroundings that move with blinks, squints and the brow): below the
  eye centre, an ellipse around the eye corners widened by ``ORBIT_WIDENING_MM`` (≈ the orbital
  rim), ``LOWER_ORBIT_MM`` half-height; above it, from the nose bridge (``BRIDGE_MM``) to the same
  lateral rim and up to the forehead_brow line (brow landmarks − ``BROW_MARGIN_MM``): the upper
  lid fold and the skin under the brow are eye;
- **nose**: between the glabella and 4 mm under the nose base, half-width growing from
  ``BRIDGE_MM`` to the alar width + 8 mm;
- **forehead_brow**: above the brow landmarks − ``BROW_MARGIN_MM``, the glabella above the nose,
  and the temple — beside the orbit (lateral of its rim) above the eye centre line;
- **chin**: below the mouth centre line, inside the jaw landmarks 4–12;
- else **cheek**: below and beside the orbit (under the eye centre line), down to mouth and chin.

Labels: ``REGION_NN_S`` — the region in capitals first (``FOREHEAD_BROW_03_L``, ``NOSE_01_C``),
a number within the region, side ``L`` (+X, character's left), ``C`` (midline) or ``R``; a right
marker has its left twin's number. The region is ``label.rsplit("_", 2)[0].lower()``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from mocaptk.errors import OptionError

from .face_model import FaceModel

REGIONS = ("forehead_brow", "eye", "nose", "cheek", "mouth", "chin")
FOREHEAD_HEIGHT_MM = 25.0
MIN_FORWARD_NORMAL = 0.3
EYELID_MARGIN_MM = 7.0
#: forehead_brow reaches this far below the brow landmarks; the orbit (eye) lies under that line.
BROW_MARGIN_MM = 8.0
#: Half-width of the nose bridge and the glabella, mm.
BRIDGE_MM = 10.0
#: The orbit reaches this far beyond the eye corners (≈ the orbital rim), medially and laterally.
ORBIT_WIDENING_MM = 9.0
#: Half-height of the orbit below the eye centre (lower lid and the top of the infraorbital skin).
LOWER_ORBIT_MM = 14.0
INNER_LIP_MARGIN_MM = 1.0
#: The wide zone's bounds (skin facing down to 107° from the front, eyelids, inner lips).
WIDE_MIN_FORWARD_NORMAL = -0.3
WIDE_EYELID_MARGIN_MM = 1.0
WIDE_INNER_LIP_MARGIN_MM = -3.0
#: Vertices closer than this to x = 0 are on the midline (ICT midline vertices have x = 0 exactly).
MIDLINE_TOLERANCE_MM = 0.5


@dataclass(frozen=True, eq=False)
class MarkerLayout:
    """Markers anchored on a mesh.

    Attributes
    ----------
    labels, regions, sides : tuple of str, length M
        ``MOUTH_03_L``; region name; ``"L"`` (+X), ``"C"`` (midline) or ``"R"``.
    vertices : (M,) int64
        Mesh vertex each marker sits on.
    triangles : (M,) int64
        Index of the anchoring triangle in the model's ``faces``.
    corners : (M, 3) int64
        Vertex indices of that triangle.
    barycentric : (M, 3) float64
        Barycentric coordinates in it (rows sum to 1).
    spacing_mm : float
    mode : str
        ``"half"`` or ``"full"``.
    """

    labels: tuple[str, ...]
    regions: tuple[str, ...]
    sides: tuple[str, ...]
    vertices: np.ndarray
    triangles: np.ndarray
    corners: np.ndarray
    barycentric: np.ndarray
    spacing_mm: float
    mode: str

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    def positions(self, mesh_vertices: np.ndarray) -> np.ndarray:
        """Marker positions on meshes ``(..., V, 3)`` → ``(..., M, 3)`` (barycentric interpolation)."""
        corners = np.asarray(mesh_vertices)[..., self.corners, :]  # (..., M, 3 corners, 3 xyz)
        return np.einsum("...mcx,mc->...mx", corners, self.barycentric)

    def regions_dict(self) -> dict[str, list[str]]:
        """``{region: [labels...]}`` in :data:`REGIONS` order (the regions-file content)."""
        return {region: [lab for lab, reg in zip(self.labels, self.regions) if reg == region]
                for region in REGIONS if region in self.regions}


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``(V, 3)`` of a triangle mesh (outward for ICT)."""
    tri = vertices[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def _edge_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    graph = sp.coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return graph.maximum(graph.T)


def _boundary_loops(faces: np.ndarray, n_vertices: int) -> list[np.ndarray]:
    """Vertex sets of the mesh's boundary loops (edges used by one triangle)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    border = unique[counts == 1]
    graph = sp.coo_matrix((np.ones(len(border)), (border[:, 0], border[:, 1])),
                          shape=(n_vertices, n_vertices))
    _, component = connected_components(graph + graph.T, directed=False)
    on_border = np.unique(border)
    return [on_border[component[on_border] == c] for c in np.unique(component[on_border])]


def _inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Even-odd rule: which 2-D ``points (N, 2)`` lie inside ``polygon (K, 2)``."""
    x, y = points[:, 0:1], points[:, 1:2]
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return (crosses & (x < x_at)).sum(axis=1) % 2 == 1


def marker_zone(model: FaceModel, *, wide: bool = False) -> np.ndarray:
    """Which face-region vertices may carry a marker, ``(face_vertex_count,)`` bool (rules above;
    ``wide``: the wide zone)."""
    min_forward, eyelid_margin, lip_margin = (
        (WIDE_MIN_FORWARD_NORMAL, WIDE_EYELID_MARGIN_MM, WIDE_INNER_LIP_MARGIN_MM) if wide
        else (MIN_FORWARD_NORMAL, EYELID_MARGIN_MM, INNER_LIP_MARGIN_MM))
    n = model.face_vertex_count
    vertices = model.neutral[:n]
    faces = model.face_triangles
    marks = vertices[model.landmarks]
    brow_top = marks[17:27, 1].max()
    jaw = marks[0:17, :2]
    arc_x = np.array([0.9, 0.6, 0.3, 0.0, -0.3, -0.6, -0.9]) * jaw[16, 0]
    arc_y = brow_top + FOREHEAD_HEIGHT_MM * np.sqrt(1.0 - (arc_x / jaw[16, 0]) ** 2 * 0.6)
    outline = np.vstack([jaw, np.column_stack([arc_x, arc_y])])
    inside = _inside_polygon(vertices[:, :2], outline)
    # the ear's concha and tragus project inside the outline: keep to skin in front of the ear
    inside &= vertices[:, 2] >= marks[[0, 16], 2].min()
    forward = vertex_normals(vertices, faces)[:, 2] >= min_forward

    graph = _edge_graph(vertices, faces)
    loops = _boundary_loops(faces, n)
    mouth_center = marks[60:68].mean(axis=0)
    loop_centers = np.array([vertices[loop].mean(axis=0) for loop in loops])
    loop_size = np.array([len(loop) for loop in loops])
    # the outer border is the longest loop; the mouth loop is the other one nearest the inner lips
    openings = [i for i in range(len(loops)) if loop_size[i] != loop_size.max()]
    mouth = min(openings, key=lambda i: np.linalg.norm(loop_centers[i] - mouth_center))
    eyes = [i for i in openings if i != mouth]
    mouth_distance = dijkstra(graph, indices=loops[mouth], min_only=True)
    eye_distance = dijkstra(graph, indices=np.concatenate([loops[i] for i in eyes]), min_only=True)
    inner_lip = mouth_distance[model.landmarks[60:68]].max() + lip_margin
    return inside & forward & (mouth_distance > inner_lip) & (eye_distance >= eyelid_margin)


def face_regions(model: FaceModel) -> np.ndarray:
    """Region name of every face-region vertex, ``(face_vertex_count,)`` str (rules above)."""
    vertices = model.neutral[:model.face_vertex_count]
    marks = model.neutral[model.landmarks]
    x, y = np.abs(vertices[:, 0]), vertices[:, 1]

    lips = marks[48:60]
    mouth_c = lips.mean(axis=0)
    mouth_a = lips[:, 0].max() - mouth_c[0] + 10.0
    mouth_b = (lips[:, 1].max() - lips[:, 1].min()) / 2 + 10.0
    mouth = ((x - abs(mouth_c[0])) / mouth_a) ** 2 + ((y - mouth_c[1]) / mouth_b) ** 2 <= 1.0

    brow = marks[22:27]  # +X brow, landmarks ordered from the midline outwards
    brow_y = np.interp(x, brow[:, 0], brow[:, 1])
    forehead_y = brow_y - BROW_MARGIN_MM

    eye_marks = marks[42:48]  # the +X (character's left) eye
    eye_c = eye_marks.mean(axis=0)
    eye_a = (eye_marks[:, 0].max() - eye_marks[:, 0].min()) / 2 + ORBIT_WIDENING_MM
    lower_orbit = (y < eye_c[1]) & (((x - eye_c[0]) / eye_a) ** 2
                                    + ((y - eye_c[1]) / LOWER_ORBIT_MM) ** 2 <= 1.0)
    # medially the orbit reaches the nose bridge / glabella
    upper_orbit = (y >= eye_c[1]) & (y < forehead_y) & (x > BRIDGE_MM) & (x <= eye_c[0] + eye_a)
    eye = lower_orbit | upper_orbit

    base_y = marks[33, 1] - 4.0
    top_y = marks[27, 1] + 5.0
    alar = marks[35, 0] + 8.0
    widening = np.clip((top_y - y) / (top_y - base_y), 0.0, 1.0)
    half_width = BRIDGE_MM + (alar - BRIDGE_MM) * widening
    nose = (y >= base_y) & (y <= top_y) & (x <= half_width)

    # the glabella is brow; the temple beside the orbit is brow above the eye centre line
    forehead = ((y >= forehead_y) | ((y > top_y) & (x <= BRIDGE_MM))
                | ((y >= eye_c[1]) & (x > eye_c[0] + eye_a)))

    jaw = marks[8:13]  # chin bottom to the +X jaw angle (x increasing)
    chin = (y < mouth_c[1]) & (x <= np.interp(y, jaw[::-1, 1], jaw[::-1, 0], left=jaw[0, 0],
                                              right=jaw[-1, 0]))
    names = np.full(len(vertices), "cheek", dtype=object)
    for rule, name in ((chin, "chin"), (forehead, "forehead_brow"), (nose, "nose"),
                       (eye, "eye"), (mouth, "mouth")):
        names[rule] = name  # later rules win: mouth > eye > nose > forehead_brow > chin
    return names.astype(str)


def _farthest_points(points: np.ndarray, candidates: np.ndarray, chosen: list[int],
                     spacing: float, start: int) -> list[int]:
    """Extend ``chosen`` by farthest-point sampling over ``candidates`` until all are < ``spacing``."""
    chosen = list(chosen)
    distance = np.full(len(candidates), np.inf)
    for c in chosen:
        distance = np.minimum(distance, np.linalg.norm(points[candidates] - points[c], axis=1))
    if not chosen:
        chosen.append(int(candidates[start]))
        distance = np.linalg.norm(points[candidates] - points[candidates[start]], axis=1)
    while True:
        far = int(np.argmax(distance))
        if distance[far] < spacing:
            return chosen
        chosen.append(int(candidates[far]))
        distance = np.minimum(distance, np.linalg.norm(points[candidates] - points[candidates[far]],
                                                       axis=1))


def dense_layout(model: FaceModel, *, mode: str = "half", spacing_mm: float = 8.0,
                 seed: int = 0, wide: bool = False) -> MarkerLayout:
    """A dense marker layout on the face (see the module docstring for the rules).

    Parameters
    ----------
    model : FaceModel
    mode : {"half", "full"}
        ``half``: midline + character's left side (+X); ``full``: both sides, mirrored.
    spacing_mm : float
        Minimum distance between markers, mm (all zone vertices are within it of a marker); the
        default 8 mm gives ≈ 140 half-face markers with a median nearest neighbour ≈ 9.3 mm.
    seed : int
        Chooses the starting vertices of the sampling (same seed ⇒ same layout).
    wide : bool
        Sample the wide zone (:func:`marker_zone`): also under the chin, eyelids, inner lips.
    """
    if mode not in ("half", "full"):
        raise OptionError(f"layout mode must be 'half' or 'full', got {mode!r}")
    if not 3.0 <= spacing_mm <= 50.0:
        raise OptionError(f"marker spacing must be within 3–50 mm, got {spacing_mm}")
    n = model.face_vertex_count
    vertices = model.neutral[:n]
    zone = marker_zone(model, wide=wide)
    region_of = face_regions(model)
    rng = np.random.default_rng(seed)
    midline = np.flatnonzero(zone & (np.abs(vertices[:, 0]) < MIDLINE_TOLERANCE_MM))
    left = np.flatnonzero(zone & (vertices[:, 0] >= MIDLINE_TOLERANCE_MM))
    on_midline = _farthest_points(vertices, midline, [], spacing_mm,
                                  int(rng.integers(len(midline))))
    picked = _farthest_points(vertices, np.concatenate([midline, left]), on_midline, spacing_mm, 0)
    picked = np.array(picked, dtype=np.int64)
    sides = np.where(np.abs(vertices[picked, 0]) < MIDLINE_TOLERANCE_MM, "C", "L")

    # number per region, top to bottom then medial to lateral, so labels read like a chart
    order = np.lexsort((vertices[picked, 0], -vertices[picked, 1]))
    picked, sides = picked[order], sides[order]
    labels, regions = [], []
    counters = dict.fromkeys(REGIONS, 0)
    for vertex, side in zip(picked, sides):
        region = str(region_of[vertex])
        counters[region] += 1
        labels.append(f"{region.upper()}_{counters[region]:02d}_{side}")
        regions.append(region)
    markers = list(zip(labels, regions, sides, picked.tolist()))
    if mode == "full":
        mirror = cKDTree(vertices).query(vertices * np.array([-1.0, 1.0, 1.0]))[1]
        markers += [(label[:-1] + "R", region, "R", int(mirror[vertex]))
                    for label, region, side, vertex in markers if side == "L"]
    # regions in REGIONS order, then by number, then C < L < R
    markers.sort(key=lambda m: (REGIONS.index(m[1]), m[0][:-2], m[2]))
    anchor_vertices = np.array([m[3] for m in markers], dtype=np.int64)
    triangles, barycentric = _vertex_anchors(model.face_triangles, anchor_vertices)
    return MarkerLayout(
        labels=tuple(m[0] for m in markers),
        regions=tuple(m[1] for m in markers),
        sides=tuple(str(m[2]) for m in markers),
        vertices=anchor_vertices,
        triangles=triangles,
        corners=model.faces[triangles],
        barycentric=barycentric,
        spacing_mm=float(spacing_mm),
        mode=mode,
    )


def _vertex_anchors(faces: np.ndarray, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each vertex: the first triangle using it and the barycentric coordinates of that corner."""
    triangles = np.empty(len(vertices), dtype=np.int64)
    barycentric = np.zeros((len(vertices), 3))
    for i, vertex in enumerate(vertices):
        tri, corner = np.argwhere(faces == vertex)[0]
        triangles[i] = tri
        barycentric[i, corner] = 1.0
    return triangles, barycentric
