"""The one data type every stage speaks: labelled 3-D marker trajectories in millimetres."""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import MocaptkError

#: Frame rates (Hz) a session may declare: beyond them a header is damaged (1e-45 Hz, 1e300 Hz).
RATE_RANGE = (1e-3, 1e7)
#: Control characters of a label become spaces.
_CONTROL = {c: " " for c in (*range(32), *range(127, 160))}

#: Metadata keys with a fixed meaning (others are free-form):
#: ``source`` (str path), ``format`` (str), ``original_units`` (str),
#: ``subjects`` (list of subject prefixes), ``takes`` (list of take dicts, see :class:`Take`).


@dataclass(frozen=True)
class Take:
    """A named frame range of a session, 0-based, ``end`` exclusive.

    ``region`` names the facial region the take was captured for (``None``: any region).
    """

    name: str
    start: int
    end: int
    region: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "start": self.start, "end": self.end}
        if self.region is not None:
            out["region"] = self.region
        return out


@dataclass(frozen=True)
class GapStats:
    """Gap statistics of a session.

    ``missing_fraction``: NaN frames / all frames, per marker ``(markers,)``;
    ``longest_gap``: longest run of consecutive missing frames, per marker ``(markers,)``;
    ``gap_count``: number of missing runs per marker ``(markers,)``.
    """

    missing_fraction: np.ndarray
    longest_gap: np.ndarray
    gap_count: np.ndarray

    @property
    def total_missing_fraction(self) -> float:
        return float(self.missing_fraction.mean()) if self.missing_fraction.size else 0.0


@dataclass(frozen=True, eq=False)
class Trajectories:
    """Labelled marker trajectories.

    Parameters
    ----------
    positions : (frames, markers, 3) float64
        Millimetres; NaN where a marker is missing in a frame.
    labels : sequence of str, length ``markers``
        Unique marker labels (may carry ``Subject:`` prefixes).
    rate : float
        Frame rate in Hz (> 0).
    first_frame : int
        Number of the first frame in the source (C3D ``first_frame``; informational).
    residuals : (frames, markers) float64, optional
        Per-point residual (e.g. reprojection error in px); NaN where missing.
    metadata : dict
        Source path, original units, subject prefixes, ``takes`` (list of :class:`Take`), ...
    """

    positions: np.ndarray
    labels: tuple[str, ...]
    rate: float
    first_frame: int = 0
    residuals: np.ndarray | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        pos = np.asarray(self.positions, dtype=np.float64)
        if pos.ndim != 3 or pos.shape[2] != 3:
            raise MocaptkError(f"positions must have shape (frames, markers, 3), got {pos.shape}")
        # control characters (a tab, a line break) would break CSV rows, messages and pictures
        labels = tuple(str(label).translate(_CONTROL) for label in self.labels)
        if len(labels) != pos.shape[1]:
            raise MocaptkError(f"{len(labels)} labels for {pos.shape[1]} markers")
        duplicates = sorted(lab for lab, n in Counter(labels).items() if n > 1)  # O(n): 65,535 labels
        if duplicates:
            raise MocaptkError(f"duplicate marker labels: {', '.join(duplicates[:5])}")
        rate = float(self.rate)
        if not np.isfinite(rate) or rate <= 0:
            raise MocaptkError(f"frame rate must be a positive number, got {self.rate}")
        if not RATE_RANGE[0] <= rate <= RATE_RANGE[1]:  # a damaged header: durations over- or underflow
            raise MocaptkError(f"frame rate {rate:g} Hz is outside {RATE_RANGE[0]:g}..{RATE_RANGE[1]:g} Hz")
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate", rate)
        object.__setattr__(self, "first_frame", int(self.first_frame))
        if self.residuals is not None:
            res = np.asarray(self.residuals, dtype=np.float64)
            if res.shape != pos.shape[:2]:
                raise MocaptkError(f"residuals must have shape {pos.shape[:2]}, got {res.shape}")
            object.__setattr__(self, "residuals", res)
        meta = dict(self.metadata)
        meta["takes"] = [_as_take(t) for t in meta.get("takes", [])]
        for take in meta["takes"]:
            if not 0 <= take.start < take.end <= pos.shape[0]:
                raise MocaptkError(
                    f"take {take.name!r} [{take.start}, {take.end}) is outside 0..{pos.shape[0]}")
        object.__setattr__(self, "metadata", meta)

    # -- shape -------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_markers(self) -> int:
        return int(self.positions.shape[1])

    @property
    def duration(self) -> float:
        """Duration in seconds."""
        return self.n_frames / self.rate

    @property
    def takes(self) -> list[Take]:
        return list(self.metadata["takes"])

    def index(self, labels: Iterable[str]) -> np.ndarray:
        """Column indices of ``labels`` (in the given order); unknown labels raise."""
        lookup = {label: i for i, label in enumerate(self.labels)}
        wanted = list(labels)
        missing = [label for label in wanted if label not in lookup]
        if missing:
            raise MocaptkError(f"unknown marker labels: {', '.join(missing[:5])}"
                               + (f" (+{len(missing) - 5} more)" if len(missing) > 5 else ""))
        return np.array([lookup[label] for label in wanted], dtype=np.intp)

    # -- new objects -------------------------------------------------------------------
    def replace(self, **changes: Any) -> Trajectories:
        """A copy with some fields replaced (metadata is deep-copied unless given)."""
        values = {
            "positions": self.positions, "labels": self.labels, "rate": self.rate,
            "first_frame": self.first_frame, "residuals": self.residuals,
            "metadata": copy.deepcopy(self.metadata),
        }
        values.update(changes)
        return Trajectories(**values)

    def select(self, labels: Sequence[str]) -> Trajectories:
        """Only the markers ``labels``, in that order."""
        idx = self.index(labels)
        return self.replace(
            positions=self.positions[:, idx], labels=tuple(self.labels[i] for i in idx),
            residuals=None if self.residuals is None else self.residuals[:, idx])

    def frames(self, start: int = 0, stop: int | None = None) -> Trajectories:
        """Frames ``[start, stop)`` (0-based); takes are clipped and shifted."""
        n = self.n_frames
        start, stop, _ = slice(start, stop).indices(n)
        stop = max(stop, start)
        takes = []
        for take in self.takes:
            lo, hi = max(take.start, start), min(take.end, stop)
            if lo < hi:
                takes.append(Take(take.name, lo - start, hi - start, take.region))
        meta = copy.deepcopy(self.metadata)
        meta["takes"] = takes
        return self.replace(
            positions=self.positions[start:stop],
            residuals=None if self.residuals is None else self.residuals[start:stop],
            first_frame=self.first_frame + start, metadata=meta)

    def take(self, name: str) -> Trajectories:
        """The frames of the take called ``name``."""
        for take in self.takes:
            if take.name == name:
                return self.frames(take.start, take.end)
        raise MocaptkError(f"no take named {name!r} (takes: {', '.join(t.name for t in self.takes)})")

    def strip_prefixes(self) -> Trajectories:
        """Labels without ``Subject:`` prefixes (``"Anna:NOSE_01"`` → ``"NOSE_01"``)."""
        stripped = tuple(label.rsplit(":", 1)[-1] for label in self.labels)
        return self.replace(labels=stripped)

    # -- analysis ----------------------------------------------------------------------
    def gap_stats(self) -> GapStats:
        """Missing fraction, longest gap and gap count per marker."""
        missing = np.isnan(self.positions).any(axis=2)  # (frames, markers)
        n_frames, n_markers = missing.shape
        if n_frames == 0:
            zeros = np.zeros(n_markers, dtype=np.int64)
            return GapStats(np.zeros(n_markers), zeros, zeros)
        padded = np.zeros((n_frames + 2, n_markers), dtype=np.int8)
        padded[1:-1] = missing
        edges = np.diff(padded, axis=0)  # +1 gap start, -1 gap end
        starts_f, starts_m = np.nonzero(edges == 1)
        ends_f, ends_m = np.nonzero(edges == -1)
        # nonzero is row-major (frame first); sort by marker to pair starts with ends
        s_order = np.lexsort((starts_f, starts_m))
        e_order = np.lexsort((ends_f, ends_m))
        lengths = ends_f[e_order] - starts_f[s_order]
        longest = np.zeros(n_markers, dtype=np.int64)
        np.maximum.at(longest, starts_m[s_order], lengths)
        counts = np.bincount(starts_m, minlength=n_markers).astype(np.int64)
        return GapStats(missing.mean(axis=0), longest, counts)


