"""Bake captured motion onto a rig: per-frame joint tracks + the head pose on ``face_root``.

One function, :func:`bake_animation`, turns per-frame positions of the rig's marker joints
(head-relative, rig frame, mm) and optionally the head's rigid pose into a :class:`RigAnimation`
that the FBX, glTF and rig.json writers key unchanged (``mocaptk rig``/``cluster`` and
``mocaptk solve`` all go through it).

Tracks (rig frame: Y up, face looking down +Z, mm):

- a marker joint's **local translation** is its head-relative position minus the root's bind
  position (its bind local translation plus its displacement); joints never rotate;
- ``face_root`` carries the head: rotation ``A_f`` and translation ``A_f c + b_f`` (``c`` its
  bind position) where the captured head pose maps head-relative points ``y`` to the raw
  capture ``A_f y + b_f``. So the world position of every joint equals the raw, unstabilized
  marker position, and the skinned mesh moves with the head as captured.

Gaps. Missing joint positions (NaN) are filled with the session's gap filler
(:func:`~mocaptk.acquisition.gapfill.fill_gaps`: splines for short gaps, regression on the most
correlated other joints for long ones). What it cannot fill (a marker missing at the start or
end of a take, beyond ``max_gap``) holds the nearest filled value of that take, and a marker never
seen in a take stays at its bind position. Every filled frame is listed in
:attr:`RigAnimation.gaps` (method ``cubic``/``akima``/``neighbours``/``hold``/``rest``), as are
frames without a head pose (``hold``). No key is ever NaN.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mocaptk.acquisition.gapfill import GapRecord, fill_gaps
from mocaptk.acquisition.runs import true_runs
from mocaptk.trajectories import Take, Trajectories

from .rig import Rig

__all__ = ["HEAD_POSE", "RigAnimation", "bake_animation", "concatenate_animations", "continuous",
           "head_pose_between", "rotation_to_quaternion"]

#: ``GapRecord.marker`` of the gaps in the head pose.
HEAD_POSE = "head pose"
#: Longest gap (frames) filled by spline, and longest leading/trailing gap filled by neighbours.
FILL_MAX_GAP = 10


@dataclass(frozen=True, eq=False)
class RigAnimation:
    """A rig's baked motion.

    Attributes
    ----------
    joint_names : tuple of str, length J
        The rig's joints (joint 0 = the root).
    rate : float
        Frames per second of the capture.
    translations : (F, J, 3) float64
        Local translation of each joint (parent space), mm, rig frame; never NaN.
    rotations : (F, R, 4) float64
        Local rotations of the joints ``rotated`` as unit quaternions ``(x, y, z, w)``, sign
        chosen continuous from frame to frame; the other joints never rotate.
    takes : tuple of Take
        Non-overlapping frame ranges covering the animation, one animation clip each
        (FBX AnimationStack, glTF animation); frames are 0-based in this animation.
    gaps : tuple of GapRecord
        Every filled run of frames: ``marker`` is the joint's marker label (or
        :data:`HEAD_POSE`), ``method`` how it was filled.
    name : str
        What was captured (file stem), for clip names.
    rotated : tuple of int, length R
        The joints that rotate (default: the root, as :func:`bake_animation` bakes).
    parents : tuple of int, length J, optional
        Each joint's parent (-1 for the root); default every joint under joint 0.
    first_frames : tuple of int, one per take
        The capture's frame number of each take's first frame (an excerpt keeps its own);
        default: the take's start.
    """

    joint_names: tuple[str, ...]
    rate: float
    translations: np.ndarray
    rotations: np.ndarray
    takes: tuple[Take, ...]
    gaps: tuple[GapRecord, ...]
    name: str = "take"
    rotated: tuple[int, ...] = (0,)
    parents: tuple[int, ...] | None = None
    first_frames: tuple[int, ...] = ()

    def first_frame(self, take: int) -> int:
        """The capture's frame number of take ``take``'s first frame."""
        return self.first_frames[take] if self.first_frames else self.takes[take].start

    @property
    def frame_count(self) -> int:
        return int(self.translations.shape[0])

    @property
    def joint_parents(self) -> tuple[int, ...]:
        """Each joint's parent (-1 for the root)."""
        return self.parents or (-1, *([0] * (len(self.joint_names) - 1)))

    @property
    def root_rotations(self) -> np.ndarray:
        """The root's rotations (F, 4) ``(x, y, z, w)`` (identity when it does not rotate)."""
        if 0 in self.rotated:
            return self.rotations[:, self.rotated.index(0)]
        return np.tile([0.0, 0.0, 0.0, 1.0], (self.frame_count, 1))

    def world_transforms(self, frames: np.ndarray | slice = slice(None)
                         ) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (n, J, 3, 3) and positions (n, J, 3) mm of every joint at ``frames``
        (forward kinematics over :attr:`joint_parents`)."""
        from scipy.spatial.transform import Rotation

        local_t = self.translations[frames]
        n = local_t.shape[0]
        rotations = np.empty((n, len(self.joint_names), 3, 3))
        positions = np.empty((n, len(self.joint_names), 3))
        quats = self.rotations[frames]
        for joint, parent in enumerate(self.joint_parents):
            local_r = (Rotation.from_quat(quats[:, self.rotated.index(joint)]).as_matrix()
                       if joint in self.rotated else np.eye(3))
            if parent < 0:
                rotations[:, joint] = local_r
                positions[:, joint] = local_t[:, joint]
                continue
            rotations[:, joint] = rotations[:, parent] @ local_r
            positions[:, joint] = (np.einsum("fij,fj->fi", rotations[:, parent], local_t[:, joint])
                                   + positions[:, parent])
        return rotations, positions

    def check_rig(self, rig) -> None:
        """Raise ValueError unless this animation was baked for ``rig`` (same joint names)."""
        if self.joint_names != rig.joint_names:
            raise ValueError("the animation was baked for another rig (joint names differ)")

    def world_positions(self) -> np.ndarray:
        """World position (F, J, 3) mm of every joint."""
        return self.world_transforms()[1]

    def filled_frames(self) -> int:
        """Marker-frames filled before keying (head-pose gaps not counted)."""
        return sum(g.length for g in self.gaps if g.marker != HEAD_POSE)

    def report(self) -> dict[str, object]:
        """JSON-ready summary: frames, rate, takes and every filled gap."""
        return {"name": self.name, "frames": self.frame_count, "rate_hz": self.rate,
                "joints": len(self.joint_names),
                "takes": [{**t.as_dict(), "first_frame": self.first_frame(k)}
                          for k, t in enumerate(self.takes)],
                "filled_marker_frames": self.filled_frames(),
                "head_pose_frames_held": sum(g.length for g in self.gaps if g.marker == HEAD_POSE),
                "gaps": [g.as_dict() for g in self.gaps]}


def bake_animation(rig: Rig, joint_positions: np.ndarray, *, rate: float,
                   head_rotations: np.ndarray | None = None,
                   head_translations: np.ndarray | None = None,
                   takes: Sequence[Take] = (), name: str = "take",
                   max_gap: int = FILL_MAX_GAP, first_frame: int = 0) -> RigAnimation:
    """Bake marker-joint positions (and the head pose) into joint tracks.

    Parameters
    ----------
    rig : Rig
        Its joints 1..J-1 are parented to the root (joint 0), as :meth:`Rig.from_markers` makes.
    joint_positions : (F, J-1, 3) float
        Head-relative positions of the marker joints (order of ``rig.joint_names[1:]``), mm,
        rig frame; NaN where missing.
    rate : float
        Frames per second (> 0).
    head_rotations, head_translations : (F, 3, 3), (F, 3), optional
        Head pose in the rig frame: raw capture = ``R_f @ y + t_f`` for head-relative ``y``;
        NaN frames (no pose) are held from the nearest posed frame. Default: no head motion.
    takes : sequence of Take
        Clips (frames of this animation); default one clip ``name`` over every frame.
    name : str
        Clip name of the default take.
    max_gap : int
        Longest gap filled by spline (longer interior gaps: neighbour regression).
    first_frame : int
        The capture's number of frame 0 (C3D ``first_frame``: an excerpt's clips keep it).

    Raises
    ------
    ValueError
        Shapes that do not match the rig, a non-positive rate, no frames.
    """
    positions = np.asarray(joint_positions, dtype=np.float64)  # not written to: fill_gaps copies
    count = rig.joint_count
    if positions.ndim != 3 or positions.shape[1:] != (count - 1, 3) or len(positions) == 0:
        raise ValueError(f"joint_positions must have shape (F >= 1, {count - 1}, 3), "
                         f"got {positions.shape}")
    if np.any(rig.joint_parents[1:] != 0) or rig.root != 0:
        raise ValueError("bake_animation needs every marker joint parented to the root joint 0")
    if not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    frames = len(positions)
    clips = tuple(takes) or (Take(name, 0, frames),)
    labels = [m or n for m, n in zip(rig.joint_markers[1:], rig.joint_names[1:])]
    track = Trajectories(positions, labels=tuple(f"j{i}" for i in range(count - 1)), rate=rate,
                         metadata={"takes": list(clips)})
    filled, fill = fill_gaps(track, max_gap=max_gap)
    positions = filled.positions
    gaps = [GapRecord(labels[int(r.marker[1:])], r.start, r.end, r.position, r.method, r.note)
            for r in fill.filled]
    bind = np.asarray(rig.joint_positions, dtype=np.float64)
    for r in fill.unfilled:  # beyond the filler: hold the take's nearest value, else rest
        j = int(r.marker[1:])
        method = _hold(positions[:, j], r.start, r.end, fallback=bind[1 + j], position=r.position)
        gaps.append(GapRecord(labels[j], r.start, r.end, r.position, method, r.note))

    rotations = np.tile(np.eye(3), (frames, 1, 1))
    translations = np.zeros((frames, 3))
    if head_rotations is not None or head_translations is not None:
        if head_rotations is None or head_translations is None:
            raise ValueError("give both head_rotations and head_translations, or neither")
        rotations = np.array(head_rotations, dtype=np.float64).reshape(frames, 3, 3)
        translations = np.array(head_translations, dtype=np.float64).reshape(frames, 3)
        missing = ~(np.isfinite(rotations).all(axis=(1, 2)) & np.isfinite(translations).all(axis=1))
        for start, end in true_runs(missing):
            if missing.all():
                rotations[:], translations[:] = np.eye(3), 0.0
                method = "rest"
            else:
                _hold(rotations.reshape(frames, 9), start, end, fallback=np.eye(3).ravel())
                method = _hold(translations, start, end, fallback=np.zeros(3))
            gaps.append(GapRecord(HEAD_POSE, start, end, "interior", method, "no head pose"))

    root_bind = bind[0]
    local = np.empty((frames, count, 3))
    local[:, 0] = np.einsum("fij,j->fi", rotations, root_bind) + translations
    local[:, 1:] = positions - root_bind
    gaps.sort(key=lambda g: (g.marker != HEAD_POSE, g.marker, g.start))
    return RigAnimation(tuple(rig.joint_names), float(rate), local,
                        continuous(rotation_to_quaternion(rotations))[:, None], clips, tuple(gaps),
                        name, first_frames=tuple(int(first_frame) + t.start for t in clips))


def concatenate_animations(animations: Sequence[RigAnimation]) -> RigAnimation:
    """One animation playing ``animations`` (same rig, same rate) one after the other; takes and
    gaps are shifted to the combined frame numbers, clip names made unique."""
    first = animations[0]
    for other in animations[1:]:
        if (other.joint_names, other.rotated, other.parents) != (first.joint_names, first.rotated,
                                                                 first.parents):
            raise ValueError("animations of different rigs cannot be concatenated")
        if other.rate != first.rate:
            raise ValueError(f"{other.name} is at {other.rate:g} Hz, {first.name} at "
                             f"{first.rate:g} Hz: bake them into separate files")
    takes: list[Take] = []
    gaps: list[GapRecord] = []
    firsts: list[int] = []
    offset = 0
    for animation in animations:
        names = {t.name for t in takes}
        for k, take in enumerate(animation.takes):
            name = take.name if take.name not in names else f"{animation.name}_{take.name}"
            takes.append(Take(name, take.start + offset, take.end + offset, take.region))
            firsts.append(animation.first_frame(k))
        gaps += [GapRecord(g.marker, g.start + offset, g.end + offset, g.position, g.method,
                           g.note) for g in animation.gaps]
        offset += animation.frame_count
    return RigAnimation(first.joint_names, first.rate,
                        np.concatenate([a.translations for a in animations]),
                        continuous(np.concatenate([a.rotations for a in animations])),
                        tuple(takes), tuple(gaps), "+".join(a.name for a in animations),
                        first.rotated, first.parents, tuple(firsts))


def head_pose_between(raw: np.ndarray, relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid pose per frame with ``raw ≈ R_f @ relative + t_f``.

    ``raw``, ``relative`` (F, M, 3) mm: the same markers as captured and after stabilization
    (frames with fewer than 3 markers seen in both give NaN). Stabilization moves every marker
    by the same rigid transform, so the fit is exact up to rounding.
    """
    from mocaptk.acquisition.stabilize import kabsch

    seen = np.isfinite(raw).all(axis=2) & np.isfinite(relative).all(axis=2)
    return kabsch(np.nan_to_num(relative), np.nan_to_num(raw), seen.astype(float))


