"""Skin weights: smooth, interpolating thin-shell weights, shaped by the influence regions, capped.

1. **Thin-shell interpolation** (Le, Zhu & Deng 2013; :mod:`mocaptk.thin_shell`):
   ``W = Â⁻¹B̂`` (V, J) - each vertex follows the joints (pinned at their marker vertices) with
   the minimal stretching + bending energy; ``W`` is exactly 1 on a joint's own vertex, 0 on the
   other joints' vertices, smooth in between, rows sum to 1. It is purely geometric.
2. **Region shaping** (the paper's influence regions "extended smoothly past cluster borders"):
   the clustering says which vertices move with which marker. Each joint's column is multiplied
   by a mask that is 1 inside its main influence region and falls smoothly (smoothstep of the
   geodesic distance) to 0 at ``falloff_mm`` past the region's border; negative thin-shell
   lobes are clipped; rows are renormalized. Marker vertices stay exact (their own joint's mask
   is 1 there). ``falloff_mm=None`` keeps the pure thin-shell weights.
3. **Capping**: top ``max_influences`` per vertex, drop weights < ``min_weight``, renormalize to
   sum 1; a vertex left with nothing gets its fallback joint (nearest joint) at weight 1.
4. **Symmetry** (mirrored layouts on a mirror-symmetric mesh): the weights are averaged with
   their mirror image (vertex v ↔ its mirror, L ↔ R joints) before capping, and a midline
   vertex's capping never splits an L/R pair of equal weights, so mirrored vertices get mirrored
   weights to rounding (:func:`symmetric_weights`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from mocaptk.errors import OptionError
from mocaptk.geometry import smoothstep
from mocaptk.thin_shell import interpolation_weights, thin_shell_operator

from .influence import geodesic_distance

__all__ = ["blend_corners", "cap_weights", "corner_joints", "fill_unsupported", "masked_support", "mirror_maps", "pin_fade",
           "region_masks", "shape_by_regions", "symmetric_weights", "thin_shell_weights"]


def thin_shell_weights(vertices: np.ndarray, faces: np.ndarray, joint_vertices: np.ndarray, *,
                       graph: sp.csr_matrix, ks: float = 1.0, kb: float = 10.0) -> np.ndarray:
    """Interpolating weights (V, J) of the joints pinned at ``joint_vertices`` (J,).

    Solved per connected mesh part (``graph``: the mesh edge graph); a part holding no joint
    follows its Euclidean-nearest joint rigidly (weight 1). Joints pinned at the same vertex
    (coincident markers) split that vertex's weight equally.
    """
    vertices = np.asarray(vertices, dtype=float)
    faces = np.asarray(faces, dtype=np.int64)
    joint_vertices = np.asarray(joint_vertices, dtype=np.int64)
    pins, shared = np.unique(joint_vertices, return_inverse=True)
    if len(pins) < len(joint_vertices):  # coincident markers share their vertex's weight
        unique = thin_shell_weights(vertices, faces, pins, graph=graph, ks=ks, kb=kb)
        count = np.bincount(np.ravel(shared))
        return unique[:, np.ravel(shared)] / count[np.ravel(shared)]
    n, n_joints = len(vertices), len(joint_vertices)
    weights = np.zeros((n, n_joints))
    _, part = connected_components(graph, directed=False)
    face_part = part[faces[:, 0]]
    for p in np.unique(part):
        members = np.flatnonzero(part == p)
        pinned = np.flatnonzero(part[joint_vertices] == p)
        if len(pinned) == 0 or len(members) == 1:
            nearest = np.argmin(np.linalg.norm(vertices[members][:, None, :]
                                               - vertices[joint_vertices][None], axis=2), axis=1)
            weights[members, nearest] = 1.0
            continue
        local = np.full(n, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        op = thin_shell_operator(vertices[members], local[faces[face_part == p]], ks=ks, kb=kb)
        weights[np.ix_(members, pinned)] = interpolation_weights(op, local[joint_vertices[pinned]])
    return weights


def region_masks(graph: sp.csr_matrix, regions: np.ndarray, n_joints: int, *,
                 falloff_mm: float, members: list[np.ndarray] | None = None) -> np.ndarray:
    """(V, J) masks: 1 in joint j's main influence region, smoothstep to 0 at ``falloff_mm``
    (geodesic) past its border. ``members[j]`` (vertex indices) are inside j's region too, also
    where another joint's region took them (a midline marker shared by mirrored twins)."""
    masks = np.zeros((graph.shape[0], n_joints))
    for j in range(n_joints):
        inside = np.flatnonzero(regions == j)
        if members is not None:
            inside = np.union1d(inside, np.asarray(members[j], dtype=np.int64))
        if len(inside) == 0:
            continue
        if falloff_mm > 0:
            dist = geodesic_distance(graph, inside, limit=falloff_mm)
            near = np.flatnonzero(dist != np.inf)  # beyond the limit the mask is 0, as zeros() has it
            masks[near, j] = smoothstep(1.0 - dist[near] / falloff_mm)
        masks[inside, j] = 1.0
    return masks


