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
  the head's row to the jaw's across the mouth's line, over :data:`JAW_BLEND_MM` of height.
"""

from __future__ import annotations

import numpy as np

__all__ = ["JAW_BLEND_MM", "part_weights", "skin_faces"]

#: A part spanning the mouth's line blends from the head's row to the jaw's over this height (mm).
JAW_BLEND_MM = 6.0


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
        else:
            low = np.clip((mouth_y + JAW_BLEND_MM / 2 - y) / JAW_BLEND_MM, 0.0, 1.0)
        weights[members] = (1.0 - low)[:, None] * head + low[:, None] * jaw
    return weights
