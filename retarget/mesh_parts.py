"""The separate parts of a user's ``--mesh`` (issue 30): a production head is a skin with teeth,
gums and tongue, eyeballs and lashes in it, each its own connected piece.

Skinned like the skin, a part takes the weights of whatever markers its thin-shell solve
reaches, and its triangles are pulled across the lips and lids (the ICT-FaceKit head: 50x edge
stretch, 715 triangles facing backward). Instead every part moves with what it belongs to:

- the skin is the largest part (:func:`skin_faces`); only it is cut, anchored and weighted;
- a closed part (no border: a tooth, an eyeball) moves rigidly with one weight row: the head's
  (the layout joint that moves least, e.g. the nose bridge) when its centre is above the
  mouth's line, the jaw's (the chin joints) below it;
- an open part around an eye (above the nose tip: lashes, the eye's wet rim) follows the skin:
  each vertex takes the weights of its nearest skin vertex (the lid's, for a lash);
- an open part below the nose (gums and tongue, one piece on the ICT-FaceKit head) blends from
  the head's row at its top to the jaw's at its bottom, linearly in height (across a 6 mm band
  at the mouth's line its edges stretched 10x);
- skin beyond the markers and above the mouth (ears, the back of the head;
  :func:`beyond_markers`) blends towards the head's row: thin-shell weights only extrapolate
  there, and an ear's small edges stretched 3x.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BEYOND_SPACINGS", "beyond_markers", "part_weights", "skin_faces"]

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
                 head: np.ndarray, jaw: np.ndarray, mouth_y: float, nose_y: float) -> np.ndarray:
    """``weights`` (V, J) with the rows of the parts other than the skin (``faces[skin:]``) set
    as the module says: ``head``/``jaw`` (J,) the rigid rows, ``mouth_y``/``nose_y`` mm the
    heights of the mouth's line and the nose tip (rig frame, Y up)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from mocaptk.surface_mesh import boundary_edges

    faces = np.asarray(faces, dtype=np.int64)
    others = faces[skin:]
    if not len(others):
        return weights
    weights = np.array(weights, dtype=float)
    on = np.unique(faces[:skin])
    tree = cKDTree(vertices[on])
    used = np.unique(others)
    new = np.full(len(vertices), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    local = new[others]
    pairs = np.concatenate([local[:, [0, 1]], local[:, [1, 2]]])
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(used),) * 2)
    _, part = connected_components(graph, directed=False)
    nearest = tree.query(vertices[used])[1]
    open_parts = np.unique(part[new[boundary_edges(others).ravel()]])
    for p in range(part.max() + 1):
        members = used[part == p]
        y = vertices[members, 1]
        if p not in open_parts:  # a tooth, an eyeball: one row
            low = np.full(len(members), float(y.mean() < mouth_y))
        elif y.mean() > nose_y:  # lashes: with the lid
            weights[members] = weights[on[nearest[part == p]]]
            continue
        else:  # gums and tongue: from the head's at its top to the jaw's at its bottom
            low = (y.max() - y) / max(float(np.ptp(y)), 1e-9)
        weights[members] = (1.0 - low)[:, None] * head + low[:, None] * jaw
    return weights


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
    t = _smooth((d - near) / near) * _smooth((vertices[:, 1] - mouth_y + near) / near)
    return (1.0 - t)[:, None] * weights + t[:, None] * head


def _smooth(x: np.ndarray) -> np.ndarray:
    """Smoothstep of ``x`` clipped to [0, 1]: no kink where a blend starts or ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)
