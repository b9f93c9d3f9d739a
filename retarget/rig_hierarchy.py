"""The joint hierarchy an animator opens: ``face_root`` → ``head`` → ``jaw`` → lower-face joints,
the upper-face joints and the stabilization locators under ``head``.

The product's rig is flat (one translating joint per layout marker under a root that carries the
head pose, :mod:`~mocaptk.retarget.bake`); this module turns it and its baked motion into the
hierarchy written to rig.json, rig.fbx and rig.glb **without changing the deformation** (every
joint's world position and rotation stays what it was, so the skinned mesh is the same):

- ``face_root`` (static, at the flat root's bind position) → ``head`` (same place; the head's
  rigid motion: rotation + translation) → the upper-face joints, the lid joints and one locator
  per stabilization marker (``stabilization_H1``…, the guide's squares; no weights, fixed in the
  head frame at the layout's reference);
- ``jaw`` under ``head`` at the pivot :func:`fit_jaw_pivot` estimates from the session's jaw
  opening (near the condyles), rotating per frame by :func:`jaw_rotations` (the rotation about
  the pivot that best carries the chin and lower-lip joints from their bind positions);
- the lower-face joints (chin region, and mouth-region joints below the mouth's centre) under
  ``jaw``: their local translation is their position in the jaw's frame and their local
  rotation undoes the jaw's, so their world rotation is the head's as before.

Every bind rotation is the identity (joint axes = the rig's: X the actor's left, Y up, Z forward).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .bake import RigAnimation, continuous, rotation_to_quaternion
from .rig import STABILIZATION_REGION, Rig

__all__ = ["HEAD", "JAW", "JawPivot", "RigHierarchy", "STABILIZATION_REGION", "fit_jaw_pivot",
           "hierarchical_animation", "jaw_members", "jaw_rotations", "rig_hierarchy"]

HEAD, JAW = "head", "jaw"
#: Frames whose jaw rotation (fitted with translation) is at least this fraction of the
#: session's largest fix the pivot (the open-jaw frames; small rotations carry no pivot).
PIVOT_FRAMES_FRACTION = 0.5
#: A fitted pivot is kept when it lies this far behind the chin (mm, rig Z) at least, at most
#: :data:`PIVOT_MAX_MM` from it, and above it; else the default pivot is used.
PIVOT_MIN_BEHIND_MM, PIVOT_MAX_MM = 30.0, 180.0
#: Default pivot when no opening is seen, from the jaw joints' box (height h): on the midline,
#: ``DEFAULT_UP`` h above its top and ``DEFAULT_BACK`` h behind its front - about the condyles.
DEFAULT_UP, DEFAULT_BACK = 0.5, 1.5
#: Least jaw rotation (degrees) over the session for a pivot to be fitted.
MIN_OPENING_DEG = 3.0


@dataclass(frozen=True)
class JawPivot:
    """The jaw's pivot ``position`` (3,) mm (rig frame), how it was found (``fitted`` /
    ``default``), the frames it was fitted on and the fit's RMS residual (mm)."""

    position: np.ndarray
    method: str
    frames: int
    residual_mm: float

    def as_dict(self) -> dict[str, object]:
        return {"pivot_mm": [float(v) for v in self.position], "method": self.method,
                "frames": self.frames, "residual_mm": self.residual_mm}


