"""Zero-phase low-pass filtering of marker trajectories (Butterworth, NaN- and take-aware)."""

from __future__ import annotations

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.trajectories import Trajectories

from .runs import take_segments, true_runs


def check_cutoff(cutoff_hz: float, *, rate: float, order: int = 4) -> None:
    """Raise :class:`OptionError` unless ``0 < cutoff_hz < rate / 2`` and ``order >= 1``."""
    nyquist = rate / 2
    if not 0 < cutoff_hz < nyquist:
        raise OptionError(f"low-pass cut-off must be between 0 and {nyquist:g} Hz "
                          f"(half the {rate:g} Hz frame rate), got {cutoff_hz:g}")
    if order < 1:
        raise OptionError(f"filter order must be >= 1, got {order}")


def lowpass(traj: Trajectories, *, cutoff_hz: float, order: int = 4) -> Trajectories:
    """Butterworth low-pass filter run forward and backward (``sosfiltfilt``: zero phase).

    Parameters
    ----------
    traj : session (frames, markers, 3) mm
    cutoff_hz : float
        Cut-off frequency in Hz, below the Nyquist frequency ``rate / 2``.
    order : int
        Filter order (the forward-backward pass doubles the effective order).

    Each run of consecutive observed frames of a marker inside one take is filtered on its own:
    gaps stay NaN and never bleed into their neighbours, take boundaries are hard cuts. Runs
    shorter than the filter's default padding are filtered with a shorter padding; single frames
    are left as they are.
    """
    from scipy.signal import butter, sosfiltfilt  # here: scipy.signal costs ~1 CPU-s to import

    check_cutoff(cutoff_hz, rate=traj.rate, order=order)
    sos = butter(order, cutoff_hz, fs=traj.rate, output="sos")
    default_pad = 3 * (2 * len(sos) + 1)
    out = traj.positions.copy()
    missing = np.isnan(out).any(axis=2)
    out[missing] = np.nan
    for s, e in take_segments(traj):
        for m in range(traj.n_markers):
            for a, b in true_runs(~missing[s:e, m]):
                if b - a < 2:
                    continue
                run = out[s + a:s + b, m]
                out[s + a:s + b, m] = sosfiltfilt(sos, run, axis=0, padlen=min(default_pad, b - a - 1))
    return traj.replace(positions=out)
