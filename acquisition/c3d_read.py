"""Read C3D files into :class:`mocaptk.Trajectories` (millimetres, NaN gaps).

Every file is first checked by our own header/parameter parser (:mod:`.c3d_raw`): a malformed
file is refused with an :class:`InputFileError`, and the declared point data must fit in the file
(so memory is bounded by the file size). Point values are then read by our numpy reader
(:func:`.c3d_raw.read_points`), which reads every file the check accepts (any processor,
integer or float storage, any frame count); ezc3d in a guarded child process
(:mod:`.c3d_ezc3d`) is the fallback should it ever fail, and can be asked for with
``reader="ezc3d"`` (cross-checks). ``metadata["reader"]`` says which one supplied the points.
Labels, units, rate and metadata always come from the checked parameter section.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.errors import InputFileError, MocaptkError
from mocaptk.trajectories import Take, Trajectories

from . import c3d_ezc3d, c3d_raw
from .c3d_raw import C3DStructure

#: POINT:UNITS spellings -> millimetres per unit (matched on the lower-cased, stripped text).
UNIT_SCALES = {"mm": 1.0, "millimeter": 1.0, "millimeters": 1.0, "millimetre": 1.0,
               "millimetres": 1.0, "cm": 10.0, "centimeter": 10.0, "centimeters": 10.0,
               "centimetre": 10.0, "centimetres": 10.0, "m": 1000.0, "meter": 1000.0,
               "meters": 1000.0, "metre": 1000.0, "metres": 1000.0, "mete": 1000.0}
#: Parameter group in which :func:`.c3d_write.write_c3d` stores takes.
TAKES_GROUP = "MOCAPTK"
EZC3D_MAX_FRAMES = 0xFFFF
#: ezc3d 1.7 reads POINT:USED as signed: from 32,768 points it fails (vector::_M_default_append).
EZC3D_MAX_POINTS = 0x7FFF


def read_c3d(path: str | os.PathLike[str], *, strip_prefixes: bool = False,
             reader: str = "mocaptk", model_outputs: bool = True) -> Trajectories:
    """Read the 3-D points of a C3D file.

    Parameters
    ----------
    path : path of a ``.c3d`` file (any processor type, integer or float storage).
    strip_prefixes : drop ``Subject:`` label prefixes (the subjects stay in the metadata).
    reader : ``"mocaptk"`` (our numpy reader, ezc3d if it fails) or ``"ezc3d"`` (ezc3d in a
        guarded child, our reader where ezc3d cannot read or misreads the file, noted).
    model_outputs : keep the points POINT:ANGLES / FORCES / MOMENTS / POWERS list (Plug-in Gait's
        joint angles in degrees, forces...; every point, as other C3D readers give them); False
        leaves them out (noted, counted in metadata ``model_outputs``), as ``read_trajectories``
        and so every command does: they are no markers.

    Returns
    -------
    Trajectories
        ``positions`` (frames, markers, 3) in mm, NaN where the file marks a point invalid
        (residual < 0) or a value is not finite; ``residuals`` (frames, markers) in mm;
        ``first_frame`` as numbered in the file; metadata ``source``, ``format`` ("c3d"),
        ``original_units``, ``subjects``, ``takes``, ``descriptions``, ``events``, ``reader``,
        ``processor``, ``storage`` and ``notes`` (repairs such as renamed duplicate labels).
    """
    path = Path(path)
    structure = c3d_raw.read_structure(path)
    if structure.n_points == 0:
        raise InputFileError(path, "no 3-D marker data (the file holds 0 points; "
                                   "analog or rotation data only)")
    notes = list(structure.notes)
    mm_per_unit, units = _units(structure)
    labels = _labels(structure, notes)
    try:
        xyz, residual, reader = _read_point_values(structure, notes, mm_per_unit, reader)
    except MemoryError:  # within MAX_POINT_SAMPLES but more than this machine/process can hold
        raise InputFileError(path, f"not enough memory to read {structure.n_frames} frames of "
                                   f"{structure.n_points} markers") from None
    outputs = {} if model_outputs else _model_outputs(structure, labels)
    if outputs:  # Plug-in Gait's angles, forces, moments, powers share POINT but are no markers
        dropped = sorted(i for columns in outputs.values() for i in columns)
        if len(dropped) == len(labels):
            raise InputFileError(path, "no 3-D marker data (every point is a model output: "
                                       + ", ".join(f"POINT:{k}" for k in outputs) + ")")
        keep = np.setdiff1d(np.arange(len(labels)), dropped)
        xyz, residual, labels = xyz[:, keep], residual[:, keep], [labels[i] for i in keep]
        notes.append(f"{len(dropped)} model outputs are not markers and were left out ("
                     + ", ".join(f"{len(v)} POINT:{k}" for k, v in outputs.items()) + ")")
    metadata: dict[str, Any] = {
        "source": str(path), "format": "c3d", "original_units": units,
        "model_outputs": {k: len(v) for k, v in outputs.items()},
        "subjects": _subjects(structure, labels),
        "takes": _takes(structure, notes),
        "descriptions": _descriptions(structure, labels),
        "events": _events(structure),
        "reader": reader, "processor": structure.processor,
        "storage": "float" if structure.float_storage else "int",
        "notes": notes,
    }
    try:
        traj = Trajectories(xyz, labels, structure.rate, structure.first_frame, residual, metadata)
    except MocaptkError as exc:  # e.g. a bad rate or take range
        raise InputFileError(path, str(exc)) from None
    if strip_prefixes:
        try:
            traj = traj.strip_prefixes()
        except MocaptkError as exc:
            raise InputFileError(path, f"cannot strip subject prefixes: {exc}") from None
    return traj


def _read_point_values(s: C3DStructure, notes: list[str], mm_per_unit: float,
                       reader: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(xyz (F, N, 3) mm, residual (F, N) mm, NaN at gaps, name of the reader used)."""
    if reader == "ezc3d":
        result = _ezc3d_points(s)
        if not isinstance(result, str):
            xyz, residual = result
            xyz *= mm_per_unit
            residual *= mm_per_unit
            c3d_raw.mark_gaps(xyz, residual)
            return xyz, residual, "ezc3d"
        notes.append(f"{result}; points read with mocaptk's own C3D reader")
    elif reader != "mocaptk":
        raise ValueError(f"unknown C3D reader {reader!r} (expected 'mocaptk' or 'ezc3d')")
    try:
        xyz, residual = c3d_raw.read_points(s, unit_scale=mm_per_unit, gaps_as_nan=True)
    except (MocaptkError, MemoryError):
        raise
    except Exception as exc:  # noqa: BLE001 - a defect of ours on an odd file: try ezc3d
        if reader == "ezc3d":
            raise
        notes.append(f"mocaptk's C3D reader failed ({type(exc).__name__}: {exc}); "
                     "points read with ezc3d")
        return _read_point_values(s, notes, mm_per_unit, "ezc3d")
    return xyz, residual, "mocaptk"


