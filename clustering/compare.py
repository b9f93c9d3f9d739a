"""Every layout method on the same data and the same held-out metric (``mocaptk compare``).

Protocol: a method only ever sees training frames. With a separate test performance, each method
runs once on the whole session and is scored on the test take; otherwise the session's takes are
left out one at a time (contiguous blocks without takes): the method runs on the other takes and
is scored on the left-out one, errors pooled over folds. The score is the team's held-out ridge
reconstruction (:mod:`mocaptk.clustering.evaluation`): RMSE and 95th percentile of the per-point
error over all dense markers, mm. The reconstruction is fitted on the gap-free training frames
(a frame with any gap is left out of the fit; the evaluation's per-column gap handling costs
minutes per layout on long sessions and changes the fit by little) and evenly subsampled to at
most 3,000 frames; test frames keep their gaps and are all scored.
Random layouts are averaged over several seeds.

Every layout (the one chosen on the whole session) also gets Zell & McDonnell's layout statistics
(:func:`~mocaptk.clustering.methods.set_cover.layout_statistics`) over the shapes set cover
covers — the session's extreme frames: per ε (0.3, 0.7) the % of layout markers where no shape
moves ≥ ε (relative to the shape's largest displacement) and the number of shapes no layout
marker sees move ≥ ε.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.threads import single_threaded
from mocaptk.trajectories import Trajectories

from .evaluation import GapFreeRidge, error_summary, heldout_errors, holdout_splits
from .figures import _pyplot, _save
from .lost_marker import heldout_folds, pooled_worst_lost
from .regions import face_frame
from .methods import LayoutProblem, method_names, select_layout
from .methods.set_cover import layout_statistics, problem_shapes
from .neutral import neutral_pose

#: Seeds averaged for the random baseline.
RANDOM_SEEDS = 5
DEFAULT_COUNTS = (20, 30, 40, 60)
DEFAULT_METHODS = ("paper", "random", "farthest-point", "kmeans", "qr", "greedy", "thin-shell", "hybrid")


@dataclass
class CompareRow:
    """One method at one marker count."""

    method: str
    count: int
    rmse_mm: float
    p95_mm: float
    seconds: float
    layout: np.ndarray  # chosen on the whole session (for the gallery / JSON)
    details: dict[str, Any] = field(default_factory=dict)
    error: str | None = None  # the method could not produce this count
    #: Zell & McDonnell's statistics of ``layout``: {"0.3": {"idle_markers_percent", "unseen_shapes"}, "0.7": ...}
    statistics: dict[str, dict[str, float]] = field(default_factory=dict)
    #: held-out RMSE (mm, gap-free frames) when each scored layout loses its most important marker
    lost_rmse_mm: float = float("nan")


def _problem(positions: np.ndarray, session: Trajectories, frames: np.ndarray | None,
             regions: Mapping[str, np.ndarray]) -> LayoutProblem:
    pos = positions if frames is None else positions[frames]
    neutral = neutral_pose(pos)
    if not np.isfinite(neutral).all():  # a marker unseen in these frames: use the session's
        neutral = np.where(np.isfinite(neutral), neutral, neutral_pose(positions))
    segments: list[tuple[int, int]] = []
    if frames is not None:
        for take in session.takes:
            lo, hi = np.searchsorted(frames, [take.start, take.end])
            if hi > lo:
                segments.append((int(lo), int(hi)))
    else:
        segments = [(t.start, t.end) for t in session.takes]
    return LayoutProblem(pos - neutral[None], neutral, labels=session.labels, regions=regions,
                         segments=tuple(segments))


#: At most this many training frames enter the reconstruction fit (evenly subsampled).
FIT_FRAMES = 3000


def _gap_free(positions: np.ndarray) -> np.ndarray:
    """The frames without any gap (all frames when fewer than 10 are complete), subsampled
    evenly to at most :data:`FIT_FRAMES` (neighbouring frames at 60 Hz add little)."""
    complete = np.isfinite(positions).all(axis=(1, 2))
    kept = positions[complete] if complete.sum() >= 10 else positions
    step = -(-kept.shape[0] // FIT_FRAMES)
    return kept[::step]


def _scorer(train: np.ndarray) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``errors(layout, test)`` (frames, markers) mm: the held-out ridge fitted on ``train``'s
    :func:`_gap_free` frames — from one Gram matrix per fold when they are gap-free (every
    method and count shares it), else by the per-pattern fits of :func:`heldout_errors`."""
    fit = _gap_free(train)
    if np.isfinite(fit).all():
        return GapFreeRidge.fit(fit).errors
    return lambda layout, test: heldout_errors(fit, layout, [], test=test)


