"""A capture's head pose in every frame, from the layout's stabilization markers (or, when the
capture lacks them, from its least-moving layout markers), robust to ghosts on those markers.

Per frame, the largest set of pose markers that one rigid fit (Kabsch) of their head-frame
reference places within :data:`OUTLIER_MM` (tried from every 3 markers, as RANSAC would, but
exhaustively: a head carries at most a handful); the others (a ghost, a swap) are dropped. The kept markers are then low-passed at
:data:`~mocaptk.acquisition.stabilize.POSE_CUTOFF_HZ` (skin jitter is not head motion) and fitted
again. ``x_capture = R x_head + t``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import combinations

import numpy as np
from scipy.spatial.transform import Rotation

from mocaptk.acquisition.filtering import lowpass
from mocaptk.acquisition.runs import take_segments
from mocaptk.acquisition.stabilize import POSE_CUTOFF_HZ, bridge_poses, in_head_frame, kabsch
from mocaptk.trajectories import Trajectories

from .consistency import LayoutGaussian

__all__ = ["HeadPoses", "least_moving_markers", "refine_poses", "robust_head_poses", "skin_following_poses"]

#: A pose marker farther than this from where the other pose markers place it is dropped (mm):
#: skin slides ~1 mm over the skull; a ghost or a swap is centimetres off.
OUTLIER_MM = 2.5
#: Frames without a pose (no 3 consistent markers) in runs of at most this many take poses
#: interpolated from their neighbours (as stabilization does).
MAX_POSE_GAP = 10
#: Gauss-Newton steps of :func:`refine_poses` (the first step from a few-marker pose does most).
REFINE_ITERATIONS = 3
#: Fallback pose markers: at most this many, pairwise at least ``FALLBACK_SPREAD_MM`` apart.
FALLBACK_COUNT = 5
FALLBACK_SPREAD_MM = 15.0


@dataclass(frozen=True)
class HeadPoses:
    """Per frame ``rotations`` (F, 3, 3) and ``translations`` (F, 3) (NaN: no pose), the RMS fit
    residual ``residual_mm`` (F,) of the markers kept, ``dropped`` (F, K) the pose markers found
    contradicted, from the markers ``labels`` (``source``: ``"stabilization markers"`` or
    ``"least-moving layout markers"``); ``motion_rms_mm`` the RMS distance of the markers kept
    from their head-frame reference, unposed; ``still``: under ~1 mm, the capture is taken as in
    the head frame and the poses are the identity."""

    rotations: np.ndarray
    translations: np.ndarray
    residual_mm: np.ndarray
    dropped: np.ndarray
    labels: tuple[str, ...]
    source: str
    motion_rms_mm: float = float("nan")
    still: bool = False

    def select(self, frames: np.ndarray | slice) -> HeadPoses:
        """The poses of ``frames`` only."""
        return replace(self, rotations=self.rotations[frames], translations=self.translations[frames],
                       residual_mm=self.residual_mm[frames], dropped=self.dropped[frames])


def robust_head_poses(reference: np.ndarray, capture: Trajectories, labels: Sequence[str], *,
                      source: str, max_gap: int = MAX_POSE_GAP) -> HeadPoses:
    """Head poses of ``capture`` from its markers ``labels`` whose head-frame positions are
    ``reference`` (K, 3) mm; frames without 3 consistent markers take poses interpolated from
    their neighbours over gaps of at most ``max_gap`` frames (else NaN)."""
    points = capture.positions[:, capture.index(list(labels))]
    reference = _own_shape(np.asarray(reference, dtype=np.float64), points)
    dropped = np.isfinite(points).all(axis=2) & ~_consensus(reference, points)
    kept = np.where(dropped[..., None], np.nan, points)
    rot, trans, residual = _steady_fit(reference, kept, capture, max_gap=max_gap)
    offsets = np.sum((kept - reference) ** 2, axis=2)
    offsets = offsets[np.isfinite(offsets)]
    motion = float(np.sqrt(offsets.mean())) if offsets.size else float("nan")
    return HeadPoses(rot, trans, residual, dropped, tuple(labels), source, motion)


def skin_following_poses(poses: HeadPoses, reference: np.ndarray, capture: Trajectories, skin: np.ndarray, *,
                         max_gap: int = MAX_POSE_GAP) -> HeadPoses:
    """``poses`` fitted again, each frame's pose markers laid on their head-frame shape in that
    frame: the capture's own shape of them (from the session's ``reference`` (K, 3) mm, as
    :func:`robust_head_poses` takes it) plus ``skin`` (F, K, 3) mm, how far the face's expression
    moves each from its median (0 for a skull or headband marker). The markers found contradicted
    stay dropped."""
    points = capture.positions[:, capture.index(list(poses.labels))]
    own = _own_shape(np.asarray(reference, dtype=np.float64), points)
    kept = np.where(poses.dropped[..., None], np.nan, points)
    rot, trans, residual = _steady_fit(own + np.nan_to_num(skin), kept, capture, max_gap=max_gap)
    return replace(poses, rotations=rot, translations=trans, residual_mm=residual)


def _steady_fit(reference: np.ndarray, kept: np.ndarray, capture: Trajectories, *,
                max_gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses (F, 3, 3), (F, 3) and RMS fit residuals (F,) mm of the pose markers ``kept``
    (F, K, 3) mm (NaN: lost or dropped), low-passed, onto ``reference`` (K, 3) or per frame
    (F, K, 3); short gaps bridged."""
    steady = Trajectories(kept, tuple(f"p{k}" for k in range(kept.shape[1])), capture.rate,
                          capture.first_frame, metadata=capture.metadata)
    if POSE_CUTOFF_HZ < capture.rate / 2:
        steady = lowpass(steady, cutoff_hz=POSE_CUTOFF_HZ)
    seen = np.isfinite(steady.positions).all(axis=2)
    rot, trans = kabsch(reference, steady.positions, seen.astype(float))
    frames = np.broadcast_to(reference, steady.positions.shape)
    fitted = np.einsum("fij,fkj->fki", rot, frames) + trans[:, None]
    sq = np.where(seen, np.sum((fitted - steady.positions) ** 2, axis=2), 0.0)
    count = seen.sum(axis=1)
    ok = np.isfinite(rot[:, 0, 0]) & (count > 0)
    residual = np.where(ok, np.sqrt(np.nan_to_num(sq).sum(axis=1) / np.maximum(count, 1)), np.nan)
    bridge_poses(rot, trans, take_segments(capture), max_gap=max_gap)
    return rot, trans, residual