def _ezc3d_points(s: C3DStructure) -> tuple[np.ndarray, np.ndarray] | str:
    """ezc3d's (xyz, residual) in file units, or why ezc3d cannot supply them."""
    if s.processor == "mips":
        return "ezc3d does not read MIPS files"
    if s.n_frames > EZC3D_MAX_FRAMES:
        return f"ezc3d reads at most {EZC3D_MAX_FRAMES} frames"
    if s.n_points > EZC3D_MAX_POINTS:
        return f"ezc3d reads at most {EZC3D_MAX_POINTS} points"
    if "POINT" not in s.parameters:
        return "no POINT parameters (ezc3d would see no points)"
    result = c3d_ezc3d.read_points(s.path, s.n_frames, s.n_points)
    if isinstance(result, str):
        return result
    if result.analog_words != s.analog_words:
        # e.g. sample28/*.C3D: no ANALOG:RATE, ezc3d assumes no analog data and misreads
        return (f"ezc3d's frame layout ({result.analog_words} analog samples per frame) "
                f"disagrees with the file's ({s.analog_words})")
    return result.xyz, result.residual


#: POINT groups of model outputs (Vicon Plug-in Gait and others): points that are no markers.
MODEL_OUTPUTS = ("ANGLES", "FORCES", "MOMENTS", "POWERS")


def _model_outputs(s: C3DStructure, labels: list[str]) -> dict[str, list[int]]:
    """Columns of ``labels`` that POINT:ANGLES / FORCES / MOMENTS / POWERS list, per group."""
    index: dict[str, int] = {}
    for i, label in enumerate(labels):
        index.setdefault(label.strip(), i)
    found = {}
    for group in MODEL_OUTPUTS:
        value = s.param("POINT", group)
        if value is None or isinstance(value, np.ndarray):
            continue
        columns = sorted({index[v.strip()] for v in value if isinstance(v, str) and v.strip() in index})
        if columns:
            found[group] = columns
    return found


def _units(s: C3DStructure) -> tuple[float, str]:
    value = s.param("POINT", "UNITS")
    if isinstance(value, np.ndarray):  # a numeric parameter: the file is corrupt
        shown = ", ".join(f"{v:g}" for v in value[:4]) + (", ..." if value.size > 4 else "")
        raise InputFileError(s.path, f"POINT:UNITS is a number ({shown}), not text such as "
                                     "'mm' (corrupt parameter section)")
    if not value or not value[0].strip():
        return 1.0, "mm"  # C3D default when POINT:UNITS is absent
    text = value[0].strip()
    scale = UNIT_SCALES.get(text.lower())
    if scale is None:
        raise InputFileError(s.path, f"unknown POINT:UNITS {text!r} (expected mm, cm or m)")
    return scale, text


