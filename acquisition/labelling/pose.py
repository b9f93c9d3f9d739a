"""Head pose and expression of one frame: fit the template model to assigned points, or find the
pose of an unlabelled cloud from scratch (RANSAC on the template's least-moving markers).

Pose convention as in :mod:`..stabilize`: ``x_capture = R @ x_head + t``.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
from scipy.spatial import cKDTree

from ..stabilize import kabsch
from .template import LabelTemplate
from .track_kernel import gauss_newton, model_arrays

#: Triangles of pose markers tried by :func:`find_pose` (the largest ones: the best-conditioned).
TRIANGLES = 6
#: Candidate point triangles scored per template triangle, at most.
MAX_CANDIDATES = 20000
#: Candidates scored on all markers after a first score on the pose markers alone.
FINALISTS = 20
#: The search stops at the first triangle whose pose puts this fraction of the template markers
#: (or of the points, when fewer) on a point: later triangles only repeat it.
GOOD_POSE = 0.9
#: Side lengths match when within this fraction (or 3 mm): the capture's face may differ a little.
SIDE_TOLERANCE = 0.12


def model_shape(template: LabelTemplate, coeffs: np.ndarray) -> np.ndarray:
    """(M, 3) head-coordinate marker positions for expression coefficients ``coeffs (K,)``."""
    return template.mean + (coeffs @ template.basis.reshape(len(coeffs), -1)).reshape(-1, 3)


def fit_frame(template: LabelTemplate, idx: np.ndarray, points: np.ndarray, rot: np.ndarray,
              trans: np.ndarray, offset: np.ndarray, *, expression: bool = True,
              rounds: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose and expression from assigned points: ``(rot (3, 3), trans (3,), coeffs (K,))``.

    ``idx (a,)`` template markers of ``points (a, 3)`` mm; ``rot``/``trans`` the starting pose;
    ``offset (M, 3)``: per-marker correction added to the model (the capture face's own shape).
    Gauss-Newton on pose and expression together (``rounds`` steps, linearized rotation): the
    head-coordinate points ``R^T (p - t)`` should equal ``mean + offset + basis · coeffs``, each
    marker weighted by ``1 / sigma²``, the expression under a Gaussian prior of the PCA modes
    (MAP); without ``expression`` a rigid fit only.
    """
    k = len(template.mode_std) if expression else 0
    return gauss_newton(template.mean, *model_arrays(template.basis), template.mode_std,
                        template.sigma, offset,
                        np.asarray(idx, dtype=np.int64), np.ascontiguousarray(points, dtype=np.float64),
                        np.asarray(rot, dtype=np.float64), np.asarray(trans, dtype=np.float64), k, rounds)


def find_pose(template: LabelTemplate, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The head pose of an unlabelled cloud ``points (n, 3)`` mm: ``(rot, trans, inliers)``.

    Triangles of the template's least-moving markers are matched to point triangles with the
    same side lengths; each match gives a pose (Kabsch), scored first by how many pose markers,
    then (the best :data:`FINALISTS`) by how many template markers land within half their
    nearest-neighbour distance of a point; a score of :data:`GOOD_POSE` ends the search.
    ``inliers`` 0: no pose found (identity returned).
    """
    best = (np.eye(3), np.zeros(3), 0)
    if len(points) < 3:
        return best
    tree = cKDTree(points)
    dist = np.linalg.norm(points[:, None] - points[None], axis=2)
    radius = 0.5 * template.nearest
    pose = template.pose_markers
    for tri in _triangles(template):
        ref = template.mean[list(tri)]
        sides = [np.linalg.norm(ref[a] - ref[b]) for a, b in ((0, 1), (0, 2), (1, 2))]
        ok = [np.abs(dist - s) <= max(3.0, SIDE_TOLERANCE * s) for s in sides]
        i, j = np.nonzero(ok[0])
        pair, k = np.nonzero(ok[1][i] & ok[2][j])
        if not len(pair):
            continue
        keep = np.linspace(0, len(pair) - 1, min(len(pair), MAX_CANDIDATES)).astype(np.intp)
        cand = np.stack([i[pair[keep]], j[pair[keep]], k[keep]], axis=1)
        rot, trans = kabsch(ref, points[cand], np.ones(cand.shape))
        good = np.isfinite(rot).all(axis=(1, 2))
        rot, trans = rot[good], trans[good]
        if not len(rot):
            continue
        posed = np.einsum("cij,mj->cmi", rot, template.mean[pose]) + trans[:, None]
        near, _ = tree.query(posed.reshape(-1, 3))
        first = (near.reshape(len(rot), -1) <= radius[pose]).sum(axis=1)
        top = np.argsort(-first, kind="stable")[:FINALISTS]
        posed = np.einsum("cij,mj->cmi", rot[top], template.mean) + trans[top, None]
        near, _ = tree.query(posed.reshape(-1, 3))
        score = (near.reshape(len(top), -1) <= radius).sum(axis=1)
        best_k = int(np.argmax(score))
        if score[best_k] > best[2]:
            best = (rot[top[best_k]], trans[top[best_k]], int(score[best_k]))
        if best[2] >= GOOD_POSE * min(len(points), template.n_markers):
            break
    return best


def _triangles(template: LabelTemplate) -> list[tuple[int, int, int]]:
    """The :data:`TRIANGLES` largest-area triangles of the pose markers."""
    pose = template.pose_markers.tolist()
    tris = list(combinations(pose, 3))
    area = [np.linalg.norm(np.cross(template.mean[b] - template.mean[a], template.mean[c] - template.mean[a]))
            for a, b, c in tris]
    order = np.argsort(area, kind="stable")[::-1][:TRIANGLES]
    return [tris[k] for k in order]