# thousands of small solves (scores, lost markers): BLAS threads only contend (17x the CPU at 60 markers)
@single_threaded
def compare_methods(session: Trajectories, *, test: Trajectories | None = None,
                    counts: Sequence[int] = DEFAULT_COUNTS, methods: Sequence[str] = DEFAULT_METHODS,
                    regions: Mapping[str, Sequence[int]] | None = None, seed: int = 0,
                    options: Mapping[str, Mapping[str, Any]] | None = None,
                    progress: Callable[[str], None] | None = None, rig: str | None = None) -> list[CompareRow]:
    """Score every ``method`` at every ``count`` (see the module docstring for the protocol).

    ``rig`` (``cara``, ``room`` or a rig file): the methods weigh how it sees every marker
    (:func:`rig_aware`; the paper's rule ignores it); the score stays the held-out one.

    ``options``: per-method keyword options, e.g. ``{"thin-shell": {"restarts": 3}}``.
    A count larger than the session's markers is skipped; a method that cannot reach a count
    (e.g. the correlation rule) gets a row with ``error`` set.
    """
    unknown = [m for m in methods if m not in method_names()]
    if unknown:
        raise OptionError(f"unknown method(s) {', '.join(unknown)} (choose from {', '.join(method_names())})")
    if test is not None and test.labels != session.labels:
        raise OptionError("the test performance must have the same markers as the session "
                          f"({test.n_markers} vs {session.n_markers}, or different labels)")
    counts = sorted({int(c) for c in counts if 1 <= int(c) < session.n_markers})
    if not counts:
        raise OptionError(f"no marker count below the session's {session.n_markers} markers")
    positions = session.positions
    region_idx = {k: np.asarray(v, dtype=np.intp) for k, v in (regions or {}).items()}
    if test is not None:
        folds: list[tuple[np.ndarray, np.ndarray]] = []
    elif len(session.takes) >= 2:
        folds = holdout_splits(session.n_frames, session.takes, split="takes")
    else:
        folds = holdout_splits(session.n_frames, split="blocks", folds=5)
    full = _problem(positions, session, None, region_idx)
    shapes = problem_shapes(full)
    fold_problems = [_problem(positions, session, train, region_idx) for train, _ in folds]
    if rig is not None:
        aware = rig_aware(session, rig)
        full, fold_problems = aware(full), [aware(p) for p in fold_problems]
    # one scorer per scored layout for the worst single lost marker (gap-free frames)
    lost_folds = ([heldout_folds(positions, test=test.positions)] if test is not None
                  else [heldout_folds(positions, [fold]) for fold in folds])
    scorers = ([_scorer(positions)] if test is not None
               else [_scorer(positions[train]) for train, _ in folds])
    options = options or {}
    rows: list[CompareRow] = []
    for method in methods:
        seeds = range(seed, seed + RANDOM_SEEDS) if method == "random" else [seed]
        for count in counts:
            if progress:
                progress(f"{method} × {count}")
            try:
                summaries, seconds, lost, layout, details = [], [], [], None, {}
                for s in seeds:
                    chosen = select_layout(full, count, method=method, seed=s, **options.get(method, {}))
                    layout = chosen.layout if layout is None else layout
                    details = details or chosen.details
                    if test is not None:
                        errors = scorers[0](chosen.layout, test.positions)
                        seconds.append(chosen.seconds)
                        scored = [chosen.layout]
                    else:
                        errors = np.full(positions.shape[:2], np.nan)
                        scored = []
                        for problem, (_, held), score in zip(fold_problems, folds, scorers):
                            fold = select_layout(problem, count, method=method, seed=s,
                                                 **options.get(method, {}))
                            seconds.append(fold.seconds)
                            scored.append(fold.layout)
                            errors[held] = score(fold.layout, positions[held])
                    summaries.append(error_summary(errors))
                    lost.append(pooled_worst_lost(lost_folds, scored))
            except OptionError as exc:
                rows.append(CompareRow(method, count, float("nan"), float("nan"), 0.0,
                                       np.zeros(0, dtype=np.intp), error=str(exc)))
                continue
            rows.append(CompareRow(method, count, float(np.mean([s["rmse_mm"] for s in summaries])),
                                   float(np.mean([s["p95_mm"] for s in summaries])),
                                   float(np.mean(seconds)), layout, details,
                                   statistics=layout_statistics(shapes, layout),
                                   lost_rmse_mm=float(np.mean(lost))))
    return rows


def rig_aware(session: Trajectories, rig: str) -> Callable[[LayoutProblem], LayoutProblem]:
    """A function making a problem of ``session`` camera-aware for ``rig``: the rig films the whole
    session once (a half face with its mirror image across the estimated sagittal plane)."""
    from .camera_cost import session_costs
    from .methods.problem import camera_aware
    from .neutral import max_displacement
    from .symmetry import estimate_sagittal_plane, is_half_capture

    labels = list(session.labels)
    plane = None
    if is_half_capture(labels):
        neutral = neutral_pose(session.positions)
        plane = estimate_sagittal_plane(labels, neutral, max_displacement(session.positions, neutral), half=True)
    costs = session_costs(session.positions, labels, rig, plane=plane).select(labels)
    return lambda problem: camera_aware(problem, visibility=costs.visibility,
                                        triangulation_error_mm=costs.triangulation_error_mm)


