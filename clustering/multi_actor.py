"""One marker layout for several actors (Le, Zhu & Deng §4.7): register, pool, score per actor.

**Registration.** Every actor's markers are put in the order of one reference marker set (the
first session's): by labels when the actor has every reference label; otherwise by nearest
neighbour after a similarity alignment (rotation, translation, uniform scale; ICP from the
principal axes) of the actor's neutral pose onto the reference's. That correspondence is refused
(:class:`~mocaptk.errors.InputFileError`) when it is not one-to-one or not clear-cut (a
reference marker's nearest actor marker is not well nearer than its second nearest).

**Pooling.** Each registered actor keeps its own motion in its own millimetres: its trajectories
are rotated into the reference's orientation (not scaled) and its displacements from its own
neutral pose are placed on the reference's neutral pose. The pool is one session whose takes are
every actor's takes (``actor:take``): the paper's correlations, every layout method and the
reconstruction fit see all actors' evidence at once, on the reference's face geometry.

**Scoring.** Per actor, the reconstruction is fitted on that actor's own training frames and
scored on its held-out frames, as in ``compare``: the shared layout (chosen on the pool without
those held-out frames) beside the actor's own layout (the same method on that actor's training
frames alone).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mocaptk.errors import InputFileError, OptionError
from mocaptk.geometry import Similarity, similarity_transform
from mocaptk.trajectories import Take, Trajectories

from .compare import RANDOM_SEEDS, _gap_free
from .evaluation import error_summary, heldout_errors, holdout_splits
from .methods import LayoutProblem, method_names, select_layout
from .neutral import neutral_pose

#: A reference marker's nearest actor marker must be nearer than this share of its second nearest.
CLEAR_CUT = 0.6


@dataclass(frozen=True)
class Registration:
    """How one actor's markers map onto the reference marker set.

    ``order`` (N_ref,): the actor's marker index for each reference marker; ``transform``: the
    similarity taking the actor's neutral pose onto the reference's; ``residual_mm``: RMS
    distance (reference mm) of the registered markers after it; ``by``: "labels" or "nearest".
    """

    by: str
    order: np.ndarray
    transform: Similarity
    residual_mm: float

    def as_dict(self) -> dict[str, Any]:
        return {"by": self.by, "scale": self.transform.scale, "residual_mm": self.residual_mm}


def _principal_starts(moving: np.ndarray, fixed: np.ndarray) -> list[Similarity]:
    """Starts for ICP: the identity rotation and the 4 proper rotations matching principal axes,
    each with the RMS-radius scale ratio and the centroids matched."""
    cm, cf = moving.mean(axis=0), fixed.mean(axis=0)
    scale = float(np.sqrt(((fixed - cf) ** 2).sum(axis=1).mean() / max(((moving - cm) ** 2).sum(axis=1).mean(), 1e-300)))
    axes_m = np.linalg.svd(moving - cm, full_matrices=False)[2]  # rows: principal axes
    axes_f = np.linalg.svd(fixed - cf, full_matrices=False)[2]
    rotations = [np.eye(3)]
    for signs in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1)):
        rot = axes_f.T @ np.diag(signs) @ axes_m
        rotations.append(rot if np.linalg.det(rot) > 0 else axes_f.T @ np.diag(signs) @ np.diag([1, 1, -1]) @ axes_m)
    return [Similarity(scale, r, cf - scale * r @ cm) for r in rotations]


def _icp(moving: np.ndarray, fixed: np.ndarray, start: Similarity, *, iterations: int = 50) -> tuple[Similarity, float]:
    """Similarity ICP: each fixed point to its nearest moved point. Returns (transform, RMS mm)."""
    transform = start
    for _ in range(iterations):
        tree = cKDTree(transform.apply(moving))
        _, nearest = tree.query(fixed)
        step = similarity_transform(moving[nearest], fixed)
        change = np.abs(step.apply(moving) - transform.apply(moving)).max()
        transform = step
        if change < 1e-6:
            break
    dist = cKDTree(transform.apply(moving)).query(fixed)[0]
    return transform, float(np.sqrt(np.mean(dist ** 2)))


def register_actor(reference: Trajectories, actor: Trajectories, *, source: str | None = None) -> Registration:
    """Register ``actor``'s markers to ``reference``'s (both head-stabilized, mm); see the module
    docstring. ``source`` names the actor's file in a refusal."""
    ref_neutral = neutral_pose(reference.positions)
    act_neutral = neutral_pose(actor.positions)
    if set(reference.labels) <= set(actor.labels):
        order = np.array(actor.index(list(reference.labels)), dtype=np.intp)
        usable = np.isfinite(ref_neutral).all(axis=1) & np.isfinite(act_neutral[order]).all(axis=1)
        transform = similarity_transform(act_neutral[order][usable], ref_neutral[usable])
        dist = np.linalg.norm(transform.apply(act_neutral[order][usable]) - ref_neutral[usable], axis=1)
        return Registration("labels", order, transform, float(np.sqrt(np.mean(dist ** 2))))
    file = source or str(actor.metadata.get("source", "actor"))
    if not (np.isfinite(ref_neutral).all() and np.isfinite(act_neutral).all()):
        raise InputFileError(file, "a marker is never seen, so it cannot be matched to the reference "
                                   "markers by position; give it the reference's labels")
    if actor.n_markers < reference.n_markers:
        raise InputFileError(file, f"has {actor.n_markers} markers, fewer than the reference's "
                                   f"{reference.n_markers}, and not the reference's labels")
    fits = [_icp(act_neutral, ref_neutral, s) for s in _principal_starts(act_neutral, ref_neutral)]
    transform, residual = min(fits, key=lambda f: f[1])
    moved = transform.apply(act_neutral)
    dist, nearest = cKDTree(moved).query(ref_neutral, k=2)
    back = cKDTree(ref_neutral).query(moved[nearest[:, 0]])[1]
    one_to_one = back == np.arange(reference.n_markers)
    clear = dist[:, 0] < CLEAR_CUT * dist[:, 1]
    bad = np.flatnonzero(~(one_to_one & clear))
    if bad.size:
        worst = int(bad[np.argmax(dist[bad, 0] / np.maximum(dist[bad, 1], 1e-12))])
        raise InputFileError(file, (
            f"ambiguous marker correspondence with the reference by nearest neighbour after similarity "
            f"alignment: {bad.size} of {reference.n_markers} reference markers (e.g. "
            f"{reference.labels[worst]}: {dist[worst, 0]:.1f} mm to {actor.labels[nearest[worst, 0]]}, "
            f"{dist[worst, 1]:.1f} mm to {actor.labels[nearest[worst, 1]]}); give it the reference's labels"))
    return Registration("nearest", nearest[:, 0].astype(np.intp), transform, residual)


