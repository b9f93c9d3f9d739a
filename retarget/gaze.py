"""Eye gaze (yaw, pitch) from eye markers, for the Live Link columns ``LeftEye*``/``RightEye*``.

A facial marker layout has no eye markers (skin markers cannot sit on the eyeball); a capture
may still carry one point per eye that follows the gaze (a pupil/cornea marker, or an eye
tracker's gaze point exported as a marker). Such a marker is recognised by its whole label
(:func:`eye_labels`): ``PUPIL_L``, ``L_PUPIL``, ``LeftPupil``, ``IRIS_R``, ``CORNEA_L``,
``EYEBALL_R``, ``GAZE_L`` … (``pupil | iris | cornea | eyeball | gaze`` with a side tag
``L/R/Left/Right`` before or after, any case and ``_ - . `` separators). Skin markers named
``EYE_01`` are lid or socket markers and never taken.

The marker is on the front of an eyeball of radius :data:`EYE_RADIUS_MM` whose centre is fixed in
the head frame: :data:`EYE_RADIUS_MM` behind the marker's median head-relative position along the
face's forward direction (the actor looks ahead most of the time). The gaze is the direction from
that centre to the marker, in the character's axes (+X the character's left, +Y up, +Z forward):
``d = (sin yaw cos pitch, −sin pitch, cos yaw cos pitch)``, i.e. ``R = Ry(yaw)·Rx(pitch)`` as the
head's columns (yaw > 0 towards the character's left, pitch > 0 down). Roll is 0. A frame where
the marker is lost holds 0.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

__all__ = ["EYE_RADIUS_MM", "eye_labels", "gaze_angles"]

#: An adult eyeball's radius (mm; axial length ≈ 24 mm).
EYE_RADIUS_MM = 12.0
_PART = r"(?:pupil|iris|cornea|eyeball|gaze)"
_SEP = r"[_\-. ]?"
_SIDE = {"l": "left", "left": "left", "r": "right", "right": "right"}
_EYE = re.compile(rf"^(?:(?P<a>l|left|r|right){_SEP}{_PART}|{_PART}{_SEP}(?P<b>l|left|r|right))$",
                  re.IGNORECASE)


def eye_labels(labels: Sequence[str]) -> dict[str, str]:
    """``{"left": label, "right": label}`` of the eye markers among ``labels`` (the first match
    per side; a side without one is absent)."""
    found: dict[str, str] = {}
    for label in labels:
        match = _EYE.match(label)
        if match:
            found.setdefault(_SIDE[(match.group("a") or match.group("b")).lower()], label)
    return found


def gaze_angles(eye: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """(F, 2) yaw, pitch (radians) of an eye marker's head-relative positions ``eye`` (F, 3) mm
    (NaN: lost, giving 0); ``axes`` (3, 3) the character's left, up, forward as the columns, in
    the head frame."""
    eye = np.asarray(eye, dtype=np.float64)
    out = np.zeros((len(eye), 2))
    seen = np.isfinite(eye).all(axis=1)
    if not seen.any():
        return out
    left, up, forward = np.asarray(axes, dtype=np.float64).T
    centre = np.median(eye[seen], axis=0) - EYE_RADIUS_MM * forward
    d = (eye[seen] - centre) @ np.stack([left, up, forward], axis=1)  # character axes
    out[seen, 0] = np.arctan2(d[:, 0], d[:, 2])
    out[seen, 1] = np.arctan2(-d[:, 1], np.hypot(d[:, 0], d[:, 2]))
    return out
