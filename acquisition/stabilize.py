"""Rigid head stabilization: per-frame Kabsch fit of a rigid marker set, head-relative trajectories.

The pose of frame ``f`` maps reference coordinates to the capture: ``x_f = R_f @ x_ref + t_f``;
head-relative positions are ``R_f.T @ (x_f - t_f)``, i.e. every frame expressed in the head
coordinates of the reference frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mocaptk.errors import InputFileError, MocaptkError, OptionError
from mocaptk.trajectories import Trajectories

from .filtering import lowpass
from .runs import take_segments, true_runs

#: Automatic rigid set: at most this many markers ...
AUTO_RIGID_MAX = 6
#: ... pairwise at least this fraction of the marker cloud's diameter apart (a spread set: markers
#: that merely move together with their close neighbours keep their distances too) ...
AUTO_RIGID_SPREAD = 0.25
#: ... each added while the 95th percentile of its distance changes stays below
#: ``max(AUTO_RIGID_MIN_TOLERANCE_MM, 2.5 × that of the first pair)``.
AUTO_RIGID_MIN_TOLERANCE_MM = 1.0
#: The third marker must lie at least this far (mm) from the line through the first two.
AUTO_RIGID_MIN_SPREAD_MM = 10.0
#: Default low-pass cut-off (Hz) of the rigid markers before the pose fit: head motion is slow,
#: marker noise is white, so the fitted pose keeps the motion and sheds most of the noise (noise in
#: the pose would move every stabilized marker together and read as correlated facial motion).
POSE_CUTOFF_HZ = 12.0
#: Sessions with more markers than this search rigid pairs among this many candidates only,
#: picked by their distance changes to a few spread probe markers (O(markers x probes)).
AUTO_RIGID_CANDIDATES = 100
_PROBES = 12
_DETECT_FRAMES = 300  # frames sampled to score distance variation
_MIN_SHARED = 0.5     # a pair counts only if seen together in half the sampled frames that have data
_REFINE_ROUNDS = 2    # stabilize-and-reselect rounds after the pairwise-distance pick


@dataclass(frozen=True)
class StabilizeResult:
    """Head-relative trajectories and the head pose per frame.

    ``trajectories``: positions in the reference frame's head coordinates (mm), NaN in frames
    without a pose; ``rotations (F, 3, 3)`` and ``translations (F, 3)`` mm with
    ``x_f = R_f x_ref + t_f`` (NaN where fewer than 3 consistent rigid markers are seen);
    ``rigid_labels``: the markers used; ``rms_residual_mm (F,)``: RMS distance of the rigid
    markers from the fitted rigid body; ``reference_frame``: index of the reference frame (-1: a
    given reference shape).
    """

    trajectories: Trajectories
    rotations: np.ndarray
    translations: np.ndarray
    rigid_labels: tuple[str, ...]
    rms_residual_mm: np.ndarray
    reference_frame: int


def kabsch(reference: np.ndarray, moving: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted rigid fit ``moving ≈ R @ reference + t``.

    Parameters
    ----------
    reference : (M, 3) or (F, M, 3) mm
    moving : (F, M, 3) mm (NaN allowed where ``weights`` is 0)
    weights : (F, M) >= 0

    Returns
    -------
    rotations (F, 3, 3), translations (F, 3); NaN for frames with fewer than 3 weighted markers
    or a degenerate (collinear) set.
    """
    w = np.asarray(weights, dtype=float)
    ref = np.broadcast_to(reference, moving.shape)
    ref = np.where(w[..., None] > 0, ref, 0.0)
    mov = np.where(w[..., None] > 0, moving, 0.0)
    total = w.sum(axis=1)
    ok = ((w > 0).sum(axis=1) >= 3) & (total > 0)
    safe = np.where(ok, total, 1.0)[:, None]
    c_ref = np.einsum("fm,fmk->fk", w, ref) / safe
    c_mov = np.einsum("fm,fmk->fk", w, mov) / safe
    cov = np.einsum("fm,fmi,fmj->fij", w, ref - c_ref[:, None], mov - c_mov[:, None])
    u, s, vt = np.linalg.svd(cov)
    ok &= s[:, 1] > 1e-9 * np.maximum(s[:, 0], 1e-300)
    d = np.sign(np.linalg.det(np.einsum("fji,fkj->fik", vt, u)))  # det(V U^T)
    d[d == 0] = 1.0
    fix = np.ones_like(s)
    fix[:, 2] = d
    rot = np.einsum("fji,fj,fkj->fik", vt, fix, u)  # V diag(1,1,d) U^T
    trans = c_mov - np.einsum("fij,fj->fi", rot, c_ref)
    rot[~ok] = np.nan
    trans[~ok] = np.nan
    return rot, trans


