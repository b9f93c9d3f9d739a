"""The separate parts of a user's ``--mesh`` (issue 30): a production head is a skin with teeth,
gums and tongue, eyeballs and lashes in it, each its own connected piece.

Skinned like the skin, a part takes the weights of whatever markers its thin-shell solve
reaches, and its triangles are pulled across the lips and lids (the ICT-FaceKit head: 50x edge
stretch, 715 triangles facing backward). Instead every part moves with what it belongs to:

- the skin is the largest part (:func:`skin_faces`); only it is cut, anchored and weighted;
- a closed part (no border: a tooth, an eyeball) moves rigidly with one weight row: the head's
  (the layout joint that moves least, e.g. the nose bridge) when its centre is above the
  mouth's line, the jaw's (the chin joints) below it;
- an open part around an eye (above the nose tip: lashes, the eye's wet rim and shading
  shells) that lies along one lid's margin (a lash card) follows that lid: each vertex takes
  the weights of its nearest margin vertex; one spanning the eye's opening (the ICT-FaceKit
  head's eye-occlusion shell over the eyeball) moves rigidly with the head, as the eyeball
  does (following the nearest skin, its halves went with the upper and the lower lid and tore
  apart in a blink: 8.4x, 41 triangles backward). Without lids, the nearest skin vertex's;
- an open part below the nose (gums and tongue, one piece on the ICT-FaceKit head) blends from
  the head's row at its top to the jaw's at its bottom, linearly in height (across a 6 mm band
  at the mouth's line its edges stretched 10x);
- skin beyond the markers and above the mouth (ears, the back of the head;
  :func:`beyond_markers`) blends towards the head's row: thin-shell weights only extrapolate
  there, and an ear's small edges stretched 3x.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mocaptk.geometry import smoothstep

__all__ = ["BEYOND_SPACINGS", "ONE_LID_SHARE", "beyond_markers", "head_jaw_rows", "nose_height", "part_weights",
           "parts", "skin_faces"]

#: An open part around an eye follows one lid when at least this share of its vertices is
#: nearest that lid's margin (a lash card); else it spans the opening and moves with the head.
ONE_LID_SHARE = 0.9
#: Skin this many marker spacings from the nearest dense marker starts to blend towards the
#: head's row, and follows it wholly at twice that.
BEYOND_SPACINGS = 3.0


def skin_faces(faces: np.ndarray) -> np.ndarray:
    """Which triangles (T,) bool are the skin: the connected part (triangles sharing vertices)
    with the most triangles."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    if not len(faces):
        return np.zeros(0, bool)
    count = int(faces.max()) + 1
    rows = np.repeat(np.arange(len(faces)), 3)
    incidence = sp.csr_matrix((np.ones(rows.size), (rows, faces.ravel())), shape=(len(faces), count))
    _, part = connected_components(incidence.T @ incidence, directed=False)
    of_face = part[faces[:, 0]]
    return of_face == np.argmax(np.bincount(of_face))


def part_weights(weights: np.ndarray, vertices: np.ndarray, faces: np.ndarray, skin: int, *,
                 head: np.ndarray, jaw: np.ndarray, mouth_y: float, nose_y: float,
                 margins: Sequence[np.ndarray] = ()) -> np.ndarray:
    """``weights`` (V, J) with the rows of the parts other than the skin (``faces[skin:]``) set
    as the module says: ``head``/``jaw`` (J,) the rigid rows, ``mouth_y``/``nose_y`` mm the
    heights of the mouth's line and the nose tip (rig frame, Y up), ``margins`` the lids' margin
    vertices (one array per lid: each eye's upper and lower rim; none: the skin's nearest)."""
    from scipy.spatial import cKDTree

    faces = np.asarray(faces, dtype=np.int64)
    weights = np.array(weights, dtype=float)
    on = np.unique(faces[:skin])
    tree = cKDTree(vertices[on])
    rim = np.concatenate([np.asarray(m, dtype=np.int64) for m in margins]) if len(margins) else on
    lid_of = np.concatenate([np.full(len(m), i) for i, m in enumerate(margins)]) if len(margins) \
        else np.zeros(len(on), dtype=np.int64)
    rims = cKDTree(vertices[rim])
    for members, kind in parts(vertices, faces, skin, nose_y=nose_y):
        y = vertices[members, 1]
        if kind == "rigid":  # a tooth, an eyeball: one row
            low = np.full(len(members), float(y.mean() < mouth_y))
        elif kind == "lid" and not len(margins):  # no lids found: with the nearest skin
            weights[members] = weights[on[tree.query(vertices[members])[1]]]
            continue
        elif kind == "lid":  # a lash card with its lid; a shell over the eye with the head
            near = rims.query(vertices[members])[1]
            share = np.bincount(lid_of[near]).max() / len(members)
            weights[members] = weights[rim[near]] if share >= ONE_LID_SHARE else head
            continue
        else:  # gums and tongue: from the head's at its top to the jaw's at its bottom
            low = (y.max() - y) / max(float(np.ptp(y)), 1e-9)
        weights[members] = (1.0 - low)[:, None] * head + low[:, None] * jaw
    return weights


