"""Write and read a :class:`Rig` as deterministic JSON (``format: "mocaptk.rig"``).

Schema in docs/rig-format.md. Positions are millimetres rounded to 1e-6 mm, weights to 1e-9.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.errors import InputFileError
from mocaptk.jsonio import read_json, to_plain, write_json

from .rig import MESH_DIGITS, Rig, RigError, mesh_sha256

FORMAT = "mocaptk.rig"
VERSION = 1
#: Decimals kept for weights (positions keep :data:`MESH_DIGITS`).
WEIGHT_DIGITS = 9


def rig_to_dict(rig: Rig) -> dict[str, Any]:
    """The JSON document of ``rig`` (weights as arrays; :mod:`mocaptk.jsonio` rounds them)."""
    positions = to_plain(rig.joint_positions, digits=MESH_DIGITS)
    vertices = to_plain(rig.vertices, digits=MESH_DIGITS)
    faces = rig.faces.tolist()
    joints = [{"name": name,
               "parent": None if parent < 0 else rig.joint_names[parent],
               "bind_position": position, "side": side, "region": region, "marker": marker}
              for name, parent, position, side, region, marker in zip(
                  rig.joint_names, rig.joint_parents.tolist(), positions, rig.joint_sides,
                  rig.joint_regions, rig.joint_markers)]
    return {
        "format": FORMAT, "version": VERSION, "unit": "mm", "up_axis": "Y", "front_axis": "+Z",
        "mesh": {"vertex_count": rig.vertex_count, "face_count": len(faces),
                 "sha256": mesh_sha256(vertices, faces), "vertices": vertices, "faces": faces},
        "joints": joints,
        "weights": {"max_influences": rig.max_influences,
                    "joint_index": rig.weight_index.tolist(),
                    "value": rig.weight_value},  # rounded to WEIGHT_DIGITS when written
    }


def write_rig_json(rig: Rig, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Atomically write ``rig`` as deterministic JSON at ``path``; returns the path."""
    return write_json(path, rig_to_dict(rig), digits=WEIGHT_DIGITS, force=force)


def read_rig_json(path: str | os.PathLike[str]) -> Rig:
    """Read a rig written by :func:`write_rig_json`.

    Raises
    ------
    InputFileError
        The file is missing, not JSON, not a ``mocaptk.rig`` document, or inconsistent
        (mesh hash or vertex count mismatch, bad joints or weights).
    """
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputFileError(path, f"not a {FORMAT} document (no format: {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise InputFileError(path, f"unsupported {FORMAT} version {doc.get('version')!r} "
                                   f"(this mocaptk reads version {VERSION})")
    if doc.get("unit") != "mm" or doc.get("up_axis") != "Y":
        raise InputFileError(path, "expected unit 'mm' and up_axis 'Y'")
    try:
        rig = _rig_from_dict(doc)
    except (KeyError, TypeError, ValueError) as exc:  # RigError is a ValueError
        what = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
        raise InputFileError(path, f"malformed rig: {what}") from None
    mesh = doc["mesh"]
    if mesh.get("vertex_count") != rig.vertex_count:
        raise InputFileError(path, f"mesh has {rig.vertex_count} vertices but vertex_count "
                                   f"says {mesh.get('vertex_count')}")
    if mesh.get("sha256") != rig.mesh_sha256():
        raise InputFileError(path, "mesh vertices/faces do not match the stored sha256")
    return rig


def _rig_from_dict(doc: dict[str, Any]) -> Rig:
    joints = doc["joints"]
    names = [str(j["name"]) for j in joints]
    lookup = {name: i for i, name in enumerate(names)}
    parents = []
    for joint in joints:
        parent = joint["parent"]
        if parent is not None and parent not in lookup:
            raise RigError(f"joint {joint['name']!r} has unknown parent {parent!r}")
        parents.append(-1 if parent is None else lookup[parent])
    weights = doc["weights"]
    return Rig(
        vertices=np.array(doc["mesh"]["vertices"], dtype=np.float64),
        faces=np.array(doc["mesh"]["faces"], dtype=np.int64),
        joint_names=tuple(names),
        joint_parents=np.array(parents, dtype=np.int64),
        joint_positions=np.array([j["bind_position"] for j in joints], dtype=np.float64),
        joint_sides=tuple(str(j["side"]) for j in joints),
        joint_regions=tuple(str(j["region"]) for j in joints),
        joint_markers=tuple(str(j["marker"]) for j in joints),
        weight_index=np.array(weights["joint_index"], dtype=np.int64),
        weight_value=np.array(weights["value"], dtype=np.float64),
    )
