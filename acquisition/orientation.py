"""Which way a face capture looks: up, forward and the actor's left from the geometry.

A file's axes are the capture volume's (Y or Z up, upside down, any yaw), and its L/R labels may
name the viewer's side (blenderFace: ``CL7`` is on the viewer's left). The face itself says
which way it is turned:

- forward: the face is a cap bulging towards the viewer; its rim (forehead top, cheeks, jaw
  line) lies behind its centre (:func:`mocaptk.surface_mesh.front_direction`);
- up, as a line: the largest spread of the neutral markers (faces are taller than wide);
- up, as a sign, two votes: the jaw and mouth move more than the forehead (motion: each marker's
  median distance from its neutral position, which a few glitches or a turn of the head do not
  set as they set the largest), and the face is wider at the brows and eyes than at the chin
  (shape);
- the actor's left: up × forward (a right-handed world), never the labels.

The labels' sides are used only where they agree with the geometry, or to decide up when the
geometric votes are weak (none clear, or cancelling out); when the geometry is clear and they
contradict it, the caller warns (:func:`labels_warning`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocaptk.surface_mesh import front_direction

_SIDE_TAG = re.compile(r"_([LRCM])$")

#: The geometry overrules the labels' sides only with a clear vote (|vote| >= CLEAR_VOTE, each
#: in -1..1) and a sum of at least UNDECIDED_SCORE; else the labels decide up.
UNDECIDED_SCORE = 0.15
CLEAR_VOTE = 0.3
#: Fraction of the height taken as the top and the bottom band for the width vote.
BAND = 1.0 / 3.0
#: A face's taper (top band 10-13 % wider than the bottom one: blenderFace, synth) counts like a
#: clear motion correlation (~0.5): the motion vote alone turned blenderFace Subject_02 upside
#: down once stabilized (its detected rigid set holds mouth markers).
SHAPE_WEIGHT = 4.0


def side_tag(label: str) -> str | None:
    """``"L"``, ``"R"`` or ``"C"`` from a label's ``_L`` / ``_R`` / ``_C`` (or ``_M``) suffix, else None."""
    match = _SIDE_TAG.search(label)
    if match is None:
        return None
    return "C" if match.group(1) in "CM" else match.group(1)


def mirror_label(label: str) -> str:
    """Label of the mirror image: ``_L`` ↔ ``_R``; untagged labels get ``_mirror``."""
    tag = side_tag(label)
    if tag in ("L", "R"):
        return label[:-1] + ("R" if tag == "L" else "L")
    return f"{label}_mirror"


def label_pairs(labels: Sequence[str]) -> list[tuple[int, int]]:
    """Mirror pairs named by the labels: ``(left index, right index)`` for labels equal but for one
    ``L`` ↔ ``R`` (``CL4``/``CR4``, ``MOUTH_03_L``/``MOUTH_03_R``, ``LEyeOuter``/``REyeOuter``)."""
    index = {label: i for i, label in enumerate(labels)}
    pairs = []
    for i, label in enumerate(labels):
        for k, char in enumerate(label):
            if char in "Ll":
                partner = index.get(label[:k] + ("R" if char == "L" else "r") + label[k + 1:])
                if partner is not None:
                    pairs.append((i, partner))
                    break
    return pairs


@dataclass(frozen=True)
class Orientation:
    """The face's axes in file coordinates and how the labels relate to them.

    ``frame`` (3, 3): rows the actor's left, up, forward (unit, right-handed);
    ``up_votes``: motion and shape votes for up (each -1..1, positive = agrees with ``frame``);
    ``labels``: ``"agree"``, ``"contradict"`` (their L is the actor's right), ``"decided"``
    (the geometry could not tell up from down; the labels' sides chose) or ``"none"`` (no sides).
    """

    frame: np.ndarray
    up_votes: dict[str, float]
    labels: str

    def as_dict(self) -> dict[str, Any]:
        """For layout.json: ``frame`` rows, the votes and the labels' verdict."""
        return {"frame": [[float(x) for x in row] for row in self.frame],
                "up_votes": {k: float(v) for k, v in self.up_votes.items()}, "labels": self.labels}


