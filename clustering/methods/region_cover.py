"""Region cover: a facial region that moves on its own keeps a marker of its own, on each side.

The paper's rule clusters each region separately, so every region has a representative. A layout
chosen over the whole face (the hybrid) may leave a region without one; that is harmless where
the region's markers follow their neighbours (their motion is the neighbours'), but not where
the region moves on its own: a blink moves the lid 6 mm and the brow and cheek markers around it
less than the capture's noise, so a layout without a lid marker cannot see blinks at all (the
identity actor's 20-marker layout: retarget's eyeBlink r 0.00). Such a region-side gets the
marker that moves most on its own, in place of the layout marker whose loss the local error
(:mod:`.local_fit`, the hybrid's own judge) feels least.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .hybrid import local_error
from .problem import LayoutProblem

#: mm: a marker moves on its own when its local fit leaves a residual at least this large (99.9th
#: percentile over the training frames; 5x the 0.2 mm marker noise of our captures) ...
OWN_MOTION_MM = 1.0
#: ... and explains less than this fraction of its motion energy (blenderFace's under-eye markers,
#: which follow the cheek: 0.96; the identity actor's lid markers: 0.02-0.06).
MAX_EXPLAINED = 0.5
#: the local fit: each point from its this many nearest layout markers (the local error's largest k)
NEAREST = 2


def own_motion(problem: LayoutProblem, layout: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) mm: each point's motion the layout does not explain — the 99.9th-percentile residual of
    a least-squares fit from its ``NEAREST`` nearest layout markers (neutral face) over the training
    frames; 0 where that fit explains ``MAX_EXPLAINED`` of its motion energy or more."""
    disp = problem.displacements
    out = np.zeros(len(points))
    for i, p in enumerate(points):
        near = layout[np.argsort(np.linalg.norm(problem.neutral[layout] - problem.neutral[p], axis=1),
                                 kind="stable")[:NEAREST]]
        x, y = disp[:, near].reshape(len(disp), -1), disp[:, p]
        ok = np.isfinite(x).all(axis=1) & np.isfinite(y).all(axis=1)
        if ok.sum() <= x.shape[1]:
            continue
        residual = y[ok] - x[ok] @ np.linalg.lstsq(x[ok], y[ok], rcond=None)[0]
        energy = float(np.sum(y[ok] ** 2))
        if energy > 0 and 1.0 - float(np.sum(residual ** 2)) / energy < MAX_EXPLAINED:
            out[i] = float(np.percentile(np.linalg.norm(residual, axis=1), 99.9))
    return out


def cover_regions(problem: LayoutProblem, layout: np.ndarray, groups: Mapping[str, np.ndarray]
                  ) -> tuple[np.ndarray, list[str]]:
    """``layout`` (sorted point indices) with a marker in every group (a region's points on one
    side, midline included) that has none and holds a point moving on its own ≥ ``OWN_MOTION_MM``.

    That point (the one moving most on its own) replaces the layout marker whose loss raises the
    local error least, never the only marker of another group. Returns the layout (same size,
    sorted) and a note per swap."""
    layout = np.sort(np.asarray(layout, dtype=np.intp))
    notes: list[str] = []
    allowed = set(problem.candidate_points().tolist())
    for name, points in groups.items():
        points = np.array([p for p in points if p in allowed], dtype=np.intp)
        if points.size == 0 or np.isin(points, layout).any():
            continue
        moving = own_motion(problem, layout, points)
        if moving.max() < OWN_MOTION_MM:
            continue
        new = int(points[np.argmax(moving)])
        sole = {int(g[np.isin(g, layout)][0]) for g in groups.values() if np.isin(g, layout).sum() == 1}
        removable = [int(p) for p in layout if int(p) not in sole]
        if not removable:
            continue
        trials = [np.sort(np.append(layout[layout != out], new)) for out in removable]
        errors = local_error(problem).rmse_many(trials)
        best = int(np.argmin(errors))
        label = (lambda p: problem.labels[p] if problem.labels else str(p))
        notes.append(f"region cover: {name} had no layout marker and {label(new)} moves "
                     f"{moving.max():.1f} mm on its own; it replaces {label(removable[best])}")
        layout = trials[best]
    return layout, notes


__all__ = ["cover_regions", "own_motion", "OWN_MOTION_MM", "MAX_EXPLAINED"]
