"""Write an animated face mesh as USD (usd-core): one ``UsdGeomMesh`` with time-sampled points.

Conventions: millimetres (``metersPerUnit`` 0.001), Y up, time codes = the capture's frame
numbers (``timeCodesPerSecond`` = ``framesPerSecond`` = the capture rate; an excerpt starting
at capture frame 700 starts at time code 700; the takes in the layer's ``customLayerData``);
triangles counter-clockwise (``orientation`` rightHanded), a ``primvars:displayColor``, vertex
normals of the rest pose, ``primvars:st`` texture coordinates when the mesh has them, and one
``UsdPreviewSurface`` material (a skin tone) bound to the mesh.
Blender, Houdini, Maya, Unreal and Omniverse read this. The binary crate (``.usdc`` content) is
written to a temporary sibling and renamed into place.

usd-core keeps a layer's time samples in memory until the layer is saved (``frames × vertices × 12``
bytes: 8 GB for 72,000 frames of a 9,400-vertex face). With ``clip_frames`` the samples go instead
into USD *value clips*, ``<stem>_clips/<stem>.NNNN.usdc`` of ``clip_frames`` frames each, which the
file names in its ``clips`` metadata (with a manifest); one clip is in memory at a time. Readers
that resolve USD composition (usdview, Blender, Houdini, Maya, Omniverse) see one animated mesh.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path, staged_folder
from mocaptk.geometry import bounds
from mocaptk.trajectories import Take

__all__ = ["new_stage", "write_mesh_usd"]

MESH_PATH = "/Face/face_mesh"
CLIP_SET = "default"


def write_mesh_usd(path: str | os.PathLike[str], *, rest: np.ndarray, faces: np.ndarray,
                   frames: Iterable[np.ndarray], n_frames: int, rate: float,
                   uv: np.ndarray | None = None, first_frame: int = 0,
                   takes: Sequence[Take] = (), clip_frames: int | None = None,
                   materials: np.ndarray | None = None, force: bool = True) -> Path:
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
    clip_frames : when set and below ``n_frames``, the points' time samples go into value clips of
        this many frames in the folder ``<stem>_clips`` beside ``path`` (replaced whole)
    materials : (T,) each triangle's (:data:`~mocaptk.retarget.face_materials.MATERIALS`; None:
        all skin): one ``UsdPreviewSurface`` each, bound to a ``materialBind`` GeomSubset
    """
    from pxr import Sdf, Vt  # ~0.3 s to import: only when writing USD

    rest = np.asarray(rest, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    path = Path(path)
    frames = (frame for chunk in frames for frame in np.asarray(chunk, dtype=np.float32))
    clipped = clip_frames is not None and n_frames > clip_frames
    clip_dir = path.with_name(f"{path.stem}_clips")
    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(atomic_path(path, force=force))
        # the clips land before the file that names them (exits run in reverse)
        clip_tmp = stack.enter_context(staged_folder(clip_dir, force=force)) if clipped else None
        layer = _mesh_layer(tmp, path, rest=rest, faces=faces, uv=uv, rate=rate, n_frames=n_frames,
                            first_frame=first_frame, takes=takes, rest_points=not clipped,
                            materials=materials)
        if clipped:
            starts = list(range(first_frame, first_frame + n_frames, clip_frames))
            low, high = _write_clips(clip_tmp, path.stem, frames, rest=rest, starts=starts,
                                     clip_frames=clip_frames)
            _anchor_clips(layer, [f"./{clip_dir.name}/{path.stem}.{k:04d}.usdc" for k in range(len(starts))],
                          starts=starts, last=first_frame + n_frames - 1,
                          manifest=f"./{clip_dir.name}/manifest.usda")
        else:
            low, high = _write_samples(layer, frames, rest=rest, first_frame=first_frame,
                                       count=n_frames)
        extent = Sdf.AttributeSpec(layer.GetPrimAtPath(MESH_PATH), "extent",
                                   Sdf.ValueTypeNames.Float3Array)
        extent.default = Vt.Vec3fArray.FromNumpy(np.stack([low, high]).astype(np.float32))
        layer.Save()
    return Path(path)


def _mesh_layer(tmp: Path, path: Path, *, rest: np.ndarray, faces: np.ndarray, uv: np.ndarray | None,
                rate: float, n_frames: int, first_frame: int, takes: Sequence[Take],
                rest_points: bool, materials: np.ndarray | None = None):
    """The layer at ``tmp`` holding the mesh (topology, normals, UVs, material; the rest pose as
    the points' default when ``rest_points``), its stage already released so that later edits
    do not recompose it."""
    from pxr import Gf, Sdf, UsdGeom, UsdShade, Vt

    from mocaptk.surface_mesh import vertex_normals

    from .face_materials import LOOKS, MATERIALS, groups, material_name

    layer, stage = new_stage(tmp, path, rate=rate, n_frames=n_frames, first_frame=first_frame)
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
    used = groups(materials, len(faces))
    for m, tris in used:
        name = material_name(m)
        colour, opacity = LOOKS[MATERIALS[m]]
        material = UsdShade.Material.Define(stage, f"/Face/{name}")
        shader = UsdShade.Shader.Define(stage, f"/Face/{name}/surface")
        shader.CreateIdAttr("UsdPreviewSurface")
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*colour))
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
        if opacity < 1:  # lash cards, eye-occlusion shells
            shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(opacity)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        if len(used) == 1:  # one material: bound to the mesh
            UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        else:  # one GeomSubset a material, together a partition of the faces
            subset = UsdGeom.Subset.CreateGeomSubset(
                mesh, MATERIALS[m], UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(tris.astype(np.int32)),
                UsdShade.Tokens.materialBind, UsdGeom.Tokens.partition)
            UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
    if len(used) > 1:
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    if rest_points:  # with clips a default would override every clip: rest is mesh_neutral.obj's
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rest))
    return layer


