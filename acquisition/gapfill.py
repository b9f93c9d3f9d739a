"""Gap filling: spline interpolation for short gaps, neighbour regression for long ones.

Takes are hard cuts: a gap is looked at inside its take only (a gap that reaches a take boundary
is a leading/trailing gap of that take), and interpolation never uses frames of another take.
Leading and trailing gaps are never extrapolated in time; they are filled from neighbouring
markers only when no longer than ``max_gap``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.threads import single_threaded
from mocaptk.trajectories import Trajectories

from .runs import take_segments, true_runs

METHODS = ("auto", "cubic", "akima", "neighbours")
_MIN_TRAINING_FRAMES = 10
_MAX_TRAINING_FRAMES = 4000
_CORRELATION_FRAMES = 600  # frames used to rank neighbours by correlation
_TRACK_BLOCK = 16  # markers whose tracks are copied contiguous at a time (16 x 72,000 frames: 28 MB)


@dataclass(frozen=True)
class GapRecord:
    """One gap: marker, frames ``[start, end)`` (0-based), where it lies in its take
    (``interior``/``leading``/``trailing``/``whole``), the fill ``method`` (``cubic``, ``akima``,
    ``neighbours``) or ``None`` if left unfilled, and a ``note`` (why unfilled / which neighbours)."""

    marker: str
    start: int
    end: int
    position: str
    method: str | None
    note: str = ""

    @property
    def length(self) -> int:
        return self.end - self.start

    def as_dict(self) -> dict[str, Any]:
        return {"marker": self.marker, "start": self.start, "end": self.end, "position": self.position,
                "method": self.method, "note": self.note}


@dataclass(frozen=True)
class FillReport:
    """Every gap found, filled or not (``records``, in marker then frame order)."""

    records: tuple[GapRecord, ...]

    @property
    def filled(self) -> list[GapRecord]:
        return [r for r in self.records if r.method is not None]

    @property
    def unfilled(self) -> list[GapRecord]:
        return [r for r in self.records if r.method is None]

    def frames_filled(self, method: str | None = None) -> int:
        """Number of marker-frames filled (by ``method``, default any)."""
        return sum(r.length for r in self.filled if method is None or r.method == method)

    def as_dict(self) -> dict[str, Any]:
        return {"filled_frames": self.frames_filled(),
                "filled_frames_by_method": {m: self.frames_filled(m) for m in METHODS[1:]},
                "unfilled_frames": sum(r.length for r in self.unfilled),
                "gaps": [r.as_dict() for r in self.records]}

    def summary(self) -> str:
        """One line: gaps filled per method and gaps left."""
        parts = [f"{sum(1 for r in self.filled if r.method == m)} gaps / {self.frames_filled(m)} frames by {m}"
                 for m in METHODS[1:] if self.frames_filled(m)]
        left = self.unfilled
        parts.append(f"{len(left)} gaps / {sum(r.length for r in left)} frames left unfilled")
        return "; ".join(parts)


def fill_gaps(traj: Trajectories, *, max_gap: int = 10, method: str = "auto",
              max_neighbour_gap: int | None = None, neighbours: int = 4) -> tuple[Trajectories, FillReport]:
    """Fill gaps (NaN runs) of every marker, take by take.

    Parameters
    ----------
    traj : session (frames, markers, 3) mm
    max_gap : int
        Longest gap (frames) filled by interpolation, and longest leading/trailing gap filled at all.
    method : ``"auto"`` (spline up to ``max_gap``, neighbours for longer interior gaps), ``"cubic"`` /
        ``"akima"`` (only that interpolation, up to ``max_gap``), ``"neighbours"`` (neighbour
        regression for every gap).
    max_neighbour_gap : int, optional
        Longest interior gap filled from neighbours (default: any length).
    neighbours : int
        Number of most correlated markers used to predict a missing marker.

    Returns
    -------
    (filled Trajectories, FillReport). Residuals stay NaN at filled points.

    Spline fill fits a cubic (or Akima) spline through all observed frames of the marker in its
    take. Neighbour fill picks the ``neighbours`` markers seen throughout the gap whose
    displacements correlate best with the marker's, fits a linear (ridge) regression from their
    coordinates to the marker's on frames where all are seen (its take, else the whole session),
    predicts the gap, and shifts the prediction linearly so it meets the observed positions at
    both gap edges (no jump).
    """
    if method not in METHODS:
        raise OptionError(f"unknown gap-fill method {method!r} (known: {', '.join(METHODS)})")
    if max_gap < 0 or (max_neighbour_gap is not None and max_neighbour_gap < 0):
        raise OptionError("gap lengths must be >= 0 frames")
    if neighbours < 1:
        raise OptionError("neighbours must be >= 1")
    observed = traj.positions
    missing = np.isnan(observed).any(axis=2)
    out = observed.copy()
    out[missing] = np.nan
    records: list[GapRecord] = []
    long_gaps: list[tuple[int, int, int, int, int, str]] = []  # marker, seg start/end, gap start/end, kind
    segments = take_segments(traj)
    for m, label in enumerate(traj.labels):
        if m % _TRACK_BLOCK == 0:  # the next markers' tracks contiguous: the splines' reads in cache
            tracks = np.ascontiguousarray(out[:, m:m + _TRACK_BLOCK].transpose(1, 0, 2))
            misses = np.ascontiguousarray(missing[:, m:m + _TRACK_BLOCK].T)
        for s, e in segments:
            miss = misses[m % _TRACK_BLOCK, s:e]
            runs = true_runs(miss)
            if not runs:
                continue
            if len(runs) == 1 and runs[0] == (0, e - s):
                records.append(GapRecord(label, s, e, "whole", None, "marker never seen in this take"))
                continue
            interp = []
            for gs, ge in runs:
                kind = "leading" if gs == 0 else "trailing" if ge == e - s else "interior"
                length = ge - gs
                if kind == "interior" and length <= max_gap and method in ("auto", "cubic", "akima"):
                    interp.append((gs, ge))
                elif method in ("cubic", "akima"):
                    note = ("not extrapolated" if kind != "interior" else f"longer than max_gap {max_gap}")
                    records.append(GapRecord(label, s + gs, s + ge, kind, None, note))
                elif kind != "interior" and length > max_gap:
                    records.append(GapRecord(label, s + gs, s + ge, kind, None,
                                             f"{kind} gap longer than max_gap {max_gap}"))
                elif kind == "interior" and max_neighbour_gap is not None and length > max_neighbour_gap:
                    records.append(GapRecord(label, s + gs, s + ge, kind, None,
                                             f"longer than max_neighbour_gap {max_neighbour_gap}"))
                else:
                    long_gaps.append((m, s, e, s + gs, s + ge, kind))
            if interp:
                kind_name = "akima" if method == "akima" else "cubic"
                frames, values = _interpolate(tracks[m % _TRACK_BLOCK, s:e], ~miss, interp,
                                              akima=method == "akima")
                out[s + frames, m] = values
                records += [GapRecord(label, s + gs, s + ge, "interior", kind_name) for gs, ge in interp]
    visible = ~np.isnan(out).any(axis=2)  # includes points filled by splines; kept up to date
    for m, s, e, gs, ge, kind in long_gaps:
        note = _neighbour_fill(out, missing, visible, m, (s, e), (gs, ge), k=neighbours,
                               labels=traj.labels)
        visible[gs:ge, m] = ~np.isnan(out[gs:ge, m]).any(axis=1)
        filled = bool(visible[gs, m])
        records.append(GapRecord(traj.labels[m], gs, ge, kind, "neighbours" if filled else None, note))
    records.sort(key=lambda r: (traj.labels.index(r.marker), r.start))
    return traj.replace(positions=out), FillReport(tuple(records))


def held_out_gaps(traj: Trajectories, *, rng: np.random.Generator, length: int = 30,
                  every: int = 3) -> tuple[Trajectories, list[tuple[int, int]]]:
    """Cut one ``length``-frame gap at a random place into every ``every``-th marker, where the
    marker is observed there and one frame either side — held-out gaps for measuring a filler.

    Returns the cut session and ``(marker, first frame)`` of every gap.
    """
    cut = traj.positions.copy()
    holes = []
    for m in range(0, traj.n_markers, every):
        start = int(rng.integers(10, traj.n_frames - length - 10))
        if not np.isnan(traj.positions[start - 1:start + length + 1, m]).any():
            cut[start:start + length, m] = np.nan
            holes.append((m, start))
    return traj.replace(positions=cut), holes


def held_out_errors(filled: np.ndarray, truth: np.ndarray, holes: list[tuple[int, int]], *,
                    length: int = 30) -> np.ndarray:
    """Distances (mm) between ``filled`` and ``truth`` positions (frames, markers, 3) over the
    frames of the :func:`held_out_gaps` ``holes``, concatenated."""
    return np.concatenate([np.linalg.norm(filled[s:s + length, m] - truth[s:s + length, m], axis=1)
                           for m, s in holes])


def _interpolate(track: np.ndarray, valid: np.ndarray, gaps: list[tuple[int, int]], *,
                 akima: bool) -> tuple[np.ndarray, np.ndarray]:
    """The frames (G,) of ``gaps`` in one marker's (frames, 3) ``track`` and their positions
    (G, 3) from a spline through its ``valid`` frames."""
    # here: scipy.interpolate (with scipy.optimize, scipy.fft) costs ~0.2 CPU-s to import, and
    # every `cluster` and `rig` run imports this module through retarget's bake
    from scipy.interpolate import Akima1DInterpolator, CubicSpline

    known = np.flatnonzero(valid)
    frames = np.concatenate([np.arange(a, b) for a, b in gaps])
    if akima and len(known) >= 3:
        return frames, Akima1DInterpolator(known, track[known], axis=0)(frames)
    return frames, CubicSpline(known, track[known], axis=0)(frames)


def _neighbour_fill(out: np.ndarray, missing: np.ndarray, visible_now: np.ndarray, m: int,
                    segment: tuple[int, int], gap: tuple[int, int], *, k: int,
                    labels: tuple[str, ...]) -> str:
    """Fill one gap of marker ``m`` in ``out`` from its best-correlated neighbours; returns a note.

    ``visible_now`` (frames, markers) is where ``out`` holds a position now (the caller updates it
    after each fill), so a gap's work does not scale with the session's length."""
    gs, ge = gap
    candidates = np.flatnonzero(visible_now[gs:ge].all(axis=0))
    candidates = candidates[candidates != m]
    if candidates.size == 0:
        return "no other marker seen throughout the gap"
    training = _training_frames(~missing[:, m], segment)
    if training.size < _MIN_TRAINING_FRAMES:
        return "too few frames where the marker is seen"
    sample = training[np.linspace(0, training.size - 1, min(training.size, _CORRELATION_FRAMES)).astype(int)]
    target = out[sample, m]
    cand = out[np.ix_(sample, candidates)]  # (T, C, 3)
    seen = visible_now[np.ix_(sample, candidates)]
    score = _displacement_correlation(target, cand, seen)
    order = np.argsort(-score, kind="stable")[:k]
    chosen = candidates[order]
    rows = training[visible_now[np.ix_(training, chosen)].all(axis=1)]
    if rows.size < _MIN_TRAINING_FRAMES:
        return "too few frames where the marker and its neighbours are seen together"
    x = out[np.ix_(rows, chosen)].reshape(len(rows), -1)
    y = out[rows, m]
    x_mean, y_mean = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - x_mean, y - y_mean
    gram = xc.T @ xc
    ridge = 1e-6 * np.trace(gram) / len(gram) + 1e-12
    beta = np.linalg.solve(gram + ridge * np.eye(len(gram)), xc.T @ yc)
    span = np.arange(gs - 1, ge + 1)
    inside = (span >= 0) & (span < out.shape[0])
    pred = np.full((len(span), 3), np.nan)
    ok = inside.copy()
    ok[inside] &= visible_now[np.ix_(span[inside], chosen)].all(axis=1)
    pred[ok] = (out[np.ix_(span[ok], chosen)].reshape(ok.sum(), -1) - x_mean) @ beta + y_mean
    # shift the prediction so it meets the observed marker at the gap edges (linear blend)
    s, e = segment
    before = gs - 1 >= s and not missing[gs - 1, m] and ok[0]
    after = ge < e and not missing[ge, m] and ok[-1]
    off_a = out[gs - 1, m] - pred[0] if before else None
    off_b = out[ge, m] - pred[-1] if after else None
    if off_a is None and off_b is None:
        offset = np.zeros((ge - gs, 3))
    elif off_a is None or off_b is None:
        offset = np.broadcast_to(off_a if off_b is None else off_b, (ge - gs, 3))
    else:
        w = (np.arange(1, ge - gs + 1) / (ge - gs + 1))[:, None]
        offset = (1 - w) * off_a + w * off_b
    out[gs:ge, m] = pred[1:-1] + offset
    return "from " + ", ".join(labels[c] for c in chosen)


def _training_frames(seen: np.ndarray, segment: tuple[int, int]) -> np.ndarray:
    """Frames where the marker is observed: in its take if enough, else the whole session (capped)."""
    s, e = segment
    frames = s + np.flatnonzero(seen[s:e])
    if frames.size < _MIN_TRAINING_FRAMES:
        frames = np.flatnonzero(seen)
    if frames.size > _MAX_TRAINING_FRAMES:
        frames = frames[np.linspace(0, frames.size - 1, _MAX_TRAINING_FRAMES).astype(int)]
    return frames


def _displacement_correlation(target: np.ndarray, cand: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Correlation of 3-D displacements (from the mean) between ``target (T, 3)`` and each
    candidate ``(T, C, 3)`` over frames where the candidate is seen; -inf with < 3 common frames."""
    w = seen.astype(float)[..., None]
    n = w.sum(axis=0)  # (C, 1)
    safe = np.maximum(n, 1.0)
    t = target[:, None, :] * w
    c = np.where(w > 0, cand, 0.0)
    t_mean, c_mean = t.sum(axis=0) / safe, c.sum(axis=0) / safe
    dt, dc = (t - t_mean) * w, (c - c_mean) * w
    num = (dt * dc).sum(axis=(0, 2))
    den = np.sqrt((dt ** 2).sum(axis=(0, 2)) * (dc ** 2).sum(axis=(0, 2)))
    score = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.where(n[:, 0] >= 3, score, -np.inf)


