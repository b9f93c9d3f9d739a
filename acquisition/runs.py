"""Frame runs: take segments (hard cuts for cleaning) and runs of valid / missing frames."""

from __future__ import annotations

import numpy as np

from mocaptk.trajectories import Trajectories


def take_segments(traj: Trajectories) -> list[tuple[int, int]]:
    """Frame ranges ``[start, end)`` that cleaning treats independently, covering every frame.

    A cut is made wherever a take starts or ends, so each take is a segment (split further only
    where takes overlap) and frames outside all takes form segments of their own.
    """
    cuts = {0, traj.n_frames}
    for take in traj.takes:
        cuts.update((take.start, take.end))
    edges = sorted(cuts)
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` ranges of consecutive True values of a 1-D boolean array."""
    padded = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))