def _anchor_clips(layer, asset_paths: Sequence[str], *, starts: Sequence[int], last: int,
                  manifest: str) -> None:
    """Name the clips in the mesh's ``clips`` metadata (set ``CLIP_SET``): clip k from time code
    ``starts[k]``, clip time = stage time, up to ``last``."""
    from pxr import Gf, Sdf, Vt

    spec = layer.GetPrimAtPath(MESH_PATH)
    spec.SetInfo("clips", {CLIP_SET: {
        "assetPaths": Sdf.AssetPathArray(list(asset_paths)),
        "primPath": MESH_PATH,
        "active": Vt.Vec2dArray([Gf.Vec2d(t, k) for k, t in enumerate(starts)]),
        "times": Vt.Vec2dArray([Gf.Vec2d(starts[0], starts[0]), Gf.Vec2d(last, last)]),
        "manifestAssetPath": Sdf.AssetPath(manifest)}})


def _write_clips(folder: Path, stem: str, frames: Iterator[np.ndarray], *, rest: np.ndarray,
                 starts: Sequence[int], clip_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Write the points' time samples as clip layers ``folder/stem.NNNN.usdc`` (one saved and
    released before the next starts) and their manifest; returns the extent ``(low, high)``."""
    from pxr import Sdf, Usd

    low, high = bounds(rest)
    for k, start in enumerate(starts):
        layer = Sdf.Layer.CreateNew(str(folder / f"{stem}.{k:04d}.usdc"))
        clip_low, clip_high = _write_samples(layer, frames, rest=rest, first_frame=start, count=clip_frames)
        low, high = np.minimum(low, clip_low), np.maximum(high, clip_high)
        if k == 0:  # every clip holds the same attribute: its manifest is the first clip's
            manifest = Usd.ClipsAPI.GenerateClipManifestFromLayers([layer], MESH_PATH)
            manifest.Export(str(folder / "manifest.usda"))
        layer.Save()
    return low, high


def _write_samples(layer, frames: Iterator[np.ndarray], *, rest: np.ndarray, first_frame: int,
                   count: int) -> tuple[np.ndarray, np.ndarray]:
    """Set the next ``count`` frames of ``frames`` ((V, 3) float32 mm each; NaN rows: rest) as
    time samples of the mesh's points in ``layer``, from time code ``first_frame``; returns the
    extent ``(low, high)`` of ``rest`` and those frames."""
    from pxr import Sdf, Vt

    prim = Sdf.CreatePrimInLayer(layer, MESH_PATH)
    attribute = prim.attributes.get("points") or Sdf.AttributeSpec(
        prim, "points", Sdf.ValueTypeNames.Point3fArray)
    low, high = bounds(rest)
    for i, frame in zip(range(count), frames):  # range first: zip takes no frame past count
        if not np.isfinite(frame).all():  # (one pass; most frames have no NaN row)
            frame = np.where(np.isfinite(frame).all(axis=1, keepdims=True), frame, rest)
        frame_low, frame_high = bounds(frame)
        low, high = np.minimum(low, frame_low), np.maximum(high, frame_high)
        layer.SetTimeSample(attribute.path, first_frame + i,
                            Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(frame)))
    return low, high


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
