"""The labelling template: a labelled session turned into a head-relative linear motion model.

The session is stabilized (rigid head fit, :func:`..stabilize.stabilize_head`); its head-relative
marker positions give the mean shape ``mean (M, 3)`` and a PCA basis ``basis (K, M, 3)`` of the
expression motion, so the labeller can predict every marker from the ones it has already
assigned. Per marker it keeps the model's residual (how well the rest predicts it), its motion
range and its nearest-neighbour distance (how far off a point may be before it is another marker).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocaptk.errors import MocaptkError, source_error
from mocaptk.trajectories import Trajectories

#: PCA modes kept: enough for this fraction of the motion variance, at most MAX_MODES.
VARIANCE_KEPT = 0.99
MAX_MODES = 16
#: Frames used to build the model (evenly spaced), bounding the cost of a long session.
MAX_FRAMES = 4000
#: Markers the pose search samples triangles from: the least-moving ones.
POSE_MARKERS = 8
#: Floor of the per-marker prediction spread (mm): marker noise and template/capture mismatch.
MIN_SIGMA_MM = 0.6


@dataclass(frozen=True, eq=False)
class LabelTemplate:
    """Everything the labeller knows about the face (head coordinates, mm).

    ``labels (M,)``; ``mean (M, 3)``; ``basis (K, M, 3)`` orthonormal PCA modes;
    ``mode_std (K,)`` their spread; ``sigma (M,)`` rms residual of each marker when the model is fitted
    to all markers (floored at :data:`MIN_SIGMA_MM`); ``motion (M,)`` rms distance from the mean;
    ``nearest (M,)`` distance to the nearest other marker of the mean shape; ``rigidity (M,)`` pose
    weights ``1 / (motion² + 1)``; ``pose_markers``: indices of the least-moving markers.
    """

    labels: tuple[str, ...]
    mean: np.ndarray
    basis: np.ndarray
    mode_std: np.ndarray
    sigma: np.ndarray
    motion: np.ndarray
    nearest: np.ndarray
    rigidity: np.ndarray
    pose_markers: np.ndarray

    @property
    def n_markers(self) -> int:
        return len(self.labels)

    @property
    def spacing(self) -> float:
        """Median nearest-neighbour distance (mm)."""
        return float(np.median(self.nearest))

    def scaled(self, factor: float) -> LabelTemplate:
        """The template of a face ``factor`` times as large (mean and motion scaled)."""
        return _finish(self.labels, self.mean * factor, self.basis, self.mode_std * factor,
                       self.sigma * factor, self.motion * factor)

    def subset(self, labels: list[str]) -> LabelTemplate:
        """The template of the markers ``labels`` only (the model refitted on them is not needed:
        the modes restricted to the subset still span its motion)."""
        lookup = {label: k for k, label in enumerate(self.labels)}
        idx = np.array([lookup[label] for label in labels])
        mean = self.mean[idx]
        return _finish(tuple(labels), mean, self.basis[:, idx], self.mode_std, self.sigma[idx], self.motion[idx])


def build_template(traj: Trajectories, *, stabilize: bool = True) -> LabelTemplate:
    """The motion model of a labelled session ``traj`` (frames, markers, 3) mm.

    Raises a one-line error naming the file when it has fewer than 4 markers with data or no
    frame with most of them.
    """
    source = traj.metadata.get("source")
    seen = ~np.isnan(traj.positions).any(axis=2)
    keep = seen.any(axis=0)
    if keep.sum() < 4:
        raise source_error(source, f"the template has {int(keep.sum())} markers with data; the labeller "
                                   "needs at least 4 labelled markers")
    traj = traj.select([label for label, k in zip(traj.labels, keep) if k])
    step = max(1, traj.n_frames // MAX_FRAMES)
    if step > 1:
        traj = traj.replace(positions=traj.positions[::step], residuals=None, metadata={})
    positions = _head_relative(traj) if stabilize else traj.positions
    seen = ~np.isnan(positions).any(axis=2)
    rows = seen.mean(axis=1) >= 0.9
    if rows.sum() < 1:
        raise source_error(source, "the template has no frame with 90 % of its markers: cannot "
                                   "build its motion model")
    mean = np.nanmean(positions, axis=0)
    filled = np.where(seen[..., None], positions, mean)[rows]  # a missing marker: its mean
    centred = (filled - mean).reshape(len(filled), -1)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    var = sv ** 2
    total = var.sum()
    k = int(np.searchsorted(np.cumsum(var) / total, VARIANCE_KEPT) + 1) if total > 0 else 0
    k = min(k, MAX_MODES, len(sv))
    basis = vt[:k].reshape(k, -1, 3)
    mode_std = sv[:k] / np.sqrt(max(len(filled) - 1, 1))
    residual = centred - (centred @ vt[:k].T) @ vt[:k]
    sigma = np.sqrt((residual.reshape(len(filled), -1, 3) ** 2).sum(axis=2).mean(axis=0))
    motion = np.sqrt((centred.reshape(len(filled), -1, 3) ** 2).sum(axis=2).mean(axis=0))
    return _finish(traj.labels, mean, basis, mode_std, sigma, motion)


def _finish(labels: tuple[str, ...], mean: np.ndarray, basis: np.ndarray, mode_std: np.ndarray,
            sigma: np.ndarray, motion: np.ndarray) -> LabelTemplate:
    d = np.linalg.norm(mean[:, None] - mean[None], axis=2)
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    rigidity = 1.0 / (motion ** 2 + 1.0)
    pose = np.argsort(motion, kind="stable")[:max(POSE_MARKERS, 3)]
    return LabelTemplate(tuple(labels), mean, basis, mode_std, np.maximum(sigma, MIN_SIGMA_MM),
                         motion, nearest, rigidity, np.sort(pose))


def _head_relative(traj: Trajectories) -> np.ndarray:
    """Positions with the head motion removed (the session's own coordinates when it cannot be)."""
    from ..stabilize import stabilize_head

    try:
        return stabilize_head(traj).trajectories.positions
    except MocaptkError:  # too few steady markers: the face model then also holds the head motion
        return traj.positions
