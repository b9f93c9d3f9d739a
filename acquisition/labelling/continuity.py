"""Evidence across time: a label's runs must join up; a run its marker could not have made is dropped.

A real marker's offset from the face model (its residual, head coordinates) changes slowly: from
one of its trajectory fragments to the next (a random break, an occlusion) it moves a little, more
the longer the gap. A ghost that took an occluded marker's label sits 1-5 mm from where the
marker is: inside the gate, so no single frame tells them apart, but the label's residual jumps
where the ghost takes over and jumps back where the marker returns. So, per label, the runs
(consecutive frames of one fragment under that label) are chained in time, each link allowed only
when the residual moves by at most ``s × (JUMP_SIGMA + JUMP_GROWTH × √(t / TICK_S))`` from the
end of one run to the start of the next (``t`` the time from the one's last frame to the other's
first; ``s`` the marker's model spread, or :data:`TYPICAL` times the median of its runs' moves in
the bound's units where that is larger: where the expression goes beyond the template, or at a
low frame rate, a marker's residual moves more from run to run, and so may it); the chain keeping
the most points stands, and the runs it passes over are unlabelled (not those before its first run
or after its last: there only one side is seen).
"""

from __future__ import annotations

import numba
import numpy as np

#: Residual movement allowed between two runs of a label, in model spreads ...
JUMP_SIGMA = 2.0
#: ... plus this many per square root of the time between them in :data:`TICK_S` (the bound grows
#: with time, not frames: at 6 Hz a marker moves off the model between two frames as much as over
#: ten at 60 Hz).
JUMP_GROWTH = 1.0
TICK_S = 1 / 60
#: A label whose typical move between runs (median, in the bound's units) times this exceeds its
#: model spread is bounded by that instead (at 60 Hz on the sample: about 0.1 mm × 3, under the
#: 0.6 mm floor of the spread, so no change there).
TYPICAL = 3.0
#: A run's start (end) residual: the mean over its first (last) this many frames.
END_FRAMES = 3
#: A run may follow any of the label's this many runs before it (a chain may skip that many).
LOOK_BACK = 12


def drop_jumps(labels: np.ndarray, fragments: np.ndarray, residual: np.ndarray, sigma: np.ndarray, *,
               rate: float) -> tuple[np.ndarray, int]:
    """``(labels, dropped)``: ``labels (F, N)`` with the runs left out of their label's chain set to
    -1, and how many points that unlabelled. ``residual (F, N, 3)`` mm: :class:`.tracker.PointLabels`'
    residual; ``sigma (M,)`` mm: the template's model spread; ``rate`` Hz."""
    out = labels.copy()
    dropped = _drop(out, fragments, residual, np.asarray(sigma, dtype=np.float64), JUMP_SIGMA,
                    JUMP_GROWTH / np.sqrt(rate * TICK_S), TYPICAL, END_FRAMES, LOOK_BACK)
    return out, int(dropped)


@numba.njit(cache=True, nogil=True)
def _drop(labels, fragments, resid, sigma, base, growth, typical, end, back):  # pragma: no cover - compiled
    """:func:`drop_jumps` in place on ``labels``: each label's points are gathered in frame order
    (frame and column, 8 bytes a point: a 72,000-frame capture stays small), then chained."""
    n_markers = len(sigma)
    offsets = np.zeros(n_markers + 1, dtype=np.int64)
    for f in range(labels.shape[0]):
        for c in range(labels.shape[1]):
            if labels[f, c] >= 0:
                offsets[labels[f, c] + 1] += 1
    for m in range(n_markers):
        offsets[m + 1] += offsets[m]
    frames = np.empty(offsets[-1], dtype=np.int32)
    cols = np.empty(offsets[-1], dtype=np.int32)
    fill = offsets[:-1].copy()
    for f in range(labels.shape[0]):
        for c in range(labels.shape[1]):
            m = labels[f, c]
            if m >= 0:
                frames[fill[m]], cols[fill[m]] = f, c
                fill[m] += 1
    dropped = 0
    for m in range(n_markers):
        a, b = offsets[m], offsets[m + 1]
        if b > a:
            dropped += _chain(frames[a:b], cols[a:b], labels, fragments, resid, sigma[m], base, growth, typical,
                              end, back)
    return dropped


@numba.njit(cache=True, nogil=True)
def _chain(frame, col, labels, fragments, resid, sigma, base, growth, typical, end,
           back):  # pragma: no cover - compiled
    """One label's points (``frame``, ``col``, in frame order): unlabel those whose run is not in
    its best chain; returns how many (``growth`` per square root of frames)."""
    n = len(frame)
    start = np.zeros(n + 1, dtype=np.int64)
    runs = 0
    for i in range(n):  # a new run where the fragment changes or a frame is skipped
        if i == 0 or fragments[frame[i], col[i]] != fragments[frame[i - 1], col[i - 1]] \
                or frame[i] != frame[i - 1] + 1:
            start[runs] = i
            runs += 1
    start[runs] = n
    if runs < 2:
        return 0
    head, tail = np.zeros((runs, 3)), np.zeros((runs, 3))
    for r in range(runs):
        a, b = start[r], start[r + 1]
        k = min(end, b - a)
        for c in range(3):
            s, e = 0.0, 0.0
            for i in range(k):
                s += resid[frame[a + i], col[a + i], c]
                e += resid[frame[b - 1 - i], col[b - 1 - i], c]
            head[r, c], tail[r, c] = s / k, e / k
    # the label's own scale: where its runs' residuals move more than the model's spread explains
    # (an expression beyond the template, a low frame rate), the bound widens with them
    moved = np.empty(runs - 1)
    for r in range(1, runs):
        gap = frame[start[r]] - frame[start[r] - 1]
        moved[r - 1] = _jump(head, r, tail, r - 1) / (base + growth * np.sqrt(gap))
    spread = max(sigma, typical * np.median(moved))
    best = np.zeros(runs)
    prev = np.full(runs, -1, dtype=np.int64)
    top = 0
    for r in range(runs):
        size = start[r + 1] - start[r]
        best[r] = size
        for q in range(max(0, r - back), r):
            gap = frame[start[r]] - frame[start[q + 1] - 1]  # frames from one to the other
            if best[q] + size > best[r] and _jump(head, r, tail, q) <= spread * (base + growth * np.sqrt(gap)):
                best[r], prev[r] = best[q] + size, q
        if best[r] > best[top]:
            top = r
    keep = np.zeros(runs, dtype=np.bool_)
    r = top
    while r >= 0:
        keep[r] = True
        r = prev[r]
    first, last = 0, runs - 1
    while not keep[first]:
        first += 1
    while not keep[last]:
        last -= 1
    dropped = 0
    for r in range(first + 1, last):  # only runs the chain passes over: both sides' evidence
        if not keep[r]:
            for i in range(start[r], start[r + 1]):
                labels[frame[i], col[i]] = -1
            dropped += start[r + 1] - start[r]
    return dropped


@numba.njit(cache=True, nogil=True, inline="always")
def _jump(head, r, tail, q):  # pragma: no cover - compiled
    return np.sqrt((head[r, 0] - tail[q, 0]) ** 2 + (head[r, 1] - tail[q, 1]) ** 2 + (head[r, 2] - tail[q, 2]) ** 2)
