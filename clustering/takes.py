"""Takes per region and the frames sampled from them.

Rules: a take feeds the region named by its ``region``; without one, the region whose name equals
the take's name; a take matching no region feeds every region. A region fed by no take uses all
frames. Each take is a hard cut: sampling restarts at every take start, and nothing interpolates
or correlates across a cut (frames of different takes are only pooled as samples).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError, OptionError
from mocaptk.jsonio import read_json
from mocaptk.trajectories import Take


def read_takes(path: str | os.PathLike[str], n_frames: int) -> list[Take]:
    """Read ``{"takes": [{"name", "start", "end", "region"?}, ...]}`` (0-based, end exclusive)."""
    path = Path(path)
    data = read_json(path)
    items = data.get("takes") if isinstance(data, dict) else None
    if not isinstance(items, list) or not items:
        raise InputFileError(path, 'expected {"takes": [{"name": ..., "start": ..., "end": ...}, ...]}')
    takes = []
    for number, item in enumerate(items, start=1):
        try:
            name, start, end = str(item["name"]), item["start"], item["end"]
            region = None if item.get("region") is None else str(item["region"])
        except (KeyError, TypeError, AttributeError):
            raise InputFileError(path, f"take {number}: needs name, start and end (integers)") from None
        take = Take(name, _frame_number(start, path=path, number=number, name=name, key="start"),
                    _frame_number(end, path=path, number=number, name=name, key="end"), region)
        if not 0 <= take.start < take.end <= n_frames:
            raise InputFileError(path, f"take {take.name!r} [{take.start}, {take.end}) is outside the "
                                 f"session's frames 0..{n_frames}")
        takes.append(take)
    return takes


def _frame_number(value: object, *, path: Path, number: int, name: str, key: str) -> int:
    """A take's ``start``/``end``: a whole frame number (``12`` or ``12.0``); fractions, infinities
    (``1e400``, ``-Infinity``), booleans and strings are refused, never truncated."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputFileError(path, f"take {number} ({name!r}): {key} must be a whole frame number, got {value!r}")
    if isinstance(value, float) and not (np.isfinite(value) and value.is_integer()):
        raise InputFileError(path, f"take {number} ({name!r}): {key} {value!r} is not a whole frame number "
                                   "(takes count 0-based frames, end exclusive)")
    return int(value)


def region_segments(takes: Sequence[Take], regions: Sequence[str],
                    n_frames: int) -> dict[str, list[tuple[int, int]]]:
    """Frame ranges ``[(start, end), ...]`` feeding each region, by the rules above."""
    names = set(regions)
    segments: dict[str, list[tuple[int, int]]] = {region: [] for region in regions}
    for take in takes:
        target = take.region if take.region is not None else take.name
        fed = [target] if target in names else list(regions)
        for region in fed:
            segments[region].append((take.start, take.end))
    return {region: sorted(segs) if segs else [(0, n_frames)] for region, segs in segments.items()}


def sample_frames(segments: Sequence[tuple[int, int]], step: int) -> np.ndarray:
    """Every ``step``-th frame of each segment, restarting at each segment start; sorted, unique."""
    if step < 1:
        raise OptionError(f"step must be >= 1 frame, got {step}")
    parts = [np.arange(start, end, step) for start, end in segments]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.intp)


def all_frames(segments: Sequence[tuple[int, int]]) -> np.ndarray:
    """Every frame of the segments; sorted, unique."""
    return sample_frames(segments, 1)
