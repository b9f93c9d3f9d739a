"""Read a glTF 2.0 / GLB character: the first mesh primitive with morph targets.

Positions and target deltas come from their accessors (any bufferView stride, sparse accessors
included), metres → mm, in the mesh's own frame (node transforms are not applied: a character is
expected at the origin, Y up, facing +Z). Names: ``mesh.extras.targetNames`` (the convention
Blender, three.js and Babylon share), else ``target_<k>``. Triangles only (mode 4).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

from .character import Character

__all__ = ["read_gltf_character"]

_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
           5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
M_TO_MM = 1000.0


def read_gltf_character(path: Path) -> Character:
    """The character in ``path`` (no shapes: empty names; the caller refuses it)."""
    import pygltflib

    try:
        gltf = pygltflib.GLTF2().load(str(path))
    except Exception as exc:  # pygltflib raises many types for malformed files
        raise InputFileError(path, f"cannot read glTF ({type(exc).__name__}: {exc})") from None
    if gltf is None:
        raise InputFileError(path, "cannot read glTF")
    try:
        return _character(gltf, path)
    except (IndexError, KeyError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed glTF ({type(exc).__name__}: {exc})") from None


def _character(gltf, path: Path) -> Character:
    blob = gltf.binary_blob() if path.suffix.lower() == ".glb" else None
    if blob is None and gltf.buffers and gltf.buffers[0].uri:
        uri = gltf.buffers[0].uri
        if uri.startswith("data:"):
            import base64
            blob = base64.b64decode(uri.split(",", 1)[1])
        else:
            blob = (path.parent / uri).read_bytes()

    def accessor(index: int) -> np.ndarray:
        acc = gltf.accessors[index]
        dtype = np.dtype(_DTYPES[acc.componentType]).newbyteorder("<")
        width = _WIDTH[acc.type]
        out = np.zeros((acc.count, width), dtype=np.float64)
        if acc.bufferView is not None:
            view = gltf.bufferViews[acc.bufferView]
            stride = view.byteStride or dtype.itemsize * width
            start = (view.byteOffset or 0) + (acc.byteOffset or 0)
            raw = np.frombuffer(blob, dtype=np.uint8, count=stride * (acc.count - 1) + dtype.itemsize * width,
                                offset=start)
            rows = np.lib.stride_tricks.as_strided(raw, shape=(acc.count, dtype.itemsize * width),
                                                   strides=(stride, 1))
            out = np.ascontiguousarray(rows).view(dtype).reshape(acc.count, width).astype(np.float64)
        if acc.sparse is not None:
            sparse = acc.sparse
            iv = gltf.bufferViews[sparse.indices.bufferView]
            idx = np.frombuffer(blob, dtype=np.dtype(_DTYPES[sparse.indices.componentType]).newbyteorder("<"),
                                count=sparse.count,
                                offset=(iv.byteOffset or 0) + (sparse.indices.byteOffset or 0))
            vv = gltf.bufferViews[sparse.values.bufferView]
            vals = np.frombuffer(blob, dtype=dtype, count=sparse.count * width,
                                 offset=(vv.byteOffset or 0) + (sparse.values.byteOffset or 0))
            out[idx.astype(np.int64)] = vals.reshape(sparse.count, width)
        return out

    fallback = None
    for mesh in gltf.meshes:
        for primitive in mesh.primitives:
            if primitive.mode not in (None, 4) or primitive.attributes.POSITION is None:
                continue
            vertices = accessor(primitive.attributes.POSITION) * M_TO_MM
            faces = (accessor(primitive.indices).astype(np.int64).reshape(-1, 3)
                     if primitive.indices is not None else np.arange(len(vertices)).reshape(-1, 3))
            if not primitive.targets:
                fallback = fallback or Character(vertices, faces, (), np.zeros((0, len(vertices), 3)),
                                                 str(path))
                continue
            extras = mesh.extras if isinstance(mesh.extras, dict) else {}
            names = list(extras.get("targetNames") or [])
            if len(names) != len(primitive.targets):
                names = [f"target_{k}" for k in range(len(primitive.targets))]
            deltas = np.stack([accessor(t["POSITION"]) * M_TO_MM if t.get("POSITION") is not None
                               else np.zeros_like(vertices) for t in primitive.targets])
            return Character(vertices, faces, tuple(str(n) for n in names), deltas.astype(np.float32),
                             str(path))
    if fallback is None:
        raise InputFileError(path, "the glTF holds no triangle mesh")
    return fallback
