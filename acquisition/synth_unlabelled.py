"""Raw, unlabelled captures made from a labelled one, as an optical system delivers them.

A labelled session (the truth) is moved rigidly (random head motion), loses marker-frames to
occlusions, gains ghost points (reflections that follow the face near a marker), and is cut into
trajectory fragments: at every occlusion and at random (a Poisson process, ~2 s apart by default).
The fragments are then packed, in random order, into unlabelled columns ``*0``, ``*1``, ... (a
column holds several fragments, separated by at least one empty frame, so memory stays that of the
point count); or, as untracked per-frame point clouds, each frame's points are shuffled across
the columns. The truth says which source marker every output point is (``-1`` ghost, ``-2``
empty).
"""

from __future__ import annotations

import heapq
import os
from dataclasses import dataclass

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.trajectories import Trajectories

from .runs import true_runs
from .synth_session import random_head_motion

#: The issue's raw-capture settings: peak head rotation (deg) and translation (mm) per axis,
#: ghost points per visible point, occluded fraction of marker-frames, mean fragment length (s).
ROTATION_DEG = 15.0
TRANSLATION_MM = 30.0
GHOST_FRACTION = 0.02
OCCLUDED_FRACTION = 0.05
FRAGMENT_SECONDS = 2.0
#: Occlusion and ghost durations (frames), log-uniform between these bounds.
OCCLUSION_FRAMES = (2, 60)
GHOST_FRAMES = (1, 30)
#: Ghosts appear this far (mm) from the marker they follow.
GHOST_OFFSET_MM = (5.0, 30.0)
TRUTH_FORMAT = "mocaptk.label-truth"
TRUTH_VERSION = 1
GHOST, EMPTY = -1, -2


@dataclass(frozen=True, eq=False)
class RawCapture:
    """An unlabelled capture and what it really is.

    ``trajectories``: columns ``*0``... (frames, columns, 3) mm; ``truth (frames, columns)`` int:
    index into ``labels`` (the source markers), :data:`GHOST` or :data:`EMPTY`;
    ``head_rotations (F, 3, 3)``, ``head_translations (F, 3)`` mm: the motion added, about
    ``pivot (3,)`` mm.
    """

    trajectories: Trajectories
    truth: np.ndarray
    labels: tuple[str, ...]
    head_rotations: np.ndarray
    head_translations: np.ndarray
    pivot: np.ndarray


def spread_subset(traj: Trajectories, count: int) -> list[str]:
    """``count`` labels spread over the face: farthest-point sampling of the mean positions,
    starting from the marker nearest the centroid (deterministic)."""
    mean = np.nanmean(traj.positions, axis=0)
    seen = np.flatnonzero(~np.isnan(mean).any(axis=1))
    if count > len(seen):
        raise OptionError(f"cannot pick {count} markers from {len(seen)} with data")
    pts = mean[seen]
    picked = [int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(pts - pts[picked[0]], axis=1)
    while len(picked) < count:
        nxt = int(np.argmax(dist))
        picked.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(pts - pts[nxt], axis=1))
    return [traj.labels[seen[k]] for k in sorted(picked)]