def shape_by_regions(weights: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Clip negative weights, multiply by the region masks, renormalize rows (V, J).

    Rows the masks zero out entirely keep their clipped, renormalized thin-shell weights.
    """
    clipped = np.clip(weights, 0.0, None)
    shaped = clipped * masks
    total = shaped.sum(axis=1, keepdims=True)
    empty = total[:, 0] <= 1e-12
    shaped[empty] = clipped[empty]
    total[empty] = clipped[empty].sum(axis=1, keepdims=True)
    return np.divide(shaped, total, out=np.zeros_like(shaped), where=total > 0)


def masked_support(weights: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Each row's (V,) masked thin-shell weight: ``weights`` (V, J) clipped at 0 times the region
    ``masks`` (V, J) (:func:`region_masks`), summed; small where no driver's region reaches."""
    return (np.clip(weights, 0.0, None) * masks).sum(axis=1)


def fill_unsupported(weights: np.ndarray, support: np.ndarray, vertices: np.ndarray,
                     faces: np.ndarray, *, min_support: float) -> np.ndarray:
    """``weights`` (V, J) with the rows whose ``support`` (V,) is below ``min_support`` replaced
    by the harmonic interpolation of the other rows over the mesh (``vertices`` (V, 3) mm,
    ``faces`` (T, 3)); negatives clipped, rows renormalized. Vertices in no triangle keep theirs.

    ``support``: each row's masked thin-shell weight before renormalizing
    (:func:`masked_support`, :func:`shape_by_regions`). Far from every marker (behind the ears) that is a ratio of tiny
    numbers, so neighbours' rows swung between joints: an edge behind the ear stretched 2.06x
    at the widest jaw (issue 30). Filled, the weights there continue the face's smoothly."""
    import igl

    w = np.array(weights, dtype=float)
    used = np.zeros(len(w), dtype=bool)
    used[np.asarray(faces, dtype=np.int64).ravel()] = True
    unknown = used & (np.asarray(support) < min_support)
    known = np.flatnonzero(used & ~unknown)
    if not unknown.any() or known.size == 0:
        return w
    filled = igl.harmonic(np.ascontiguousarray(vertices, dtype=float),
                          np.ascontiguousarray(faces, dtype=np.int64), known.astype(np.int64),
                          np.ascontiguousarray(w[known]), 1)
    rows = np.clip(filled[unknown], 0.0, None)
    w[unknown] = rows / rows.sum(axis=1, keepdims=True)
    return w


def blend_corners(weights: np.ndarray, vertices: np.ndarray, corners: np.ndarray, *,
                  reach_mm: float, pinned: np.ndarray, pin_fade_mm: float = 0.0,
                  pin_hold: float = 1.0) -> np.ndarray:
    """``weights`` (V, J) blended towards each of the ``corners`` (C,) vertex's own row, fully at
    the corner and not at all ``reach_mm`` away ((1 - r / reach)² of the distance r); the
    ``pinned`` (P,) vertices' rows are kept (``pin_hold`` 1; with 0.3 they take 70 % of the
    blend), and with ``pin_fade_mm`` the blend fades in smoothly over that distance (mm) from
    them (:func:`pin_fade`).

    At an opening's corner (the mouth's, an eye's) the upper and lower rims' weights differ
    from one vertex to the next, so the skin there tears like a crack's tip and its small
    triangles fold when the jaw opens; blended, the opening parts as a lens does, more and more
    away from its corners (issue 30)."""
    w = np.array(weights, dtype=float)
    v = np.asarray(vertices, dtype=float)
    keep = 1.0 - pin_hold * (1.0 - pin_fade(v, pinned, fade_mm=pin_fade_mm))
    for corner in np.asarray(corners, dtype=np.int64):
        alpha = np.clip(1.0 - np.linalg.norm(v - v[corner], axis=1) / reach_mm, 0.0, 1.0) ** 2
        w += (alpha * keep)[:, None] * (w[corner] - w)
    return w


def pin_fade(vertices: np.ndarray, pinned: np.ndarray, *, fade_mm: float) -> np.ndarray:
    """(V,) in [0, 1]: 0 at the ``pinned`` vertices, rising as a smoothstep of the distance to
    the nearest one to 1 at ``fade_mm`` (0: a step, 1 everywhere else).

    A change made to every row but a joint's own vertex (weight 1 there) leaves a spike at that
    vertex: at the widest jaw the edges around a lip joint blended 0.3 towards a mouth corner
    stretched 2.3x (issue 30)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=float)
    pinned = np.asarray(pinned, dtype=np.int64)
    if fade_mm <= 0 or pinned.size == 0:
        fade = np.ones(len(v))
        fade[pinned] = 0.0
        return fade
    return smoothstep(cKDTree(v[pinned]).query(v)[0] / fade_mm)


def corner_joints(weights: np.ndarray, vertices: np.ndarray, corners: np.ndarray, *,
                  inner_mm: float, outer_mm: float, count: int, pinned: np.ndarray,
                  pin_fade_mm: float, others_fade_mm: float) -> np.ndarray:
    """``weights`` (V, J) led, within ``inner_mm`` of each of the ``corners`` (C,), onto that
    corner's ``count`` strongest joints (their weights renormalized), fading back to the rows
    as they are at ``outer_mm`` (smoothstep) and near the ``pinned`` (J,) vertices
    (:func:`pin_fade`): over ``pin_fade_mm``, and over ``others_fade_mm`` from the joints the
    corner's set leaves out (their own vertex keeps weight 1 on them, the rows around it had
    none: a spike; sample, 2.08x beside MOUTH_11 below a corner; a 45-joint actor, 3.85x).

    Blended towards a corner (:func:`blend_corners`), a row has its own joints and the corner's:
    up to 8 where the skin keeps 4, so the kept ones changed from one vertex to the next and the
    skin stepped (a 0.2 weight swapped across a 1.4 mm edge below a mouth corner stretched it
    2.5x at the widest jaw; issue 30). Around the corner the rows now share one set of joints."""
    w = np.array(weights, dtype=float)
    v = np.asarray(vertices, dtype=float)
    pinned = np.asarray(pinned, dtype=np.int64)
    keep = pin_fade(v, pinned, fade_mm=pin_fade_mm)
    for corner in np.asarray(corners, dtype=np.int64):
        t = (outer_mm - np.linalg.norm(v - v[corner], axis=1)) / (outer_mm - inner_mm)
        own = np.argsort(-w[corner], kind="stable")[:count]
        left_out = pinned[np.setdiff1d(np.arange(w.shape[1]), own)]
        beta = smoothstep(t) * np.minimum(keep, pin_fade(v, left_out, fade_mm=others_fade_mm))
        led = np.zeros_like(w)
        led[:, own] = w[:, own]
        total = led.sum(axis=1)
        rows = total > 0  # a row without any of the corner's joints keeps its own
        led[rows] /= total[rows, None]
        w[rows] += beta[rows, None] * (led[rows] - w[rows])
    return w


def mirror_maps(vertices: np.ndarray, plane_point: np.ndarray, plane_normal: np.ndarray, *,
                tolerance_mm: float) -> np.ndarray | None:
    """Each vertex's mirror vertex (V,) across the plane, or None when the mesh is not
    mirror-symmetric (a mirror image farther than ``tolerance_mm`` from every vertex)."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, dtype=float)
    normal = np.asarray(plane_normal, dtype=float) / np.linalg.norm(plane_normal)
    image = v - 2.0 * ((v - plane_point) @ normal)[:, None] * normal
    dist, mirror = cKDTree(v).query(image)
    if dist.max() > tolerance_mm or np.any(mirror[mirror] != np.arange(len(v))):
        return None
    return mirror.astype(np.int64)


