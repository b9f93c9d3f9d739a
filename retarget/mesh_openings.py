"""The mouth and eye openings cut on a user's ``--mesh`` (issue 30).

A production face often has its lips joined (the MediaPipe canonical face is one sheet over the
mouth): skinned as it is, the lips stretch into a membrane when the jaw opens. The lip line is
found from the landmarks and the geometry: the bundled ICT-FaceKit face, fitted to the dense
neutral markers (:func:`~mocaptk.retarget.face_template.fit_template`), gives the mouth's corners
and the mid-curve between its inner-lip rims; the cut is the mesh's shortest edge path between
the mesh vertices nearest those corners, each edge's length weighted up by its distance from
that mid-curve. The path's inner vertices are duplicated, the triangles below the path taking
the copies: the lips become two rims of one opening, so no weight crosses it (weights follow
the mesh's edges) and they part when the jaw opens. A mesh that already has its own mouth
opening (a hole there, or lips that roll into a mouth socket) is left as it is.

Covered eyes (MediaPipe's) are opened the same way: each eye's rims are the mesh's edge paths
nearest the template's upper and lower eye rims, the triangles between them are removed, and
the lids are made as the default face's (:func:`mesh_lids`).

Corner landmarks (:data:`CORNERS`, ``--landmarks`` keys naming a vertex of the given mesh) steer
both: the template's curves are bent so that their ends fall on the given corners.
Only the skin is opened (the mesh's largest connected part, :func:`~mocaptk.retarget.mesh_parts.skin_faces`):
teeth, eyeballs and lashes are separate parts. :func:`open_mesh` does all of it, for ``rig``
and ``solve`` alike.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.surface_mesh import boundary_edges, mesh_edges

from .default_face import (EYE_CORNER_MM, LID_REACH_MM, Lid, along_rim, closing_field, loop_area,
                           split_loop, template_openings)
from .eye_openings import eye_loops
from .face_template import FittedTemplate
from .mesh_parts import beyond_markers, head_jaw_rows, nose_height, part_weights, skin_faces

__all__ = ["CORNERS", "LipCut", "OpenedMesh", "cut_lip_line", "eye_corner_reach", "fill_sockets", "kept_out",
           "lip_midcurve", "lip_path", "lips_joined", "mesh_lids", "open_mesh", "parts_follow",
           "split_along", "weighted_faces"]

#: Corner landmarks: the ends of the mouth's and each eye's rims, subject's right (R, smaller X)
#: to left, as the template's rims run.
CORNERS = ("mouth_R", "mouth_L", "eye_R_outer", "eye_R_inner", "eye_L_inner", "eye_L_outer")
#: Up in the rig frame.
UP = np.array([0.0, 1.0, 0.0])

#: An edge this far (mm) from the template's lip mid-curve costs twice its length on the path.
LIP_PATH_MM = 1.5
#: Lips are joined when the surface path across them (from this far, mm, above the lip line to
#: as far below) is under DETOUR times the straight distance (sample: MediaPipe 1.0x; the
#: ICT-FaceKit head, whose lips roll into its mouth socket, no path: it is not cut).
LIPS_ACROSS_MM = 4.0
DETOUR = 2.0
#: The piece of mesh an eye's rims enclose is a socket (the lids roll into it: not cut), not a
#: film over the eye, when its area is over this many times the aperture's (the MediaPipe
#: face: 1.0; the ICT-FaceKit head: its sockets, much more).
SOCKET_AREA = 2.0
#: Eyes whose lids roll into a socket blend their corners this much farther (no weight crosses
#: the socket, so the lid closes fully and its joint is the 5th influence of rows by the outer
#: corner, dropped by the cap; chosen on the ICT-FaceKit head, sample, 4 influences: at 1x one
#: triangle backward by the outer corner at the fullest blink, at 1.25x none and the aperture
#: 17.5 % of rest, at 1.5x none and 22 %).
SOCKET_CORNER_SCALE = 1.25


@dataclass(frozen=True, eq=False)
class LipCut:
    """A mesh cut along its lip line: ``vertices`` (V + K, 3) mm and ``faces`` (T, 3) with the
    path's K inner vertices duplicated (the copies last, taken by the lower lip's triangles);
    ``path`` (K + 2,) the original vertex indices from the right corner to the left one."""

    vertices: np.ndarray
    faces: np.ndarray
    path: np.ndarray

    @property
    def corners(self) -> np.ndarray:
        return self.path[[0, -1]]

    @property
    def edges(self) -> np.ndarray:
        """The cut edges (K + 1, 2) as original vertex index pairs."""
        return np.stack([self.path[:-1], self.path[1:]], axis=1)


def lip_midcurve(template: FittedTemplate, corners: Mapping[str, np.ndarray] | None = None
                 ) -> np.ndarray:
    """The fitted template's lip mid-curve (K, 3) mm, right corner to left: midway between its
    inner-lip rims at each upper-rim vertex's arc-length fraction, its ends bent onto the
    ``corners`` ``mouth_R``/``mouth_L`` (3,) mm given (:func:`bent`)."""
    (upper, lower), _, _ = template_openings()
    return bent(along_rim(template.vertices, upper, lower, 0.5), corners, "mouth_R", "mouth_L")


def bent(curve: np.ndarray, corners: Mapping[str, np.ndarray] | None, first: str, last: str
         ) -> np.ndarray:
    """``curve`` (K, 3) mm with its ends moved onto ``corners[first]`` / ``corners[last]`` (3,)
    mm where given, each point by the ends' shifts blended along the arc length."""
    corners = corners or {}
    if first not in corners and last not in corners:
        return curve
    run = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    t = (run / run[-1])[:, None]
    start = np.asarray(corners.get(first, curve[0]), float) - curve[0]
    end = np.asarray(corners.get(last, curve[-1]), float) - curve[-1]
    return curve + (1.0 - t) * start + t * end


