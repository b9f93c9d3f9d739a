"""Label a whole capture (fragments or per-frame clouds), or check the labels of a labelled one.

``label_capture``: fragments (or clouds linked into fragments, :mod:`.fragments`) → per-frame
labels (:mod:`.tracker`) → fragment voting (:mod:`.vote`) → each label's runs chained in time
(:mod:`.continuity`) → a capture with the template's labels,
the points left over kept as ``*N`` columns. ``check_labels``: the capture's own columns are the
fragments; where the labeller puts a column's points under another label for 2 frames or more,
that run is reported (a swap when two columns trade places), and ``fix`` moves those points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mocaptk.errors import source_error
from mocaptk.trajectories import Trajectories

from ..runs import true_runs
from .continuity import drop_jumps
from .fragments import column_fragments, link_clouds, looks_untracked
from .template import LabelTemplate
from .tracker import PointLabels, label_points, threads
from .vote import vote

#: The capture's typical marker spacing may differ from the template's by at most this factor.
SCALE_FACTOR = 1.8
#: The template is scaled to the capture when their spacings differ by more than this fraction.
RESCALE = 0.05
#: Fewer labelled points than this fraction: not a capture of the template's face.
MIN_LABELLED = 0.5
#: A check reports a column's points found under another label for at least this many frames.
MIN_SWAP_FRAMES = 2


@dataclass(frozen=True, eq=False)
class Labelled:
    """The labelling of a capture: ``labels (F, N)`` template index per input point (-1 none),
    ``confidence (F, N)``, the fragment ids, how many fragments were split, the mode."""

    labels: np.ndarray
    confidence: np.ndarray
    fragments: np.ndarray
    split: int
    mode: str


def label_capture(template: LabelTemplate, capture: Trajectories, *, clouds: bool | None = None,
                  tracked: bool = True) -> Labelled:
    """Label every point of ``capture`` (its column names are ignored).

    ``clouds`` None: detected (columns that jump between markers frame to frame are clouds).
    ``tracked`` False: the baseline (no fragments, no motion model).
    """
    pos = capture.positions
    seen = ~np.isnan(pos).any(axis=2)
    if seen.sum(axis=1).max(initial=0) < 3:
        raise source_error(capture.metadata.get("source"), "fewer than 3 points in every frame: "
                                                           "nothing to find a head pose from")
    ratio = check_scale(template, capture)
    if abs(ratio - 1) > RESCALE:  # a smaller or larger face than the template's
        template = template.scaled(ratio)
    if clouds is None:
        clouds = looks_untracked(pos, template.spacing)
    fragments = link_clouds(pos, template.spacing, threads=threads()) if clouds else column_fragments(pos)
    if not tracked:
        fragments = np.where(seen, 0, -1)
    found: PointLabels = label_points(template, pos, fragments, tracked=tracked)
    labels, split = vote(found.label, found.confidence, fragments) if tracked else (found.label, 0)
    if tracked:  # a run the label's marker could not have made: a ghost on an occluded marker's place
        labels, _ = drop_jumps(labels, fragments, found.residual, template.sigma, rate=capture.rate)
    confidence = np.where(labels >= 0, found.confidence, 0.0).astype(np.float32)
    return Labelled(labels, confidence, fragments, split, "clouds" if clouds else "fragments")


def check_scale(template: LabelTemplate, capture: Trajectories) -> float:
    """The capture's marker spacing over the template's (a face's size ratio); refuses a capture
    spaced unlike the template by more than :data:`SCALE_FACTOR` (other units, a body)."""
    pos = capture.positions
    counts = (~np.isnan(pos).any(axis=2)).sum(axis=1)
    frames = np.flatnonzero(counts >= 3)
    if not len(frames):
        return 1.0
    frames = frames[np.linspace(0, len(frames) - 1, min(len(frames), 50)).astype(np.intp)]
    spacing = []
    for f in frames:
        pts = pos[f][~np.isnan(pos[f]).any(axis=1)]
        spacing.append(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1]))
    ratio = float(np.median(spacing)) / template.spacing
    if not 1 / SCALE_FACTOR <= ratio <= SCALE_FACTOR:
        raise source_error(capture.metadata.get("source"),
                           f"its points are {ratio:.3g} times as far apart as the template's markers "
                           f"({np.median(spacing):.3g} vs {template.spacing:.3g} mm): other units (see "
                           "--units), or not a capture of this face")
    return ratio


def check_match(capture: Trajectories, result: Labelled) -> None:
    """Refuse a labelling that found under half of the points: another face, layout or body."""
    points = int((result.fragments >= 0).sum())
    done = int((result.labels >= 0).sum())
    if points and done < MIN_LABELLED * points:
        raise source_error(capture.metadata.get("source"),
                           f"only {done / points:.1%} of its points match the template: a capture of "
                           "another face, layout or a body?")


def labelled_trajectories(template: LabelTemplate, capture: Trajectories, result: Labelled, *,
                          keep_unlabelled: bool = True) -> Trajectories:
    """The capture under the template's labels (NaN where a marker was not found), the points left
    over as ``*N`` columns (one per input column that has any, named after it when it is
    ``*``-named and free); rate, first frame and takes kept."""
    m = template.n_markers
    labels = list(template.labels)
    leftover = np.empty(0, dtype=np.intp)
    if keep_unlabelled:
        left = (result.labels < 0) & (result.fragments >= 0)
        leftover = np.flatnonzero(left.any(axis=0))
        taken = set(labels)
        for col in leftover:
            name = capture.labels[col]
            name = name if name.startswith("*") and name not in taken else f"*{col}"
            while name in taken:
                name = f"*{name}"
            taken.add(name)
            labels.append(name)
    # one output array, filled in place (a 72,000-frame capture is hundreds of MB)
    positions = np.full((capture.n_frames, len(labels), 3), np.nan)
    f, c = np.nonzero(result.labels >= 0)
    positions[f, result.labels[f, c]] = capture.positions[f, c]
    del f, c
    for k, col in enumerate(leftover):
        rows = np.flatnonzero(left[:, col])
        positions[rows, m + k] = capture.positions[rows, col]
    meta = {"takes": capture.takes, "source": capture.metadata.get("source", ""), "format": "labelled"}
    return Trajectories(positions, labels, capture.rate, first_frame=capture.first_frame, metadata=meta)


@dataclass(frozen=True)
class Mislabel:
    """Frames ``[start, end)`` (0-based) where the points of column ``label`` belong to ``found``
    (a template label); ``swap``: ``found``'s column holds ``label``'s points over the same frames."""

    label: str
    found: str
    start: int
    end: int
    swap: bool


def check_labels(template: LabelTemplate, capture: Trajectories) -> tuple[list[Mislabel], np.ndarray]:
    """The runs where the labeller disagrees with the capture's labels, and its labels ``(F, M)``
    for the capture's template-labelled columns (template order; -1 where not found).

    Only columns named like template markers are checked; the others are ignored.
    """
    names = [label for label in template.labels if label in set(capture.labels)]
    if len(names) < 3:
        raise source_error(capture.metadata.get("source"),
                           f"only {len(names)} of its labels are template markers: not a labelled "
                           "capture of this face (label it without --check)")
    sub = capture.select(names)
    cols = np.array([template.labels.index(n) for n in names])
    pos = np.full((capture.n_frames, template.n_markers, 3), np.nan)
    pos[:, cols] = sub.positions
    found = label_points(template, pos, column_fragments(pos))
    runs: list[Mislabel] = []
    for col in cols:
        other = found.label[:, col]
        wrong = (other >= 0) & (other != col)
        for a, b in true_runs(wrong):
            if b - a < MIN_SWAP_FRAMES:
                continue
            k = int(np.bincount(other[a:b]).argmax())
            back = found.label[a:b, k] == col
            runs.append(Mislabel(template.labels[col], template.labels[k], a, b, bool(back.mean() >= 0.5)))
    return runs, found.label


def fix_labels(template: LabelTemplate, capture: Trajectories, runs: list[Mislabel]) -> Trajectories:
    """``capture`` with the points of every run moved to the label they belong to."""
    pos = capture.positions.copy()
    index = {label: k for k, label in enumerate(capture.labels)}
    moved = {}
    for run in runs:
        src, dst = index[run.label], index[run.found]
        moved[(src, dst, run.start, run.end)] = capture.positions[run.start:run.end, src]
    for (src, _, a, b) in moved:
        pos[a:b, src] = np.nan
    for (src, dst, a, b), points in moved.items():
        free = np.isnan(pos[a:b, dst]).any(axis=1)  # a swap's partner was moved out first
        pos[a:b, dst][free] = points[free]
        stay = ~free & ~np.isnan(points).any(axis=1)  # no room: the point stays where it was
        pos[a:b, src][stay] = points[stay]
    return capture.replace(positions=pos)
