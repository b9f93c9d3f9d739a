"""Write an animated face mesh as USD (usd-core): one ``UsdGeomMesh`` with time-sampled points.

Conventions: millimetres (``metersPerUnit`` 0.001), Y up, time codes = the capture's frame
numbers (``timeCodesPerSecond`` = ``framesPerSecond`` = the capture rate; an excerpt starting
at capture frame 700 starts at time code 700; the takes in the layer's ``customLayerData``);
triangles counter-clockwise (``orientation`` rightHanded), a ``primvars:displayColor``, vertex
normals of the rest pose, ``primvars:st`` texture coordinates when the mesh has them, and one
``UsdPreviewSurface`` material (a skin tone) bound to the mesh.
Blender, Houdini, Maya, Unreal and Omniverse read this. The binary crate (``.usdc`` content) is
written to a temporary sibling and renamed into place. usd-core keeps every time sample in memory
until the file is saved (about ``frames × vertices × 12`` bytes).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path
from mocaptk.trajectories import Take

__all__ = ["new_stage", "write_mesh_usd"]

MESH_PATH = "/Face/face_mesh"


def write_mesh_usd(path: str | os.PathLike[str], *, rest: np.ndarray, faces: np.ndarray,
                   frames: Iterable[np.ndarray], n_frames: int, rate: float,
                   uv: np.ndarray | None = None, first_frame: int = 0,
                   takes: Sequence[Take] = (), force: bool = True) -> Path:
    """Write the mesh animation to ``path`` (``.usd``/``.usdc``; ``.usda`` for text).

    Parameters
    ----------
    rest : (V, 3) mm, the neutral mesh (the mesh's default points)
    faces : (T, 3) vertex indices
    frames : chunks (f, V, 3) mm, in order, ``n_frames`` frames in all (NaN rows: rest pose)
    rate : capture rate, Hz
    uv : (V, 2) texture coordinates in [0, 1] (V up), optional
    first_frame : the capture's number of the first frame (its time code)
    takes : the capture's takes (frames from 0): ``customLayerData["takes"][name]`` holds each
        one's ``startTimeCode`` and ``endTimeCode``
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt  # ~0.3 s to import: only when writing USD

    from mocaptk.surface_mesh import vertex_normals

    from .export_fbx import SKIN_COLOUR

    rest = np.asarray(rest, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    with atomic_path(path, force=force) as tmp:
        layer, stage = new_stage(tmp, Path(path), rate=rate, n_frames=n_frames,
                                 first_frame=first_frame)
        if takes:
            layer.customLayerData = {"takes": {
                t.name: {"startTimeCode": float(first_frame + t.start),
                         "endTimeCode": float(first_frame + t.end - 1)} for t in takes}}
        root = UsdGeom.Xform.Define(stage, "/Face")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, MESH_PATH)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDisplayColorAttr([Gf.Vec3f(0.8, 0.66, 0.58)])
        normals = vertex_normals(rest, faces)
        normals[~np.any(normals, axis=1)] = (0.0, 0.0, 1.0)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        if uv is not None:
            st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                         UsdGeom.Tokens.vertex)
            st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uv, dtype=np.float32)))
        material = UsdShade.Material.Define(stage, "/Face/face_skin")
        shader = UsdShade.Shader.Define(stage, "/Face/face_skin/surface")
        shader.CreateIdAttr("UsdPreviewSurface")
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*SKIN_COLOUR))
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        points = mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rest))
        low, high = rest.min(axis=0), rest.max(axis=0)
        written = 0
        for chunk in frames:
            chunk = np.asarray(chunk, dtype=np.float32)
            for i, frame in enumerate(chunk):
                frame = np.where(np.isfinite(frame).all(axis=1, keepdims=True), frame, rest)
                points.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(frame)),
                           first_frame + written + i)
            finite = chunk[np.isfinite(chunk).all(axis=2)]
            if finite.size:
                low, high = np.minimum(low, finite.min(axis=0)), np.maximum(high, finite.max(axis=0))
            written += len(chunk)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([low, high]).astype(np.float32)))
        layer.Save()
    return Path(path)


def new_stage(tmp: Path, path: Path, *, rate: float, n_frames: int, first_frame: int = 0):
    """A new layer at ``tmp`` (format from ``path``'s suffix) and its stage: Y up, mm, time codes
    = frames ``first_frame`` .. ``first_frame + n_frames - 1`` at ``rate``. Returns
    ``(layer, stage)``."""
    from pxr import Sdf, Usd, UsdGeom

    layer = Sdf.Layer.CreateNew(str(tmp), args={"format": _format(path)})
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    stage.SetTimeCodesPerSecond(float(rate))
    stage.SetFramesPerSecond(float(rate))
    stage.SetStartTimeCode(first_frame)
    stage.SetEndTimeCode(first_frame + max(n_frames - 1, 0))
    return layer, stage


def _format(path: Path) -> str:
    return "usda" if path.suffix.lower() == ".usda" else "usdc"