#: Motion patterns kept by :func:`fill_low_rank` (a face's expressions span about a dozen).
LOW_RANK = 12


@single_threaded  # 100 small products: BLAS threads only spin against each other (60x the CPU)
def fill_low_rank(positions: np.ndarray, *, rank: int = LOW_RANK, iterations: int = 100,
                  tolerance_mm: float = 1e-3) -> np.ndarray:
    """Every gap of ``positions (F, N, 3)`` mm filled from the session's main motion patterns,
    regardless of time (frames may be far apart): the frames x coordinates matrix is fitted by a
    rank-``rank`` truncated SVD, the missing entries (starting at each coordinate's mean) replaced
    by the fit until they move less than ``tolerance_mm``. Markers never seen stay NaN."""
    frames, markers, _ = positions.shape
    matrix = positions.reshape(frames, 3 * markers).astype(np.float64)
    missing = np.isnan(matrix)
    seen = ~missing.all(axis=0)
    if not missing[:, seen].any():
        return positions.copy()
    work = matrix[:, seen]
    gaps = missing[:, seen]
    work[gaps] = np.take(np.nanmean(work, axis=0), np.nonzero(gaps)[1])
    keep = min(rank, min(work.shape) - 1)
    for _ in range(iterations):
        mean = work.mean(axis=0)
        centred = work - mean
        # the leading right singular vectors from the (coordinates x coordinates) scatter matrix
        basis = np.linalg.eigh(centred.T @ centred)[1][:, -keep:]
        fitted = (centred @ basis) @ basis.T + mean
        change = np.max(np.abs(fitted[gaps] - work[gaps]))
        work[gaps] = fitted[gaps]
        if change < tolerance_mm:
            break
    matrix[:, seen] = work
    return matrix.reshape(frames, markers, 3)
