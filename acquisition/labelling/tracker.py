"""Frame-by-frame labelling of fragments against the template model.

In each frame the points of fragments that carried a label in the previous frame keep it; the pose
and expression are fitted to them (:func:`.pose.fit_frame`), and a carried point now farther from
its label's prediction than the gate is released (the fragment jumped to another marker). The
released and new points are matched to the free labels by the Hungarian method
(:func:`scipy.optimize.linear_sum_assignment`) on the squared distance to each label's prediction
in units of its model spread, with a "no label" option at the gate, so ghosts stay unlabelled. A
frame with fewer than 3 carried points starts over: the pose from :func:`.pose.find_pose`, then
assignment and refit rounds.

Each label's prediction is the model fitted to this frame's assigned markers plus the marker's own
offset from the model when it was last seen, so a fragment broken at random is picked up where it
stopped and a face that differs from the template's is followed.

The tracked frames run in the compiled kernel (:mod:`.track_kernel`); Python sees only the
frames that start over or need a real matching (a few per capture). A long capture is labelled
in chunks side by side on two threads (:func:`label_points`), the same labels on any number.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from mocaptk.threads import machine_workers

from .pose import find_pose, fit_frame, model_shape
from .template import LabelTemplate
from .track_kernel import DONE, MATCH, finish_frame, model_arrays, track

#: A point may be at most this fraction of its label's nearest-neighbour distance from the
#: prediction (beyond half, it is nearer another marker's place) ...
GATE_NEAREST = 0.45
#: ... and at most this many model spreads (sigma) off, with a floor in mm, to keep a label
#: (a carried point beyond is released) ...
GATE_SIGMA = 5.0
GATE_FLOOR_MM = 2.5
#: ... and this many to take a free label: tighter, so that a ghost near an occluded marker's place
#: rarely takes it (a fragment missed here is tried again in every frame).
NEW_GATE_SIGMA = 4.0
#: Start-over rounds (assign, refit) after a pose search.
INIT_ROUNDS = 3
#: Gauss-Newton steps per tracked frame (the pose starts from the previous frame's).
TRACK_ROUNDS = 1
#: A start-over is kept when it labels at least this fraction of the frame's points.
INIT_MATCH = 0.5
#: The baseline: match, rigid fit, match again.
BASELINE_ROUNDS = 2
#: The marker offset follows the capture at this rate per sighting (1: last sighting only).
OFFSET_RATE = 0.5
#: Frames per independently labelled chunk, at least (a capture shorter than two is one chunk) ...
CHUNK_FRAMES = 500
#: ... and at most this many chunks (each starts over: a pose search and a warm-up).
MAX_CHUNKS = 16
#: A chunk after the first is labelled from this many frames before its start (labels dropped),
#: so that its pose, offsets and carried labels are settled when its own frames begin.
WARMUP = 30
#: A chunk whose warm-up labels agree with the chunk before on fewer than this fraction of points
#: started from a wrong pose: it is labelled again, continuing the chunk before.
SEAM_AGREE = 0.9
#: Threads labelling chunks side by side (the issue's 2 cores; fewer if this process has fewer).
THREADS = 2


@dataclass(frozen=True, eq=False)
class PointLabels:
    """Per input point: ``label (F, N)`` template index or -1; ``confidence (F, N)`` in [0, 1]
    (``exp(-z²/2)``, z the distance to the label's prediction in model spreads; 0 unlabelled);
    ``residual (F, N, 3)`` float32 mm, a labelled point's offset from the model fitted in its frame
    (head coordinates, without its marker's learnt offset; 0 unlabelled or untracked);
    ``released (F, N)`` True where a carried label was dropped (a fragment split)."""

    label: np.ndarray
    confidence: np.ndarray
    residual: np.ndarray
    released: np.ndarray


def gates(template: LabelTemplate, *, new: bool = False) -> np.ndarray:
    """(M,) mm: how far a point may be from a label's prediction to keep it (``new``: to take it)."""
    return np.minimum(GATE_NEAREST * template.nearest,
                      np.maximum((NEW_GATE_SIGMA if new else GATE_SIGMA) * template.sigma, GATE_FLOOR_MM))


def label_points(template: LabelTemplate, positions: np.ndarray, fragments: np.ndarray, *,
                 tracked: bool = True) -> PointLabels:
    """Label every point of ``positions (F, N, 3)`` mm; ``fragments (F, N)`` fragment ids (-1 no point).

    The frames are labelled in :func:`chunks`, side by side on up to :data:`THREADS` threads (the
    compiled kernels release the GIL); the chunks depend only on the frame count, so the labels
    do not depend on the threads. ``tracked`` False: the baseline — no fragments, no motion model,
    no offsets; each frame is matched to the template's mean shape after a rigid fit (pose from the
    previous frame), in one run.
    """
    n_frames, n_cols = fragments.shape
    out = _outputs(n_frames, n_cols)
    label = out[0]
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    fragments = np.ascontiguousarray(fragments, dtype=np.int32)
    n_frag = int(fragments.max()) + 1 if fragments.size else 0
    bounds = chunks(n_frames) if tracked else [(0, n_frames)]
    runs: list[_Run | None] = [None] * len(bounds)
    overlap: list[np.ndarray | None] = [None] * len(bounds)  # each chunk's labels of its warm-up frames

    def run(k: int) -> None:
        start, stop = bounds[k]
        run_ = _Run(template, n_cols, n_frag, tracked=tracked)
        warm = max(start - WARMUP, 0)
        seam = _outputs(start - warm, n_cols)
        # the frames before the chunk set its pose, offsets and carried labels
        run_.frames(positions[warm:start], fragments[warm:start], seam)
        run_.frames(positions[start:stop], fragments[start:stop], [a[start:stop] for a in out])
        runs[k], overlap[k] = run_, seam[0]

    with ThreadPoolExecutor(min(threads(), len(bounds))) as pool:
        list(pool.map(run, range(len(bounds))))
    for k in range(1, len(bounds)):  # a chunk that started wrong is labelled again, continuing the one before
        start, stop = bounds[k]
        if not _agree(label[start - len(overlap[k]):start], overlap[k]):
            for a, blank in zip(out, _outputs(1, 1)):
                a[start:stop] = blank[0, 0]
            runs[k - 1].frames(positions[start:stop], fragments[start:stop], [a[start:stop] for a in out])
            runs[k] = runs[k - 1]
    return PointLabels(*out)


def _outputs(n_frames: int, n_cols: int) -> list[np.ndarray]:
    """Empty ``label``, ``confidence``, ``residual``, ``released`` arrays (see :class:`PointLabels`)."""
    return [np.full((n_frames, n_cols), -1, dtype=np.int32), np.zeros((n_frames, n_cols), dtype=np.float32),
            np.zeros((n_frames, n_cols, 3), dtype=np.float32), np.zeros((n_frames, n_cols), dtype=bool)]


def _agree(before: np.ndarray, warm: np.ndarray) -> bool:
    """Whether a chunk's warm-up labels ``warm`` match the labels of the chunk before over the same
    frames ``before`` (both (W, N)), over the warm-up's second half (its start has settled)."""
    a, b = before[len(before) // 2:], warm[len(warm) // 2:]
    either = (a >= 0) | (b >= 0)
    return bool(either.sum() == 0 or ((a == b) & either).sum() >= SEAM_AGREE * either.sum())


def chunks(n_frames: int) -> list[tuple[int, int]]:
    """Frame ranges ``[start, stop)`` labelled independently: :data:`CHUNK_FRAMES` or more each."""
    count = max(1, min(MAX_CHUNKS, n_frames // CHUNK_FRAMES))
    edges = [n_frames * k // count for k in range(count + 1)]
    return list(zip(edges[:-1], edges[1:]))


def threads() -> int:
    """Threads to label with: :data:`THREADS`, or fewer when this process may use fewer CPUs."""
    return max(1, min(THREADS, machine_workers()))


class _Run:
    """The labeller along consecutive frames: the pose, marker offsets, last sightings and the
    fragments' carried labels, kept from one call of :meth:`frames` to the next."""

    def __init__(self, template: LabelTemplate, n_cols: int, n_frag: int, *, tracked: bool) -> None:
        self.template, self.tracked = template, tracked
        self.gate, self.new_gate = gates(template), gates(template, new=True)
        self.basis_t, self.gram = model_arrays(template.basis)
        self.frag_label = np.full(max(n_frag, 1), -1, dtype=np.int64)
        self.offset = np.zeros_like(template.mean)
        self.last = np.zeros_like(template.mean)
        self.seen = np.full(template.n_markers, -2, dtype=np.int64)
        self.rot, self.trans, self.have_pose = np.eye(3), np.zeros(3), False
        self.cols = np.empty(n_cols, dtype=np.int64)
        self.lab = np.empty(n_cols, dtype=np.int64)
        self.carried = np.empty(n_cols, dtype=bool)
        self.head = np.empty((n_cols, 3))
        self.pred = np.empty_like(template.mean)
        self.new_pred = np.empty_like(template.mean)

    def frames(self, positions: np.ndarray, fragments: np.ndarray, out: list[np.ndarray]) -> None:
        """Label ``positions (F, N, 3)`` into ``out``: :func:`_outputs`' arrays, in place."""
        label, conf, resid, released = out
        template, tracked = self.template, self.tracked
        cols, lab, carried, head, pred = self.cols, self.lab, self.carried, self.head, self.pred
        rot, trans, offset, seen = self.rot, self.trans, self.offset, self.seen
        tpl = (template.mean, template.basis, self.basis_t, self.gram, template.mode_std, template.sigma)

        def store(f: int, n: int, pred: np.ndarray) -> None:
            finish_frame(f, n, cols, lab, head, pred, template.sigma, fragments, label, conf, resid,
                         self.frag_label, offset, OFFSET_RATE, self.last, seen, tracked)

        n_frames = len(fragments)
        f = 0
        while f < n_frames:
            if tracked:  # the compiled kernel runs until a frame needs a start-over or a matching
                f, code, n = track(f, positions, fragments, self.frag_label, offset, self.last, seen, rot, trans,
                                   *tpl, self.gate, self.new_gate, TRACK_ROUNDS, OFFSET_RATE, label, conf,
                                   resid, released, cols, lab, carried, head, pred, self.new_pred)
                if code == DONE:
                    break
                if code == MATCH:
                    _assign(template, pred, self.new_gate, head[:n], lab[:n], ~carried[:n], also=self.new_pred)
                    store(f, n, pred)
                    f += 1
                    continue
            else:
                n = int(np.count_nonzero(fragments[f] >= 0))
                cols[:n] = np.flatnonzero(fragments[f] >= 0)
                if not n:
                    f += 1
                    continue
            # a start-over (the baseline: every frame)
            pts = positions[f, cols[:n]]
            lab[:n] = -1
            if tracked or not self.have_pose:  # the baseline keeps the previous frame's pose
                found_rot, found_trans, inliers = find_pose(template, pts)
                rot[:], trans[:] = found_rot, found_trans
                self.have_pose = inliers >= 3
                offset[:] = 0.0
                seen[:] = -2  # a new pose: no marker continues from the frame before
            if not self.have_pose:
                f += 1
                continue
            start_pred = template.mean
            wide = GATE_NEAREST * template.nearest  # a start-over: the face may differ from the template's
            for round_ in range(INIT_ROUNDS if tracked else BASELINE_ROUNDS):
                if round_:
                    keep = lab[:n] >= 0
                    if keep.sum() >= 3:
                        fit_rot, fit_trans, coeffs = fit_frame(template, lab[:n][keep], pts[keep], rot, trans,
                                                               offset, expression=tracked)
                        rot[:], trans[:] = fit_rot, fit_trans
                        start_pred = model_shape(template, coeffs) + offset
                    lab[:n] = -1
                head[:n] = (pts - trans) @ rot
                _assign(template, start_pred, wide, head[:n], lab[:n], np.ones(n, dtype=bool))
            if not tracked or (lab[:n] >= 0).sum() >= INIT_MATCH * n:  # else a wrong pose or a frame of ghosts
                store(f, n, np.ascontiguousarray(start_pred))
            f += 1
        seen -= n_frames  # the next call's frames follow these


def _assign(template: LabelTemplate, pred: np.ndarray, gate: np.ndarray, head: np.ndarray,
            lab: np.ndarray, todo: np.ndarray, *, also: np.ndarray | None = None) -> None:
    """Match the points ``head[todo]`` (head coordinates) to the labels not in ``lab`` (in place);
    ``also (M, 3)``: a second prediction per label, the nearer of the two counts."""
    rows = np.flatnonzero(todo)
    if not len(rows):
        return
    taken = np.zeros(template.n_markers, dtype=bool)
    taken[lab[lab >= 0]] = True
    free = np.flatnonzero(~taken)
    if not len(free):
        return
    d = np.linalg.norm(head[rows, None] - pred[free][None], axis=2)
    if also is not None:
        d = np.minimum(d, np.linalg.norm(head[rows, None] - also[free][None], axis=2))
    within = d <= gate[free]
    useful_rows = within.any(axis=1)
    useful_cols = within.any(axis=0)
    if not useful_rows.any():
        return
    rows, free = rows[useful_rows], free[useful_cols]
    d, within = d[np.ix_(useful_rows, useful_cols)], within[np.ix_(useful_rows, useful_cols)]
    single = within.sum(axis=1) == 1
    if single.all() and within.sum(axis=0).max() <= 1:  # no competition: no matching needed
        r, c = np.nonzero(within)
        lab[rows[r]] = free[c]
        return
    z2 = (d / template.sigma[free]) ** 2
    limit = (gate[free] / template.sigma[free]) ** 2
    big = float(limit.max()) * 4 + 1.0
    cost = np.where(within, z2 - limit, big)  # < 0 within the gate: better than no label (0)
    full = np.hstack([cost, np.zeros((len(rows), len(rows)))])
    r, c = linear_sum_assignment(full)
    hit = (c < len(free))
    hit[hit] &= within[r[hit], c[hit]]
    lab[rows[r[hit]]] = free[c[hit]]