def symmetric_weights(weights: np.ndarray, vertex_mirror: np.ndarray,
                      joint_mirror: np.ndarray) -> np.ndarray:
    """``(W + W[mirror(v), mirror(j)]) / 2`` (V, J): exactly mirror-symmetric weights.

    ``vertex_mirror`` (V,) and ``joint_mirror`` (J,) are involutions (midline items map to
    themselves)."""
    w = np.asarray(weights, dtype=float)
    return 0.5 * (w + w[np.asarray(vertex_mirror)][:, np.asarray(joint_mirror)])


def cap_weights(weights: np.ndarray, *, max_influences: int = 4, min_weight: float = 1e-3,
                fallback: np.ndarray | None = None,
                mirror: tuple[np.ndarray, np.ndarray] | None = None,
                continuous: bool | np.ndarray = False) -> tuple[np.ndarray, np.ndarray]:
    """Keep each vertex's ``max_influences`` largest weights >= ``min_weight``, sum 1.

    ``continuous`` (True, or (V,) bool: these vertices): the kept weights less the largest one
    dropped (and less ``min_weight``), so a weight reaches 0 before it is dropped and the skin
    has no step where the kept joints change (a step of 0.1 x 8 mm over a 0.2 mm edge of a lid
    stretches it 4x; issue 30).

    Parameters
    ----------
    weights : (V, J) float
    fallback : (V,) int, optional
        Joint given weight 1 where no weight survives (default: the row's largest weight).
    mirror : (vertex_mirror (V,), joint_mirror (J,)), optional
        For symmetric ``weights``: ties between a joint and its mirror are kept or dropped
        together, and a vertex's result is the mirror image of its mirror vertex's.

    Returns
    -------
    index : (V, k) int64
        Joint indices, strongest first; unused slots 0.
    value : (V, k) float64
        Weights, rows summing to 1; unused slots 0.
    """
    if max_influences < 1:
        raise OptionError(f"--max-influences must be >= 1, got {max_influences}")
    w = np.asarray(weights, dtype=float)
    if mirror is not None:
        return _cap_mirrored(w, max_influences=max_influences, min_weight=min_weight,
                             fallback=fallback, mirror=mirror, continuous=continuous)
    k = min(max_influences, w.shape[1])
    order = np.argsort(-w, axis=1, kind="stable")
    value = np.take_along_axis(w, order[:, :k], axis=1)
    rows = np.broadcast_to(np.asarray(continuous, dtype=bool), (len(w),))
    if rows.any():
        dropped = np.take_along_axis(w, order[:, k:k + 1], axis=1) if k < w.shape[1] else 0.0
        soft = np.clip(value - np.maximum(dropped, 0.0) - min_weight, 0.0, None)
        rows = rows & (soft.sum(axis=1) > 0)  # ties all the way down: kept as they are
        value[rows] = soft[rows]
    order = order[:, :k]
    while True:  # renormalizing can push a kept weight under min_weight (rows summing > 1)
        value[value < min_weight] = 0.0
        total = value.sum(axis=1)
        empty = total <= 0
        if np.any(empty):
            fb = np.argmax(w, axis=1) if fallback is None else np.asarray(fallback, dtype=np.int64)
            order[empty, 0] = fb[empty]
            value[empty] = 0.0
            value[empty, 0] = 1.0
            total[empty] = 1.0
        value /= total[:, None]
        if not np.any((value > 0) & (value < min_weight)):
            break
    index = np.where(value > 0, order, 0).astype(np.int64)
    if k < max_influences:  # fewer joints than slots: pad
        pad = max_influences - k
        index = np.pad(index, ((0, 0), (0, pad)))
        value = np.pad(value, ((0, 0), (0, pad)))
    return index, value


