"""Write and read a :class:`Rig` as deterministic JSON (``format: "mocaptk.rig"``).

Schema in docs/rig-format.md. Positions are millimetres rounded to 1e-6 mm, weights to 1e-9.
A baked animation goes to a sibling ``.npz`` (:func:`write_rig_animation`) that rig.json names
under ``animation`` with its SHA-256, frame rate, takes and filled gaps.
"""

from __future__ import annotations

import hashlib
import io
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.atomic import write_bytes
from mocaptk.errors import InputFileError
from mocaptk.jsonio import read_json, to_plain, write_json
from mocaptk.trajectories import Take

from .bake import RigAnimation
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
                 "sha256": mesh_sha256(vertices, faces), "vertices": vertices, "faces": faces,
                 **({} if rig.texcoords is None else
                    {"uv": to_plain(rig.texcoords, digits=MESH_DIGITS)})},
        "joints": joints,
        "weights": {"max_influences": rig.max_influences,
                    "joint_index": rig.weight_index.tolist(),
                    "value": rig.weight_value},  # rounded to WEIGHT_DIGITS when written
    }


def write_rig_json(rig: Rig, path: str | os.PathLike[str], *, animation: RigAnimation | None = None,
                   force: bool = True) -> Path:
    """Atomically write ``rig`` as deterministic JSON at ``path``; returns the path.

    With ``animation``, its tracks go to ``<stem>_animation.npz`` beside ``path`` first
    (:func:`write_rig_animation`), and rig.json names that file.
    """
    doc = rig_to_dict(rig)
    if animation is not None:
        target = Path(path)
        tracks = target.with_name(f"{target.stem}_animation.npz")
        data = rig_animation_bytes(animation)
        write_bytes(tracks, data, force=force)
        doc["animation"] = {"file": tracks.name, "sha256": hashlib.sha256(data).hexdigest(),
                            **animation.report()}
    return write_json(path, doc, digits=WEIGHT_DIGITS, force=force)


def rig_animation_bytes(animation: RigAnimation) -> bytes:
    """The ``.npz`` of an animation (deterministic: fixed zip dates, stored uncompressed).

    Arrays: ``translations`` (F, J, 3) float32 mm (local, rig frame), ``rotations`` (F, R, 4)
    float32 local quaternions (x, y, z, w) of the joints ``rotated_joints`` (R,) int64,
    ``joint_parents`` (J,) int64 (-1: the root), ``joint_names`` (J,), ``rate`` (),
    ``take_names`` (T,), ``take_frames`` (T, 2) int64 ``[start, end)``, ``take_first_frames``
    (T,) int64 the capture's frame number of each take's first frame.
    """
    arrays = {"joint_names": np.array(animation.joint_names),
              "joint_parents": np.array(animation.joint_parents, dtype=np.int64),
              "rate": np.array(animation.rate),
              "rotated_joints": np.array(animation.rotated, dtype=np.int64),
              "rotations": animation.rotations.astype(np.float32),
              "take_first_frames": np.array([animation.first_frame(k)
                                             for k in range(len(animation.takes))], dtype=np.int64),
              "take_frames": np.array([[t.start, t.end] for t in animation.takes], dtype=np.int64),
              "take_names": np.array([t.name for t in animation.takes]),
              "translations": animation.translations.astype(np.float32)}
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, array, allow_pickle=False)
            archive.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)),
                             member.getvalue())
    return out.getvalue()


def read_rig_animation(path: str | os.PathLike[str]) -> RigAnimation:
    """Read the ``.npz`` written beside a rig.json (gaps are in rig.json, not here)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            takes = tuple(Take(str(n), int(a), int(b))
                          for n, (a, b) in zip(data["take_names"], data["take_frames"]))
            return RigAnimation(tuple(str(n) for n in data["joint_names"]), float(data["rate"]),
                                data["translations"].astype(np.float64),
                                data["rotations"].astype(np.float64), takes, (),
                                rotated=tuple(int(j) for j in data["rotated_joints"]),
                                parents=tuple(int(p) for p in data["joint_parents"]),
                                first_frames=tuple(int(f) for f in data.get("take_first_frames", ())))
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as exc:
        raise InputFileError(path, f"not a rig animation ({exc})") from None


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
        texcoords=(np.array(doc["mesh"]["uv"], dtype=np.float64) if "uv" in doc["mesh"] else None),
    )