def fixed_pose(reference: np.ndarray, capture: Trajectories,
               labels: Sequence[str]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """One pose for the whole capture: rotation (3, 3) and translation (3,) mm laying the
    session's head-frame ``reference`` (K, 3) mm of the markers ``labels`` onto their median
    position in the capture, and how far (RMS, mm) they move about that median. A head that
    does not move (a head-relative capture in another frame) needs this one pose, not one per
    frame fitted to markers that move with the face. None with fewer than 3 markers seen."""
    from mocaptk.clustering.neutral import neutral_pose

    points = capture.positions[:, capture.index(list(labels))]
    median = neutral_pose(points)
    seen = np.isfinite(median).all(axis=1)
    if seen.sum() < 3:
        return None
    rot, trans = kabsch(np.asarray(reference, dtype=np.float64), np.nan_to_num(median)[None],
                        seen[None].astype(float))
    sq = np.sum((points - median) ** 2, axis=2)
    sq = sq[np.isfinite(sq)]
    return rot[0], trans[0], float(np.sqrt(sq.mean())) if sq.size else float("nan")


def _own_shape(reference: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The capture's own shape of its pose markers (K, 3) mm, laid onto ``reference`` (the
    session's): per frame a plain rigid fit, then each marker's median in that frame. Another
    actor's forehead is not the session actor's: against the session's shape no 3 of its markers
    would agree within :data:`OUTLIER_MM`. Ghosts are too rare to move a median."""
    from mocaptk.clustering.neutral import neutral_pose

    seen = np.isfinite(points).all(axis=2)
    rot, trans = kabsch(reference, points, seen.astype(float))
    head = np.einsum("fji,fkj->fki", rot, points - trans[:, None])
    own = neutral_pose(head)
    if not np.isfinite(own).all():
        return reference
    # the median shape's own placement drifts with the frames' fits: lay it back onto the reference
    r, t = kabsch(reference[None], own[None], np.ones((1, len(own))))
    return np.einsum("ji,kj->ki", r[0], own - t[0]) if np.isfinite(r).all() else reference


def _consensus(reference: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(F, K) bool: the pose markers of the largest set that one rigid fit places within
    :data:`OUTLIER_MM` (ties: the smallest RMS), tried from every 3 markers; none where no 3
    agree. A least-squares fit of all markers cannot name the outlier: a ghost drags the fit
    toward itself until a good marker looks worst."""
    n_frames, n_markers = points.shape[:2]
    seen = np.isfinite(points).all(axis=2)
    best = np.zeros((n_frames, n_markers), dtype=bool)
    best_count = np.zeros(n_frames, dtype=int)
    best_rms = np.full(n_frames, np.inf)
    for trio in combinations(range(n_markers), 3):
        weights = np.zeros((n_frames, n_markers))
        weights[:, trio] = seen[:, trio]
        rot, trans = kabsch(reference, points, weights)
        off = np.linalg.norm(np.einsum("fij,kj->fki", rot, reference) + trans[:, None] - points, axis=2)
        inliers = seen & (np.nan_to_num(off, nan=np.inf) <= OUTLIER_MM)
        count = inliers.sum(axis=1)
        rms = np.sqrt(np.where(inliers, np.nan_to_num(off) ** 2, 0.0).sum(axis=1) / np.maximum(count, 1))
        better = (count >= 3) & ((count > best_count) | ((count == best_count) & (rms < best_rms)))
        best[better], best_count[better], best_rms[better] = inliers[better], count[better], rms[better]
    return best


def refine_poses(poses: HeadPoses, gaussian: LayoutGaussian, x: np.ndarray, *,
                 iterations: int = REFINE_ITERATIONS, chunk: int = 4096) -> HeadPoses:
    """Poses moved to where the layout markers ``x`` (F, L, 3) mm look most like the session's
    expressions: per frame, Gauss-Newton on the Mahalanobis distance of the head-relative layout
    under ``gaussian``. Expression directions cost little in it and rigid ones much (a
    head-relative session has no rigid motion), so a brow raise no longer tilts the head as it
    does when a few forehead markers alone give the pose. A frame without a pose (its pose
    markers lost) starts from the nearest frame's and is fitted on the layout markers it has."""
    rot, trans = _held(poses.rotations, poses.translations)
    mean = gaussian.mean.reshape(-1, 3)
    for start in range(0, len(x), chunk):
        rows = slice(start, start + chunk)
        xs = np.asarray(x[rows], dtype=np.float64)
        present = np.isfinite(xs).all(axis=2) & np.isfinite(rot[rows, 0, 0])[:, None]
        r, t = rot[rows], trans[rows]
        for _ in range(iterations):
            y = in_head_frame(xs, r, t)  # head frame
            e = np.where(present[..., None], y - mean, 0.0).reshape(len(xs), -1, 1)
            jac = np.zeros((len(xs), y.shape[1], 3, 6))  # d y / d (omega, tau): [-[y]x, I]
            jac[..., 0, 1], jac[..., 0, 2] = y[..., 2], -y[..., 1]
            jac[..., 1, 0], jac[..., 1, 2] = -y[..., 2], y[..., 0]
            jac[..., 2, 0], jac[..., 2, 1] = y[..., 1], -y[..., 0]
            jac[..., :, 3:] = np.eye(3)
            jac = np.nan_to_num(jac).reshape(len(xs), -1, 6)
            weighted = gaussian.solve_present(present, np.concatenate([e, jac], axis=2))
            normal = np.einsum("fai,faj->fij", jac, weighted[..., 1:])
            ok = present.sum(axis=1) >= 3
            step = np.zeros((len(xs), 6))
            step[ok] = -np.linalg.solve(normal[ok], np.einsum("fai,fa->fi", jac[ok], weighted[ok, :, 0])[..., None])[..., 0]
            q = Rotation.from_rotvec(step[:, :3]).as_matrix()  # y_new = Q y + tau
            r = np.einsum("fij,fkj->fik", r, q)  # R Q^T
            t = t - np.einsum("fij,fj->fi", r, step[:, 3:])
        rot[rows], trans[rows] = r, t
    return replace(poses, rotations=rot, translations=trans)


def _held(rot: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Copies of poses with each frame lacking one given the nearest posed frame's (unchanged if none is)."""
    valid = np.flatnonzero(np.isfinite(rot[:, 0, 0]))
    if not valid.size:
        return rot.copy(), trans.copy()
    frames = np.arange(len(rot))
    right = np.clip(np.searchsorted(valid, frames), 0, valid.size - 1)
    left = np.clip(right - 1, 0, valid.size - 1)
    nearest = np.where(np.abs(valid[left] - frames) <= np.abs(valid[right] - frames), valid[left], valid[right])
    return rot[nearest], trans[nearest]


def least_moving_markers(neutral: np.ndarray, motion_mm: np.ndarray, labels: Sequence[str]) -> tuple[str, ...]:
    """Up to :data:`FALLBACK_COUNT` of ``labels`` that move least (``motion_mm`` (L,), e.g. the 95th
    percentile distance from the neutral in the head-relative session), pairwise at least
    :data:`FALLBACK_SPREAD_MM` apart and not on one line (``neutral`` (L, 3) mm)."""
    picked: list[int] = []
    for m in np.argsort(np.where(np.isfinite(motion_mm), motion_mm, np.inf), kind="stable"):
        if len(picked) == FALLBACK_COUNT or not np.isfinite(motion_mm[m]):
            break
        if any(np.linalg.norm(neutral[m] - neutral[k]) < FALLBACK_SPREAD_MM for k in picked):
            continue
        if len(picked) == 2:
            a, b = neutral[picked[0]], neutral[picked[1]]
            axis = (b - a) / np.linalg.norm(b - a)
            rel = neutral[m] - a
            if np.linalg.norm(rel - rel.dot(axis) * axis) < FALLBACK_SPREAD_MM / 2:
                continue
        picked.append(int(m))
    return tuple(labels[m] for m in picked) if len(picked) >= 3 else ()