def detect_rigid_markers(traj: Trajectories) -> tuple[str, ...]:
    """Markers that move as one rigid body, spread over it (on a face: nose bridge, temples, forehead).

    Rule, on up to 300 evenly spaced frames (sessions of more than 100 markers: among the 100
    candidates of :func:`_candidates`, so the cost is O(markers x probes), not all pairs):
    for every marker pair seen together in at least half
    of those with data, take the 95th percentile of ``|d(f) - median d|`` (its distance changes, mm). Only
    pairs at least ``AUTO_RIGID_SPREAD`` (25 %) of the cloud's diameter apart count — neighbouring
    skin markers keep their distances while moving together, distant ones only if both sit on the
    rigid skull. Start from the steadiest such pair; repeatedly add the marker, far enough from all
    chosen ones, whose largest change to them is smallest, while it stays below
    ``max(1 mm, 2.5 × the first pair's)`` and the set is smaller than 6; the third marker is always
    added (≥ 10 mm off the line through the first two). Then, twice: stabilize on the set and
    re-pick by head-relative motion (95th percentile distance from the marker's median position in
    head coordinates): the steadiest markers pairwise 25 % of the diameter apart, then the steadiest
    others, up to 6, all moving less than ``max(1 mm, 2.5 × the steadiest one's motion)``.
    Raises :class:`InputFileError` naming ``metadata["source"]`` (else :class:`OptionError`) if
    no 3 markers qualify.
    """
    pos, visible = _sample(traj)
    n_markers = visible.shape[1]
    if n_markers < 3:
        raise OptionError(f"stabilization needs at least 3 markers, the session has {n_markers}")
    candidates = _candidates(pos, visible)
    typical, change = _pair_distance_stats(pos[:, candidates], visible[:, candidates])
    sub_visible = visible[:, candidates]
    shared = sub_visible.T.astype(float) @ sub_visible.astype(float)
    with_data = max(1, int(visible.any(axis=1).sum()))  # frames outside takes may be empty
    usable = (shared >= _MIN_SHARED * with_data) & np.isfinite(change)
    np.fill_diagonal(usable, False)
    if not usable.any():
        raise _undetected(traj, "no two markers are seen together often enough")
    spread = typical >= AUTO_RIGID_SPREAD * typical[usable].max()
    score = np.where(usable & spread, change, np.inf)
    i, j = np.unravel_index(np.argmin(score), score.shape)
    if not np.isfinite(score[i, j]):
        raise _undetected(traj, "no distant marker pair is seen together")
    tolerance = max(AUTO_RIGID_MIN_TOLERANCE_MM, 2.5 * float(score[i, j]))
    chosen = [int(i), int(j)]
    while len(chosen) < AUTO_RIGID_MAX:
        worst = score[:, chosen].max(axis=1)  # inf unless far from / co-visible with every chosen
        worst[chosen] = np.inf
        if len(chosen) == 2:
            off = _off_line(pos[:, candidates], sub_visible, chosen)
            worst = np.where(off >= AUTO_RIGID_MIN_SPREAD_MM, worst, np.inf)
        k = int(np.argmin(worst))
        if not np.isfinite(worst[k]):
            if len(chosen) < 3:
                raise _undetected(traj, "no third marker far from the first two")
            break
        if worst[k] > tolerance and len(chosen) >= 3:
            break
        chosen.append(k)
    chosen = [int(candidates[k]) for k in chosen]
    sample = Trajectories(pos, traj.labels, traj.rate)
    for _ in range(_REFINE_ROUNDS):
        chosen = _least_moving_spread_set(sample, chosen, spread_mm=AUTO_RIGID_SPREAD * typical[usable].max())
    return tuple(traj.labels[k] for k in sorted(chosen))