def parts(vertices: np.ndarray, faces: np.ndarray, skin: int, *, nose_y: float
          ) -> list[tuple[np.ndarray, str]]:
    """The connected parts of ``faces[skin:]`` (the mesh's pieces other than its skin), each as
    ``(vertices (K,), kind)``: ``"rigid"`` a closed piece (a tooth, an eyeball), ``"lid"`` an
    open one above the nose tip's height ``nose_y`` mm (lashes, the eye's wet rim and shading
    shells: they follow the lids, and are drawn with an alpha or transparent material),
    ``"blend"`` an open one below it (gums and tongue)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from mocaptk.surface_mesh import boundary_edges

    others = np.asarray(faces, dtype=np.int64)[skin:]
    if not len(others):
        return []
    used = np.unique(others)
    new = np.full(len(vertices), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    local = new[others]
    pairs = np.concatenate([local[:, [0, 1]], local[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(used),) * 2)
    _, part = connected_components(graph, directed=False)
    open_parts = np.unique(part[new[boundary_edges(others).ravel()]])
    found = []
    for p in range(part.max() + 1):
        members = used[part == p]
        kind = ("rigid" if p not in open_parts else
                "lid" if vertices[members, 1].mean() > nose_y else "blend")
        found.append((members, kind))
    return found


def nose_height(vertices: np.ndarray, faces: np.ndarray, skin: int) -> float:
    """The nose tip's height (mm, Y up): of the skin's (``faces[:skin]``) most forward (+Z)
    vertex."""
    on = np.unique(np.asarray(faces)[:skin])
    return float(vertices[on[np.argmax(vertices[on, 2])], 1])


def head_jaw_rows(head: int, regions: Sequence[str], positions: np.ndarray, *,
                  count: int) -> tuple[np.ndarray, np.ndarray]:
    """The head's and the jaw's rows (J,) over J columns (the rig's joints, solve's dense
    markers): the head's all on column ``head`` (one that moves least), the jaw's on the
    ``count`` lowest jaw columns (:func:`~mocaptk.retarget.rig_hierarchy.jaw_members` of their
    ``regions`` and ``positions`` (J, 3) mm, rig frame, Y up), equally."""
    from .rig_hierarchy import jaw_members

    positions = np.asarray(positions, dtype=float)
    lower = np.flatnonzero(jaw_members(list(regions), positions))
    lower = lower[np.argsort(positions[lower, 1], kind="stable")[:count]]
    jaw = np.zeros(len(positions))
    jaw[lower] = 1.0 / len(lower)
    return np.eye(len(positions))[int(head)], jaw


def beyond_markers(weights: np.ndarray, vertices: np.ndarray, markers: np.ndarray, *,
                   head: np.ndarray, spacing: float, mouth_y: float) -> np.ndarray:
    """``weights`` (V, J) blended towards the ``head`` row (J,) with each vertex's distance d
    from the nearest of the dense ``markers`` (M, 3) mm: not at all within
    :data:`BEYOND_SPACINGS` x ``spacing`` (mm), wholly at twice that, smoothly between; and
    only above the mouth's line ``mouth_y`` (mm, Y up), fading out over that distance below it
    (the skin under the chin follows the jaw: held with the head, it folded as the jaw opened)."""
    from scipy.spatial import cKDTree

    near = BEYOND_SPACINGS * spacing
    d = cKDTree(markers).query(vertices)[0]
    t = smoothstep((d - near) / near) * smoothstep((vertices[:, 1] - mouth_y + near) / near)
    return (1.0 - t)[:, None] * weights + t[:, None] * head
