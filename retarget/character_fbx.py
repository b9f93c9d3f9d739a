"""Read a binary FBX character: the mesh a ``BlendShape`` deformer is attached to, and its
channels' ``Shape`` geometries (sparse deltas).

The binary FBX layout (public, as written by :mod:`.fbx_binary`): records of end offset, property
count, property bytes, name, typed properties (arrays optionally zlib-compressed), then nested
records closed by a null record; 32-bit offsets before version 7500, 64-bit from it. Units:
``GlobalSettings.UnitScaleFactor`` centimetres per file unit (→ mm). Shape names: the channels'
names (what Blender shows as shape keys). ASCII FBX is refused.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

from .character import Character

__all__ = ["read_fbx_character"]

_MAGIC = b"Kaydara FBX Binary  \x00"
_ARRAYS = {b"f": "<f4", b"d": "<f8", b"l": "<i8", b"i": "<i4", b"b": "?"}
_SCALARS = {b"Y": "<h", b"C": "?", b"I": "<i", b"F": "<f", b"D": "<d", b"L": "<q"}


def read_fbx_character(path: Path) -> Character:
    """The character in ``path`` (no blend shapes: empty names; the caller refuses it)."""
    data = path.read_bytes()
    if not data.startswith(_MAGIC):
        raise InputFileError(path, "not a binary FBX (ASCII FBX is not read)")
    try:
        version = struct.unpack_from("<I", data, 23)[0]
        nodes, _ = _records(data, 27, version >= 7500, len(data))
        return _character(nodes, path)
    except (struct.error, zlib.error, ValueError, KeyError, IndexError) as exc:
        raise InputFileError(path, f"malformed FBX ({type(exc).__name__}: {exc})") from None


def _records(data: bytes, offset: int, wide: bool, limit: int) -> tuple[list, int]:
    """The records from ``offset`` up to a null record (or ``limit``): ``(name, props, children)``."""
    head = "<QQQB" if wide else "<IIIB"
    size = struct.calcsize(head)
    out = []
    while offset + size <= limit:
        end, count, _, name_len = struct.unpack_from(head, data, offset)
        if end == 0:
            return out, offset + size
        offset += size
        name = data[offset:offset + name_len].decode("latin-1")
        offset += name_len
        props = []
        for _ in range(count):
            kind = data[offset:offset + 1]
            offset += 1
            if kind in _SCALARS:
                fmt = _SCALARS[kind]
                props.append(struct.unpack_from(fmt, data, offset)[0])
                offset += struct.calcsize(fmt)
            elif kind in _ARRAYS:
                length, encoding, stored = struct.unpack_from("<III", data, offset)
                raw = data[offset + 12:offset + 12 + stored]
                props.append(np.frombuffer(zlib.decompress(raw) if encoding else raw,
                                           dtype=_ARRAYS[kind], count=length))
                offset += 12 + stored
            elif kind in (b"S", b"R"):
                length = struct.unpack_from("<I", data, offset)[0]
                props.append(data[offset + 4:offset + 4 + length])
                offset += 4 + length
            else:
                raise ValueError(f"unknown property type {kind!r}")
        children, _ = _records(data, offset, wide, end) if offset < end else ([], end)
        out.append((name, props, children))
        offset = end
    return out, offset


def _child(node: tuple, name: str) -> tuple | None:
    return next((c for c in node[2] if c[0] == name), None)


def _character(nodes: list, path: Path) -> Character:
    top = {n[0]: n for n in nodes}
    scale = 10.0  # mm per file unit: centimetres unless GlobalSettings says otherwise
    settings = _child(top["GlobalSettings"], "Properties70") if "GlobalSettings" in top else None
    for p in settings[2] if settings else []:
        if p[1][0] == b"UnitScaleFactor":
            scale = 10.0 * float(p[1][4])
    objects = {n[1][0]: n for n in top.get("Objects", ("", [], []))[2]}
    parents: dict[int, list[int]] = {}
    for c in top.get("Connections", ("", [], []))[2]:
        if c[1][0] == b"OO":
            parents.setdefault(c[1][1], []).append(c[1][2])
    children: dict[int, list[int]] = {}
    for child, ups in parents.items():
        for up in ups:
            children.setdefault(up, []).append(child)

    def name(node: tuple) -> str:
        return node[1][1].split(b"\x00\x01")[0].decode("utf-8", "replace")

    meshes = [oid for oid, n in objects.items() if n[0] == "Geometry" and n[1][2] == b"Mesh"]
    if not meshes:
        raise InputFileError(path, "the FBX holds no mesh")
    for mesh_id in meshes:
        mesh = objects[mesh_id]
        vertices = np.asarray(_child(mesh, "Vertices")[1][0], dtype=np.float64).reshape(-1, 3) * scale
        faces = _triangles(np.asarray(_child(mesh, "PolygonVertexIndex")[1][0], dtype=np.int64))
        blend = [b for b in children.get(mesh_id, []) if objects.get(b, ("",))[0] == "Deformer"
                 and objects[b][1][2] == b"BlendShape"]
        names, deltas = [], []
        for b in blend:
            for channel in children.get(b, []):
                shapes = [s for s in children.get(channel, []) if objects.get(s, ("",))[0] == "Geometry"]
                if not shapes:
                    continue
                shape = objects[shapes[0]]
                delta = np.zeros_like(vertices)
                rows = np.asarray(_child(shape, "Indexes")[1][0], dtype=np.int64)
                delta[rows] = np.asarray(_child(shape, "Vertices")[1][0], dtype=np.float64).reshape(-1, 3) * scale
                names.append(name(objects[channel]))
                deltas.append(delta)
        if names:
            linear, shift = _model_transform(objects, parents.get(mesh_id, []))
            return Character(vertices @ linear.T + shift * scale, faces, tuple(names),
                             (np.stack(deltas) @ linear.T).astype(np.float32), str(path))
    mesh = objects[meshes[0]]
    vertices = np.asarray(_child(mesh, "Vertices")[1][0], dtype=np.float64).reshape(-1, 3) * scale
    return Character(vertices, _triangles(np.asarray(_child(mesh, "PolygonVertexIndex")[1][0])), (),
                     np.zeros((0, len(vertices), 3), np.float32), str(path))


def _model_transform(objects: dict, models: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's Model local transform: linear part (3, 3) (scale, then rotation, pre-rotation)
    and translation (3,) in file units (identity when there is no Model)."""
    from scipy.spatial.transform import Rotation

    model = next((objects[m] for m in models if objects.get(m, ("",))[0] == "Model"), None)
    values = {"Lcl Translation": np.zeros(3), "Lcl Rotation": np.zeros(3), "Lcl Scaling": np.ones(3),
              "PreRotation": np.zeros(3)}
    props = _child(model, "Properties70") if model else None
    for p in props[2] if props else []:
        key = p[1][0].decode("latin-1")
        if key in values:
            values[key] = np.array([float(v) for v in p[1][4:7]])
    # FBX rotation order XYZ: x applied first; PreRotation before the local rotation
    rotation = (Rotation.from_euler("xyz", values["PreRotation"], degrees=True)
                * Rotation.from_euler("xyz", values["Lcl Rotation"], degrees=True)).as_matrix()
    return rotation @ np.diag(values["Lcl Scaling"]), values["Lcl Translation"]


def _triangles(polygon_index: np.ndarray) -> np.ndarray:
    """FBX polygons (last corner stored as ``~i``) fanned into triangles (T, 3)."""
    ends = np.flatnonzero(polygon_index < 0)
    corners = np.where(polygon_index < 0, ~polygon_index, polygon_index)
    out, start = [], 0
    for end in ends:
        poly = corners[start:end + 1]
        out += [(poly[0], poly[k], poly[k + 1]) for k in range(1, len(poly) - 1)]
        start = end + 1
    return np.array(out, dtype=np.int64).reshape(-1, 3)
