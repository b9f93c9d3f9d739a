"""End-to-end error of a layout: capture a performance through a rig with only the layout's markers,
reconstruct the dense face, score it against the truth.

The capture is :func:`mocaptk.acquisition.synth_session.capture_points` (projection with
back-facing and field-of-view occlusion, detection noise, dropouts, ghosts, robust triangulation,
spike removal), then gaps up to ``max_gap`` frames filled as capture software does. The dense face
is the evaluation's ridge reconstruction (:func:`~mocaptk.clustering.reconstruction_models.fit_reconstruction`)
fitted on the training session's gap-free frames; a frame's missing layout markers are left out
of its prediction (models per presence pattern), present ones are copied. The score is the RMS
distance (mm) from the true dense markers over every frame and marker.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mocaptk.acquisition.cameras import CameraRig
from mocaptk.trajectories import Trajectories

from .reconstruction_models import fit_reconstruction


def capture_layout(rig: CameraRig, truth: np.ndarray, normals: np.ndarray, layout: Sequence[int], *,
                   noise_mm: float = 0.3, dropout: float = 0.01, ghost_rate: float = 0.002,
                   seed: int = 0, max_gap: int = 6) -> np.ndarray:
    """The layout markers of ``truth`` (F, N, 3) mm with outward ``normals`` (F, N, 3) as the rig
    delivers them: ``(F, L, 3)`` mm, NaN where lost. Detection noise is ``noise_mm`` in px for the
    whole face (as ``mocaptk synth``), so every layout sees the same pixel noise."""
    from mocaptk.acquisition.gapfill import fill_gaps
    from mocaptk.acquisition.synth_session import capture_points, detection_noise_px

    layout = np.asarray(layout, dtype=np.intp)
    # synth's marker_normals gives normals per frame block, (start, stop) -> (frames, N, 3)
    layout_normals = ((lambda a, b: normals(a, b)[:, layout]) if callable(normals)
                      else normals[:, layout])
    traj = capture_points(rig, truth[:, layout], layout_normals,
                          pixel_noise=detection_noise_px(rig, truth, noise_mm),
                          labels=[f"L{i:03d}" for i in range(layout.size)], rate=rig.rate or 60.0,
                          dropout=dropout, ghost_rate=ghost_rate, seed=seed)
    if max_gap > 0:
        traj, _ = fill_gaps(Trajectories(traj.positions, traj.labels, traj.rate), max_gap=max_gap,
                            method="cubic")
    return traj.positions


def end_to_end_errors(train: np.ndarray, layout: Sequence[int], captured: np.ndarray,
                      truth: np.ndarray) -> np.ndarray:
    """Per-point error ``(F, N)`` mm of the dense face reconstructed from ``captured`` (F, L, 3) mm
    (:func:`capture_layout`) by the ridge fitted on the gap-free frames of ``train`` (F', N, 3) mm,
    against ``truth`` (F, N, 3) mm; NaN in frames where no layout marker was captured."""
    train = np.asarray(train, dtype=np.float64)
    complete = np.isfinite(train).all(axis=(1, 2))
    model = fit_reconstruction(train[complete] if complete.sum() >= 10 else train, layout)
    predicted = model.predict_positions(np.asarray(captured, dtype=np.float64))
    return np.linalg.norm(predicted - truth, axis=2)


def rmse(errors: np.ndarray) -> float:
    """RMS (mm) of the finite errors."""
    finite = errors[np.isfinite(errors)]
    return float(np.sqrt(np.mean(finite ** 2))) if finite.size else float("nan")