def registered(reference: Trajectories, actor: Trajectories, registration: Registration) -> Trajectories:
    """``actor`` in the reference's marker order and labels, rotated into its orientation and
    translated onto it (not scaled: the actor's own mm)."""
    rot = registration.transform.rotation
    pos = actor.positions[:, registration.order]
    centre = np.nanmean(neutral_pose(pos), axis=0)
    target = np.nanmean(neutral_pose(reference.positions), axis=0)
    moved = (pos - centre) @ rot.T + target
    meta = {k: v for k, v in actor.metadata.items() if k != "regions"}
    return Trajectories(moved, reference.labels, actor.rate, metadata=meta)


def pooled_session(actors: Sequence[Trajectories], names: Sequence[str]) -> Trajectories:
    """One session of every registered actor's motion on the first actor's neutral pose (the
    reference); takes ``name:take`` (one take per actor without takes)."""
    reference = actors[0]
    base = neutral_pose(reference.positions)
    parts, takes, start = [], [], 0
    for actor, name in zip(actors, names):
        own = neutral_pose(actor.positions)
        parts.append(actor.positions - own[None] + base[None])
        for take in actor.takes or [Take("all", 0, actor.n_frames)]:
            takes.append(Take(f"{name}:{take.name}", start + take.start, start + take.end, take.region))
        start += actor.n_frames
    meta = dict(reference.metadata, takes=takes, actors=list(names))
    return Trajectories(np.concatenate(parts), reference.labels, reference.rate, metadata=meta)


@dataclass
class ActorRow:
    """One method at one count for one actor: held-out error with the shared and the own layout."""

    method: str
    count: int
    actor: str
    shared_rmse_mm: float
    own_rmse_mm: float
    shared_p95_mm: float
    own_p95_mm: float
    shared_layout: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    own_layout: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    error: str | None = None


def _part(actor: Trajectories, frames: np.ndarray | None = None) -> tuple[np.ndarray, tuple[tuple[int, int], ...]]:
    """The actor's ``frames`` (default: all) as displacements from its neutral pose over them, and
    its takes' ranges within them (as ``compare`` builds a problem)."""
    pos = actor.positions if frames is None else actor.positions[frames]
    frames = np.arange(actor.n_frames) if frames is None else frames
    segments = []
    for take in actor.takes:
        lo, hi = np.searchsorted(frames, [take.start, take.end])
        if hi > lo:
            segments.append((int(lo), int(hi)))
    return pos - neutral_pose(pos)[None], tuple(segments) or ((0, pos.shape[0]),)