def jaw_members(regions: Sequence[str], positions: np.ndarray) -> np.ndarray:
    """Which joints (J,) ride the jaw: the ``chin`` region and ``mouth`` joints below the mouth's
    centre (the lower lip); without a chin region, the lowest third of the joints."""
    regions = np.asarray(regions)
    y = np.asarray(positions, dtype=float)[:, 1]
    chin, mouth = regions == "chin", regions == "mouth"
    if not chin.any():
        return y <= np.percentile(y, 100 / 3)
    below = y < y[mouth].mean() if mouth.any() else np.zeros(len(y), bool)
    return chin | (mouth & below)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations (F, 3, 3) minimizing |R a_i - b_i| per frame for points a (n, 3), b (F, n, 3)
    (no translation: both already relative to the centre of rotation)."""
    h = np.einsum("ni,fnj->fij", a, b)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("fij,fjk->fik", u, vt)))
    u[:, :, 2] *= d[:, None]
    return np.einsum("fij,fjk->fki", u, vt)


def fit_jaw_pivot(bind: np.ndarray, frames: np.ndarray, *, midline_x: float) -> JawPivot:
    """The pivot (rig frame, mm) about which the jaw joints ``bind`` (n, 3) rotate into their
    positions ``frames`` (F, n, 3) (head-relative; NaN frames skipped).

    Per frame the rigid motion ``y = R x + t`` of the joints is fitted; a rotation about ``P``
    has ``t = (I - R) P``, solved in least squares over the frames with the larger openings,
    ``P``'s X held on the midline (the hinge axis is left-right, so X is not observed). A pivot
    in front of the chin, below it or implausibly far (:data:`PIVOT_MAX_MM`), or a session
    without an opening of :data:`MIN_OPENING_DEG`, gives the default (:data:`DEFAULT_UP`,
    :data:`DEFAULT_BACK`)."""
    bind = np.asarray(bind, dtype=float)
    seen = np.isfinite(frames).all(axis=(1, 2))
    moved = np.asarray(frames, dtype=float)[seen]
    low, high = bind.min(axis=0), bind.max(axis=0)
    height = float(high[1] - low[1])
    default = np.array([midline_x, high[1] + DEFAULT_UP * height, high[2] - DEFAULT_BACK * height])
    fallback = JawPivot(default, "default", 0, float("nan"))
    if len(moved) < 3:
        return fallback
    centre = bind.mean(axis=0)
    centres = moved.mean(axis=1)
    rotations = _kabsch(bind - centre, moved - centres[:, None])
    translations = centres - np.einsum("fij,j->fi", rotations, centre)
    angles = np.degrees(np.arccos(np.clip((np.trace(rotations, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    if angles.max() < MIN_OPENING_DEG:
        return fallback
    used = angles >= PIVOT_FRAMES_FRACTION * angles.max()
    a = np.eye(3) - rotations[used]  # (f, 3, 3)
    rhs = translations[used] - a[:, :, 0] * midline_x
    yz, *_ = np.linalg.lstsq(a[:, :, 1:].reshape(-1, 2), rhs.reshape(-1), rcond=None)
    pivot = np.array([midline_x, *yz])
    residual = float(np.sqrt(np.mean((a[:, :, 1:] @ yz - rhs) ** 2)))
    chin = bind[np.argmin(bind[:, 1])]
    distance = float(np.linalg.norm(pivot - chin))
    plausible = (pivot[2] <= chin[2] - PIVOT_MIN_BEHIND_MM and pivot[1] > chin[1]
                 and distance <= PIVOT_MAX_MM)
    if not plausible:
        return JawPivot(default, "default", int(used.sum()), residual)
    return JawPivot(pivot, "fitted", int(used.sum()), residual)


def jaw_rotations(bind: np.ndarray, frames: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """Per frame the rotation (F, 3, 3) about ``pivot`` (3,) that best carries the jaw joints'
    ``bind`` (n, 3) to ``frames`` (F, n, 3) mm (gap-free: a baked animation's)."""
    return _kabsch(np.asarray(bind, float) - pivot, np.asarray(frames, float) - pivot)


@dataclass(frozen=True, eq=False)
class RigHierarchy:
    """The hierarchical ``rig`` made from a flat one: ``joint_of`` (J_flat,) the new index of
    each flat joint, ``lower`` the new indices of the joints under the jaw, the jaw's
    ``pivot``."""

    rig: Rig
    joint_of: np.ndarray
    lower: np.ndarray
    pivot: JawPivot

    def report(self) -> dict[str, object]:
        """JSON-ready summary for rig_report.json."""
        names = self.rig.joint_names
        return {"head": HEAD, "jaw": {**self.pivot.as_dict(),
                                      "children": [names[j] for j in self.lower]},
                "stabilization_locators": [n for n, r in zip(names, self.rig.joint_regions)
                                           if r == STABILIZATION_REGION]}


def rig_hierarchy(flat: Rig, *, lower: np.ndarray, pivot: JawPivot,
                  stabilization: Sequence[tuple[str, str, np.ndarray]] = ()) -> RigHierarchy:
    """The hierarchy of the flat rig ``flat`` (every joint under the root 0): ``lower`` (J - 1,)
    bool the joints after the root that ride the jaw, ``pivot`` the jaw's, ``stabilization``
    ``(marker label, side, position (3,) mm rig frame)`` of each stabilization marker (locators
    ``stabilization_H1``…, in this order). Weights are the same (re-indexed)."""
    count = flat.joint_count
    if np.any(flat.joint_parents[1:] != 0) or flat.root != 0:
        raise ValueError("rig_hierarchy needs a flat rig (every joint under joint 0)")
    lower = np.asarray(lower, bool)
    joint_of = np.concatenate([[0], np.arange(1, count) + 2])
    root = flat.joint_positions[0]
    markers = len(stabilization)
    rig = Rig(
        vertices=flat.vertices, faces=flat.faces,
        joint_names=(flat.joint_names[0], HEAD, JAW, *flat.joint_names[1:],
                     *(f"{STABILIZATION_REGION}_H{k + 1}" for k in range(markers))),
        joint_parents=np.concatenate([[-1, 0, 1], np.where(lower, 2, 1), np.ones(markers, int)]),
        joint_positions=np.vstack([root, root, pivot.position, flat.joint_positions[1:],
                                   *(np.reshape(p, (1, 3)) for _, _, p in stabilization)]),
        joint_sides=("C", "C", "C", *flat.joint_sides[1:], *(s for _, s, _ in stabilization)),
        joint_regions=("", "", "", *flat.joint_regions[1:], *([STABILIZATION_REGION] * markers)),
        joint_markers=("", "", "", *flat.joint_markers[1:], *(m for m, _, _ in stabilization)),
        weight_index=joint_of[flat.weight_index], weight_value=flat.weight_value,
        texcoords=flat.texcoords, materials=flat.materials)
    return RigHierarchy(rig, joint_of, joint_of[1:][lower], pivot)


def hierarchical_animation(hierarchy: RigHierarchy, flat: RigAnimation) -> RigAnimation:
    """``flat`` (baked on the flat rig: local translations under the root, the head pose on the
    root) keyed on the hierarchy: world joint positions and rotations unchanged, the jaw's
    rotation fitted per frame (:func:`jaw_rotations`)."""
    rig = hierarchy.rig
    joint_of = hierarchy.joint_of
    root = rig.joint_positions[0]
    frames, count = flat.frame_count, rig.joint_count
    relative = flat.translations[:, 1:] + root  # head-relative positions of the flat joints
    pivot = hierarchy.pivot.position
    lower_flat = np.flatnonzero(np.isin(joint_of[1:], hierarchy.lower))
    bind_lower = rig.joint_positions[hierarchy.lower]
    jaw = jaw_rotations(bind_lower, relative[:, lower_flat], pivot)
    local = np.empty((frames, count, 3))
    local[:, 0] = root  # face_root stays; the head moves
    local[:, 1] = flat.translations[:, 0] - root
    local[:, 2] = pivot - root
    local[:, joint_of[1:]] = relative - root
    local[:, hierarchy.lower] = np.einsum("fji,fnj->fni", jaw, relative[:, lower_flat] - pivot)
    stabilization = [j for j, r in enumerate(rig.joint_regions) if r == STABILIZATION_REGION]
    local[:, stabilization] = rig.joint_positions[stabilization] - root
    jaw_q = continuous(rotation_to_quaternion(jaw))
    inverse = jaw_q * (-1.0, -1.0, -1.0, 1.0)  # the conjugate: the jaw's rotation undone
    rotations = np.concatenate([flat.root_rotations[:, None], jaw_q[:, None],
                                np.repeat(inverse[:, None], len(hierarchy.lower), axis=1)], axis=1)
    return RigAnimation(rig.joint_names, flat.rate, local, rotations, flat.takes, flat.gaps,
                        flat.name, rotated=(1, 2, *(int(j) for j in hierarchy.lower)),
                        parents=tuple(int(p) for p in rig.joint_parents),
                        first_frames=flat.first_frames)