def _labels(s: C3DStructure, notes: list[str]) -> list[str]:
    """POINT:LABELS, LABELS2, LABELS3... trimmed to the point count; empty -> ``M###``,
    duplicates -> ``LABEL_2``, ``LABEL_3`` (noted)."""
    found: list[str] = []
    for key in ["LABELS"] + [f"LABELS{k}" for k in range(2, 1000)]:
        value = s.param("POINT", key)
        if value is None:
            break
        found.extend(str(v).strip() for v in value)
    generated = c3d_raw.header_only_labels(s.n_points)
    labels = [found[k] if k < len(found) and found[k] else "" for k in range(s.n_points)]
    if not any(labels):
        return generated
    taken = set(labels)
    seen: set[str] = set()
    out: list[str] = []
    renamed: list[str] = []
    for k, label in enumerate(labels):
        if not label:
            label = _fresh(generated[k], taken)
        elif label in seen:
            new = _fresh(label, taken, start=2)
            renamed.append(f"{label}->{new}")
            label = new
        taken.add(label)
        seen.add(label)
        out.append(label)
    if renamed:
        notes.append(f"duplicate labels renamed: {', '.join(renamed[:10])}"
                     + (f" (+{len(renamed) - 10} more)" if len(renamed) > 10 else ""))
    return out


def _fresh(base: str, taken: set[str], start: int | None = None) -> str:
    if start is None and base not in taken:
        return base
    k = start or 2
    while f"{base}_{k}" in taken:
        k += 1
    return f"{base}_{k}"


def _subjects(s: C3DStructure, labels: list[str]) -> list[str]:
    """Subject names from SUBJECTS:NAMES, else from ``Subject:`` label prefixes (in order)."""
    names = s.param("SUBJECTS", "NAMES")
    subjects = [n for n in names if n] if isinstance(names, list) else []
    for label in labels:
        if ":" in label:
            prefix = label.rsplit(":", 1)[0]
            if prefix not in subjects:
                subjects.append(prefix)
    return subjects


def _takes(s: C3DStructure, notes: list[str]) -> list[Take]:
    """Takes stored by :func:`.c3d_write.write_c3d` (``MOCAPTK:TAKE_NAMES/STARTS/ENDS``)."""
    group = s.parameters.get(TAKES_GROUP, {})
    names, starts, ends = group.get("TAKE_NAMES"), group.get("TAKE_STARTS"), group.get("TAKE_ENDS")
    if not isinstance(names, list) or not isinstance(starts, np.ndarray) \
            or not isinstance(ends, np.ndarray):
        return []
    regions = group.get("TAKE_REGIONS")
    regions = regions if isinstance(regions, list) else []
    takes = []
    for k, name in enumerate(names):
        if k >= min(len(starts), len(ends)):
            break
        if not (np.isfinite(starts[k]) and np.isfinite(ends[k])):
            notes.append(f"take {name!r} has no valid frame range; ignored")
            continue
        start, end = int(starts[k]), int(ends[k])
        if not 0 <= start < end <= s.n_frames:
            notes.append(f"take {name!r} [{start}, {end}) outside the data; ignored")
            continue
        region = regions[k] if k < len(regions) and regions[k] else None
        takes.append(Take(name, start, end, region))
    return takes


def _descriptions(s: C3DStructure, labels: list[str]) -> dict[str, str]:
    """Non-empty POINT:DESCRIPTIONS by label."""
    found: list[str] = []
    for key in ["DESCRIPTIONS"] + [f"DESCRIPTIONS{k}" for k in range(2, 1000)]:
        value = s.param("POINT", key)
        if not isinstance(value, list):
            break
        found.extend(value)
    return {label: desc.strip() for label, desc in zip(labels, found) if desc.strip()}


def _events(s: C3DStructure) -> list[dict[str, Any]]:
    """EVENT:LABELS / CONTEXTS / TIMES as ``{"label", "context", "time"}`` (time in s)."""
    labels, times = s.param("EVENT", "LABELS"), s.param("EVENT", "TIMES")
    if not isinstance(labels, list) or not isinstance(times, np.ndarray) or times.size < 2:
        return []
    contexts = s.param("EVENT", "CONTEXTS")
    contexts = contexts if isinstance(contexts, list) else []
    pairs = times[: 2 * (times.size // 2)].reshape(-1, 2)  # (minutes, seconds) per event
    events = []
    for k, label in enumerate(labels[:len(pairs)]):
        minutes, seconds = pairs[k]
        if not (np.isfinite(minutes) and np.isfinite(seconds)):
            continue
        events.append({"label": label, "context": contexts[k] if k < len(contexts) else "",
                       "time": round(float(minutes * 60 + seconds), 6)})
    return events