def _problem(parts: Sequence[tuple[np.ndarray, tuple[tuple[int, int], ...]]], neutral: np.ndarray,
             labels: Sequence[str]) -> LayoutProblem:
    """One layout problem of several actors' parts (:func:`_part`) on the ``neutral`` face."""
    segments, start = [], 0
    for disp, own in parts:
        segments += [(start + a, start + b) for a, b in own]
        start += disp.shape[0]
    return LayoutProblem(np.concatenate([d for d, _ in parts]), neutral, labels=labels,
                         segments=tuple(segments))


def compare_actors(actors: Sequence[Trajectories], names: Sequence[str], *,
                   tests: Sequence[Trajectories] | None = None, counts: Sequence[int] = (20, 30, 40),
                   methods: Sequence[str] = ("hybrid",), seed: int = 0,
                   options: Mapping[str, Mapping[str, Any]] | None = None,
                   progress: Callable[[str], None] | None = None) -> list[ActorRow]:
    """Per method, count and actor: held-out RMSE / p95 (mm) with the shared layout and with the
    actor's own (see the module docstring). ``actors`` are registered (reference order, same
    labels); ``tests``: one held-out performance per actor (else leave one take out per actor, 5
    contiguous blocks without takes). Random layouts: mean over :data:`RANDOM_SEEDS` seeds."""
    unknown = [m for m in methods if m not in method_names()]
    if unknown:
        raise OptionError(f"unknown method(s) {', '.join(unknown)} (choose from {', '.join(method_names())})")
    n_markers = actors[0].n_markers
    counts = sorted({int(c) for c in counts if 1 <= int(c) < n_markers})
    if not counts:
        raise OptionError(f"no marker count below the sessions' {n_markers} markers")
    neutral = neutral_pose(actors[0].positions)  # the reference's face carries the shared layout
    labels = actors[0].labels
    options = options or {}
    # per actor: (shared problem, own problem, train frames, test positions) per fold
    folds: list[list[tuple[LayoutProblem, LayoutProblem, np.ndarray, np.ndarray]]] = []
    for i, actor in enumerate(actors):
        if tests is not None:
            splits = [(np.arange(actor.n_frames), None)]
        elif len(actor.takes) >= 2:
            splits = holdout_splits(actor.n_frames, actor.takes, split="takes")
        else:
            splits = holdout_splits(actor.n_frames, actor.takes, split="blocks", folds=5)
        actor_folds = []
        for train, held in splits:
            mine = _part(actor, train)
            test = tests[i].positions if tests is not None else actor.positions[held]
            pool = [mine if j == i else _part(a) for j, a in enumerate(actors)]  # actor order: with
            # --test every actor's shared problem is the same, so is its layout
            actor_folds.append((_problem(pool, neutral, labels),
                                _problem([mine], neutral_pose(actor.positions[train]), labels),
                                actor.positions[train], test))
        folds.append(actor_folds)
    # the layouts a user takes away: chosen on whole sessions (with tests, the folds' own)
    full = ([(f[0][0], f[0][1]) for f in folds] if tests is not None else
            [(_problem([_part(a) for a in actors], neutral, labels),
              _problem([_part(a)], neutral_pose(a.positions), labels)) for a in actors])
    rows: list[ActorRow] = []
    for method in methods:
        seeds = range(seed, seed + RANDOM_SEEDS) if method == "random" else [seed]
        for count in counts:
            for i, name in enumerate(names):
                if progress:
                    progress(f"{method} × {count}, {name}")
                try:
                    rows.append(_actor_row(method, count, name, folds[i], full[i], seeds,
                                           options.get(method, {})))
                except OptionError as exc:
                    rows.append(ActorRow(method, count, name, *[float("nan")] * 4, error=str(exc)))
    return rows


def _actor_row(method: str, count: int, name: str, folds, full: tuple[LayoutProblem, LayoutProblem],
               seeds, options: Mapping[str, Any]) -> ActorRow:
    summaries: dict[str, list[dict]] = {"shared": [], "own": []}
    layouts = [select_layout(problem, count, method=method, seed=seeds[0], **options).layout
               for problem in full]
    for s in seeds:
        for kind, which in (("shared", 0), ("own", 1)):
            errors = []
            for fold in folds:
                same = s == seeds[0] and fold[which] is full[which]  # with --test: chosen above
                layout = layouts[which] if same else select_layout(fold[which], count, method=method,
                                                                   seed=s, **options).layout
                errors.append(heldout_errors(_gap_free(fold[2]), layout, [], test=fold[3]))
            summaries[kind].append(error_summary(np.concatenate(errors)))
    mean = {k: {key: float(np.mean([v[key] for v in vals])) for key in ("rmse_mm", "p95_mm")}
            for k, vals in summaries.items()}
    return ActorRow(method, count, name, mean["shared"]["rmse_mm"], mean["own"]["rmse_mm"],
                    mean["shared"]["p95_mm"], mean["own"]["p95_mm"], *layouts)


