"""Is a session a face in millimetres? Checks of the input before it is clustered.

Two checks on the neutral pose and the labels:

- **units**: a face is 100–250 mm across (the largest extent of the neutral markers, strays left
  out). Outside that, a warning names the unit (m, cm, mm, in) that would make it face-sized, or the
  number of mm per file unit (``--units N``) when none does (e.g. Blender units).
- **not a face**: a full-body or limb capture: it spans more than 600 mm, or its labels are
  body-marker names (LASI, RKNE, Foot_Marker1, genou...) rather than facial ones.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mocaptk.errors import MocaptkError
from mocaptk.trajectories import Trajectories

#: Largest extent of a face's neutral markers (mm): forehead to chin, or ear to ear.
FACE_SPAN_MM = (100.0, 250.0)
#: No face, in any units the file declares, spans more than this (mm): a body or a room.
BODY_SPAN_MM = 600.0
#: Length units a marker file is commonly in, mm per unit (a face-sized reading is looked for).
CANDIDATE_UNITS = {"m": 1000.0, "cm": 10.0, "mm": 1.0, "in": 25.4}

_BODY_WORDS = frozenset("""
shoulder should sho elbow elb wrist wra wrb hand finger fin pala palm hip pelvis asis asi psis psi
sacrum sacr thigh thi knee kne shank tib tibia ankle ank heel hee toe foot feet leg met femur
trochanter malleolus epicondyle acromion acro clav clavicle strn sternum ster xiph xiphoid spine bak
upa frm forearm arm radius ulna epaule coude poignet main doigt hanche bassin genou cheville talon
orteil pied cuisse jambe bras thorax
""".split())
_FACE_WORDS = frozenset("""
forehead brow eyebrow eye lid eyelid nose nostril nasal nasion cheek mouth lip lips chin jaw temple
glabella philtrum smile face ear sourcil front oeil nez joue bouche levre menton
""".split())


@dataclass(frozen=True)
class FaceCheck:
    """Outcome of :func:`check_face`: the measured span and what is wrong, if anything."""

    span_mm: float  # largest extent of the neutral pose (NaN when too few markers to tell)
    units_warning: str | None  # the face is not 100-250 mm across: which units would make it so
    not_a_face: str | None  # why the session is not a face capture (None: it may be one)


def face_span(neutral: np.ndarray) -> float:
    """Largest principal extent (mm) of neutral positions ``(M, 3)``, markers farther than 3x the
    median distance from the median point (strays, a calibration wand) left out; NaN if < 3 markers."""
    pts = neutral[np.isfinite(neutral).all(axis=1)]
    if len(pts) < 3:
        return float("nan")
    with np.errstate(over="ignore", invalid="ignore"):
        distance = np.linalg.norm(pts - np.median(pts, axis=0), axis=1)
        keep = distance <= 3 * np.median(distance) if np.median(distance) > 0 else np.ones(len(pts), bool)
        pts = pts[keep] - pts[keep].mean(axis=0)
        if len(pts) < 3 or not np.isfinite(pts).all():
            return float("inf")
        _, _, vt = np.linalg.svd(pts, full_matrices=False)
        return float(np.ptp(pts @ vt[0]))


def _tokens(label: str) -> set[str]:
    """Lower-case word candidates of a label: ``R.Shoulder`` -> shoulder; ``LKNE`` -> kne; ``ASISr`` -> asis."""
    words = re.split(r"[^A-Za-z0-9]+|(?<=[a-z])(?=[A-Z])", label.split(":")[-1])
    out = set()
    for word in filter(None, words):
        word = word.lower()
        if re.fullmatch(r"[ct]\d{1,2}", word):  # spine levels: C7, T10
            out.add("spine")
        alpha = word.rstrip("0123456789")
        if len(alpha) < 3:
            continue
        out.add(alpha)
        if alpha[0] in "lr":
            out.add(alpha[1:])
        if alpha[-1] in "lr":
            out.add(alpha[:-1])
    return out


def body_labels(labels: Sequence[str]) -> tuple[list[str], int]:
    """Labels naming body landmarks, and the number naming facial ones."""
    body, face = [], 0
    for label in labels:
        tokens = _tokens(label)
        if tokens & _FACE_WORDS:
            face += 1
        elif tokens & _BODY_WORDS:
            body.append(label)
    return body, face


def units_advice(span_mm: float, *, mm_per_file_unit: float, units: str, assumed: bool,
                 text_file: bool) -> str | None:
    """A warning when ``span_mm`` is no face size, naming the units that would make it one."""
    low, high = FACE_SPAN_MM
    if not np.isfinite(span_mm) or low <= span_mm <= high or span_mm > BODY_SPAN_MM:
        return None
    file_span = span_mm / mm_per_file_unit
    read = f"read as {units}{', assumed' if assumed else ''}"
    head = (f"the face spans {span_mm:.3g} mm ({read}), but a face is {low:.0f}-{high:.0f} mm across "
            "(unless the markers cover only part of it)")
    fits = [u for u, mm in CANDIDATE_UNITS.items() if low <= file_span * mm <= high and u != units]
    if fits:
        fix = f"give --units {fits[0]}" if text_file else f"although the file declares {units}"
        return f"{head}: the file is probably in {fits[0]} ({fix})"
    if not text_file:
        return f"{head}; no unit among {', '.join(CANDIDATE_UNITS)} makes it face-sized"
    return (f"{head}; no unit among {', '.join(CANDIDATE_UNITS)} makes it face-sized: give the mm per file "
            f"unit, --units N (here N = {low / file_span:.3g} to {high / file_span:.3g})")


def check_face(labels: Sequence[str], neutral: np.ndarray, *, mm_per_file_unit: float = 1.0,
               units: str = "mm", assumed: bool = False, text_file: bool = True) -> FaceCheck:
    """Check that neutral positions ``(M, 3)`` mm with ``labels`` look like a face in mm.

    ``mm_per_file_unit``/``units``/``assumed``: how the reader converted the file (for the advice);
    ``text_file``: the units can be overridden with ``--units`` (not for C3D).
    """
    span = face_span(neutral)
    reasons = []
    if span > BODY_SPAN_MM:
        reasons.append(f"it spans {span / 1000:.3g} m (a face is {FACE_SPAN_MM[0]:.0f}-{FACE_SPAN_MM[1]:.0f} mm)")
    body, face = body_labels(labels)
    if len(body) >= max(3, 0.25 * len(labels)) and len(body) > face:
        reasons.append(f"{len(body)} of its {len(labels)} labels name body landmarks ({', '.join(body[:4])}"
                       + (", ..." if len(body) > 4 else "") + ")")
    advice = None if reasons else units_advice(span, mm_per_file_unit=mm_per_file_unit, units=units,
                                                assumed=assumed, text_file=text_file)
    return FaceCheck(span, advice, "; ".join(reasons) or None)


def check_session(traj: Trajectories, *, neutral: np.ndarray | None = None) -> FaceCheck:
    """:func:`check_face` of a session as read (its neutral pose, ``neutral`` (markers, 3) mm
    when the caller has it; units from its metadata)."""
    from mocaptk.acquisition.text_io import mm_per_unit
    from .neutral import neutral_pose

    meta = traj.metadata
    units = str(meta.get("original_units") or "mm")
    try:
        scale = mm_per_unit(units)
    except MocaptkError:  # "mixed" units of a Vicon CSV: no advice in file units
        scale = 1.0
    if neutral is None:
        with np.errstate(all="ignore"):
            neutral = neutral_pose(traj.positions)
    return check_face(traj.labels, neutral, mm_per_file_unit=scale, units=units,
                      assumed=bool(meta.get("units_assumed")),
                      text_file=meta.get("format") in ("trc", "vicon_csv", "generic_csv"))