def lip_path(vertices: np.ndarray, faces: np.ndarray, curve: np.ndarray, *,
             tolerance_mm: float = LIP_PATH_MM) -> np.ndarray | None:
    """Vertex path (K,) int64 through the mesh's interior from the vertex nearest ``curve[0]``
    to the one nearest ``curve[-1]`` ((K, 3) mm), each edge's length times 1 + (d / tolerance)²
    for d its midpoint's distance from the curve; None when no such path (or a corner on the
    mesh's border)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, dtype=float)
    curve = np.asarray(curve, dtype=float)
    dense = np.concatenate([np.linspace(a, b, 8, endpoint=False) for a, b in zip(curve[:-1], curve[1:])]
                           + [curve[-1:]])
    edges, _ = mesh_edges(faces)
    a, b = edges[:, 0], edges[:, 1]
    border = np.zeros(len(vertices), bool)
    border[boundary_edges(faces).ravel()] = True
    inside = ~(border[a] | border[b])  # an opening's rim has no border vertex
    a, b = a[inside], b[inside]
    distance = cKDTree(dense).query((vertices[a] + vertices[b]) / 2)[0]
    cost = np.linalg.norm(vertices[a] - vertices[b], axis=1) * (1.0 + (distance / tolerance_mm) ** 2)
    graph = sp.coo_matrix((cost, (a, b)), shape=(len(vertices),) * 2).tocsr()
    used = np.unique(faces)  # not another part's vertices
    tree = cKDTree(vertices[used])
    start, end = (int(used[tree.query(p)[1]]) for p in (curve[0], curve[-1]))
    if border[start] or border[end] or start == end:
        return None
    _, previous = dijkstra(graph, directed=False, indices=start, return_predecessors=True)
    if previous[end] < 0:
        return None
    path = [end]
    while path[-1] != start:
        path.append(int(previous[path[-1]]))
    return np.array(path[::-1], dtype=np.int64)


def split_along(vertices: np.ndarray, faces: np.ndarray, path: np.ndarray, *,
                up: np.ndarray) -> LipCut | None:
    """The mesh opened along ``path`` (K,) (its ends stay joined): each inner vertex's triangles
    on the ``up`` (3,) side keep it, the others take its copy. None where a path vertex's
    triangles are not two fans split by the path (a non-manifold vertex)."""
    vertices = np.asarray(vertices, dtype=float)
    faces = np.array(faces, dtype=np.int64)
    original = faces.copy()
    copies = []
    for k in range(1, len(path) - 1):
        v, neighbours = int(path[k]), {int(path[k - 1]), int(path[k + 1])}
        fan = np.flatnonzero((original == v).any(axis=1))
        group = np.arange(len(fan))
        changed = True
        while changed:  # join triangles sharing an edge through v that is not on the path
            changed = False
            for i in range(len(fan)):
                for j in range(i + 1, len(fan)):
                    shared = (set(original[fan[i]].tolist()) & set(original[fan[j]].tolist())) - {v}
                    if shared and not shared <= neighbours and group[i] != group[j]:
                        group[group == group[j]] = group[i]
                        changed = True
        sides = np.unique(group)
        if len(sides) != 2:
            return None
        height = [((vertices[original[fan[group == s]]].mean(axis=1) - vertices[v]) @ up).mean()
                  for s in sides]
        lower = fan[group == sides[int(np.argmin(height))]]
        copy = len(vertices) + len(copies)
        faces[lower] = np.where(original[lower] == v, copy, faces[lower])
        copies.append(v)
    return LipCut(np.concatenate([vertices, vertices[copies]]), faces, np.asarray(path, np.int64))


def lips_joined(vertices: np.ndarray, faces: np.ndarray, curve: np.ndarray, *,
                up: np.ndarray, across_mm: float = LIPS_ACROSS_MM) -> bool:
    """Whether the mesh's lips are joined at the middle of the lip ``curve`` (K, 3) mm: the
    surface path between the vertices nearest ``across_mm`` above and below it is under
    :data:`DETOUR` times their distance. A mouth hole, or lips that roll into a mouth socket
    (the ICT-FaceKit head), make it a long way round."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra
    from scipy.spatial import cKDTree

    vertices = np.asarray(vertices, dtype=float)
    middle = curve[len(curve) // 2]
    used = np.unique(faces)  # not another part's vertices
    ends = used[cKDTree(vertices[used]).query([middle + across_mm * up, middle - across_mm * up])[1]]
    straight = float(np.linalg.norm(vertices[ends[0]] - vertices[ends[1]]))
    edges, _ = mesh_edges(faces)
    length = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    graph = sp.coo_matrix((length, (edges[:, 0], edges[:, 1])), shape=(len(vertices),) * 2).tocsr()
    around = dijkstra(graph, directed=False, indices=int(ends[0]), limit=DETOUR * straight)[ends[1]]
    return bool(straight > 0 and around < DETOUR * straight)


def cut_lip_line(vertices: np.ndarray, faces: np.ndarray, template: FittedTemplate | None, *,
                 up: np.ndarray, corners: Mapping[str, np.ndarray] | None = None) -> LipCut | None:
    """The mesh cut along its lip line (see the module; ``corners`` as :func:`lip_midcurve`),
    or None: no template fit, lips that are not joined (:func:`lips_joined`), or no clean path."""
    if template is None:
        return None
    curve = lip_midcurve(template, corners)
    if not lips_joined(vertices, faces, curve, up=up):
        return None
    path = lip_path(vertices, faces, curve)
    return None if path is None or len(path) < 3 else split_along(vertices, faces, path, up=up)


def mesh_lids(vertices: np.ndarray, faces: np.ndarray, template: FittedTemplate | None, *,
              corners: Mapping[str, np.ndarray] | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[Lid, ...], np.ndarray]:
    """``(vertices, faces, kept, lids, sockets)``: the mesh with eye openings, ``kept`` (V',) the
    given vertex of each of its vertices, the two eyes' :class:`~mocaptk.retarget.default_face.Lid`
    (right eye first; each with its full blink, the upper rim onto the lower, as on the default
    face) and ``sockets`` (S,) the triangles of eye sockets the lids roll into (below). A mesh with its own eye holes keeps them; on a mesh whose eyes are covered, each
    eye's rims are the mesh's edge paths nearest the fitted template's upper and lower rims
    (:func:`lip_path`), the triangles they enclose are removed and so are the vertices no
    triangle uses any more (a glTF reader drops them). No lids (and the mesh unchanged) unless
    two eyes result. An eye whose lids are not joined (:func:`lips_joined` at the middle of its
    aperture: lids that roll into a socket) is not cut: its rims are those edge paths, its lid
    margins, and the triangles they enclose are its ``sockets``. ``corners`` (``eye_*`` of
    :data:`CORNERS`, (3,) mm) bend the template's rims
    onto them (:func:`bent`), and split an eye hole of the mesh's own at the loop vertices
    nearest them. Vertices ``faces`` does not use stay (another part's)."""
    kept = np.arange(len(vertices))
    none = np.zeros(0, dtype=np.int64)
    loops = eye_loops(vertices, faces)
    opened = faces
    ends = (("eye_R_outer", "eye_R_inner"), ("eye_L_inner", "eye_L_outer"))
    sockets = []  # eyes open into a socket (no hole: the ICT-FaceKit head's): rims, triangles
    if len(loops) != 2 and template is not None:
        _, eyes, _ = template_openings()
        for (upper, lower), (first, last) in zip(eyes, ends):
            opened, socket = _eye_hole(vertices, opened,
                                       bent(template.vertices[upper], corners, first, last),
                                       bent(template.vertices[lower], corners, first, last))
            if socket is not None:
                sockets.append(socket)
        loops = eye_loops(vertices, opened)
    if len(sockets) == 2:
        return vertices, faces, kept, tuple(
            Lid(upper, lower, closing_field(vertices, faces, [(upper, lower, 0.0)],
                                            reach_mm=LID_REACH_MM)) for upper, lower, _ in sockets
        ), np.concatenate([inside for _, _, inside in sockets])
    if len(loops) != 2:
        return vertices, faces, kept, (), none
    gone = np.setdiff1d(np.unique(faces), np.unique(opened))
    if gone.size:  # the covered eyes' inner vertices
        kept = np.setdiff1d(kept, gone)
        new = np.full(len(vertices), -1, dtype=np.int64)
        new[kept] = np.arange(len(kept))
        vertices, opened = vertices[kept], new[opened]
        loops = [new[loop] for loop in loops]
    loops = sorted(loops, key=lambda l: vertices[l, 0].mean())
    rims = [_split_at(vertices, loop, corners, first, last) for loop, (first, last) in zip(loops, ends)]
    return vertices, opened, kept, tuple(
        Lid(upper, lower, closing_field(vertices, opened, [(upper, lower, 0.0)], reach_mm=LID_REACH_MM))
        for upper, lower in rims), none


def _split_at(vertices: np.ndarray, loop: np.ndarray, corners: Mapping[str, np.ndarray] | None,
              first: str, last: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`split_loop`, at the loop's vertices nearest ``corners[first]`` and ``[last]`` when
    both are given."""
    corners = corners or {}
    if first not in corners or last not in corners:
        return split_loop(vertices, loop)
    right, left = (int(np.argmin(np.linalg.norm(vertices[loop] - corners[k], axis=1)))
                   for k in (first, last))
    loop = np.roll(loop, -right)
    left = (left - right) % len(loop)
    one, other = loop[:left + 1], np.concatenate([loop[left:], loop[:1]])[::-1]
    return (one, other) if vertices[one, 1].mean() > vertices[other, 1].mean() else (other, one)


def _eye_hole(vertices: np.ndarray, faces: np.ndarray, upper: np.ndarray, lower: np.ndarray
              ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
    """``(faces, socket)``: ``faces`` without the triangles enclosed by the mesh's edge paths
    nearest the ``upper`` and ``lower`` rim curves (K, 3) mm (corner to corner), down to the
    lid margin (:func:`_margin_band`); unchanged where the paths do not enclose a piece of the
    mesh, or where it is a socket (:data:`SOCKET_AREA`): then ``socket`` is the two paths, the
    lid margins, and the enclosed triangles (S,)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    top, bottom = lip_path(vertices, faces, upper), lip_path(vertices, faces, lower)
    if top is None or bottom is None or set(top[1:-1].tolist()) & set(bottom[1:-1].tolist()):
        return faces, None
    rim = {tuple(sorted(e)) for path in (top, bottom) for e in zip(path[:-1].tolist(), path[1:].tolist())}
    faces = np.asarray(faces, dtype=np.int64)
    sides = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2)  # (T, 3, 2)
    edge_of = {}
    links = []
    for t, edges in enumerate(sides.tolist()):
        for edge in map(tuple, edges):
            if edge in rim:
                continue
            if edge in edge_of:
                links.append((edge_of[edge], t))
            else:
                edge_of[edge] = t
    pairs = np.array(links, dtype=np.int64).reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(faces),) * 2)
    _, part = connected_components(graph, directed=False)
    touching = np.unique(part[[t for t, edges in enumerate(sides.tolist())
                               if any(tuple(e) in rim for e in edges)]])
    if len(touching) < 2:
        return faces, None
    inside = part == touching[int(np.argmin(np.bincount(part)[touching]))]
    corners = vertices[faces[inside]]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                                axis=1).sum()
    if area > SOCKET_AREA * loop_area(vertices[np.concatenate([top, bottom[::-1][1:-1]])]):
        return faces, (top, bottom, np.flatnonzero(inside))
    return faces[~inside | _margin_band(vertices, faces, inside, top, bottom)], None


