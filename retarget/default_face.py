"""The default face: the bundled ICT-FaceKit face region fitted to the actor's dense neutral.

Used by the rig (``rig.fbx``/``rig.glb``) and by ``solve``'s mesh alike:

1. **Fit.** The similarity ICP of :func:`~mocaptk.retarget.face_template.fit_template`, then a
   non-rigid pass: each marker's offset from its closest point on the face, spread over the
   face by a Gaussian RBF (width :data:`RBF_WIDTH_SPACINGS` marker spacings, zero far from the
   markers, so the border keeps the template's shape), :data:`FIT_ROUNDS` rounds.
2. **Whole face.** A half-face session's cloud holds the mirrored markers already; given the
   sagittal plane, the face is then made exactly mirror-symmetric (ICT-FaceKit's own
   left/right vertex pairs), so a mirrored layout gets mirrored weights.
3. **Closed lips with a seam.** The ICT-FaceKit neutral has its lips 11 mm apart; the two
   inner-lip rims are brought onto their mid-curve (the seam) and the lips follow by a
   biharmonic deformation that vanishes :data:`LIP_REACH_MM` from the mouth. The seam stays an
   opening of the mesh: no triangle joins the lips, so the upper and lower lip part when the
   jaw opens.
4. **Lids.** Each eye opening's upper rim and where it goes in a full blink (onto the lower
   rim), spread over the lid the same way: a blink displacement per eye.

UVs are ICT-FaceKit's own texture layout. Where the template does not fit (not a face), there is
no default face and the caller keeps the marker surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from .align import SurfaceProximity
from .face_parts import FaceParts, fit_parts
from .face_template import MAX_FIT_POINTS, TEMPLATE_FILE, fit_template

__all__ = ["CORNER_JOINTS_MM", "CORNER_LEFT_OUT_FADE_MM", "CORNER_PIN_FADE_MM", "EYE_CORNER_MM", "MOUTH_CORNER_MM", "DefaultFace",
           "Lid", "along_rim", "closing_field", "default_face", "flip_slivers", "lip_anchors",
           "loop_area",
           "split_loop", "template_openings", "triangle_angles"]

#: Rounds of the non-rigid fit (closest points move as the face does).
FIT_ROUNDS = 3
#: Gaussian RBF width of the non-rigid fit, in dense marker spacings.
RBF_WIDTH_SPACINGS = 2.0
#: Ridge of the RBF (on a unit-diagonal kernel): noise in the markers is not fitted exactly.
RBF_SMOOTHING = 0.05
#: Vertices this far (mm) from the mouth opening keep their place when the lips close.
LIP_REACH_MM = 14.0
#: Vertices this far (mm) from an eye opening keep their place when its lid closes (sample: a
#: full blink at 8 mm stretched the lid's skin 2.26x, 1.98x at 12 mm; the rig calibrates what
#: its markers show of the wider blink, see :mod:`~mocaptk.retarget.lid_joints`).
LID_REACH_MM = 12.0
#: ``solve``'s mesh, whose blink is not calibrated on the session, senses it with a blink of
#: this reach (mm): the markers under the brow move less than the 12 mm field says, so sensed
#: with it the lid closed to 36 % of rest. Its lids close with the 12 mm field as the rig's
#: (sample: the upper lids' crease 2.27x -> 1.92x at most, the aperture at a full blink 11 % ->
#: 9 % of rest; the eye region's error against the true markers +2.6 %, from the skin 8-12 mm
#: off the rims moving with the lid).
SOLVE_LID_REACH_MM = 8.0
#: The template's triangles with a smallest angle below this (degrees) are flipped with a
#: neighbour (:func:`flip_slivers`): ICT-FaceKit has two such slivers inside the mouth corners
#: (2.6°, 0.005 mm²), which any skinning turned backward (issue 30); flipped, 11.3°.
SLIVER_DEG = 5.0
#: A vertex belongs to a lip when it is within this (mm, on the surface) of its inner rim...
LIP_SIDE_MM = 15.0
#: ... and nearer to it than to the other lip's rim by this (mm): not at the corners.
LIP_SIDE_MARGIN_MM = 3.0
#: Rim vertices this close (mm of arc) to an opening's corner are not pinned when it closes
#: (sample: 42 triangles folded by closing the lips -> 2; the mouth's seam area at rest
#: 0.2 -> 9.7 mm², 1.2 % of its widest opening; the lids' full blink 0.2 % -> 2 % of rest).
CORNER_FREE_MM = 5.0
#: The default face's weights (and solve's map) blend towards its mouth corners' own within
#: this (mm; :func:`~mocaptk.retarget.weights.blend_corners`; sample, the rig's most folded
#: triangles at the widest jaw: 92 with none, 54 at 8 mm, 20 at 12 mm, 2 at 16 mm; the mouth's
#: error unchanged; solve's mesh 88 -> 2).
MOUTH_CORNER_MM = 16.0
#: The blend towards a mouth corner fades in over this distance (mm) from the joints' own
#: vertices (:func:`~mocaptk.retarget.weights.pin_fade`; sample, rig and solve's mesh: the
#: edges at a lip joint blended 0.3 towards the corner stretched 2.3x at the widest jaw).
CORNER_PIN_FADE_MM = 3.0
#: Within the first (mm) of a mouth corner the rig's weights keep only the corner's strongest
#: joints, back to their own at the second (:func:`~mocaptk.retarget.weights.corner_joints`;
#: sample: the 4-influence cap swapped weights up to 0.2 across an edge below the corner).
CORNER_JOINTS_MM = (10.0, 16.0)
#: ... and fade in over this (mm) from the vertices of the joints the corner's set leaves out
#: (sample: 2.081x -> 2.077x at the widest jaw, 5 mm the same, 6 mm 2.12x; the 45-joint identity
#: actor: 20 -> 13 backward triangles, 3.85x -> 2.98x).
CORNER_LEFT_OUT_FADE_MM = 8.0
#: ... and towards its eyes' corners within this (mm; sample, most folded triangles at the
#: fullest blink: 22 with none, 2 at 8 mm, 0 at 12 mm; the eye region's error +0.5 %).
EYE_CORNER_MM = 12.0


@dataclass(frozen=True, eq=False)
class Lid:
    """One eye: ``upper``/``lower`` rim vertices (corner to corner, both with the corners),
    ``blink`` (V, 3) mm, each vertex's displacement at a full blink, and ``sensed`` (V, 3) mm
    the displacement a marker there is taken to show at a full blink (None: ``blink``)."""

    upper: np.ndarray
    lower: np.ndarray
    blink: np.ndarray
    sensed: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class DefaultFace:
    """The fitted face: ``vertices`` (V, 3) mm with the lips closed, ``fitted`` (V, 3) mm before
    they close (where the markers are), ``faces`` (T, 3), ``uv`` (V, 2) in [0, 1], the mouth's
    ``upper_lip``/``lower_lip`` rims (corner to corner), the ``lids`` (right eye first:
    the smaller X) and ``mirror`` (V,) each vertex's mirror vertex when made symmetric, else
    None (the lips' seam has coincident vertices: a nearest-image search cannot pair them)."""

    vertices: np.ndarray
    fitted: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    upper_lip: np.ndarray
    lower_lip: np.ndarray
    lids: tuple[Lid, ...]
    mirror: np.ndarray | None
    parts: FaceParts | None = None


@lru_cache(maxsize=1)
def _template() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with resources.files(__package__).joinpath(TEMPLATE_FILE).open("rb") as handle:
        with np.load(handle, allow_pickle=False) as data:
            vertices, triangles = data["vertices"], data["triangles"].astype(np.int64)
            return vertices, flip_slivers(vertices, triangles), data["uv"]


def triangle_angles(corners: np.ndarray) -> np.ndarray:
    """Interior angles (..., 3) in degrees of triangles ``corners`` (..., 3, 3), one per corner."""
    corners = np.asarray(corners, dtype=float)
    angles = []
    for k in range(3):
        u = corners[..., (k + 1) % 3, :] - corners[..., k, :]
        w = corners[..., (k + 2) % 3, :] - corners[..., k, :]
        cos = np.einsum("...i,...i->...", u, w) / (np.linalg.norm(u, axis=-1)
                                                  * np.linalg.norm(w, axis=-1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return np.stack(angles, axis=-1)


def flip_slivers(vertices: np.ndarray, faces: np.ndarray, *,
                 min_angle_deg: float = SLIVER_DEG) -> np.ndarray:
    """``faces`` (T, 3) with each triangle whose smallest angle is below ``min_angle_deg``
    flipped with its neighbour across its longest edge, where that raises the pair's smallest
    angle (orientation kept; vertices, UVs and openings unchanged)."""
    faces = np.array(faces, dtype=np.int64)
    angles = triangle_angles(np.asarray(vertices, float)[faces])
    for t in np.flatnonzero(angles.min(axis=1) < min_angle_deg):
        k = int(np.argmax(angles[t]))  # the widest angle faces the longest edge
        apex, a, b = faces[t, k], faces[t, (k + 1) % 3], faces[t, (k + 2) % 3]
        other = np.flatnonzero((faces == a).any(axis=1) & (faces == b).any(axis=1))
        other = other[other != t]
        if len(other) != 1:  # a border edge: nothing to flip with
            continue
        far = int(np.setdiff1d(faces[other[0]], [a, b])[0])
        pair = np.array([[apex, a, far], [apex, far, b]])  # the quad apex-a-far-b, other diagonal
        if triangle_angles(vertices[pair]).min() > min(angles[t].min(), angles[other[0]].min()):
            faces[t], faces[other[0]] = pair
    return faces


@lru_cache(maxsize=1)
def template_openings() -> tuple[tuple[np.ndarray, np.ndarray], tuple[tuple[np.ndarray, np.ndarray], ...],
                                 np.ndarray]:
    """The template's mouth ``(upper, lower)`` rims, its eyes' ``(upper, lower)`` rims (right eye
    first) and its left/right vertex pairs (V,) (an involution; the midline maps to itself)."""
    from scipy.spatial import cKDTree

    from .eye_openings import boundary_loops

    vertices, faces, _ = _template()
    loops = boundary_loops(faces)
    border = max(loops, key=len)
    inner = [loop for loop in loops if loop is not border]
    nose_y = vertices[int(np.argmax(vertices[:, 2])), 1]
    mouth = min((loop for loop in inner if vertices[loop, 1].mean() < nose_y),
                key=lambda loop: vertices[loop, 1].mean())
    eyes = sorted((loop for loop in inner if vertices[loop, 1].mean() > nose_y),
                  key=lambda loop: vertices[loop, 0].mean())
    mirror = cKDTree(vertices).query(vertices * (-1.0, 1.0, 1.0))[1].astype(np.int64)
    return split_loop(vertices, mouth), tuple(split_loop(vertices, eye) for eye in eyes), mirror


def split_loop(vertices: np.ndarray, loop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An opening's loop split at its corners (smallest and largest X) into its upper and lower
    rims, each from the right corner to the left one (both corners in both)."""
    loop = np.roll(loop, -int(np.argmin(vertices[loop, 0])))
    right = int(np.argmax(vertices[loop, 0]))
    one = loop[:right + 1]
    other = np.concatenate([loop[right:], loop[:1]])[::-1]
    return (one, other) if vertices[one, 1].mean() > vertices[other, 1].mean() else (other, one)


def default_face(points: np.ndarray, *, spacing: float,
                 plane: tuple[np.ndarray, np.ndarray] | None = None,
                 lid_reach_mm: float = LID_REACH_MM,
                 sense_reach_mm: float | None = None, parts: bool = True) -> DefaultFace | None:
    """The ICT-FaceKit face fitted to the dense neutral ``points`` (N, 3) mm (rig frame: Y up,
    facing +Z; ``spacing`` their marker spacing, mm); ``plane`` ``(point, unit normal)`` makes it
    mirror-symmetric; ``lid_reach_mm`` how far the blink reaches from an eye, ``sense_reach_mm``
    that of the lids' ``sensed`` blink (None: the same field); ``parts`` fits
    the eyeballs and mouth interior too (:mod:`~mocaptk.retarget.face_parts`). None when the
    template does not fit (see :func:`fit_template`)."""
    points = np.asarray(points, dtype=float)
    template = fit_template(points, spacing=spacing)
    if template is None:
        return None
    _, faces, uv = _template()
    (upper, lower), eyes, mirror = template_openings()
    if len(points) > MAX_FIT_POINTS:
        points = points[np.linspace(0, len(points) - 1, MAX_FIT_POINTS).round().astype(np.int64)]
    vertices = _nonrigid(template.vertices, faces, points, spacing=spacing)
    if plane is not None:
        vertices = _symmetric(vertices, mirror, *plane)
    closed = vertices + closing_field(vertices, faces, [(upper, lower, 0.5)], reach_mm=LIP_REACH_MM)
    if plane is not None:
        closed = _symmetric(closed, mirror, *plane)
    lids = [Lid(top, bottom, *(closing_field(closed, faces, [(top, bottom, 0.0)], reach_mm=reach)
                               for reach in ([lid_reach_mm] if sense_reach_mm is None
                                             else [lid_reach_mm, sense_reach_mm])))
            for top, bottom in eyes]
    if plane is not None:  # the other eye's blink: the mirror image of the first's
        normal = np.asarray(plane[1], float) / np.linalg.norm(plane[1])

        def image(field: np.ndarray | None) -> np.ndarray | None:
            return None if field is None else (field[mirror]
                                               - 2.0 * (field[mirror] @ normal)[:, None] * normal)

        lids[1] = Lid(lids[1].upper, lids[1].lower, image(lids[0].blink), image(lids[0].sensed))
    fitted_parts = None
    if parts:
        fitted_parts = fit_parts(_template()[0], vertices, closed, faces, [lid.blink for lid in lids],
                                 symmetric=None if plane is None else
                                 (lambda p, m: _symmetric(p, m, *plane)))
    return DefaultFace(closed, vertices, faces, uv, upper, lower, tuple(lids),
                       None if plane is None else mirror, fitted_parts)


def lip_anchors(face: DefaultFace, anchors: np.ndarray, points: np.ndarray,
                jaw_following: np.ndarray) -> np.ndarray:
    """``anchors`` (N,) of the markers ``points`` (N, 3) mm on ``face.fitted``, each marker moved
    to the nearest vertex of its own lip where it was anchored on the other one: a marker that
    follows the jaw (``jaw_following`` (N,) bool) on the lower lip, one that does not on the upper.

    A lip's side is the rim it is geodesically nearer by :data:`LIP_SIDE_MARGIN_MM` (within
    :data:`LIP_SIDE_MM`; near the corners, where the rims meet, nothing moves). Where the
    template's lips fit an actor's less well, a lower-lip marker's closest point can be on the
    upper lip's inner roll, and the upper lip then follows the jaw (issue 30: a synthetic actor,
    5.5x at the upper lip's midline)."""
    from .influence import edge_graph, geodesic_distance

    graph = edge_graph(face.fitted, face.faces)
    upper = geodesic_distance(graph, face.upper_lip[1:-1], limit=LIP_SIDE_MM)
    lower = geodesic_distance(graph, face.lower_lip[1:-1], limit=LIP_SIDE_MM)
    on_upper = upper + LIP_SIDE_MARGIN_MM < lower
    on_lower = lower + LIP_SIDE_MARGIN_MM < upper
    out = np.array(anchors, dtype=np.int64)
    for side, wrong in ((on_lower, on_upper[out] & jaw_following),
                        (on_upper, on_lower[out] & ~jaw_following)):
        if wrong.any():
            own = np.flatnonzero(side)
            gap = np.linalg.norm(face.fitted[own][None] - np.asarray(points)[wrong][:, None], axis=2)
            out[wrong] = own[np.argmin(gap, axis=1)]
    return out


def _nonrigid(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, *,
              spacing: float) -> np.ndarray:
    """``vertices`` moved onto ``points`` by :data:`FIT_ROUNDS` rounds of a Gaussian RBF of
    the points' offsets from their closest surface points."""
    from scipy.interpolate import RBFInterpolator

    vertices = np.array(vertices, dtype=float)
    for _ in range(FIT_ROUNDS):
        closest, _, _ = SurfaceProximity(vertices, faces).query(points)
        field = RBFInterpolator(closest, points - closest, kernel="gaussian",
                                epsilon=1.0 / (RBF_WIDTH_SPACINGS * spacing),
                                smoothing=RBF_SMOOTHING, degree=-1)
        vertices += field(vertices)
    return vertices


def _symmetric(vertices: np.ndarray, mirror: np.ndarray, point: np.ndarray,
               normal: np.ndarray) -> np.ndarray:
    """``vertices`` averaged with their mirror vertices' reflections: mirror-symmetric."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    image = vertices[mirror]
    image = image - 2.0 * ((image - point) @ normal)[:, None] * normal
    return (vertices + image) / 2


def closing_field(vertices: np.ndarray, faces: np.ndarray,
             rims: list[tuple[np.ndarray, np.ndarray, float]], *, reach_mm: float) -> np.ndarray:
    """Displacements (V, 3) mm closing openings: each ``(upper, lower, line)`` rim pair meets on
    the curve ``lower + line (upper - lower)`` (at each rim vertex's arc-length fraction; line 0:
    the lower rim stays), and a biharmonic field carries it over, zero ``reach_mm`` away (the
    rims' ends near the corners follow the field)."""
    import igl
    from scipy.spatial import cKDTree

    fixed, values = [], []
    for upper, lower, line in rims:
        fixed += [upper, lower]
        values += [along_rim(vertices, upper, lower, line) - vertices[upper],
                   along_rim(vertices, lower, upper, 1.0 - line) - vertices[lower]]
    rim, first = np.unique(np.concatenate(fixed), return_index=True)  # corners: in both rims
    moved = np.concatenate(values)[first]
    # the rims' last CORNER_FREE_MM to each corner are left to the field: pinned there, where
    # the rims meet at an angle, the closing folded the corner's small triangles
    keep = ~np.isin(rim, np.concatenate([_near_corners(vertices, r) for r in fixed]))
    rim, moved = rim[keep], moved[keep]
    far = cKDTree(vertices[rim]).query(vertices)[0] > reach_mm
    far[np.setdiff1d(np.arange(len(vertices)), faces)] = True  # no triangle (a --mesh's eye cut)
    far = np.flatnonzero(far & ~np.isin(np.arange(len(vertices)), rim))
    b = np.concatenate([rim, far]).astype(np.int64)
    bc = np.concatenate([moved, np.zeros((len(far), 3))])
    return np.asarray(igl.harmonic(np.ascontiguousarray(vertices), np.ascontiguousarray(faces),
                                   b, bc, 2))


def _near_corners(vertices: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """The vertices of ``rim`` (corner to corner) within :data:`CORNER_FREE_MM` of arc length
    from either corner (the corners too)."""
    run = _fractions(vertices[rim]) * np.linalg.norm(np.diff(vertices[rim], axis=0), axis=1).sum()
    return rim[np.minimum(run, run[-1] - run) < CORNER_FREE_MM]


def along_rim(vertices: np.ndarray, rim: np.ndarray, other: np.ndarray, line: float) -> np.ndarray:
    """Points (K, 3) on the curve ``other + line (rim - other)`` at the arc-length fractions of
    ``rim``'s vertices (both rims run corner to corner)."""
    own = _fractions(vertices[rim])
    theirs = _fractions(vertices[other])
    across = np.stack([np.interp(own, theirs, vertices[other][:, k]) for k in range(3)], axis=1)
    return across + line * (vertices[rim] - across)


def _fractions(polyline: np.ndarray) -> np.ndarray:
    steps = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    run = np.concatenate([[0.0], np.cumsum(steps)])
    return run / run[-1]


def loop_area(points: np.ndarray) -> np.ndarray:
    """Area (...,) mm² enclosed by closed polygons ``points`` (..., K, 3) mm: half the norm of
    their vector area (0 for a closed seam, the opening's size when open)."""
    p = np.asarray(points, dtype=float)
    return 0.5 * np.linalg.norm(np.cross(p, np.roll(p, -1, axis=-2)).sum(axis=-2), axis=-1)