def rows_as_json(rows: Sequence[CompareRow], labels: Sequence[str], *,
                 source: Mapping[str, Any] | None = None, protocol: str = "") -> dict[str, Any]:
    """The comparison as a JSON-ready dict (``format``/``version``, one entry per row)."""
    return {
        "format": "mocaptk-compare", "version": 1, "protocol": protocol, "source": dict(source or {}),
        "rows": [{"method": r.method, "count": r.count, "rmse_mm": r.rmse_mm, "p95_mm": r.p95_mm,
                  "lost_marker_rmse_mm": r.lost_rmse_mm, "seconds": r.seconds, "error": r.error, "layout_statistics": r.statistics,
                  "layout": [labels[i] for i in r.layout]} for r in rows],
    }


def rows_as_markdown(rows: Sequence[CompareRow], *, times: bool = True) -> str:
    """Two tables, one line per method. First, per count: RMSE / p95 / worst single lost marker
    RMSE (mm) and, with ``times``, run time (best RMSE in bold). Second, per count: the layout
    statistics (% idle markers and unseen shapes per ε). Without times the text is the same for
    the same input (report.html)."""
    counts = sorted({r.count for r in rows})
    methods = list(dict.fromkeys(r.method for r in rows))
    cell = {(r.method, r.count): r for r in rows}
    best = {c: min((r.rmse_mm for r in rows if r.count == c and r.error is None), default=np.nan)
            for c in counts}

    def table(head: str, text: Callable[[CompareRow], str]) -> list[str]:
        lines = ["| method | " + " | ".join(head.format(c) for c in counts) + " |", "|---|" + "---|" * len(counts)]
        for m in methods:
            found = [cell.get((m, c)) for c in counts]
            lines.append(f"| {m} | " + " | ".join("—" if r is None or r.error is not None else text(r)
                                                   for r in found) + " |")
        return lines

    def scores(r: CompareRow) -> str:
        rmse = f"**{r.rmse_mm:.3f}**" if r.rmse_mm == best[r.count] else f"{r.rmse_mm:.3f}"
        return f"{rmse} / {r.p95_mm:.3f} / {r.lost_rmse_mm:.3f}" + (f" ({r.seconds:.2f})" if times else "")

    def statistics(r: CompareRow) -> str:
        eps = list(r.statistics)
        idle = " / ".join(f"{r.statistics[e]['idle_markers_percent']:.0f}" for e in eps)
        unseen = " / ".join(f"{r.statistics[e]['unseen_shapes']:d}" for e in eps)
        return f"{idle} %; {unseen}"

    epsilons = " / ".join(next((list(r.statistics) for r in rows if r.statistics), ["0.3", "0.7"]))
    return "\n".join(
        table("{} markers: RMSE / p95 / 1 lost mm" + (" (s)" if times else ""), scores)
        + ["", "1 lost = held-out RMSE when the layout loses the marker whose loss hurts most "
           "(gap-free frames; per fold its own layout's worst marker).", "", f"Layout statistics (Zell & McDonnell) at ε = {epsilons}: idle % = markers where no "
           "shape moves ≥ ε (relative to its largest displacement); unseen = shapes no marker sees "
           "move ≥ ε. Shapes: the session's extreme frames, as set cover uses.", ""]
        + table("{} markers: idle %; unseen (ε = " + epsilons + ")", statistics)) + "\n"


def compare_plot(rows: Sequence[CompareRow], path: str | os.PathLike[str], *, title: str = "") -> Path:
    """Held-out RMSE (mm) against the number of markers, one line per method (as Le et al. Fig. 12)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5))
    for k, method in enumerate(dict.fromkeys(r.method for r in rows)):
        pts = sorted((r.count, r.rmse_mm) for r in rows if r.method == method and r.error is None)
        if pts:
            xs, ys = zip(*pts)
            ax.plot(xs, ys, marker="os^vD<>ph*"[k % 10], label=method)
    ax.set_xlabel("markers in the layout")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylabel("held-out RMSE (mm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title or "held-out reconstruction error")
    fig.tight_layout()
    return _save(fig, path)


def layout_gallery(rows: Sequence[CompareRow], neutral: np.ndarray, displacement: np.ndarray,
                   path: str | os.PathLike[str]) -> Path:
    """Front views of every layout: one column per method, one row per marker count."""
    plt = _pyplot()
    methods = list(dict.fromkeys(r.method for r in rows))
    counts = sorted({r.count for r in rows})
    cell = {(r.method, r.count): r for r in rows}
    frame = face_frame(neutral, displacement)
    xy = (neutral - neutral.mean(axis=0)) @ frame[:2].T
    fig, axes = plt.subplots(len(counts), len(methods), squeeze=False,
                             figsize=(2.3 * len(methods), 2.7 * len(counts)))
    for i, count in enumerate(counts):
        for j, method in enumerate(methods):
            ax = axes[i, j]
            ax.scatter(xy[:, 0], xy[:, 1], s=4, c="lightgrey")
            row = cell.get((method, count))
            if row is not None and row.error is None:
                chosen = xy[row.layout]
                ax.scatter(chosen[:, 0], chosen[:, 1], s=22, c="crimson", edgecolors="k", linewidths=0.4)
                ax.set_title(f"{method} {count}\n{row.rmse_mm:.3f} mm", fontsize=8)
            else:
                ax.set_title(f"{method} {count}\n(not reached)", fontsize=8)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    return _save(fig, path)