def _margin_band(vertices: np.ndarray, faces: np.ndarray, inside: np.ndarray, top: np.ndarray,
                 bottom: np.ndarray) -> np.ndarray:
    """Which enclosed triangles (T,) bool lie between a path and the lid margin inside it: a
    vertex only the enclosed triangles use is the margin where the template's rim ran outside
    the mesh's own (MediaPipe's outer halves, one ring out). Each such vertex sides with the
    path whose inner vertices are nearer (a path's corner, or a vertex nearest one, sides with
    both); a triangle with such a vertex, a path vertex and every vertex on one side is kept,
    so the hole's rim is the margin. A triangle across the eye (upper and lower) stays out."""
    from scipy.spatial import cKDTree

    covered = np.setdiff1d(np.unique(faces[inside]), np.unique(faces[~inside]))
    keep = np.zeros(len(faces), bool)
    if not covered.size:
        return keep
    corners = np.array([top[0], top[-1]])
    path = np.concatenate([corners, top[1:-1], bottom[1:-1]])
    side = np.concatenate([[0, 0], np.full(len(top) - 2, 1), np.full(len(bottom) - 2, 2)])
    near = side[cKDTree(vertices[path]).query(vertices[covered])[1]]
    label = np.full(len(vertices), -1)
    label[path], label[covered] = side, near
    of = label[faces]  # -1: neither (not on a path, not covered)
    margin = np.isin(faces, covered).any(axis=1) & np.isin(faces, path).any(axis=1)
    upper = np.isin(of, (0, 1)).all(axis=1)
    lower = np.isin(of, (0, 2)).all(axis=1)
    return inside & margin & (upper | lower)


