"""The default face's eyeballs and mouth interior (issue 30): ICT-FaceKit's (MIT) eyeballs, 32
teeth and mouth socket, fitted into the actor's face as the face itself is fitted.

Without them the default face's eyes and mouth are see-through holes. The parts ship with the
package (``data/ict_face_parts.npz``, written by ``scripts/bundle_ict_face.py``, decimated to
2,864 vertices, 42 KB) and are placed in :func:`~mocaptk.retarget.default_face.default_face`:

- each eyeball by the similarity that best carries the template face around it (lids, orbit)
  onto the fitted face, the teeth and the socket by that of the face around the mouth (the
  face's own similarity ICP alone can leave them 40 mm off where the non-rigid fit moves the
  face far; an eyeball stays a ball), made mirror-symmetric with the face;
- the socket's lip vertices are the face's own rim vertices, so it closes with the lips (a
  harmonic field over the socket, zero :data:`SOCKET_REACH_MM` from the lips);
- a rigid piece that would show in front of the skin (at rest; an eyeball also at a full blink)
  is moved back along the view until it is :data:`BEHIND_MM` behind it.

The rig and ``solve``'s mesh move them as a user mesh's parts
(:func:`~mocaptk.retarget.mesh_parts.part_weights`: eyeballs and upper teeth with the head, lower
teeth with the jaw, the socket from the head at its top to the jaw at its bottom), the socket's
lip vertices with their lip (:func:`socket_rows`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from mocaptk.geometry import similarity_transform

__all__ = ["BEHIND_MM", "PARTS_FILE", "SOCKET_REACH_MM", "FaceParts", "fit_parts",
           "in_front", "socket_rows", "template_parts"]

#: The parts, packaged with mocaptk.retarget (ICT-FaceKit, MIT; its licence beside it).
PARTS_FILE = "data/ict_face_parts.npz"
#: A rigid part is moved back until it is this far (mm) behind the skin along the view.
BEHIND_MM = 1.0
#: An eyeball is placed by the face within this (mm) of its centre (its lids and orbit)...
EYE_REGION_MM = 25.0
#: ... the teeth and the socket by the face within this (mm) of the lips' centre.
MOUTH_REGION_MM = 30.0
#: The socket closes with the lips within this (mm) of them; its weights blend from its lip's
#: to the head-jaw blend over the same distance.
SOCKET_REACH_MM = 10.0


@dataclass(frozen=True, eq=False)
class FaceParts:
    """The fitted parts: ``vertices`` (P, 3) mm (rig frame), ``faces`` (Tp, 3) into them,
    ``material`` (Tp,) index into :data:`~mocaptk.retarget.face_materials.MATERIALS`,
    ``attach`` (P,) the face vertex a socket vertex is (-1: none) and ``mirror`` (P,) each
    vertex's mirror vertex (None: not symmetric)."""

    vertices: np.ndarray
    faces: np.ndarray
    material: np.ndarray
    attach: np.ndarray
    mirror: np.ndarray | None


