"""Fragment voting: a fragment's short odd runs take the label of the runs around them.

Along each fragment, the per-frame labels form runs. A run shorter than :data:`MIN_RUN` frames
between two runs of the same label (or at a fragment end, beside one run) is a blip — a frame
where a ghost came closer, a marker left the gate for an instant — and takes its neighbours'
label (which may be "no label": a ghost fragment labelled for a frame stays a ghost). Longer runs
stand: the fragment is split there (it jumped to another marker). Afterwards a label is kept by
one point per frame at most (the most confident one).
"""

from __future__ import annotations

import numba
import numpy as np

#: Runs shorter than this (frames) follow their neighbours.
MIN_RUN = 4


def vote(label: np.ndarray, confidence: np.ndarray, fragments: np.ndarray) -> tuple[np.ndarray, int]:
    """Voted labels ``(F, N)`` and the number of fragments split (label runs > 1 after voting)."""
    frame, col = np.nonzero(fragments >= 0)
    if not len(frame):
        return label.copy(), 0
    frag = fragments[frame, col]
    order = np.lexsort((frame, frag))
    frame, col, frag = frame[order], col[order], frag[order]
    seq = label[frame, col].astype(np.int64)
    new_frag = np.r_[True, frag[1:] != frag[:-1]]
    start = new_frag | np.r_[True, seq[1:] != seq[:-1]]
    run = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    length = np.diff(np.r_[first, len(seq)])
    run_label = seq[first]
    run_frag = frag[first]
    prev_same = np.r_[False, run_frag[1:] == run_frag[:-1]]
    next_same = np.r_[run_frag[:-1] == run_frag[1:], False]
    prev_label = np.where(prev_same, np.r_[-2, run_label[:-1]], -2)
    next_label = np.where(next_same, np.r_[run_label[1:], -2], -2)
    short = length < MIN_RUN
    # both neighbours agree, or there is only one neighbour
    agree = (prev_label == next_label) & prev_same & next_same
    only_prev = prev_same & ~next_same
    only_next = next_same & ~prev_same
    target = np.where(agree | only_prev, prev_label, np.where(only_next, next_label, run_label))
    # a short run beside only one neighbour run follows it only if that neighbour is longer
    longer_prev = np.r_[0, length[:-1]] > length
    longer_next = np.r_[length[1:], 0] > length
    follow = short & (agree | (only_prev & longer_prev) | (only_next & longer_next))
    new_run_label = np.where(follow, target, run_label)
    out = label.copy()
    out[frame, col] = new_run_label[run].astype(out.dtype)
    _unique_per_frame(out, confidence)
    split = _splits(out[frame, col], frag)
    return out, split


def _unique_per_frame(label: np.ndarray, confidence: np.ndarray) -> None:
    """Where a label appears twice in a frame, keep the most confident point (the first column on
    a tie; in place)."""
    if label.size:
        _keep_best(label, confidence, np.full(max(int(label.max()) + 1, 1), -1, dtype=np.int64))


@numba.njit(cache=True, nogil=True)
def _keep_best(label, confidence, best):  # pragma: no cover - compiled
    """:func:`_unique_per_frame` frame by frame; ``best (M,)`` scratch, -1."""
    for f in range(label.shape[0]):
        for c in range(label.shape[1]):
            m = label[f, c]
            if m < 0:
                continue
            b = best[m]
            if b < 0:
                best[m] = c
            elif confidence[f, c] > confidence[f, b]:
                label[f, b] = -1
                best[m] = c
            else:
                label[f, c] = -1
        for c in range(label.shape[1]):  # reset the scratch for the next frame
            if label[f, c] >= 0:
                best[label[f, c]] = -1


def _splits(seq: np.ndarray, frag: np.ndarray) -> int:
    """Fragments whose (sorted) label sequence has more than one labelled run."""
    if not len(seq):
        return 0
    labelled = seq >= 0
    change = np.r_[False, (frag[1:] == frag[:-1]) & (seq[1:] != seq[:-1]) & labelled[1:] & labelled[:-1]]
    return int(len(np.unique(frag[change])))
