"""Read a USD character: the first mesh bound (``UsdSkelBindingAPI``) to ``UsdSkelBlendShape``s.

Points and offsets are scaled by the stage's ``metersPerUnit`` to mm; sparse shapes
(``pointIndices``) are expanded; names are the mesh's ``skel:blendShapes`` tokens.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

from .character import Character

__all__ = ["read_usd_character"]


def read_usd_character(path: Path) -> Character:
    """The character in ``path`` (no shapes: empty names; the caller refuses it)."""
    from pxr import Usd, UsdGeom, UsdSkel

    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as exc:  # pxr raises Tf.ErrorException for unreadable layers
        raise InputFileError(path, f"cannot read USD ({' '.join(str(exc).split())[:120]})") from None
    to_mm = UsdGeom.GetStageMetersPerUnit(stage) * 1000.0
    fallback = None
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        points = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3) * to_mm
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        faces = _triangles(counts, indices)
        if len(faces) == 0:
            continue
        binding = UsdSkel.BindingAPI(prim)
        names = list(binding.GetBlendShapesAttr().Get() or [])
        targets = binding.GetBlendShapeTargetsRel().GetTargets()
        if not names or len(targets) != len(names):
            fallback = fallback or Character(points, faces, (), np.zeros((0, len(points), 3)), str(path))
            continue
        deltas = np.zeros((len(names), len(points), 3), dtype=np.float32)
        for k, target in enumerate(targets):
            shape = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
            offsets = np.asarray(shape.GetOffsetsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
            where = shape.GetPointIndicesAttr().Get()
            rows = np.asarray(where, dtype=np.int64) if where else np.arange(len(offsets))
            if len(rows) != len(offsets) or (len(rows) and rows.max() >= len(points)):
                raise InputFileError(path, f"blend shape {names[k]} does not fit its mesh")
            deltas[k, rows] = offsets * to_mm
        return Character(points, faces, tuple(str(n) for n in names), deltas, str(path))
    if fallback is None:
        raise InputFileError(path, "the USD holds no mesh")
    return fallback


def _triangles(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygons (fan split) as triangles (T, 3)."""
    out, start = [], 0
    for n in counts:
        out += [(indices[start], indices[start + k], indices[start + k + 1]) for k in range(1, n - 1)]
        start += n
    return np.array(out, dtype=np.int64).reshape(-1, 3)
