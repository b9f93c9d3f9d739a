"""Another actor (or the same one on another day): how far a capture's neutral is from the
session's, and the model moved onto the capture's neutral.

The capture's neutral offset ``δ`` (L, 3) mm is what separates its layout markers at rest from the
session's, in the head frame:

- from rest frames the user names (``--neutral``): their median minus the session neutral;
- otherwise from the whole capture: the median of every frame minus the session neutral, with the
  expression modes of the session (the principal directions holding
  :data:`EXPRESSION_VARIANCE` of its layout motion) projected out, so a performance that smiles
  or speaks more than it rests does not count as another face.

Adapting takes the capture through the scale and translation that best lay its neutral onto the
session's (no rotation: the head pose, from the stabilization markers, already orients the capture
in the session's head frame; a rotation fitted to every layout marker's neutral turns the other
face's shape and the performance's expression bias into a tilt), solves there, and brings the dense
markers back: a larger or smaller face is solved at the session actor's size. What is left of the
shape difference is carried by the model as the session actor's own motion would be. Measured
(benchmarks/bench_cross_actor.py, docs/solve.md): with the fitted rotation the adaptation raised
the error on 1 of 4 cross-actor pairs (+6 %) and gained 17-29 % on two; without it, it lowers the
error on all 4 (-7 % to -50 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Adaptation", "NeutralMismatch", "adapt_to_capture", "neutral_mismatch", "neutral_offset"]

#: Share of the session's layout-motion variance whose directions count as expression.
EXPRESSION_VARIANCE = 0.95
#: A capture whose neutral offset (RMS over layout markers) exceeds this is another face (mm) ...
MISMATCH_MM = 1.5
#: ... or whose size differs from the session's by more than this share (scale, units).
MISMATCH_SCALE = 0.04


@dataclass(frozen=True)
class Adaptation:
    """The scale and translation (mm) taking the capture's neutral onto the session's (head
    frame): ``p_session = scale · p_capture + translation``. Layout markers go in through it,
    solved dense markers come back through its inverse, so the model solves the new actor's
    expressions at the session actor's size."""

    scale: float
    translation: np.ndarray

    def to_session(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points + self.translation

    def to_capture(self, points: np.ndarray) -> np.ndarray:
        return (points - self.translation) / self.scale


@dataclass(frozen=True)
class NeutralMismatch:
    """``shift_rms_mm`` the RMS neutral offset over layout markers, ``scale`` the capture's size
    relative to the session's (similarity fit of the neutrals), ``mismatch`` either beyond its
    limit."""

    shift_rms_mm: float
    scale: float
    mismatch: bool

    def as_dict(self) -> dict:
        return {"shift_rms_mm": self.shift_rms_mm, "scale": self.scale, "mismatch": self.mismatch}


def neutral_offset(neutral: np.ndarray, cov: np.ndarray, x: np.ndarray, *,
                   rest: np.ndarray | None = None) -> np.ndarray:
    """The capture's neutral offset (L, 3) mm from the session's layout ``neutral`` (L, 3), the
    layout Gaussian's covariance ``cov`` (3L, 3L) and capture frames ``x`` (F, L, 3) mm in the head
    frame; ``rest`` frame indices the user says are at rest (then no projection)."""
    if rest is not None:
        return _median(x[rest]) - neutral
    d = (_median(x) - neutral).reshape(-1)
    seen = np.isfinite(d)
    d = np.where(seen, d, 0.0)
    values, vectors = np.linalg.eigh(cov)
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order]
    k = int(np.searchsorted(np.cumsum(values) / values.sum(), EXPRESSION_VARIANCE)) + 1
    modes = vectors[:, :k]
    d = d - modes @ (modes.T @ d)
    return np.where(seen, d, np.nan).reshape(neutral.shape)


def neutral_mismatch(neutral: np.ndarray, offset: np.ndarray) -> NeutralMismatch:
    """How far the capture's neutral (``neutral + offset``) is from the session's ``neutral``."""
    seen = np.isfinite(offset).all(axis=1) & np.isfinite(neutral).all(axis=1)
    if seen.sum() < 3:
        return NeutralMismatch(float("nan"), float("nan"), False)
    shift = float(np.sqrt(np.mean(np.sum(offset[seen] ** 2, axis=1))))
    a, b = neutral[seen], neutral[seen] + offset[seen]
    scale = float(np.sqrt(np.sum((b - b.mean(0)) ** 2) / np.sum((a - a.mean(0)) ** 2)))
    return NeutralMismatch(shift, scale, shift > MISMATCH_MM or abs(scale - 1.0) > MISMATCH_SCALE)


def adapt_to_capture(neutral: np.ndarray, offset: np.ndarray) -> Adaptation:
    """The scale (the ratio of the neutrals' RMS sizes about their centroids, as
    :func:`neutral_mismatch` measures it) and translation (centroid onto centroid), no rotation,
    taking the capture's neutral ``neutral + offset`` onto the session's layout ``neutral``
    (L, 3) mm."""
    seen = np.isfinite(offset).all(axis=1) & np.isfinite(neutral).all(axis=1)
    a, b = neutral[seen] + offset[seen], neutral[seen]
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    scale = float(np.sqrt(np.sum((b - cb) ** 2) / np.sum((a - ca) ** 2)))
    return Adaptation(scale, cb - scale * ca)


def _median(x: np.ndarray) -> np.ndarray:
    from mocaptk.clustering.neutral import neutral_pose

    return neutral_pose(x)