def _sample(traj: Trajectories) -> tuple[np.ndarray, np.ndarray]:
    """Up to :data:`_DETECT_FRAMES` evenly spaced frames (F', M, 3) mm and their visibility."""
    pos = traj.positions[::max(1, traj.n_frames // _DETECT_FRAMES)]
    return pos, ~np.isnan(pos).any(axis=2)


def _visible_medians(pos: np.ndarray, visible: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(M, 3) mm: per marker of ``pos`` (F, M, 3) the per-axis median of its ``visible`` (F, M)
    frames (``np.median``'s values: the middle one, or the mean of the two middle ones), NaN
    where not ``keep``; one sort of all markers (a ``np.median`` per marker: ~60 us each)."""
    counts = visible.sum(axis=0)
    ordered = np.sort(np.where(visible[..., None], pos, np.nan), axis=0)  # NaN sorts last
    markers = np.arange(pos.shape[1])
    low, high = ordered[np.maximum(counts - 1, 0) // 2, markers], ordered[counts // 2, markers]
    centre = (low + high) / 2  # odd counts: (x + x) / 2 == x exactly
    centre[~keep] = np.nan
    return centre


def _candidates(pos: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Indices of the markers worth a pairwise rigid search: all of them, or for more than
    :data:`AUTO_RIGID_CANDIDATES`, those keeping their distance best to two or more of
    :data:`_PROBES` spread probe markers far from them (a skull marker does to the skull probes;
    a skin marker to none far away). Cost O(markers x probes x frames)."""
    n_markers = visible.shape[1]
    if n_markers <= AUTO_RIGID_CANDIDATES:
        return np.arange(n_markers)
    centre = _visible_medians(pos, visible, visible.any(axis=0))
    seen = visible.sum(axis=0)
    probes = [int(np.argmax(seen))]  # farthest-point sampling among often-seen markers
    often = seen >= _MIN_SHARED * seen.max()
    gap = np.where(often, np.linalg.norm(centre - centre[probes[0]], axis=1), -np.inf)
    while len(probes) < _PROBES and np.isfinite(gap).any() and gap.max() > 0:
        probes.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.where(often, np.linalg.norm(centre - centre[probes[-1]], axis=1),
                                       -np.inf))
    typical, change = _pair_distance_stats(pos, visible, columns=np.array(probes))
    far = typical >= AUTO_RIGID_SPREAD * np.nanmax(np.where(np.isfinite(typical), typical, np.nan))
    steady = np.sort(np.where(far, change, np.inf), axis=1)[:, min(1, len(probes) - 1)]
    order = np.argsort(steady, kind="stable")
    return np.sort(order[:AUTO_RIGID_CANDIDATES])


def head_relative_markers(traj: Trajectories, *, tolerance_mm: float) -> tuple[tuple[str, ...], float] | None:
    """A spread set of 3-6 markers that already stay still (RMS distance from their median
    position below ``tolerance_mm``, on up to 300 sampled frames), and its RMS motion (mm); or
    ``None``. Such a session is head-relative already (head-mounted rig, cleaned data): finding
    and fitting a rigid set on it would only turn skin motion into head motion. O(markers x
    frames)."""
    pos, visible = _sample(traj)
    n_markers = visible.shape[1]
    counts = visible.sum(axis=0)
    enough = counts >= _MIN_SHARED * max(1, int(visible.any(axis=1).sum()))
    if n_markers < 3 or not enough.any():
        return None
    centre = _visible_medians(pos, visible, enough)
    offsets = np.linalg.norm(pos - centre, axis=2)
    motion = np.sqrt(np.where(visible, offsets ** 2, 0.0).sum(axis=0) / np.maximum(counts, 1))
    motion[~enough] = np.inf
    still = [int(m) for m in np.argsort(motion, kind="stable") if motion[m] < tolerance_mm]
    if len(still) < 3:
        return None
    known = centre[enough]
    diameter = float(np.linalg.norm(known.max(axis=0) - known.min(axis=0)))
    picked: list[int] = []
    for m in still:
        if len(picked) == AUTO_RIGID_MAX:
            break
        if all(np.linalg.norm(centre[m] - centre[k]) >= AUTO_RIGID_SPREAD * diameter for k in picked):
            if len(picked) == 2 and _distance_to_line(centre[m], centre[picked[0]],
                                                      centre[picked[1]]) < AUTO_RIGID_MIN_SPREAD_MM:
                continue
            picked.append(m)
    if len(picked) < 3:
        return None
    rms = float(np.sqrt(np.mean(motion[picked] ** 2)))
    return tuple(traj.labels[k] for k in sorted(picked)), rms


def _undetected(traj: Trajectories, why: str) -> MocaptkError:
    """The error for a session whose rigid head markers cannot be found (names the file)."""
    problem = (f"cannot detect 3 rigid head markers ({why}); name them with --rigid A,B,C, "
               "or use --no-stabilize for head-relative data")
    source = traj.metadata.get("source")
    return InputFileError(source, problem) if source else OptionError(problem)


def _least_moving_spread_set(sample: Trajectories, chosen: list[int], *, spread_mm: float) -> list[int]:
    """Refine a rigid set: stabilize on it, then take the markers that move least in head coordinates
    (95th percentile distance from their median head-relative position), first pairwise
    ``spread_mm`` apart, then any of the remaining ones that move as little (up to 6 in all)."""
    try:
        rel = stabilize_head(sample, rigid_labels=[sample.labels[k] for k in chosen],
                             pose_cutoff_hz=None).trajectories.positions  # frames subsampled: no filter
    except OptionError:
        return chosen
    seen = ~np.isnan(rel).any(axis=2)
    enough = seen.sum(axis=0) >= _MIN_SHARED * max(1, int(seen.any(axis=1).sum()))
    centre = _visible_medians(rel, seen, enough)
    motion = np.full(rel.shape[1], np.inf)
    for m in np.flatnonzero(enough):
        motion[m] = np.percentile(np.linalg.norm(rel[seen[:, m], m] - centre[m], axis=1), 95)
    order = [int(m) for m in np.argsort(motion, kind="stable") if np.isfinite(motion[m])]
    if not order:
        return chosen
    tolerance = max(AUTO_RIGID_MIN_TOLERANCE_MM, 2.5 * motion[order[0]])
    picked: list[int] = []
    for m in order:
        if len(picked) >= AUTO_RIGID_MAX or (motion[m] > tolerance and len(picked) >= 3):
            break
        if all(np.linalg.norm(centre[m] - centre[k]) >= spread_mm for k in picked):
            if len(picked) == 2 and _distance_to_line(centre[m], centre[picked[0]], centre[picked[1]]) \
                    < AUTO_RIGID_MIN_SPREAD_MM:
                continue
            picked.append(m)
    if len(picked) < 3:
        return chosen
    # then the steadiest remaining markers, close or not: more markers, fewer frames without a pose
    extra = [m for m in order if m not in picked and motion[m] <= tolerance]
    return picked + extra[:AUTO_RIGID_MAX - len(picked)]


def _distance_to_line(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-12)
    rel = point - a
    return float(np.linalg.norm(rel - rel.dot(axis) * axis))


def _pair_distance_stats(pos: np.ndarray, visible: np.ndarray,
                         columns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per marker pair over frames seen together: median distance and 95th percentile of
    ``|d - median d|`` (both (M, C) mm for the ``columns`` markers, default all; inf where never
    seen together)."""
    n_frames, n_markers = visible.shape
    cols = np.arange(n_markers) if columns is None else columns
    typical = np.full((n_markers, len(cols)), np.inf)
    change = np.full((n_markers, len(cols)), np.inf)
    rows = max(1, 8_000_000 // max(1, n_frames * len(cols)))
    for lo in range(0, n_markers, rows):  # chunks of marker rows keep (F, rows, C) arrays small
        hi = min(n_markers, lo + rows)
        both = visible[:, lo:hi, None] & visible[:, None, cols]
        d = np.linalg.norm(pos[:, lo:hi, None] - pos[:, None, cols], axis=3)
        d = np.where(both, d, np.inf)
        count = both.sum(axis=0)
        has = count > 0
        median = np.take_along_axis(np.sort(d, axis=0), np.maximum(count - 1, 0)[None] // 2, axis=0)[0]
        with np.errstate(invalid="ignore"):  # inf - inf where never seen together: dropped below
            dev = np.where(both, np.abs(d - median), np.inf)
        p95 = np.take_along_axis(np.sort(dev, axis=0), (np.maximum(count - 1, 0)[None] * 95) // 100, axis=0)[0]
        typical[lo:hi] = np.where(has, median, np.inf)
        change[lo:hi] = np.where(has, p95, np.inf)
    return typical, change


def _off_line(pos: np.ndarray, visible: np.ndarray, pair: list[int]) -> np.ndarray:
    """Median distance (mm) of every marker from the line through the markers ``pair``."""
    a, b = pos[:, pair[0]], pos[:, pair[1]]
    axis = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True).clip(1e-12)
    rel = pos - a[:, None]
    off = np.linalg.norm(rel - np.einsum("fmk,fk->fm", rel, axis)[..., None] * axis[:, None], axis=2)
    ok = visible & visible[:, pair].all(axis=1, keepdims=True)
    off = np.where(ok, off, np.nan)
    out = np.zeros(off.shape[1])
    seen = ok.any(axis=0)
    out[seen] = np.nanmedian(off[:, seen], axis=0)
    return out


def _reference_frame(traj: Trajectories, rigid: np.ndarray, visible: np.ndarray, outlier_mm: float) -> int:
    """The first clean frame with the most rigid markers seen, preferring a take named like "neutral".

    Clean: every pairwise distance of the rigid markers within ``max(outlier_mm, 3 × typical)`` of its
    median over the candidate frames (so a glitching marker in the first frame cannot become the
    reference shape); if no candidate is clean, the candidate closest to the median distances.
    """
    count = visible.sum(axis=1)
    candidates = np.flatnonzero(count == count.max())
    for take in traj.takes:
        if "neutral" in take.name.lower():
            inside = candidates[(candidates >= take.start) & (candidates < take.end)]
            if inside.size:
                candidates = inside
                break
    cols = np.flatnonzero(visible[candidates[0]])  # same markers in every candidate
    pts = rigid[candidates][:, cols]
    d = np.linalg.norm(pts[:, :, None] - pts[:, None, :], axis=3)
    dev = np.abs(d - np.median(d, axis=0)).reshape(len(candidates), -1).max(axis=1)
    clean = np.flatnonzero(dev <= max(outlier_mm, 3.0 * float(np.median(dev))))
    return int(candidates[clean[0]] if clean.size else candidates[np.argmin(dev)])


def stabilize_head(traj: Trajectories, *, rigid_labels: Sequence[str] | None = None,
                   outlier_mm: float = 2.0, max_pose_gap: int = 10,
                   pose_cutoff_hz: float | None = POSE_CUTOFF_HZ,
                   reference: np.ndarray | None = None) -> StabilizeResult:
    """Remove rigid head motion: fit the rigid marker set in every frame, express all markers in head coordinates.

    Parameters
    ----------
    traj : session (frames, markers, 3) mm
    rigid_labels : markers on the rigid part of the head (≥ 3); default: detected with
        :func:`detect_rigid_markers`.
    outlier_mm : a rigid marker is dropped from a frame's fit (if ≥ 3 remain) when its distances to
        the other rigid markers deviate from the reference shape by more than this (median over
        the others), or when its residual after the fit exceeds ``max(outlier_mm, 3 × median
        residual)``.
    max_pose_gap : frames without a pose (fewer than 3 consistent rigid markers) in runs of at most
        this many frames, inside one take and with posed frames on both sides, get a pose
        interpolated from those neighbours (rotation slerp, linear translation); their
        ``rms_residual_mm`` stays NaN. Longer runs stay without a pose (NaN output).
    pose_cutoff_hz : the poses are fitted to the rigid markers low-passed at this cut-off
        (zero-phase Butterworth, :func:`~mocaptk.acquisition.filtering.lowpass`); ``None``, or a
        frame rate not above twice the cut-off: fitted to the raw markers. The stabilized output is
        never filtered, only the pose.
    reference : (K, 3) mm, optional
        The rigid markers' positions (``rigid_labels`` order) in the head frame to express the
        output in, e.g. the training session's, so that a test or production capture lands in the
        frame its models were made in; its ``reference_frame`` is then -1.

    Each frame uses only its visible rigid markers (≥ 3). The reference shape is the rigid set in the
    reference frame (the first clean frame with the most rigid markers, in a "neutral" take if
    there is one, see :func:`_reference_frame`), refined (3 rounds) to the per-marker mean of the head-relative rigid
    positions over inlier frames, so a marker missing or glitching in the reference frame still
    takes part. The output is expressed in the reference frame's own coordinates (its pose is
    the identity).
    """
    labels = tuple(rigid_labels) if rigid_labels is not None else detect_rigid_markers(traj)
    if len(set(labels)) < 3:
        raise OptionError(f"stabilization needs at least 3 distinct rigid markers, got {len(set(labels))}")
    unknown = [label for label in labels if label not in set(traj.labels)]
    if unknown:
        raise OptionError(f"rigid markers not in the session: {', '.join(unknown[:5])}"
                          + (f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""))
    idx = traj.index(labels)
    raw = rigid = traj.positions[:, idx]
    if pose_cutoff_hz is not None and pose_cutoff_hz < traj.rate / 2:
        rigid = lowpass(traj.select(list(labels)), cutoff_hz=pose_cutoff_hz).positions
    visible = ~np.isnan(rigid).any(axis=2)
    if not visible.any():
        raise OptionError("the rigid markers are never visible")
    given = reference is not None
    if given:
        reference = np.array(reference, dtype=float)
        if reference.shape != (len(labels), 3) or not np.isfinite(reference).all():
            raise OptionError(f"the stabilization reference must be ({len(labels)}, 3) finite mm, "
                              f"got shape {reference.shape}")
        ref_frame = -1
    else:
        ref_frame = _reference_frame(traj, rigid, visible, outlier_mm)
        reference = rigid[ref_frame].copy()
    for _ in range(3):
        known = visible & ~np.isnan(reference).any(axis=1)
        # drop markers that left the rigid body in a frame (sliding skin, mislabels), keep >= 3
        weights = known & _distances_consistent(rigid, reference, outlier_mm)  # < 3 left: no pose
        rot, trans = kabsch(np.nan_to_num(reference), rigid, weights)
        residual = _residuals(np.nan_to_num(reference), rigid, rot, trans)
        median = np.zeros(len(rigid))
        rows = weights.any(axis=1) & ~np.isnan(rot[:, 0, 0])
        median[rows] = np.nanmedian(np.where(weights, residual, np.nan)[rows], axis=1)
        weights = _keep_three(weights & (residual <= np.maximum(outlier_mm, 3.0 * median)[:, None]), weights)
        rot, trans = kabsch(np.nan_to_num(reference), rigid, weights)
        if given:
            break  # the frame to land in is fixed: one round of outlier rejection is all
        # reference shape = mean head-relative position of each rigid marker over its inlier frames
        # (outliers are already out; a mean, unlike a per-axis median, does not depend on the axes)
        rel = in_head_frame(rigid, rot, trans)
        inlier = weights & ~np.isnan(rel).any(axis=2)
        for m in np.flatnonzero(inlier.any(axis=0)):
            reference[m] = rel[inlier[:, m], m].mean(axis=0)
    residual = _residuals(np.nan_to_num(reference), raw, rot, trans)  # of the markers as captured
    counts = weights.sum(axis=1)
    sq = np.where(weights, residual, 0.0) ** 2
    rms = np.full(len(rigid), np.nan)
    has = counts > 0
    rms[has] = np.sqrt(sq[has].sum(axis=1) / counts[has])
    rms[np.isnan(rot[:, 0, 0])] = np.nan
    if not given and np.isfinite(rot[ref_frame]).all():
        # rotate back to the reference frame's own coordinates
        r0, t0 = rot[ref_frame].copy(), trans[ref_frame].copy()
        rot = np.einsum("fij,kj->fik", rot, r0)  # R_f R0^T
        trans = trans - np.einsum("fij,j->fi", rot, t0)
    bridge_poses(rot, trans, take_segments(traj), max_gap=max_pose_gap)
    relative = in_head_frame(traj.positions, rot, trans)
    meta = dict(traj.metadata)
    meta["stabilized"] = {"rigid_labels": list(labels), "reference_frame": ref_frame}
    return StabilizeResult(traj.replace(positions=relative, metadata=meta), rot, trans, labels, rms, ref_frame)


def bridge_poses(rot: np.ndarray, trans: np.ndarray, segments: list[tuple[int, int]], *, max_gap: int) -> None:
    """Interpolate missing poses (NaN) in place over interior runs of at most ``max_gap`` frames."""
    missing = np.isnan(rot[:, 0, 0])
    for s, e in segments:
        for a, b in true_runs(missing[s:e]):
            if a == 0 or b == e - s or b - a > max_gap:
                continue
            lo, hi = s + a - 1, s + b
            frames = np.arange(s + a, s + b)
            rot[frames] = Slerp([lo, hi], Rotation.from_matrix(rot[[lo, hi]]))(frames).as_matrix()
            w = ((frames - lo) / (hi - lo))[:, None]
            trans[frames] = (1 - w) * trans[lo] + w * trans[hi]


def _keep_three(weights: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``weights`` per frame where they keep at least 3 markers, else ``fallback``."""
    return np.where((weights.sum(axis=1) >= 3)[:, None], weights, fallback)


def _distances_consistent(rigid: np.ndarray, reference: np.ndarray, outlier_mm: float) -> np.ndarray:
    """(F, K) True where a rigid marker keeps its reference distances to the other visible ones.

    A marker is an outlier in a frame when the (lower) median over the other markers of
    ``|d_ij(f) - d_ij(ref)|`` exceeds ``max(outlier_mm, 3 × the session's median deviation)``;
    a good marker has at most one large deviation (to the outlier), so its median stays small.
    Independent of the head pose, so it works before any fit.
    """
    d = np.linalg.norm(rigid[:, :, None] - rigid[:, None, :], axis=3)  # (F, K, K), NaN if unseen
    d_ref = np.linalg.norm(reference[:, None] - reference[None, :], axis=2)
    dev = np.abs(d - d_ref)
    k = rigid.shape[1]
    dev[:, np.arange(k), np.arange(k)] = np.nan
    valid = ~np.isnan(dev)
    count = valid.sum(axis=2)
    ordered = np.sort(np.where(valid, dev, np.inf), axis=2)
    lower_median = np.take_along_axis(ordered, np.maximum(count - 1, 0)[..., None] // 2, axis=2)[..., 0]
    typical = float(np.median(dev[valid])) if valid.any() else 0.0
    return (count > 0) & (lower_median <= max(outlier_mm, 3.0 * typical))


def in_head_frame(points: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """``R_f^T (x - t_f)`` for points (F, M, 3) mm, rotations (F, 3, 3), translations (F, 3) mm;
    NaN where the pose or the point is unknown."""
    return np.einsum("fji,fmj->fmi", rot, points - trans[:, None])


def _residuals(reference: np.ndarray, moving: np.ndarray, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Distance (F, M) mm between each moving marker and the posed reference marker."""
    posed = np.einsum("fij,mj->fmi", rot, reference) + trans[:, None]
    return np.linalg.norm(moving - posed, axis=2)