def _mouth_corners(vertices: np.ndarray, faces: np.ndarray, template: FittedTemplate | None,
                   corners: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """The skin vertices (2,) nearest the ends of the lip mid-curve (a mesh with its own mouth
    opening: where its corners' weights are blended), None without a template."""
    from scipy.spatial import cKDTree

    if template is None:
        return None
    curve = lip_midcurve(template, corners)
    used = np.unique(faces)
    return used[cKDTree(vertices[used]).query(curve[[0, -1]])[1]]


def kept_out(kept: np.ndarray, count: int) -> list[int]:
    """The vertices of ``range(count)`` not in ``kept`` (sorted), for the rig report."""
    return np.setdiff1d(np.arange(count), kept).tolist()


@dataclass(frozen=True, eq=False)
class OpenedMesh:
    """A user's mesh with its openings (:func:`open_mesh`): ``vertices`` (V', 3) mm, ``faces``
    (T', 3) (the first ``skin`` are the skin's, the other parts' after them), ``source`` (V',)
    the given vertex of each vertex (a lip copy: its original), the ``lip_cut`` (None: not cut;
    its vertex numbers the given mesh's), the eyes' ``lids``, the ``mouth_corners`` (2,) (the
    cut's ends, else the skin vertices nearest the template's; None: no template) and the eye
    cut's ``eye_report`` for the rig report (None: no lids); ``eye_corner_mm`` how far the
    eyes' corners blend the weights (:func:`eye_corner_reach`); ``sockets`` (S,) the skin's
    triangles inside eyes whose lids roll into a socket (:func:`mesh_lids`; no weight crosses
    them: :func:`weighted_faces`, :func:`fill_sockets`)."""

    vertices: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    skin: int
    lip_cut: LipCut | None
    lids: tuple[Lid, ...]
    mouth_corners: np.ndarray | None
    eye_report: dict[str, Any] | None
    eye_corner_mm: float = EYE_CORNER_MM
    sockets: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def open_mesh(vertices: np.ndarray, faces: np.ndarray, template: FittedTemplate | None, *,
              corners: Mapping[str, int] | None = None, up: np.ndarray = UP) -> OpenedMesh:
    """The given mesh ``vertices`` (V, 3) mm (rig frame: Y up, facing +Z), ``faces`` (T, 3)
    with its skin cut along the lip line (:func:`cut_lip_line`) and its eyes opened, with lids
    (:func:`mesh_lids`), steered by ``corners`` ({:data:`CORNERS` key: vertex of the given
    mesh}); the other parts' triangles follow, unchanged. ``rig --mesh`` and ``solve --mesh``
    both open their mesh with this."""
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    bad = [k for k, v in (corners or {}).items() if not 0 <= int(v) < len(vertices)]
    if bad:
        raise OptionError(f"landmark {bad[0]}: vertex index must be in 0..{len(vertices) - 1}")
    points = {k: vertices[int(v)] for k, v in (corners or {}).items()}
    skin = skin_faces(faces)
    own, others = faces[skin], faces[~skin]
    source = np.arange(len(vertices))
    lip_cut = cut_lip_line(vertices, own, template, up=up, corners=points)
    mouth = _mouth_corners(vertices, own, template, points)
    if lip_cut is not None:  # the lips become two rims of one opening
        vertices, own, mouth = lip_cut.vertices, lip_cut.faces, lip_cut.corners
        source = np.concatenate([source, lip_cut.path[1:-1]])
    before, count = len(own), len(vertices)
    vertices, own, kept, lids, sockets = mesh_lids(vertices, own, template, corners=points)
    report = None
    if lids:
        report = {"method": "the mesh's edge paths nearest the ICT-FaceKit face's eye rims",
                  "openings": len(lids), "triangles_removed": before - len(own),
                  "vertices_removed": kept_out(kept, count)}
        mouth = None if mouth is None else np.searchsorted(kept, mouth)
        others = np.searchsorted(kept, others)  # the other parts keep every vertex
    return OpenedMesh(vertices, np.concatenate([own, others]), source[kept], len(own), lip_cut,
                      lids, mouth, report, eye_corner_reach(vertices, lids, template)
                      * (SOCKET_CORNER_SCALE if len(sockets) else 1.0), sockets)


def eye_corner_reach(vertices: np.ndarray, lids: tuple[Lid, ...], template: FittedTemplate | None
                     ) -> float:
    """How far (mm) an eye's corners blend the weights (:data:`EYE_CORNER_MM` on the default
    face): scaled by the eyes' opening area over the fitted template's, between half and whole
    (MediaPipe's eyes, 123 mm² against 250 mm²: at 12 mm the blend held the lids open, 27 % of
    the aperture left at the fullest blink; 21 % at 8 mm, 19 % at 6 mm)."""
    if template is None or not lids:
        return EYE_CORNER_MM
    _, eyes, _ = template_openings()
    own = np.mean([loop_area(vertices[np.concatenate([lid.upper, lid.lower[::-1][1:-1]])])
                   for lid in lids])
    theirs = np.mean([loop_area(template.vertices[np.concatenate([upper, lower[::-1][1:-1]])])
                      for upper, lower in eyes])
    return EYE_CORNER_MM * float(np.clip(own / theirs, 0.5, 1.0))


def parts_follow(weights: np.ndarray, opened: OpenedMesh, markers: np.ndarray, *, head: int,
                 regions: Sequence[str], positions: np.ndarray, columns: np.ndarray | None = None,
                 jaw_count: int, spacing: float, template: FittedTemplate | None) -> np.ndarray:
    """``weights`` (V, K) of ``opened``'s vertices (rig frame) with its skin beyond the dense
    ``markers`` (M, 3) mm blended towards the head's row
    (:func:`~mocaptk.retarget.mesh_parts.beyond_markers`) and the rows of its parts other than
    the skin set (:func:`~mocaptk.retarget.mesh_parts.part_weights`), as ``rig --mesh`` and
    ``solve --mesh`` both weight them.

    The rows (:func:`~mocaptk.retarget.mesh_parts.head_jaw_rows`): the head's all on column
    ``head`` of ``positions`` (J, 3) mm (rig frame; the one that moves least), the jaw's on its
    ``jaw_count`` lowest jaw columns (by ``regions`` (J,)), equally; they are the weights'
    ``columns`` (J,) (default the first J), the other columns (the lids') get nothing. The
    mouth's line is the ``template``'s lip mid-curve, without one the jaw's highest column."""
    positions = np.asarray(positions, dtype=float)
    columns = np.arange(len(positions)) if columns is None else np.asarray(columns, dtype=np.int64)
    head_row, jaw_row = np.zeros((2, np.shape(weights)[1]))
    head_row[columns], jaw_row[columns] = head_jaw_rows(head, regions, positions, count=jaw_count)
    nose_y = nose_height(opened.vertices, opened.faces, opened.skin)
    mouth_y = (float(lip_midcurve(template)[:, 1].mean()) if template is not None
               else float(positions[jaw_row[columns] > 0, 1].max()))
    weights = beyond_markers(weights, opened.vertices, markers, head=head_row, spacing=spacing,
                             mouth_y=mouth_y)
    return part_weights(weights, opened.vertices, opened.faces, opened.skin, head=head_row,
                        jaw=jaw_row, mouth_y=mouth_y, nose_y=nose_y,
                        margins=[rim for lid in opened.lids for rim in (lid.upper, lid.lower)])


def weighted_faces(opened: OpenedMesh) -> np.ndarray:
    """``opened``'s triangles (T', 3) the weights are solved on: all but its eye sockets'. The
    socket joins the upper lid to the lower one a few mm behind the margins, so weights solved
    across it moved the lower lid with the markers under the brow (the ICT-FaceKit head: 0.63 of
    EYE_08 on its lower rim, 3.5-4.4 mm down in a blink, the lid closing to 30 % of the
    aperture); the eyes are openings, as the default face's are, and no weight crosses them."""
    keep = np.ones(len(opened.faces), bool)
    keep[opened.sockets] = False
    return opened.faces[keep]


def fill_sockets(weights: np.ndarray, opened: OpenedMesh) -> np.ndarray:
    """``weights`` (V, J) (solved on :func:`weighted_faces`) with the rows of the vertices only
    the eye sockets use filled biharmonically over the sockets from their rims' rows (upper lid
    to lower: the socket moves between them, without a crease; sample, ICT-FaceKit head at the
    fullest blink: harmonic 2 triangles backward, biharmonic 1)."""
    import igl

    weights = np.array(weights, dtype=float)
    if not len(opened.sockets):
        return weights
    socket = opened.faces[opened.sockets]
    inner = np.setdiff1d(np.unique(socket), weighted_faces(opened))
    used = np.unique(socket)
    local = np.full(len(opened.vertices), -1, dtype=np.int64)
    local[used] = np.arange(len(used))
    rim = np.setdiff1d(used, inner)
    weights[inner] = igl.harmonic(np.ascontiguousarray(opened.vertices[used]),
                                  np.ascontiguousarray(local[socket]), local[rim],
                                  np.ascontiguousarray(weights[rim]), 2)[local[inner]]
    return weights