@lru_cache(maxsize=1)
def template_parts() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The bundled parts in the template's frame: vertices (P, 3) mm, triangles (Tp, 3),
    materials (Tp,) (:data:`~mocaptk.retarget.face_materials.MATERIALS` index: the bundle's + 1),
    ``attach`` (P,) and the rigid groups (P,) (0 right eyeball, 1 left, 2 upper teeth, 3 lower
    teeth, -1 the socket)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    with resources.files(__package__).joinpath(PARTS_FILE).open("rb") as handle:
        with np.load(handle, allow_pickle=False) as data:
            vertices = data["vertices"].astype(np.float64)
            faces = data["triangles"].astype(np.int64)
            material = data["material"].astype(np.int64) + 1
            attach = data["attach"].astype(np.int64)
    kind = np.zeros(len(vertices), dtype=np.int64)
    kind[faces.ravel()] = np.repeat(material, 3)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    _, piece = connected_components(sp.coo_matrix((np.ones(len(edges)), edges.T),
                                                  shape=(len(vertices),) * 2), directed=False)
    centre_y = np.bincount(piece, vertices[:, 1]) / np.bincount(piece)  # a tooth's, not a vertex's
    teeth = centre_y[piece[kind == 3]]
    mouth_y = (teeth.min() + teeth.max()) / 2  # between the rows (-20..-26 and -38..-44 mm)
    group = np.where(kind <= 2, (vertices[:, 0] > 0).astype(np.int64),
                     np.where(kind == 3, 2 + (centre_y[piece] < mouth_y), -1))
    return vertices, faces, material, attach, group


def fit_parts(template: np.ndarray, fitted: np.ndarray, closed: np.ndarray, face_faces: np.ndarray,
              lid_blinks: list[np.ndarray], *,
              symmetric: Callable[[np.ndarray, np.ndarray], np.ndarray] | None) -> FaceParts:
    """The parts fitted into the face: ``template`` (V, 3) mm the bundled face region,
    ``fitted`` (V, 3) mm it fitted to the actor (lips apart), ``closed`` (V, 3) mm with its lips
    closed, ``face_faces`` (T, 3), ``lid_blinks`` the lids' full-blink displacements (V, 3) mm
    (an eyeball is kept behind the skin at rest and at each full blink, the teeth at rest);
    ``symmetric(points, mirror)`` makes points mirror-symmetric (None: the face is not)."""
    vertices, faces, material, attach, group = template_parts()
    out = np.empty_like(vertices)
    for members, near in _regions(template, vertices, attach, group):
        out[members] = similarity_transform(template[near], fitted[near]).apply(vertices[members])
    mirror = None
    if symmetric is not None:
        from scipy.spatial import cKDTree

        mirror = cKDTree(vertices).query(vertices * (-1.0, 1.0, 1.0))[1].astype(np.int64)
        out = symmetric(out, mirror)
        for g in range(4):  # each eyeball, the upper and lower teeth: rigid again
            members = np.flatnonzero(group == g)
            out[members] = similarity_transform(vertices[members], out[members]).apply(vertices[members])
    socket = group < 0
    placed = out.copy()
    out[attach >= 0] = closed[attach[attach >= 0]]
    out[socket] += _socket_closing(placed, faces, attach, closed)[socket]
    # the view: the template's +Z (its face's forward) as the face was fitted (solve's rig frame
    # is not always facing +Z: the sample's is turned 38 degrees)
    view = similarity_transform(template, fitted).rotation[:, 2]
    skins = [closed] + [closed + blink for blink in lid_blinks]
    back = np.zeros(len(out))
    for g in range(4):
        members = np.flatnonzero(group == g)
        depth = max(float(np.max(in_front(out[members], skin, face_faces, view=view), initial=-np.inf))
                    for skin in (skins if g < 2 else skins[:1]))
        back[members] = max(depth + BEHIND_MM, 0.0)
    if mirror is not None:  # an eyeball goes as far back as its mirror image
        back = np.maximum(back, back[mirror])
    out -= back[:, None] * view
    return FaceParts(out, faces, material, attach, mirror)


def _regions(template: np.ndarray, vertices: np.ndarray, attach: np.ndarray, group: np.ndarray
             ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each rigidly placed set of part vertices and the face vertices that place it: an eyeball
    by the face within :data:`EYE_REGION_MM` of its centre, the mouth's parts together by the
    face within :data:`MOUTH_REGION_MM` of the lips' centre (``template`` (V, 3) mm the face)."""
    found = []
    for g in (0, 1):
        members = np.flatnonzero(group == g)
        centre = vertices[members].mean(axis=0)
        found.append((members, np.flatnonzero(np.linalg.norm(template - centre, axis=1) < EYE_REGION_MM)))
    lips = template[attach[attach >= 0]].mean(axis=0)
    found.append((np.flatnonzero((group < 0) | (group >= 2)),
                  np.flatnonzero(np.linalg.norm(template - lips, axis=1) < MOUTH_REGION_MM)))
    return found


def _socket_closing(placed: np.ndarray, faces: np.ndarray, attach: np.ndarray,
                    closed: np.ndarray) -> np.ndarray:
    """The socket's displacements (P, 3) mm from ``placed`` as its lip vertices go onto the
    face's closed lips: harmonic over the socket, zero :data:`SOCKET_REACH_MM` from them."""
    socket, _ = _socket_mesh(faces)
    rim = attach[socket] >= 0
    shift = np.zeros_like(placed)
    shift[socket] = _over_socket(placed, faces, attach, closed[attach[socket][rim]] - placed[socket][rim],
                                 np.zeros((len(socket), 3)))
    shift[attach >= 0] = 0.0  # already on the rims
    return shift


def _over_socket(vertices: np.ndarray, faces: np.ndarray, attach: np.ndarray, at_lips: np.ndarray,
                 beyond: np.ndarray) -> np.ndarray:
    """Values (S, k) over the socket's vertices, harmonic on it: ``at_lips`` (R, k) at its lip
    vertices (``attach`` >= 0, in order), ``beyond`` (S, k) where it is :data:`SOCKET_REACH_MM`
    or farther from them (``vertices`` (P, 3) mm the parts')."""
    import igl
    from scipy.spatial import cKDTree

    socket, tris = _socket_mesh(faces)
    rim = np.flatnonzero(attach[socket] >= 0)
    far = np.flatnonzero(cKDTree(vertices[socket][rim]).query(vertices[socket])[0] >= SOCKET_REACH_MM)
    return np.asarray(igl.harmonic(np.ascontiguousarray(vertices[socket]), np.ascontiguousarray(tris),
                                   np.concatenate([rim, far]).astype(np.int64),
                                   np.ascontiguousarray(np.concatenate([at_lips, beyond[far]])), 1))


def in_front(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, *,
             view: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """How far (K,) mm each of ``points`` (K, 3) is in front (along the unit ``view``, towards the
    viewer) of the frontmost skin ``vertices`` (V, 3), ``faces`` (T, 3) over it (-inf where no
    skin is over or under it: seen through an opening); negative: behind the skin."""
    from scipy.spatial import cKDTree

    frame = _frame(np.asarray(view, float))
    points = np.asarray(points, dtype=float) @ frame.T
    corners = (np.asarray(vertices, float) @ frame.T)[np.asarray(faces)]  # (T, 3, 3)
    centre = corners[:, :, :2].mean(axis=1)
    reach = np.linalg.norm(corners[:, :, :2] - centre[:, None], axis=2).max()
    out = np.full(len(points), -np.inf)
    a, b, c = corners[:, 0, :2], corners[:, 1, :2], corners[:, 2, :2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    for k, near in enumerate(cKDTree(centre).query_ball_point(points[:, :2], reach)):
        if not near:
            continue
        near = np.asarray(near)
        p = points[k, :2] - a[near]
        d = det[near]
        ok = np.abs(d) > 1e-12
        u = np.where(ok, (p[:, 0] * (c[near, 1] - a[near, 1]) - p[:, 1] * (c[near, 0] - a[near, 0])) / np.where(ok, d, 1), -1)
        v = np.where(ok, ((b[near, 0] - a[near, 0]) * p[:, 1] - (b[near, 1] - a[near, 1]) * p[:, 0]) / np.where(ok, d, 1), -1)
        inside = (u >= 0) & (v >= 0) & (u + v <= 1)
        if inside.any():
            tri = corners[near[inside]]
            z = (1 - u[inside] - v[inside]) * tri[:, 0, 2] + u[inside] * tri[:, 1, 2] + v[inside] * tri[:, 2, 2]
            out[k] = points[k, 2] - z.max()
    return out


def _frame(view: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) whose last row is the unit ``view`` (points @ it.T: the view is +Z)."""
    view = view / np.linalg.norm(view)
    side = np.cross((0.0, 1.0, 0.0), view)
    side /= np.linalg.norm(side)
    return np.stack([side, np.cross(view, side), view])


def socket_rows(weights: np.ndarray, parts: FaceParts, offset: int) -> np.ndarray:
    """``weights`` (V + P, J) (the parts' rows at ``offset``, as
    :func:`~mocaptk.retarget.mesh_parts.part_weights` set them) with the socket's rows near the
    lips harmonic over the socket: its lip vertices (``attach``) take their face vertex's row,
    those :data:`SOCKET_REACH_MM` or farther from the lips keep theirs, so the socket opens with
    the lips (the nearest lip's row instead tore it 15x at the mouth's corners)."""
    weights = np.array(weights, dtype=float)
    socket, _ = _socket_mesh(parts.faces)
    lips = parts.attach[socket][parts.attach[socket] >= 0]
    rows = _over_socket(parts.vertices, parts.faces, parts.attach, weights[lips], weights[offset + socket])
    if weights.min() >= 0:  # skinning weights stay >= 0 (the field undershoots at obtuse triangles)
        rows = np.clip(rows, 0.0, None)
        rows /= rows.sum(axis=1, keepdims=True)
    weights[offset + socket] = rows  # each sums to 1 as the rows it interpolates
    return weights


def _socket_mesh(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The socket's vertices (S,) among the parts' and its triangles (Ts, 3) numbered over them."""
    socket = np.flatnonzero(template_parts()[4] < 0)
    local = np.full(len(template_parts()[4]), -1, dtype=np.int64)
    local[socket] = np.arange(len(socket))
    return socket, local[faces[(local[faces] >= 0).all(axis=1)]]
