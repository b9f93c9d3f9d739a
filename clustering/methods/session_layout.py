"""Swap the paper's layout in a clustering result for another method's (``mocaptk cluster --method``).

The other method chooses the same number of measured markers on the (stabilized) session; each
region's markers then join the chosen marker of their region they correlate with most (the
paper's reassignment rule, on the paper's consolidated correlation matrices), or — in a region
without a chosen marker — the nearest chosen marker. Mirroring follows the paper's run.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..layout import Cluster
from ..cluster_result import ClusterResult
from ..symmetry import SagittalPlane, marker_sides, mirror_clusters
from . import LayoutProblem, select_layout
from .problem import camera_aware

#: The layout method sees at most this many frames of the session; a longer session is sampled
#: evenly (every k-th frame, the smallest k that fits; a note says so): the method's cost grows
#: with the frames (k-means passes, Gram products, cross-validation) and this many frames of
#: facial motion already span the expressions (docs/performance.md).
METHOD_MAX_FRAMES = 8192


def relayout(result: ClusterResult, *, method: str, count: int | None = None, seed: int = 0,
             rig: str | None = None, shapes: tuple[tuple[str, ...], np.ndarray] | None = None,
             shapes_source: str | None = None) -> ClusterResult:
    """``result`` with its clusters chosen by ``method``: ``count`` measured markers (default: as
    many as ``result`` has); with ``rig``, weighing how that rig sees every marker (mirror images
    of a half face included, across the layout's sagittal plane); with ``shapes`` (labels,
    (K, M, 3) mm), set cover covers those shapes (a character's, at the session's markers;
    ``shapes_source`` recorded as the layout's ``character``)."""
    if method == "paper":
        return result
    layout = result.layout
    traj, neutral = result.trajectories, result.neutral
    labels = list(traj.labels)
    index = {label: i for i, label in enumerate(labels)}
    measured = [c for c in layout.clusters if c.mirrored_from is None]
    regions = {r.name: np.array([index[m] for m in r.markers], dtype=np.intp) for r in layout.regions}
    stride = -(-traj.n_frames // METHOD_MAX_FRAMES)
    kept = np.arange(0, traj.n_frames, stride)
    segments = tuple((t.start, t.end) for t in traj.takes)
    if stride > 1:  # the takes in sampled frames
        segments = tuple((lo, hi) for lo, hi in ((int(np.searchsorted(kept, start)),
                                                  int(np.searchsorted(kept, end))) for start, end in segments)
                         if hi > lo)
    plane_info = layout.extra["sagittal_plane"]
    plane = SagittalPlane(np.asarray(plane_info["point"]), np.asarray(plane_info["normal"]))
    trusted = layout.extra.get("orientation", {}).get("labels") != "contradict"
    sides = dict(zip(labels, marker_sides(labels, neutral, plane, trust_labels=trusted)))
    problem = LayoutProblem(traj.positions[::stride] - neutral[None], neutral, labels=traj.labels,
                            regions=regions, segments=segments, sides=tuple(sides[m] for m in labels))
    if rig is not None:
        from ..camera_cost import session_costs
        costs = session_costs(traj.positions, labels, rig,
                              plane=plane if layout.parameters.get("mirror") else None).select(labels)
        problem = camera_aware(problem, visibility=costs.visibility,
                               triangulation_error_mm=costs.triangulation_error_mm)
    if shapes is not None:  # the set cover's shapes: the character's, in this session's marker order
        given = {label: k for k, label in enumerate(shapes[0])}
        at = np.array([given.get(label, -1) for label in labels])
        problem.cache["set_cover_shapes"] = np.where((at >= 0)[None, :, None], np.asarray(shapes[1])[:, at], 0.0)
    selected = select_layout(problem, len(measured) if count is None else count, method=method, seed=seed)
    chosen = selected.layout
    members: dict[int, list[tuple[int, float]]] = {int(c): [] for c in chosen}
    region_of = {int(c): next((n for n, idx in regions.items() if c in idx), "") for c in chosen}
    for name, matrix in result.matrices.items():
        idx = np.array([index[m] for m in matrix.labels], dtype=np.intp)
        reps = np.flatnonzero(np.isin(idx, chosen))
        if reps.size:  # per point the chosen marker it correlates with most, ties to the first
            best = reps[np.argmax(matrix.matrix[reps], axis=0)]
            value = matrix.matrix[best, np.arange(idx.size)]
            for p, b, c in zip(idx.tolist(), idx[best].tolist(), value.tolist()):
                members[b].append((p, c))
            continue
        for p in idx:  # no chosen marker in this region: the nearest one (correlation not defined: 0)
            near = int(chosen[np.argmin(np.linalg.norm(neutral[chosen] - neutral[p], axis=1))])
            members[near].append((int(p), 0.0))
    clusters = []
    for rep in chosen:
        rep = int(rep)
        group = [(rep, 3.0)] + [(p, c) for p, c in members[rep] if p != rep]
        clusters.append(Cluster(
            representative=labels[rep], region=region_of[rep], members=tuple(labels[p] for p, _ in group),
            member_correlation={labels[p]: c for p, c in group},
            position=tuple(float(x) for x in neutral[rep]), side=sides[labels[rep]]))
    if bool(layout.parameters.get("mirror")):
        midline = {label for label, side in sides.items() if side == "C"}
        clusters += mirror_clusters(clusters, plane, labels, midline)
    region_results = tuple(dataclasses.replace(r, representatives=tuple(
        c.representative for c in clusters if c.mirrored_from is None and c.region == r.name))
        for r in layout.regions)
    parameters = dict(layout.parameters, method=method)
    if rig is not None:
        parameters["rig"] = rig
    if shapes is not None:
        parameters["character"] = {"source": shapes_source, "shapes": int(len(shapes[1]))}
    if "winner" in selected.details:  # which contender the hybrid chose ...
        parameters["winner"] = selected.details["winner"]
    if "region_cover" in selected.details:  # ... and the markers its region cover swapped in
        parameters["region_cover"] = selected.details["region_cover"]
    notes = result.notes + list(selected.details.get("notes", []))  # e.g. contenders skipped, cover swaps
    if stride > 1:
        notes.append(f"the layout method ({method}) used one frame in {stride} of the session's "
                     f"{traj.n_frames} ({kept.size} frames; at most {METHOD_MAX_FRAMES})")
    extra = dict(layout.extra, notes=notes) if "notes" in layout.extra else layout.extra
    new_layout = dataclasses.replace(layout, parameters=parameters, regions=region_results,
                                     clusters=tuple(clusters), extra=extra)
    return dataclasses.replace(result, layout=new_layout, notes=notes)


__all__ = ["relayout"]
