"""Write a short mesh animation as a binary glTF 2.0 (.glb) with one morph target per frame.

The mesh holds the neutral pose; frame ``k`` is morph target ``k`` (its displacement from the
neutral, metres); one animation keys the node's morph weights one-hot per frame at the capture
rate (LINEAR between frames, so playback blends neighbouring frames). Every frame costs
``vertices × 12`` bytes and the weight keys ``frames²`` floats, hence the cap of
:data:`GLB_FRAME_CAP` frames (10 s at 60 Hz); longer clips go to USD or the ``.npy`` frames.
Conventions as in :mod:`.export_glb`: metres, Y up, +Z forward.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import write_bytes
from mocaptk.errors import OptionError
from mocaptk.surface_mesh import vertex_normals

from .export_glb import (_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER, _TRIANGLES, MM_TO_M, _BufferBuilder,
                         skin_material)

__all__ = ["GLB_FRAME_CAP", "morph_glb_bytes", "write_morph_glb"]

#: Most frames a morph-target .glb holds.
GLB_FRAME_CAP = 600
_LINEAR = "LINEAR"


def write_morph_glb(path: str | os.PathLike[str], *, rest: np.ndarray, faces: np.ndarray,
                    frames: np.ndarray, rate: float, uv: np.ndarray | None = None,
                    force: bool = True) -> Path:
    """Atomically write the animation ``frames`` (F, V, 3) mm of the mesh ``rest`` (V, 3) mm,
    ``faces`` (T, 3) at ``rate`` Hz (NaN frames: neutral); ``uv`` (V, 2) its texture
    coordinates (V up) if it has them."""
    return write_bytes(path, morph_glb_bytes(rest=rest, faces=faces, frames=frames, rate=rate,
                                             uv=uv), force=force)


def morph_glb_bytes(*, rest: np.ndarray, faces: np.ndarray, frames: np.ndarray, rate: float,
                    uv: np.ndarray | None = None) -> bytes:
    """The .glb file (deterministic bytes); see :func:`write_morph_glb`."""
    import pygltflib  # ~0.2 s to import: only when writing glTF

    n_frames = len(frames)
    if n_frames == 0 or n_frames > GLB_FRAME_CAP:
        raise OptionError(f"a morph-target glTF holds 1..{GLB_FRAME_CAP} frames, got {n_frames}; "
                          "use the USD or .npy output for longer clips")
    rest = np.asarray(rest, dtype=np.float64)
    builder = _BufferBuilder()
    attributes = pygltflib.Attributes(
        POSITION=builder.add((rest * MM_TO_M).astype(np.float32), target=_ARRAY_BUFFER, bounds=True),
        NORMAL=builder.add(vertex_normals(rest, faces).astype(np.float32), target=_ARRAY_BUFFER))
    if uv is not None:  # glTF's V runs down
        attributes.TEXCOORD_0 = builder.add((np.asarray(uv) * (1.0, -1.0) + (0.0, 1.0))
                                            .astype(np.float32), target=_ARRAY_BUFFER)
    index_type = np.uint16 if len(rest) <= 65535 else np.uint32
    indices = builder.add(np.asarray(faces).astype(index_type).ravel(), target=_ELEMENT_ARRAY_BUFFER)
    targets = []
    for frame in np.asarray(frames, dtype=np.float64):
        delta = np.where(np.isfinite(frame), frame - rest, 0.0) * MM_TO_M
        targets.append({"POSITION": builder.add(delta.astype(np.float32), target=_ARRAY_BUFFER,
                                                bounds=True)})
    times = builder.add(np.arange(n_frames, dtype=np.float32) / np.float32(rate), bounds=True)
    weights = builder.add(np.eye(n_frames, dtype=np.float32).ravel())
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator=f"mocaptk {__version__}"),
        scene=0,
        scenes=[pygltflib.Scene(name="solve", nodes=[0])],
        nodes=[pygltflib.Node(name="face_mesh", mesh=0)],
        meshes=[pygltflib.Mesh(name="face_mesh", weights=[0.0] * n_frames,
                               extras={"targetNames": [f"frame_{k:05d}" for k in range(n_frames)]},
                               primitives=[pygltflib.Primitive(
                                   attributes=attributes, indices=indices, mode=_TRIANGLES,
                                   material=None if uv is None else 0, targets=targets)])],
        **(skin_material(builder) if uv is not None else {}),
        animations=[pygltflib.Animation(
            name="solve",
            samplers=[pygltflib.AnimationSampler(input=times, output=weights, interpolation=_LINEAR)],
            channels=[pygltflib.AnimationChannel(
                sampler=0, target=pygltflib.AnimationChannelTarget(node=0, path="weights"))])],
        accessors=[pygltflib.Accessor(**a) for a in builder.accessors],
        bufferViews=[pygltflib.BufferView(**v) for v in builder.views],
        buffers=[pygltflib.Buffer(byteLength=len(builder.blob))],
    )
    gltf.set_binary_blob(bytes(builder.blob))
    return b"".join(gltf.save_to_bytes())
