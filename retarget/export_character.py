"""The character animated by its blendshape weights: ``character.glb``, ``character.usd``,
``character.fbx`` (see docs/retarget.md).

- **glTF 2.0**: the neutral mesh with one morph target per shape (``extras.targetNames``), one
  animation keying the node's morph weights at every capture frame (LINEAR), times in seconds;
  metres, Y up, +Z forward.
- **USD**: ``UsdSkel``: a ``SkelRoot`` with a one-joint ``Skeleton`` whose ``SkelAnimation``
  holds ``blendShapes`` and time-sampled ``blendShapeWeights`` (time code = frame, rate = the
  capture's); the mesh binds ``UsdSkelBlendShape`` children (offsets, mm) and the skeleton.
- **FBX**: :mod:`.export_character_fbx` (blend-shape channels with DeformPercent curves).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import atomic_path, write_bytes
from mocaptk.geometry import bounds
from mocaptk.surface_mesh import vertex_normals

from .character import Character
from .export_glb import _ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER, _TRIANGLES, MM_TO_M, _BufferBuilder

__all__ = ["character_glb_bytes", "write_character_files", "write_character_usd"]


def write_character_files(folder: Path, character: Character, weights: np.ndarray, rate: float, *,
                          formats: Sequence[str], progress: Callable[[str], None] | None = None
                          ) -> list[str]:
    """Write ``character.<fmt>`` for each of ``formats`` into ``folder``; returns the names."""
    say = progress or (lambda _: None)
    written = []
    if "glb" in formats:
        say("writing character.glb")
        write_bytes(folder / "character.glb", character_glb_bytes(character, weights, rate))
        written.append("character.glb")
    if "usd" in formats:
        say("writing character.usd")
        write_character_usd(folder / "character.usd", character, weights, rate)
        written.append("character.usd")
    if "fbx" in formats:
        from .export_character_fbx import character_fbx_bytes

        say("writing character.fbx")
        write_bytes(folder / "character.fbx", character_fbx_bytes(character, weights, rate))
        written.append("character.fbx")
    return written


def character_glb_bytes(character: Character, weights: np.ndarray, rate: float) -> bytes:
    """The .glb (deterministic bytes): mesh, morph targets, weight animation (F, S) at ``rate``."""
    import pygltflib

    rest = np.asarray(character.vertices, dtype=np.float64)
    builder = _BufferBuilder()
    attributes = pygltflib.Attributes(
        POSITION=builder.add((rest * MM_TO_M).astype(np.float32), target=_ARRAY_BUFFER, bounds=True),
        NORMAL=builder.add(vertex_normals(rest, character.faces).astype(np.float32), target=_ARRAY_BUFFER))
    index_type = np.uint16 if len(rest) <= 65535 else np.uint32
    indices = builder.add(np.asarray(character.faces).astype(index_type).ravel(),
                          target=_ELEMENT_ARRAY_BUFFER)
    targets = [{"POSITION": builder.add((np.asarray(d, dtype=np.float64) * MM_TO_M).astype(np.float32),
                                        target=_ARRAY_BUFFER, bounds=True)}
               for d in character.deltas]
    n_frames = len(weights)
    animations = []
    if n_frames:
        times = builder.add(np.arange(n_frames, dtype=np.float32) / np.float32(rate), bounds=True)
        values = builder.add(np.clip(np.asarray(weights, dtype=np.float32), 0, 1).ravel())
        animations = [pygltflib.Animation(
            name="retarget",
            samplers=[pygltflib.AnimationSampler(input=times, output=values, interpolation="LINEAR")],
            channels=[pygltflib.AnimationChannel(
                sampler=0, target=pygltflib.AnimationChannelTarget(node=0, path="weights"))])]
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator=f"mocaptk {__version__}"),
        scene=0,
        scenes=[pygltflib.Scene(name="character", nodes=[0], extras={"frame_rate": float(rate)})],
        nodes=[pygltflib.Node(name="character", mesh=0)],
        meshes=[pygltflib.Mesh(name="character", weights=[0.0] * len(character.names),
                               extras={"targetNames": list(character.names)},
                               primitives=[pygltflib.Primitive(attributes=attributes, indices=indices,
                                                               mode=_TRIANGLES, targets=targets)])],
        animations=animations,
        accessors=[pygltflib.Accessor(**a) for a in builder.accessors],
        bufferViews=[pygltflib.BufferView(**v) for v in builder.views],
        buffers=[pygltflib.Buffer(byteLength=len(builder.blob))],
    )
    gltf.set_binary_blob(bytes(builder.blob))
    return b"".join(gltf.save_to_bytes())


def write_character_usd(path: Path, character: Character, weights: np.ndarray, rate: float) -> Path:
    """Write the UsdSkel character (mm, Y up) with ``weights`` (F, S) as time samples."""
    from pxr import Gf, Tf, UsdGeom, UsdSkel, Vt

    from .export_usd import new_stage

    rest = np.asarray(character.vertices, dtype=np.float32)
    faces = np.asarray(character.faces, dtype=np.int32)
    tokens = _unique_tokens([Tf.MakeValidIdentifier(n) for n in character.names])
    n_frames = len(weights)
    with atomic_path(path, force=True) as tmp:
        layer, stage = new_stage(tmp, path, rate=rate, n_frames=n_frames)
        root = UsdSkel.Root.Define(stage, "/Character")
        stage.SetDefaultPrim(root.GetPrim())
        skeleton = UsdSkel.Skeleton.Define(stage, "/Character/Skeleton")
        identity = Gf.Matrix4d(1.0)
        skeleton.CreateJointsAttr(Vt.TokenArray(["root"]))
        skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([identity]))
        skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([identity]))
        anim = UsdSkel.Animation.Define(stage, "/Character/Skeleton/Animation")
        anim.CreateJointsAttr(Vt.TokenArray(["root"]))
        anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0.0)]))
        anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1.0)]))
        anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0)]))
        anim.CreateBlendShapesAttr(Vt.TokenArray(tokens))
        weight_attr = anim.CreateBlendShapeWeightsAttr()
        clipped = np.clip(np.asarray(weights, dtype=np.float32), 0, 1)
        for frame, row in enumerate(clipped):
            weight_attr.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(row)), frame)
        UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
        mesh = UsdGeom.Mesh.Define(stage, "/Character/face")
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.ravel()))
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(rest))
        mesh.CreateDisplayColorAttr([Gf.Vec3f(0.8, 0.66, 0.58)])
        extent = _extent(character, clipped)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(extent))
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
        binding.CreateGeomBindTransformAttr(identity)
        binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
        targets = []
        for token, delta in zip(tokens, character.deltas):
            shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(token))
            moving = np.flatnonzero(np.abs(delta).max(axis=1) > 0)  # sparse: only moving points
            moving = moving if moving.size else np.zeros(1, dtype=np.int64)  # a zero shape: one zero point
            shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(delta[moving], np.float32)))
            shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moving.astype(np.int32)))
            targets.append(shape.GetPath())
        binding.CreateBlendShapeTargetsRel().SetTargets(targets)
        layer.Save()
    return path


def _extent(character: Character, weights: np.ndarray, *, chunk: int = 256) -> np.ndarray:
    """(2, 3) float32 bounds of the mesh over the neutral and every frame (chunked: bounded memory)."""
    low, high = bounds(character.vertices)
    for start in range(0, len(weights), chunk):
        moved_low, moved_high = bounds(character.deform(weights[start:start + chunk]))
        low, high = np.minimum(low, moved_low), np.maximum(high, moved_high)
    return np.stack([low, high]).astype(np.float32)


def _unique_tokens(tokens: list[str]) -> list[str]:
    """``tokens`` with repeats suffixed ``_1``, ``_2`` ... (USD prim names must differ)."""
    seen: dict[str, int] = {}
    out = []
    for token in tokens:
        count = seen.get(token, 0)
        seen[token] = count + 1
        out.append(token if count == 0 else f"{token}_{count}")
    return out
