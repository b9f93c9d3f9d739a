"""Write a :class:`Rig` as a binary glTF 2.0 (.glb) skinned mesh with pygltflib.

Conventions (see docs/rig-format.md): metres, Y up, +Z forward; the mesh node sits at the scene
root with no transform; joints are nodes with translation-only local transforms; four influences
per ``JOINTS_n``/``WEIGHTS_n`` pair (a second pair when the rig has 5-8 influences); each
joint node carries its marker label, side and region in ``extras``. An animation
(:class:`~mocaptk.retarget.bake.RigAnimation`) becomes one glTF animation per take: LINEAR
samplers on every joint's translation and on the rotating joints' rotation, times in seconds from the
take's first frame (every clip starts at 0, as in the FBX; glTF has no frame rate: it is in the
scene's ``extras``; set Blender's scene rate before importing, or its importer maps the seconds
to 24 fps frames); each animation's ``extras.first_frame`` is the capture's frame number of its
time 0 (an excerpt from frame 700 says 700).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import write_bytes

from .bake import RigAnimation
from .face_materials import LOOKS, MATERIALS, groups, material_name
from .rig import Rig

#: Millimetres to glTF metres.
MM_TO_M = 1e-3
MESH_NAME = "face_mesh"
# glTF 2.0 enumerations (bufferView targets, accessor component types, primitive mode).
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_COMPONENT = {np.dtype(np.float32): 5126, np.dtype(np.uint16): 5123, np.dtype(np.uint32): 5125}
_TYPE = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_TRIANGLES = 4


def write_rig_glb(rig: Rig, path: str | os.PathLike[str], *, animation: RigAnimation | None = None,
                  force: bool = True) -> Path:
    """Atomically write ``rig`` (and ``animation``) as a binary glTF 2.0 file; returns the path."""
    return write_bytes(path, rig_glb_bytes(rig, animation=animation), force=force)


def rig_glb_bytes(rig: Rig, *, animation: RigAnimation | None = None) -> bytes:
    """The .glb file for ``rig`` and its optional ``animation`` (deterministic)."""
    import pygltflib  # ~0.2 s to import: only when writing glTF

    if animation is not None:
        animation.check_rig(rig)
    if rig.joint_count > 65535:
        raise ValueError("glTF JOINTS_n as unsigned short holds at most 65535 joints")
    builder = _BufferBuilder()
    vertices = (rig.vertices * MM_TO_M).astype(np.float32)
    attributes = pygltflib.Attributes(
        POSITION=builder.add(vertices, target=_ARRAY_BUFFER, bounds=True),
        NORMAL=builder.add(rig.vertex_normals().astype(np.float32), target=_ARRAY_BUFFER),
        # glTF's V runs down the image: flip the rig's V-up projection
        TEXCOORD_0=builder.add((rig.uv() * (1.0, -1.0) + (0.0, 1.0)).astype(np.float32),
                               target=_ARRAY_BUFFER))
    slots = 4 * -(-rig.max_influences // 4)
    joints = np.zeros((rig.vertex_count, slots), dtype=np.uint16)
    weights = np.zeros((rig.vertex_count, slots), dtype=np.float32)
    joints[:, :rig.max_influences] = rig.weight_index
    weights[:, :rig.max_influences] = rig.weight_value
    for pair in range(slots // 4):
        columns = slice(4 * pair, 4 * pair + 4)
        setattr(attributes, f"JOINTS_{pair}",
                builder.add(np.ascontiguousarray(joints[:, columns]), target=_ARRAY_BUFFER))
        setattr(attributes, f"WEIGHTS_{pair}",
                builder.add(np.ascontiguousarray(weights[:, columns]), target=_ARRAY_BUFFER))
    index_type = np.uint16 if rig.vertex_count <= 65535 else np.uint32
    used = groups(rig.materials, len(rig.faces))  # one primitive per material
    primitives = [pygltflib.Primitive(attributes=attributes, mode=_TRIANGLES, material=k,
                                      indices=builder.add(rig.faces[tris].astype(index_type).ravel(),
                                                          target=_ELEMENT_ARRAY_BUFFER))
                  for k, (_, tris) in enumerate(used)]

    positions_m = rig.joint_positions * MM_TO_M
    inverse_bind = np.tile(np.eye(4), (rig.joint_count, 1, 1))
    inverse_bind[:, 3, :3] = -positions_m  # column-major: translation in elements 12-14
    ibm = builder.add(inverse_bind.reshape(-1, 16).astype(np.float32))

    nodes = [pygltflib.Node(name=MESH_NAME, mesh=0, skin=0)]
    for joint, name in enumerate(rig.joint_names):
        parent = int(rig.joint_parents[joint])
        local = positions_m[joint] - (positions_m[parent] if parent >= 0 else 0.0)
        children = [1 + int(c) for c in np.flatnonzero(rig.joint_parents == joint)]
        nodes.append(pygltflib.Node(name=name, translation=[float(v) for v in local],
                                    children=children or None,
                                    extras={k: v for k, v in (
                                        ("marker", rig.joint_markers[joint]),
                                        ("side", rig.joint_sides[joint]),
                                        ("region", rig.joint_regions[joint])) if v}))
    animations = [] if animation is None else _animations(builder, animation)
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator=f"mocaptk {__version__}"),
        scene=0,
        scenes=[pygltflib.Scene(name="rig", nodes=[0, 1 + rig.root], extras=(
            {"frames_per_second": animation.rate} if animation is not None else None))],
        nodes=nodes,
        meshes=[pygltflib.Mesh(name=MESH_NAME, primitives=primitives)],
        **face_materials(builder, [m for m, _ in used]),
        skins=[pygltflib.Skin(name="face_skin", inverseBindMatrices=ibm, skeleton=1 + rig.root,
                              joints=[1 + j for j in range(rig.joint_count)])],
        animations=[pygltflib.Animation(**a) for a in animations],
        accessors=[pygltflib.Accessor(**a) for a in builder.accessors],
        bufferViews=[pygltflib.BufferView(**v) for v in builder.views],
        buffers=[pygltflib.Buffer(byteLength=len(builder.blob))],
    )
    gltf.set_binary_blob(bytes(builder.blob))
    return b"".join(gltf.save_to_bytes())


def _animations(builder: _BufferBuilder, animation: RigAnimation) -> list[dict]:
    """pygltflib.Animation keyword arguments, one per take (node i + 1 = joint i)."""
    import pygltflib

    out = []
    translations = (animation.translations * MM_TO_M).astype(np.float32)
    rotations = animation.rotations.astype(np.float32)
    for k, take in enumerate(animation.takes):
        frames = slice(take.start, take.end)
        times = builder.add((np.arange(take.end - take.start) / animation.rate).astype(np.float32),
                            bounds=True)  # the clip's own time, from 0
        samplers, channels = [], []
        tracks = []
        for joint in range(len(animation.joint_names)):
            tracks.append((joint, "translation", translations[frames, joint]))
            if joint in animation.rotated:
                tracks.append((joint, "rotation",
                               rotations[frames, animation.rotated.index(joint)]))
        for joint, path, values in tracks:
            channels.append(pygltflib.AnimationChannel(
                sampler=len(samplers), target=pygltflib.AnimationChannelTarget(node=1 + joint,
                                                                                path=path)))
            samplers.append(pygltflib.AnimationSampler(
                input=times, output=builder.add(np.ascontiguousarray(values)),
                interpolation="LINEAR"))
        out.append({"name": take.name, "samplers": samplers, "channels": channels,
                    "extras": {"first_frame": animation.first_frame(k)}})  # the capture's frame
    return out


class _BufferBuilder:
    """Packs arrays into one 4-byte-aligned binary buffer, one bufferView + accessor each."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []  # pygltflib.BufferView keyword arguments
        self.accessors: list[dict] = []  # pygltflib.Accessor keyword arguments

    def add(self, array: np.ndarray, *, target: int | None = None, bounds: bool = False) -> int:
        """Append ``array`` (N,) or (N, C); returns its accessor index."""
        width = 1 if array.ndim == 1 else array.shape[1]
        data = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<")).tobytes()
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data),
                           "target": target})
        self.blob += data + b"\x00" * (-len(data) % 4)
        accessor = {"bufferView": len(self.views) - 1, "byteOffset": 0,
                    "componentType": _COMPONENT[array.dtype], "count": len(array),
                    "type": _TYPE[width]}
        if bounds:
            flat = array.reshape(len(array), width)
            accessor["min"] = [float(v) for v in flat.min(axis=0)]
            accessor["max"] = [float(v) for v in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def add_bytes(self, data: bytes) -> int:
        """Append raw bytes (an image); returns their bufferView index."""
        self.views.append({"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)})
        self.blob += data + b"\x00" * (-len(data) % 4)
        return len(self.views) - 1


#: Squares per side of the base-colour texture, a UV checker in two skin tones.
CHECKER_SQUARES = 16
CHECKER_PIXELS = 256


def face_materials(builder: _BufferBuilder, used: Sequence[int] = (0,)) -> dict:
    """The materials ``used`` (:data:`~mocaptk.retarget.face_materials.MATERIALS` indices, in
    order) of a face glTF and their texture, as pygltflib.GLTF2 keyword arguments: each its
    colour (:data:`~mocaptk.retarget.face_materials.LOOKS`) times a grey UV checker (so
    TEXCOORD_0 is used and the skin's UV layout shows), not metallic; a translucent one (lash
    cards) blended and double-sided."""
    import cv2
    import pygltflib

    cell = CHECKER_PIXELS // CHECKER_SQUARES
    squares = (np.add.outer(np.arange(CHECKER_PIXELS) // cell, np.arange(CHECKER_PIXELS) // cell)
               % 2).astype(bool)
    image = np.where(squares[..., None], np.uint8(255), np.uint8(224)).repeat(3, axis=2)
    png = cv2.imencode(".png", image)[1].tobytes()
    materials = []
    for m in used:
        colour, opacity = LOOKS[MATERIALS[m]]
        materials.append(pygltflib.Material(
            name=material_name(m), pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                baseColorTexture=pygltflib.TextureInfo(index=0, texCoord=0),
                baseColorFactor=[*colour, opacity], metallicFactor=0.0, roughnessFactor=0.6),
            **({"alphaMode": "BLEND", "doubleSided": True} if opacity < 1 else {})))
    return {"materials": materials,
            "textures": [pygltflib.Texture(sampler=0, source=0, name="face_uv_checker")],
            "images": [pygltflib.Image(bufferView=builder.add_bytes(png), mimeType="image/png",
                                       name="face_uv_checker")],
            "samplers": [pygltflib.Sampler()]}