def inject_swaps(traj: Trajectories, count: int, *, seed: int = 0,
                 frames: tuple[int, int] = (2, 60)) -> tuple[Trajectories, list[tuple[str, str, int, int]]]:
    """``traj`` with ``count`` label swaps between nearest-neighbour markers (each marker in one swap
    at most), each ``frames`` long (inclusive bounds); returns ``(swapped, [(a, b, start, end)])``."""
    rng = np.random.default_rng([seed, 31])
    pos = traj.positions.copy()
    mean = np.nanmean(pos, axis=0)
    dist = np.linalg.norm(mean[:, None] - mean[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    if count > traj.n_markers // 2:
        raise OptionError(f"cannot make {count} disjoint swaps among {traj.n_markers} markers")
    used: set[int] = set()
    swaps = []
    while len(swaps) < count:
        a = int(rng.integers(traj.n_markers))
        b = int(np.argmin(dist[a]))
        if a in used or b in used:
            continue
        length = int(rng.integers(frames[0], frames[1] + 1))
        start = int(rng.integers(0, traj.n_frames - length))
        pos[start:start + length, [a, b]] = pos[start:start + length, [b, a]]
        used |= {a, b}
        swaps.append((traj.labels[a], traj.labels[b], start, start + length))
    return traj.replace(positions=pos), swaps


def unlabelled_capture(traj: Trajectories, *, seed: int = 0, rotation_deg: float = ROTATION_DEG,
                       translation_mm: float = TRANSLATION_MM, ghosts: float = GHOST_FRACTION,
                       occluded: float = OCCLUDED_FRACTION, fragment_seconds: float = FRAGMENT_SECONDS,
                       clouds: bool = False) -> RawCapture:
    """The raw capture a system would deliver for the labelled session ``traj`` (see module doc).

    ``ghosts``: ghost points per visible marker point; ``occluded``: fraction of marker-frames
    removed (besides the source's own gaps); ``fragment_seconds``: mean time between random
    breaks of a trajectory; ``clouds``: shuffle every frame's points (no tracking at all).
    """
    if not (0 <= ghosts < 1 and 0 <= occluded < 1 and fragment_seconds > 0 and rotation_deg >= 0
            and translation_mm >= 0):
        raise OptionError("ghosts and occluded must be within [0, 1), fragment length > 0, motion ≥ 0")
    rng = np.random.default_rng([seed, 29])
    n_frames, n_markers = traj.n_frames, traj.n_markers
    rot, trans = random_head_motion(n_frames, rate=traj.rate, seed=seed, rotation_deg=rotation_deg,
                                    translation_mm=translation_mm)
    pivot = np.nanmean(traj.positions.reshape(-1, 3), axis=0)
    pos = np.einsum("fij,fmj->fmi", rot, traj.positions - pivot) + pivot + trans[:, None]
    visible = ~np.isnan(pos).any(axis=2)
    visible &= ~_occlusions(rng, n_frames, n_markers, occluded)
    pieces = _marker_fragments(rng, visible, traj.rate * fragment_seconds)
    pieces += _ghost_fragments(rng, pos, visible, ghosts)
    if clouds:
        out, truth = _clouds(rng, pos, pieces, n_frames)
    else:
        out, truth = _pack(rng, pos, pieces, n_frames)
    labels = [f"*{k}" for k in range(out.shape[1])]
    meta = {"takes": traj.takes, "source": traj.metadata.get("source", ""), "format": "synthetic raw",
            "original_units": "mm"}
    raw = Trajectories(out, labels, traj.rate, first_frame=traj.first_frame, metadata=meta)
    return RawCapture(raw, truth, traj.labels, rot, trans, pivot)


def _occlusions(rng: np.random.Generator, n_frames: int, n_markers: int, fraction: float) -> np.ndarray:
    """(F, M) True where a marker is occluded: runs of log-uniform length covering ~``fraction``."""
    mask = np.zeros((n_frames, n_markers), dtype=bool)
    lo, hi = OCCLUSION_FRAMES
    mean_len = (hi - lo) / np.log(hi / lo)
    for m in range(n_markers):
        for _ in range(rng.poisson(fraction * n_frames / mean_len)):
            length = int(np.exp(rng.uniform(np.log(lo), np.log(hi))))
            start = int(rng.integers(0, max(1, n_frames - length)))
            mask[start:start + length, m] = True
    return mask


def _marker_fragments(rng: np.random.Generator, visible: np.ndarray,
                      mean_frames: float) -> list[tuple[int, int, int, np.ndarray | None]]:
    """(marker, start, end, None) for every visible run, broken at random ~``mean_frames`` apart."""
    pieces = []
    for m in range(visible.shape[1]):
        for a, b in true_runs(visible[:, m]):
            while b - a > 1:
                cut = a + max(1, int(rng.exponential(mean_frames)))
                if cut >= b:
                    break
                pieces.append((m, a, cut, None))
                a = cut
            pieces.append((m, a, b, None))
    return pieces


def _ghost_fragments(rng: np.random.Generator, pos: np.ndarray, visible: np.ndarray,
                     fraction: float) -> list[tuple[int, int, int, np.ndarray | None]]:
    """Ghost fragments: a reflection a few cm at most from a marker, following it (+ jitter)."""
    n_frames, n_markers = visible.shape
    lo, hi = GHOST_FRAMES
    budget = int(round(fraction * visible.sum()))
    pieces = []
    while budget > 0:
        length = min(budget, int(np.exp(rng.uniform(np.log(lo), np.log(hi + 1)))), n_frames)
        start = int(rng.integers(0, n_frames - length + 1))
        anchor = int(rng.integers(0, n_markers))
        base = pos[start:start + length, anchor]
        if np.isnan(base).any():
            base = np.broadcast_to(np.nanmean(pos[:, anchor], axis=0), base.shape)
        direction = rng.normal(size=3)
        offset = direction / np.linalg.norm(direction) * rng.uniform(*GHOST_OFFSET_MM)
        points = base + offset + rng.normal(0.0, 0.5, size=base.shape)
        pieces.append((GHOST, start, start + length, points))
        budget -= length
    return pieces


def _pack(rng: np.random.Generator, pos: np.ndarray, pieces: list, n_frames: int):
    """Fragments into columns, in random order: each takes a random column free since ≥ 1 frame."""
    order = sorted(rng.permutation(len(pieces)), key=lambda k: pieces[k][1])
    busy: list[tuple[int, int]] = []  # (frame the column is free from, column)
    free: list[int] = []
    columns: list[list[int]] = []
    for k in order:
        start = pieces[k][1]
        while busy and busy[0][0] <= start:
            free.append(heapq.heappop(busy)[1])
        if free:
            col = free.pop(int(rng.integers(len(free))))
        else:
            col = len(columns)
            columns.append([])
        columns[col].append(k)
        heapq.heappush(busy, (pieces[k][2] + 1, col))  # one empty frame before the next fragment
    out = np.full((n_frames, len(columns), 3), np.nan)
    truth = np.full((n_frames, len(columns)), EMPTY, dtype=np.int32)
    shuffled = rng.permutation(len(columns))  # column names in random order too
    for col, ks in enumerate(columns):
        target = shuffled[col]
        for k in ks:
            marker, a, b, points = pieces[k]
            out[a:b, target] = pos[a:b, marker] if points is None else points
            truth[a:b, target] = marker
    return out, truth


def _clouds(rng: np.random.Generator, pos: np.ndarray, pieces: list, n_frames: int):
    """Every frame's points in random columns (no tracking)."""
    counts = np.zeros(n_frames, dtype=np.int64)
    for _, a, b, _ in pieces:
        counts[a:b] += 1
    width = int(counts.max()) if n_frames else 0
    out = np.full((n_frames, width, 3), np.nan)
    truth = np.full((n_frames, width), EMPTY, dtype=np.int32)
    slots = [rng.permutation(width)[:c].tolist() for c in counts]
    for marker, a, b, points in pieces:
        for f in range(a, b):
            col = slots[f].pop()
            out[f, col] = pos[f, marker] if points is None else points[f - a]
            truth[f, col] = marker
    return out, truth


def save_truth(raw: RawCapture, path: str | os.PathLike[str], *, force: bool = False) -> None:
    """The truth mapping as ``.npz``: ``truth (F, N)`` (index into ``labels``, -1 ghost, -2 empty),
    ``labels``, ``columns``, ``head_rotations``, ``head_translations``, ``format``, ``version``."""
    from mocaptk.atomic import atomic_open

    with atomic_open(path, "wb", force=force) as handle:
        np.savez_compressed(handle, truth=raw.truth.astype(np.int32), labels=np.array(raw.labels),
                            columns=np.array(raw.trajectories.labels),
                            head_rotations=raw.head_rotations, head_translations=raw.head_translations,
                            format=np.array(TRUTH_FORMAT), version=np.array(TRUTH_VERSION))


def load_truth(path: str | os.PathLike[str]) -> tuple[np.ndarray, tuple[str, ...]]:
    """``(truth (F, N), source labels)`` saved by :func:`save_truth`."""
    with np.load(path, allow_pickle=False) as data:
        return data["truth"], tuple(str(x) for x in data["labels"])

