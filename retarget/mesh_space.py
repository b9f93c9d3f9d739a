"""``rig --keep-mesh-space``: the rig files in the given mesh's own coordinates (issue 30).

The rig is built in the markers' frame, the mesh brought onto the actor by a similarity ``T``
(:mod:`~mocaptk.retarget.align`). Kept in the mesh's space, every point goes through ``T⁻¹``:
the mesh keeps its own size and place, the joints sit on it, and the motion is scaled to it.
A joint's local motion changes frame as ``L⁻¹ [Q, t] L`` (``L`` the scale and rotation of
``T``: rotations conjugated, translations rotated and scaled), the root's translation goes
through the whole ``T⁻¹``, so the skinned mesh is exactly ``T⁻¹`` of the
marker-frame one (joints keep identity bind rotations and no scale).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mocaptk.geometry import Similarity

from .bake import RigAnimation, continuous
from .rig import Rig

__all__ = ["animation_in_space", "inverse", "rig_in_space"]


def inverse(transform: Similarity) -> Similarity:
    """The similarity undoing ``transform``."""
    back = transform.rotation.T / transform.scale
    return Similarity(1.0 / transform.scale, transform.rotation.T, -back @ transform.translation)


def rig_in_space(rig: Rig, transform: Similarity) -> Rig:
    """``rig`` with its vertices and bind joint positions moved by ``transform`` (mm)."""
    return replace(rig, vertices=transform.apply(rig.vertices),
                   joint_positions=transform.apply(rig.joint_positions))


def animation_in_space(animation: RigAnimation, transform: Similarity) -> RigAnimation:
    """``animation`` (local translations mm, rotations ``(x, y, z, w)``) for its rig moved by
    ``transform`` (:func:`rig_in_space`)."""
    from scipy.spatial.transform import Rotation

    roots = np.array(animation.joint_parents) < 0
    translations = transform.scale * animation.translations @ transform.rotation.T
    translations[:, roots] += transform.translation
    rotations = animation.rotations
    if rotations.size:  # each rotation seen from the new frame: turn Q turn⁻¹
        turn = Rotation.from_matrix(transform.rotation)
        moved = turn * Rotation.from_quat(rotations.reshape(-1, 4)) * turn.inv()
        rotations = continuous(moved.as_quat().reshape(rotations.shape))
    return replace(animation, translations=translations, rotations=rotations)
