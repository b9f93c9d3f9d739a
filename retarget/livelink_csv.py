"""Blendshape weights as a Live Link Face CSV (Epic's iPhone app's recording layout).

Columns: ``Timecode`` (``HH:MM:SS:FF.mmm``: frame ``FF`` within the second at the capture rate,
``mmm`` thousandths of a frame), ``BlendShapeCount`` (61: the values that follow), ARKit's 52
shapes in Apple's order (``EyeBlinkLeft`` … ``TongueOut``, the names capitalised as the app
writes them), then ``HeadYaw, HeadPitch, HeadRoll, LeftEyeYaw, LeftEyePitch, LeftEyeRoll,
RightEyeYaw, RightEyePitch, RightEyeRoll`` in radians. Weights in [0, 1]; a shape the character
does not have is 0. Values with 6 decimals, ``\\n`` line ends.
"""

from __future__ import annotations

import math

import numpy as np

from .character import ARKIT_NAMES

__all__ = ["LIVELINK_COLUMNS", "POSE_COLUMNS", "livelink_csv", "timecode", "yaw_pitch_roll"]

POSE_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
LIVELINK_COLUMNS = ("Timecode", "BlendShapeCount",
                    *(name[0].upper() + name[1:] for name in ARKIT_NAMES), *POSE_COLUMNS)


def timecode(frame: int, rate: float) -> str:
    """``HH:MM:SS:FF.mmm`` of ``frame`` (0-based) at ``rate`` Hz."""
    seconds = frame / rate
    whole = math.floor(seconds + 1e-9)
    sub = (seconds - whole) * rate
    ff = math.floor(sub + 1e-6)
    milli = min(int(round((sub - ff) * 1000)), 999)
    return f"{whole // 3600:02d}:{whole // 60 % 60:02d}:{whole % 60:02d}:{ff:02d}.{milli:03d}"


def yaw_pitch_roll(rotations: np.ndarray) -> np.ndarray:
    """(F, 3) yaw (about +Y), pitch (about +X), roll (about +Z), radians, of rotations
    (F, 3, 3) ``R = Ry(yaw) Rx(pitch) Rz(roll)`` (NaN rotations give 0)."""
    r = np.nan_to_num(np.asarray(rotations, dtype=np.float64))
    pitch = np.arcsin(np.clip(-r[:, 1, 2], -1.0, 1.0))
    yaw = np.arctan2(r[:, 0, 2], r[:, 2, 2])
    roll = np.arctan2(r[:, 1, 0], r[:, 1, 1])
    return np.stack([yaw, pitch, roll], axis=1)


def livelink_csv(arkit_weights: np.ndarray, rate: float, *, head: np.ndarray | None = None,
                 eyes: np.ndarray | None = None) -> str:
    """The CSV text for ``arkit_weights`` (F, 52) in :data:`ARKIT_NAMES` order; ``head`` (F, 3)
    and ``eyes`` (F, 6) yaw/pitch/roll in radians (default 0)."""
    n = len(arkit_weights)
    values = np.zeros((n, 61))
    values[:, :52] = np.clip(np.nan_to_num(arkit_weights), 0.0, 1.0)
    if head is not None:
        values[:, 52:55] = np.nan_to_num(head)
    if eyes is not None:
        values[:, 55:61] = np.nan_to_num(eyes)
    values[values == 0] = 0.0  # no "-0.000000"
    lines = [",".join(LIVELINK_COLUMNS)]
    body = np.char.mod("%.6f", values)
    lines += [f"{timecode(i, rate)},61," + ",".join(row) for i, row in enumerate(body)]
    return "\n".join(lines) + "\n"