def face_axes(neutral: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Rows lateral (actor's left), up, forward of the neutral pose ``(M, 3)`` mm (finite rows),
    from the geometry alone, and the up votes (see the module docstring).

    ``motion`` (M,) or (M, K) mm: how far each marker moves from its neutral position, one column
    per statistic (:func:`marker_motion`; zeros: the shape vote alone decides).
    """
    pts = neutral - neutral.mean(axis=0)
    # full only for < 3 markers (3 axes even then): a full U is (M, M), 0.8 GB at 10,000 markers
    _, _, vt = np.linalg.svd(pts, full_matrices=len(pts) < 3)
    up = vt[0]
    forward = front_direction(neutral) if len(pts) >= 3 else vt[2]
    votes = up_votes(pts @ up, pts @ vt[1], motion)
    if sum(votes.values()) < 0:
        up, votes = -up, {k: -v for k, v in votes.items()}
    return np.array([np.cross(up, forward), up, forward]), votes


def up_votes(height: np.ndarray, width: np.ndarray, motion: np.ndarray) -> dict[str, float]:
    """Votes (each -1..1, positive: ``height`` grows upwards) from markers' heights and lateral
    positions (M,) mm and their motion (M,) or (M, K) mm.

    motion: minus the correlation of height and motion (the lower face moves more), averaged
    over the motion's columns; shape: :data:`SHAPE_WEIGHT` x the relative difference of the top
    and bottom bands' lateral spread (the face narrows to the chin), clipped to -1..1.
    """
    columns = np.asarray(motion, dtype=float).reshape(len(height), -1).T
    moved = [-float(np.corrcoef(height, m)[0, 1]) for m in columns if np.ptp(m) > 0 and np.ptp(height) > 0]
    motion = float(np.mean(moved)) if moved else 0.0
    shape = 0.0
    low, high = np.quantile(height, [BAND, 1.0 - BAND])
    top, bottom = width[height >= high], width[height <= low]
    if top.size >= 2 and bottom.size >= 2:
        spread = float(np.ptp(top) + np.ptp(bottom))
        shape = float(np.ptp(top) - np.ptp(bottom)) / spread if spread > 0 else 0.0
    return {"motion": motion, "shape": float(np.clip(SHAPE_WEIGHT * shape, -1.0, 1.0))}


def labelled_left(labels: Sequence[str], neutral: np.ndarray) -> np.ndarray | None:
    """Direction (3,) towards the markers the labels call left: over the mirror pairs
    (:func:`label_pairs`) the sum of L − R, else the ``_L``-tagged markers' centre minus the
    ``_R`` ones' (or the ``_C`` midline's for a half face); None when the labels name no side."""
    ok = np.isfinite(neutral).all(axis=1)
    pairs = [(i, j) for i, j in label_pairs(labels) if ok[i] and ok[j]]
    if pairs:
        direction = (neutral[[i for i, _ in pairs]] - neutral[[j for _, j in pairs]]).sum(axis=0)
    else:
        tags = np.array([side_tag(label) or "" for label in labels])
        centres = {t: neutral[(tags == t) & ok].mean(axis=0) for t in "LRC" if ((tags == t) & ok).any()}
        if "L" in centres:
            direction = centres["L"] - centres.get("R", centres.get("C", centres["L"]))
        elif "R" in centres and "C" in centres:
            direction = centres["C"] - centres["R"]
        else:
            return None
    norm = float(np.linalg.norm(direction))
    return direction / norm if norm > 0 else None


#: Frames :func:`marker_motion` looks at, at most (evenly spread).
MOTION_FRAMES = 2000


def marker_motion(positions: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Each marker's median and largest distance (M, 2) mm from its ``neutral`` position (M, 3)
    over the frames of ``positions`` (F, M, 3) mm (at most :data:`MOTION_FRAMES` of them, evenly
    spread; gaps ignored; 0 for a marker never seen)."""
    step = max(1, -(-positions.shape[0] // MOTION_FRAMES))
    distance = np.linalg.norm(positions[::step] - neutral, axis=2)
    seen = np.isfinite(distance).any(axis=0)
    motion = np.zeros((distance.shape[1], 2))
    motion[seen, 0] = np.nanmedian(distance[:, seen], axis=0)
    motion[seen, 1] = np.nanmax(distance[:, seen], axis=0)
    return motion


def infer_orientation(labels: Sequence[str], neutral: np.ndarray, motion: np.ndarray) -> Orientation:
    """The face's :class:`Orientation` from its neutral pose ``(M, 3)`` mm, each marker's motion
    ``(M,)`` or ``(M, K)`` mm (:func:`marker_motion`) and their labels (rows with NaN are ignored)."""
    neutral = np.asarray(neutral, dtype=float)
    motion = np.asarray(motion, dtype=float).reshape(len(neutral), -1)
    ok = np.isfinite(neutral).all(axis=1) & np.isfinite(motion).all(axis=1)
    frame, votes = face_axes(neutral[ok], motion[ok])
    said = labelled_left(labels, neutral)
    if said is None or abs(float(said @ frame[0])) < 1e-9:
        return Orientation(frame, votes, "none")
    if said @ frame[0] > 0:
        return Orientation(frame, votes, "agree")
    clear = max(abs(v) for v in votes.values()) >= CLEAR_VOTE
    if abs(sum(votes.values())) < UNDECIDED_SCORE or not clear:  # up and down look alike: the labels turn it
        return Orientation(np.array([-frame[0], -frame[1], frame[2]]),
                           {k: -v for k, v in votes.items()}, "decided")
    return Orientation(frame, votes, "contradict")


def labels_warning(orientation: Orientation) -> str | None:
    """The warning for labels whose L is the actor's right by the geometry, else None."""
    if orientation.labels != "contradict":
        return None
    votes = ", ".join(f"{k} {v:+.2f}" for k, v in orientation.up_votes.items())
    return ("the labels' L/R contradict the face's geometry (up and forward from its shape and motion: "
            f"{votes}; the actor's left = up x forward): their L is the actor's right, as a viewer "
            "facing the actor sees it; sides are taken from the geometry")
