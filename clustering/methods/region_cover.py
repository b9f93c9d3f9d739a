"""Region cover: a facial region that moves on its own keeps a marker of its own, on each side.

The paper's rule clusters each region separately, so every region has a representative. A layout
chosen over the whole face (the hybrid) may leave a region without one; that is harmless where
the region's markers follow their neighbours (their motion is the neighbours'), but not where
the region moves on its own: a blink moves the lid 6 mm and the brow and cheek markers around it
less than the capture's noise, so a layout without a lid marker cannot see blinks at all (the
identity actor's 20-marker layout: retarget's eyeBlink r 0.00). Such a region-side gets the
marker that moves most on its own, in place of the layout marker whose loss the local error
(:mod:`.local_fit`, the hybrid's own judge) feels least. It is the hybrid's last step
(:func:`~.hybrid.hybrid_layout`), so every caller of the method (``cluster``, ``compare``,
several actors, ``batch``) gets the same layout.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from .local_fit import local_error
from .problem import LayoutProblem, problem_regions, problem_sides

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


@dataclass(frozen=True)
class CoverSwap:
    """One swap of the region cover: ``added`` (a point moving ``own_motion_mm`` on its own in the
    region-side ``region``) in place of ``replaced``."""

    region: str
    added: int
    replaced: int
    own_motion_mm: float

    def as_dict(self, labels: tuple[str, ...]) -> dict[str, object]:
        """For layout.json's parameters: the region-side, both markers' labels and the motion (mm)."""
        name = (lambda p: labels[p] if labels else str(p))
        return {"region": self.region, "added": name(self.added), "replaced": name(self.replaced),
                "own_motion_mm": round(self.own_motion_mm, 1)}

    def note(self, labels: tuple[str, ...]) -> str:
        d = self.as_dict(labels)
        return (f"region cover: {self.region} had no layout marker and {d['added']} moves "
                f"{self.own_motion_mm:.1f} mm on its own; it replaces {d['replaced']}")


def region_groups(problem: LayoutProblem) -> dict[str, np.ndarray]:
    """{"<region> (L)": point indices, "<region> (R)": ...}: each region's points on that side,
    midline included (:func:`~.problem.problem_regions`, :func:`~.problem.problem_sides`)."""
    sides = np.array(problem_sides(problem))
    return {f"{name} ({side})": idx[np.isin(sides[idx], (side, "C"))]
            for name, idx in problem_regions(problem).items() for side in ("L", "R")}


def cover_regions(problem: LayoutProblem, layout: np.ndarray, groups: Mapping[str, np.ndarray]
                  ) -> tuple[np.ndarray, list[CoverSwap]]:
    """``layout`` (sorted point indices) with a marker in every group (e.g. :func:`region_groups`)
    that has none and holds a point moving on its own ≥ ``OWN_MOTION_MM``.

    That point (the one moving most on its own) replaces the layout marker whose loss raises the
    local error least, never the only marker of another group. Returns the layout (same size,
    sorted) and the swaps made."""
    layout = np.sort(np.asarray(layout, dtype=np.intp))
    swaps: list[CoverSwap] = []
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
        swaps.append(CoverSwap(name, new, removable[best], float(moving.max())))
        layout = trials[best]
    return layout, swaps


__all__ = ["CoverSwap", "cover_regions", "own_motion", "region_groups", "OWN_MOTION_MM", "MAX_EXPLAINED"]
