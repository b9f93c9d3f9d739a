"""Robust multi-view triangulation of labelled 2-D detections, one compiled pass over all points.

One numba kernel (:mod:`.triangulate_kernel`, imported on first use; compiled once, cached
on disk; run on threads over ranges of points) does per point: undistort every view (OpenCV's
fixed-point iteration), solve the DLT normal equations in closed form (3x3), reweight the rows by focal
/ depth so the algebraic error becomes the reprojection error in px (a Gauss-Newton-like
refinement), and check every view's reprojection error. A point seen by 4 or more cameras
whose views disagree is first refit without its worst view, and is done when the other views
all agree. Otherwise it gets a consensus search: every camera pair that sees the point
proposes a two-view point, the proposal with most views within ``outlier_threshold_px`` wins
(ties: smallest summed error), the point is refit on those views and views that agree with
the refit join in (not aniposelib's exhaustive subset loop).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import numpy as np

from mocaptk.threads import machine_workers, worker_threads
from mocaptk.trajectories import Trajectories

from .cameras import CameraRig

# Chunks of the kernel per task of a thread (8 x 512 points).
_TASK_CHUNKS = 8


def triangulate(rig: CameraRig, observations: np.ndarray, *, labels: Sequence[str] | None = None,
                rate: float | None = None, min_views: int = 2,
                outlier_threshold_px: float = 4.0, refine_iterations: int = 1) -> Trajectories:
    """Triangulate labelled 2-D detections of all cameras into marker trajectories.

    Parameters
    ----------
    rig : CameraRig with C cameras.
    observations : (C, F, M, 2) float, px; NaN where a camera did not see a marker.
    labels : M marker labels (default ``M001``, ``M002``, ...).
    rate : frame rate in Hz (default: the rig's rate, else 60).
    min_views : a point needs at least this many agreeing views (>= 2), else it is a gap.
    outlier_threshold_px : a view whose reprojection error exceeds this is an outlier.
    refine_iterations : reweighting steps after each linear fit (0: plain DLT).

    Returns
    -------
    Trajectories
        ``positions (F, M, 3)`` mm; ``residuals (F, M)`` = RMS reprojection error over the
        inlier views in px (distorted image, as detected); ``metadata["view_counts"]``
        ``(F, M)`` int = number of inlier views used; ``metadata["camera_names"]``.
    """
    observations = np.asarray(observations, dtype=np.float64)
    if observations.ndim != 4 or observations.shape[-1] != 2:
        raise ValueError(f"observations must have shape (cameras, frames, markers, 2), "
                         f"got {observations.shape}")
    if observations.shape[0] != len(rig):
        raise ValueError(f"observations have {observations.shape[0]} cameras, "
                         f"the rig has {len(rig)}")
    _, n_frames, n_markers, _ = observations.shape
    if labels is None:
        labels = [f"M{m + 1:03d}" for m in range(n_markers)]
    points, inliers, residuals = _triangulate(
        rig, observations.reshape(len(rig), -1, 2), min_views=min_views,
        outlier_threshold_px=outlier_threshold_px, refine_iterations=refine_iterations)
    rate = rate if rate is not None else (rig.rate or 60.0)
    return Trajectories(
        positions=points.reshape(n_frames, n_markers, 3), labels=labels, rate=rate,
        residuals=residuals.reshape(n_frames, n_markers),
        metadata={"view_counts": inliers.sum(axis=0).reshape(n_frames, n_markers),
                  "camera_names": rig.names})


def triangulate_points(rig: CameraRig, observations: np.ndarray, *, min_views: int = 2,
                       outlier_threshold_px: float = 4.0, refine_iterations: int = 1,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Robust triangulation of P points from ``observations (C, P, 2)`` px.

    Returns ``points (P, 3)`` mm (NaN with fewer than ``min_views`` agreeing views) and the
    inlier views ``(C, P)`` bool.
    """
    points, inliers, _ = _triangulate(rig, np.asarray(observations, dtype=np.float64),
                                      min_views=min_views,
                                      outlier_threshold_px=outlier_threshold_px,
                                      refine_iterations=refine_iterations)
    return points, inliers


def _triangulate(rig: CameraRig, observations: np.ndarray, *, min_views: int,
                 outlier_threshold_px: float, refine_iterations: int,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check the options, run the kernel: ``points (P, 3)`` mm, ``inliers (C, P)`` bool and
    the RMS reprojection error ``(P,)`` px over the inliers (NaN where none)."""
    if min_views < 2:
        raise ValueError(f"min_views must be >= 2, got {min_views}")
    if not outlier_threshold_px > 0:
        raise ValueError(f"outlier_threshold_px must be > 0, got {outlier_threshold_px}")
    if refine_iterations < 0:
        raise ValueError(f"refine_iterations must be >= 0, got {refine_iterations}")
    if observations.ndim != 3 or observations.shape[-1] != 2 or observations.shape[0] != len(rig):
        raise ValueError(f"observations must have shape ({len(rig)}, points, 2), "
                         f"got {observations.shape}")
    cameras = _camera_table(rig)
    poses = np.stack([np.hstack([cam.rotation, cam.tvec[:, None]]) for cam in rig])
    focal = np.array([cam.focal_px for cam in rig])
    n_points = observations.shape[1]
    points = np.empty((n_points, 3))
    inliers = np.empty((len(rig), n_points), dtype=np.bool_)
    rms = np.empty(n_points)
    from .triangulate_kernel import CHUNK, triangulate_kernel  # imports numba: on first use only

    observations = np.ascontiguousarray(observations)
    n_chunks = (n_points + CHUNK - 1) // CHUNK
    # tasks of a few chunks, taken in turn by the threads (a thread slowed by other processes
    # takes fewer); each point is computed alone, so the output does not depend on who ran it
    tasks = iter([(first, min(n_chunks, first + _TASK_CHUNKS))
                  for first in range(0, n_chunks, _TASK_CHUNKS)])

    def run() -> None:
        for first, last in tasks:  # one shared iterator: next() holds the GIL
            triangulate_kernel(observations, cameras, poses, focal, int(min_views),
                               float(outlier_threshold_px), int(refine_iterations), first, last,
                               points, inliers, rms)

    import numba

    # one thread per usable CPU, at most numba's setting (NUMBA_NUM_THREADS, set_num_threads);
    # the kernel releases the GIL
    threads = min(machine_workers(), numba.get_num_threads(), -(-n_chunks // _TASK_CHUNKS))
    helpers = [worker_threads().submit(run) for _ in range(threads - 1)]
    run()
    for helper in helpers:
        helper.result()
    return points, inliers, rms


def _camera_table(rig: CameraRig) -> np.ndarray:
    """``(C, 10)`` per camera: fx fy cx cy, k1 k2 p1 p2 k3, skew ``K[0, 1]`` (px)."""
    return np.array([[*cam.matrix[[0, 1, 0, 1], [0, 1, 2, 2]], *cam.distortion,
                      cam.matrix[0, 1]] for cam in rig])


@contextmanager
def compile_notice(callback: Callable[[str], None]) -> Iterator[None]:
    """Within this context, call ``callback(message)`` once when the triangulation kernel
    starts compiling (its first use in a process with no usable numba disk cache: about ten
    seconds), so that a command line can tell the user; nothing happens when the kernel is
    loaded from the cache or already compiled. ``message`` says what is happening."""
    import sys

    from numba.core import event

    kernel = f"{__package__}.triangulate_kernel"

    class Notice(event.Listener):
        called = False

        def on_start(self, ev: event.Event) -> None:
            if ev.data["dispatcher"].py_func.__module__ == kernel and not self.called:
                self.called = True
                cached = sys.modules[f"{__package__}.compiled"].CACHED
                how_often = ("once per installation" if cached
                             else "in every process: no writable cache folder")
                callback(f"compiling the triangulation kernel ({how_often}, about ten seconds)…")

        def on_end(self, ev: event.Event) -> None:
            pass

    with event.install_listener("numba:compile", Notice()):
        yield