def rotation_to_quaternion(rotations: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotation matrices to (F, 4) unit quaternions ``(x, y, z, w)``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(rotations, dtype=np.float64)).as_quat()


def continuous(quaternions: np.ndarray) -> np.ndarray:
    """Flip quaternion signs (F, ..., 4) so consecutive keys lie in the same hemisphere (no 360°
    spins under linear interpolation); the first key has ``w >= 0``."""
    q = np.array(quaternions, dtype=np.float64)
    if len(q):
        q[0] = np.where(q[0, ..., 3:] < 0, -q[0], q[0])
    flips = np.cumsum(np.einsum("f...i,f...i->f...", q[1:], q[:-1]) < 0, axis=0) % 2
    q[1:] = np.where(flips[..., None] == 1, -q[1:], q[1:])  # relative to the first key
    return q


def _hold(track: np.ndarray, start: int, end: int, *, fallback: np.ndarray,
          position: str = "interior") -> str:
    """Fill ``track[start:end]`` (F, C) with its nearest finite frame on the take's side of the
    run (``position``: ``leading`` looks after it, ``trailing`` before it, ``whole`` nowhere);
    ``fallback`` when there is none. Returns the method name (``hold`` or ``rest``)."""
    sides = {"leading": (end,), "trailing": (start - 1,), "whole": ()}.get(position,
                                                                          (start - 1, end))
    for frame in sides:
        if 0 <= frame < len(track) and np.isfinite(track[frame]).all():
            track[start:end] = track[frame]
            return "hold"
    track[start:end] = fallback
    return "rest"