def _cap_mirrored(w: np.ndarray, *, max_influences: int, min_weight: float,
                  fallback: np.ndarray | None, mirror: tuple[np.ndarray, np.ndarray],
                  continuous: bool | np.ndarray = False) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cap_weights` of symmetric weights, symmetric: cap one vertex of each mirror pair
    (rows of midline vertices with equal L/R weights at the cut dropped in pairs), then copy
    the mirror image onto the other."""
    vertex_mirror, joint_mirror = (np.asarray(m, dtype=np.int64) for m in mirror)
    w = w.copy()
    k = min(max_influences, w.shape[1])
    midline = np.flatnonzero(vertex_mirror == np.arange(len(w)))
    for v in midline:  # while a tie straddles the k-th place: drop both members of the pair
        while True:
            order = np.argsort(-w[v], kind="stable")
            if len(order) <= k or w[v, order[k - 1]] <= 0 or \
                    abs(w[v, order[k - 1]] - w[v, order[k]]) > 1e-12:
                break
            w[v, np.abs(w[v] - w[v, order[k - 1]]) <= 1e-12] = 0.0
    index, value = cap_weights(w, max_influences=max_influences, min_weight=min_weight,
                               fallback=fallback, continuous=continuous)
    copy = vertex_mirror < np.arange(len(w))  # the second vertex of each pair mirrors the first
    source = vertex_mirror[copy]
    index[copy] = np.where(value[source] > 0, joint_mirror[index[source]], 0)
    value[copy] = value[source]
    return index, value