def actor_rows_as_markdown(rows: Sequence[ActorRow]) -> str:
    """One line per method and actor: shared / own held-out RMSE (mm) per count, and the change."""
    counts = sorted({r.count for r in rows})
    cell = {(r.method, r.actor, r.count): r for r in rows}
    lines = ["| method | actor | " + " | ".join(f"{c} markers: shared / own (Δ)" for c in counts) + " |",
             "|---|---|" + "---|" * len(counts)]
    for method, actor in dict.fromkeys((r.method, r.actor) for r in rows):
        out = []
        for c in counts:
            r = cell.get((method, actor, c))
            out.append("—" if r is None or r.error is not None else
                       f"{r.shared_rmse_mm:.3f} / {r.own_rmse_mm:.3f} "
                       f"({100 * (r.shared_rmse_mm / r.own_rmse_mm - 1):+.0f} %)")
        lines.append(f"| {method} | {actor} | " + " | ".join(out) + " |")
    return "\n".join(lines) + "\n"


def actor_rows_as_json(rows: Sequence[ActorRow], labels: Sequence[str], *,
                       registrations: Mapping[str, Registration], protocol: str = "") -> dict[str, Any]:
    """The multi-actor comparison as a JSON-ready dict (``format``/``version``)."""
    return {
        "format": "mocaptk-compare-actors", "version": 1, "protocol": protocol,
        "actors": {name: reg.as_dict() for name, reg in registrations.items()},
        "rows": [{"method": r.method, "count": r.count, "actor": r.actor, "error": r.error,
                  "shared_rmse_mm": r.shared_rmse_mm, "own_rmse_mm": r.own_rmse_mm,
                  "shared_p95_mm": r.shared_p95_mm, "own_p95_mm": r.own_p95_mm,
                  "shared_layout": [labels[i] for i in r.shared_layout],
                  "own_layout": [labels[i] for i in r.own_layout]} for r in rows],
    }


def actor_names(paths: Sequence[str | Path]) -> list[str]:
    """Short unique actor names: the file stems (numbered when two stems are the same)."""
    stems = [Path(p).stem for p in paths]
    return [s if stems.count(s) == 1 else f"{s}#{i + 1}" for i, s in enumerate(stems)]


def load_actors(sessions: Sequence[str | Path], tests: Sequence[str | Path] | None, *, stabilized: bool,
                rate: float | None = None, units: str | None = None, rigid: Sequence[str] | None = None
                ) -> tuple[list[Trajectories], list[Trajectories] | None, dict[str, Registration], list[dict]]:
    """Read and prepare every actor's session (and held-out test, one per session) like
    :func:`~mocaptk.clustering.pipeline.load_session_and_test`, registered to the first session.

    Returns (registered sessions, registered tests or None, {name: registration}, sources).
    """
    from .pipeline import load_session_and_test

    if tests is not None and len(tests) != len(sessions):
        raise OptionError(f"give one --test per session ({len(sessions)} sessions, {len(tests)} --test)")
    names = actor_names(sessions)
    actors, held, registrations, sources = [], [] if tests is not None else None, {}, []
    for k, (name, path) in enumerate(zip(names, sessions)):
        traj, perf, source = load_session_and_test(path, None if tests is None else tests[k],
                                                   stabilized=stabilized, rate=rate, units=units, rigid=rigid)
        reference = actors[0] if actors else traj  # the reference keeps its data exactly
        registration = register_actor(reference, traj, source=str(path))
        actors.append(registered(reference, traj, registration) if actors else traj)
        if held is not None:
            held.append(registered(reference, perf, registration) if k else perf)
        registrations[name] = registration
        sources.append({"actor": name, **source, **registration.as_dict()})
    return actors, held, registrations, sources


def cluster_actors(actors: Sequence[Trajectories], sources: Sequence[dict], *, options, source: dict,
                   progress: Callable[[str], None] | None = None):
    """``mocaptk cluster`` of several registered actors (:func:`load_actors`): the paper's
    correlations, the count and the layout method on the pooled session; the result carries the
    reference actor's session (rig, pictures, report) and ``source["actors"]``."""
    import dataclasses

    from .pipeline import cluster_session

    names = [s["actor"] for s in sources]
    pooled = pooled_session(actors, names)
    result = cluster_session(pooled, options=dataclasses.replace(options, stabilize=False, rigid=None),
                             source=source, progress=progress)
    layout = result.layout
    layout = dataclasses.replace(
        layout, source={**layout.source, "actors": list(sources)},
        parameters={**layout.parameters, "stabilized": bool(options.stabilize)})
    reference = actors[0]
    return dataclasses.replace(result, layout=layout, trajectories=reference,
                               neutral=neutral_pose(reference.positions))
