"""Every layout method on the same data and the same held-out metric (``mocaptk compare``).

Protocol: a method only ever sees training frames. With a separate test performance, each method
runs once on the whole session and is scored on the test take; otherwise the session's takes are
left out one at a time (contiguous blocks without takes): the method runs on the other takes and
is scored on the left-out one, errors pooled over folds. The score is the team's held-out ridge
reconstruction (:mod:`mocaptk.clustering.evaluation`): RMSE and 95th percentile of the per-point
error over all dense markers, mm. The reconstruction is fitted on the gap-free training frames
(a frame with any gap is left out of the fit; the evaluation's per-column gap handling costs
minutes per layout on long sessions and changes the fit by little); test frames keep their gaps.
Random layouts are averaged over several seeds.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import OptionError
from ..trajectories import Trajectories
from .evaluation import error_summary, heldout_errors, holdout_splits
from .methods import LayoutProblem, method_names, select_layout
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


def _gap_free(positions: np.ndarray) -> np.ndarray:
    """The frames without any gap (all frames when fewer than 10 are complete)."""
    complete = np.isfinite(positions).all(axis=(1, 2))
    return positions[complete] if complete.sum() >= 10 else positions


def compare_methods(session: Trajectories, *, test: Trajectories | None = None,
                    counts: Sequence[int] = DEFAULT_COUNTS, methods: Sequence[str] = DEFAULT_METHODS,
                    regions: Mapping[str, Sequence[int]] | None = None, seed: int = 0,
                    options: Mapping[str, Mapping[str, Any]] | None = None,
                    progress: Callable[[str], None] | None = None) -> list[CompareRow]:
    """Score every ``method`` at every ``count`` (see the module docstring for the protocol).

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
    fold_problems = [_problem(positions, session, train, region_idx) for train, _ in folds]
    options = options or {}
    rows: list[CompareRow] = []
    for method in methods:
        seeds = range(seed, seed + RANDOM_SEEDS) if method == "random" else [seed]
        for count in counts:
            if progress:
                progress(f"{method} × {count}")
            try:
                summaries, seconds, layout, details = [], [], None, {}
                for s in seeds:
                    chosen = select_layout(full, count, method=method, seed=s, **options.get(method, {}))
                    layout = chosen.layout if layout is None else layout
                    details = details or chosen.details
                    if test is not None:
                        errors = heldout_errors(_gap_free(positions), chosen.layout, [],
                                                test=test.positions)
                        seconds.append(chosen.seconds)
                    else:
                        errors = np.full(positions.shape[:2], np.nan)
                        for problem, (train, held) in zip(fold_problems, folds):
                            fold = select_layout(problem, count, method=method, seed=s,
                                                 **options.get(method, {}))
                            seconds.append(fold.seconds)
                            errors[held] = heldout_errors(_gap_free(positions[train]), fold.layout,
                                                          [], test=positions[held])
                    summaries.append(error_summary(errors))
            except OptionError as exc:
                rows.append(CompareRow(method, count, float("nan"), float("nan"), 0.0,
                                       np.zeros(0, dtype=np.intp), error=str(exc)))
                continue
            rows.append(CompareRow(method, count, float(np.mean([s["rmse_mm"] for s in summaries])),
                                   float(np.mean([s["p95_mm"] for s in summaries])),
                                   float(np.mean(seconds)), layout, details))
    return rows


def rows_as_json(rows: Sequence[CompareRow], labels: Sequence[str], *,
                 source: Mapping[str, Any] | None = None, protocol: str = "") -> dict[str, Any]:
    """The comparison as a JSON-ready dict (``format``/``version``, one entry per row)."""
    return {
        "format": "mocaptk-compare", "version": 1, "protocol": protocol, "source": dict(source or {}),
        "rows": [{"method": r.method, "count": r.count, "rmse_mm": r.rmse_mm, "p95_mm": r.p95_mm,
                  "seconds": r.seconds, "error": r.error,
                  "layout": [labels[i] for i in r.layout]} for r in rows],
    }


def rows_as_markdown(rows: Sequence[CompareRow]) -> str:
    """A table: one line per method, per count RMSE / p95 (mm) and run time; best RMSE in bold."""
    counts = sorted({r.count for r in rows})
    methods = list(dict.fromkeys(r.method for r in rows))
    cell = {(r.method, r.count): r for r in rows}
    best = {c: min((r.rmse_mm for r in rows if r.count == c and r.error is None), default=np.nan)
            for c in counts}
    head = "| method | " + " | ".join(f"{c} markers: RMSE / p95 mm (s)" for c in counts) + " |"
    lines = [head, "|---|" + "---|" * len(counts)]
    for m in methods:
        out = []
        for c in counts:
            r = cell.get((m, c))
            if r is None or r.error is not None:
                out.append("—")
                continue
            rmse = f"{r.rmse_mm:.3f}"
            if r.rmse_mm == best[c]:
                rmse = f"**{rmse}**"
            out.append(f"{rmse} / {r.p95_mm:.3f} ({r.seconds:.2f})")
        lines.append(f"| {m} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"
