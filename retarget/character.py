"""A blendshape character to retarget onto: neutral mesh + named shape deltas, in mm, and ARKit's
52 shape names.

Names match ARKit's where they are the same up to case, ``_``/``-`` and a ``_L``/``Left`` /
``_R``/``Right`` side tag (:func:`arkit_name`); other names are kept as they are. Coordinates as
the rig's: Y up, the face looking down +Z, +X the character's left. Reading one:
:func:`mocaptk.retarget.character_files.load_character`.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["ARKIT_NAMES", "Character", "arkit_name", "ict_to_arkit"]

#: ARKit's 52 blendshapes in Apple's ``ARFaceAnchor.BlendShapeLocation`` / Live Link Face order.
ARKIT_NAMES = (
    "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
    "eyeSquintLeft", "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight",
    "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft",
    "jawRight", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
    "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft",
    "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight", "mouthRollLower", "mouthRollUpper",
    "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft",
    "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft", "browDownRight",
    "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
    "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
)
_SIDE = re.compile(r"(?:[_\-. ]?(left|right|l|r))$", re.IGNORECASE)
_ARKIT_KEYS = {}


def _key(name: str) -> str:
    """``mouthSmile_L``, ``MouthSmileLeft``, ``mouth_smile_left`` → ``mouthsmileleft``."""
    side = _SIDE.search(name)
    stem, tag = (name[:side.start()], side.group(1).lower()) if side else (name, "")
    tag = {"l": "left", "r": "right"}.get(tag, tag)
    return re.sub(r"[^a-z0-9]", "", stem.lower()) + tag


def arkit_name(name: str) -> str | None:
    """The ARKit name ``name`` stands for, or None."""
    if not _ARKIT_KEYS:
        _ARKIT_KEYS.update({_key(n): n for n in ARKIT_NAMES})
    return _ARKIT_KEYS.get(_key(name))


def ict_to_arkit(ict_names: Sequence[str], ict_deltas: np.ndarray) -> np.ndarray:
    """ICT-FaceKit's expression deltas (53, V, 3) as ARKit's 52 (52, V, 3), in
    :data:`ARKIT_NAMES` order: ``browInnerUp``/``cheekPuff`` the sum of their ``_L`` and ``_R``,
    ``tongueOut`` zero."""
    deltas = np.zeros((len(ARKIT_NAMES), *ict_deltas.shape[1:]), dtype=np.float64)
    for i, name in enumerate(ict_names):
        target = arkit_name(name) or arkit_name(name[:-2])  # browInnerUp_L → browInnerUp
        if target is None:
            raise ValueError(f"ICT shape {name!r} has no ARKit name")
        deltas[ARKIT_NAMES.index(target)] += ict_deltas[i]
    return deltas


@dataclass(frozen=True, eq=False)
class Character:
    """``vertices`` (V, 3) mm neutral, ``faces`` (T, 3) int64, ``deltas`` (S, V, 3) float32 mm
    the shapes ``names`` (S); ``source`` where it was read from."""

    vertices: np.ndarray
    faces: np.ndarray
    names: tuple[str, ...]
    deltas: np.ndarray
    source: str

    @property
    def arkit(self) -> tuple[str | None, ...]:
        """Each shape's ARKit name (None where it has none)."""
        return tuple(arkit_name(n) for n in self.names)

    def deform(self, weights: np.ndarray) -> np.ndarray:
        """Meshes (..., V, 3) mm for weights (..., S)."""
        w = np.asarray(weights, dtype=np.float32)
        return self.vertices + np.tensordot(w, self.deltas, axes=(w.ndim - 1, 0))

    def replace(self, **changes) -> Character:
        return Character(**{**self.__dict__, **changes})