def _as_take(take: Take | dict[str, Any]) -> Take:
    if isinstance(take, Take):
        return take
    return Take(str(take["name"]), int(take["start"]), int(take["end"]), take.get("region"))


def concatenate_takes(sessions: Sequence[Trajectories], names: Sequence[str] | None = None,
                      regions: Sequence[str | None] | None = None) -> Trajectories:
    """Join sessions end to end as takes of one session (labels must match, same rate).

    Each input becomes one take named ``names[i]`` (default: the input's source name or
    ``take_<i>``), recorded in ``metadata["takes"]``; takes already inside an input are kept.
    """
    if not sessions:
        raise MocaptkError("nothing to concatenate")
    first = sessions[0]
    for other in sessions[1:]:
        if other.labels != first.labels:
            raise MocaptkError("cannot concatenate sessions with different marker labels")
        if other.rate != first.rate:
            raise MocaptkError(f"cannot concatenate sessions at {first.rate} Hz and {other.rate} Hz")
    takes: list[Take] = []
    offset = 0
    for i, session in enumerate(sessions):
        name = names[i] if names else str(session.metadata.get("source", f"take_{i}"))
        region = regions[i] if regions else None
        inner = session.takes
        if inner:
            takes.extend(Take(t.name, t.start + offset, t.end + offset, t.region) for t in inner)
        else:
            takes.append(Take(name, offset, offset + session.n_frames, region))
        offset += session.n_frames
    residuals = None
    if all(s.residuals is not None for s in sessions):
        residuals = np.concatenate([s.residuals for s in sessions], axis=0)
    meta = copy.deepcopy(first.metadata)
    meta["takes"] = takes
    return Trajectories(np.concatenate([s.positions for s in sessions], axis=0), first.labels,
                        first.rate, first.first_frame, residuals, meta)
