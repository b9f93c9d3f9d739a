"""Write a mesh animation of any length as a binary glTF 2.0 (.glb): a small morph basis keyed per
frame, the head's rigid motion on one joint.

The mesh animation (F, V, 3) is taken head-relative (when the head pose is given) and written
as the neutral mesh plus ``K`` morph targets - an orthonormal basis of the frames'
displacements from the neutral (principal components: eigenvectors of a frame sample's Gram
matrix, completed with the worst-fitting frames' residuals until every frame is within
``tolerance_mm``, at most :data:`MAX_TARGETS`) - whose weights are keyed per frame (LINEAR),
each in [0, 1] (0.5 = the neutral, the mesh's default weights).
The whole mesh is skinned to one joint ``head`` keyed with the head pose. A face driven by a
few dozen markers needs about a hundred targets (the sample: 126 for 0.01 mm), so the file
grows by ``K x 4`` bytes a frame, not ``V x 12``: any length plays, and no frame is a shape
key. One animation per take, each from time 0; the capture's first frame is in the scene's
and each animation's ``extras``. Conventions as in :mod:`.export_glb`: metres, Y up, +Z forward.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import write_bytes
from mocaptk.errors import OptionError
from mocaptk.surface_mesh import vertex_normals
from mocaptk.trajectories import Take

from .bake import continuous, rotation_to_quaternion
from .export_glb import (_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER, _TRIANGLES, MM_TO_M, _BufferBuilder,
                         face_materials)
from .face_materials import groups

__all__ = ["MAX_TARGETS", "MorphBasis", "TOLERANCE_MM", "morph_basis", "morph_glb_bytes",
           "write_morph_glb"]

#: Largest vertex error (mm) the basis leaves on any frame.
TOLERANCE_MM = 0.01
#: Most morph targets (each costs ``vertices x 12`` bytes once).
MAX_TARGETS = 512
#: Frames the basis is first computed on (evenly spread); the rest only checked and projected.
SAMPLE_FRAMES = 800
#: Rounds of adding the worst frames' residuals, and frames added per round.
REFINE_ROUNDS, REFINE_FRAMES = 4, 16
_CHUNK = 256


@dataclass(frozen=True, eq=False)
class MorphBasis:
    """``targets`` (K, V, 3) mm orthonormal displacement shapes, ``weights`` (F, K) per frame,
    ``max_error_mm`` the largest vertex error of ``neutral + weights @ targets`` on any frame."""

    targets: np.ndarray
    weights: np.ndarray
    max_error_mm: float


def morph_basis(displacement: np.ndarray, *, tolerance_mm: float = TOLERANCE_MM,
                max_targets: int = MAX_TARGETS) -> MorphBasis:
    """The smallest basis of :func:`_principal` components (refined with the worst frames)
    reproducing every frame of ``displacement`` (F, V, 3) mm (NaN frames: zero) within
    ``tolerance_mm``, or the best of ``max_targets`` components."""
    frames, vertices = displacement.shape[:2]

    def rows(index) -> np.ndarray:
        block = np.asarray(displacement[index], dtype=np.float64).reshape(-1, 3 * vertices)
        return np.where(np.isfinite(block).all(axis=1, keepdims=True), block, 0.0)

    sample = rows(np.unique(np.linspace(0, frames - 1, min(frames, SAMPLE_FRAMES)).astype(int)))
    basis = _principal(sample)
    low, high = 1, len(basis)  # the fewest components meeting the tolerance on the sample
    while low < high:
        mid = (low + high) // 2
        if _max_error(sample, basis[:mid]) <= tolerance_mm:
            high = mid
        else:
            low = mid + 1
    basis = basis[:min(max(low, 1), max_targets)]
    for _ in range(REFINE_ROUNDS):
        weights, errors = _project(rows, frames, basis)
        if errors.max() <= tolerance_mm or len(basis) >= max_targets:
            break
        worst = np.sort(np.argsort(-errors)[:min(REFINE_FRAMES, max_targets - len(basis))])
        residual = rows(worst) - (rows(worst) @ basis.T) @ basis
        q, r = np.linalg.qr(residual.T)
        keep = np.abs(np.diag(r)) > 1e-9
        basis = np.vstack([basis, q[:, keep].T])
    else:
        weights, errors = _project(rows, frames, basis)
    return MorphBasis(basis.reshape(-1, vertices, 3), weights, float(errors.max(initial=0.0)))


def _principal(rows: np.ndarray) -> np.ndarray:
    """Orthonormal principal directions (K, C) of ``rows`` (S, C), strongest first (from the
    S x S Gram matrix: S is small, C large)."""
    values, vectors = np.linalg.eigh(rows @ rows.T)
    order = np.argsort(-values)
    values, vectors = values[order], vectors[:, order]
    keep = values > max(float(values[0]), 1e-30) * 1e-14
    return (vectors[:, keep].T @ rows) / np.sqrt(values[keep])[:, None]


def _max_error(rows: np.ndarray, basis: np.ndarray) -> float:
    residual = rows - (rows @ basis.T) @ basis
    return float(np.sqrt((residual.reshape(len(rows), -1, 3) ** 2).sum(axis=2)).max(initial=0.0))


def _project(rows, frames: int, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weights (F, K) of every frame on ``basis`` and each frame's largest vertex error (F,) mm."""
    weights = np.empty((frames, len(basis)))
    errors = np.empty(frames)
    for start in range(0, frames, _CHUNK):
        block = rows(slice(start, start + _CHUNK))
        w = block @ basis.T
        residual = (block - w @ basis).reshape(len(block), -1, 3)
        weights[start:start + len(block)] = w
        errors[start:start + len(block)] = np.sqrt((residual ** 2).sum(axis=2)).max(axis=1)
    return weights, errors


def write_morph_glb(path: str | os.PathLike[str], *, rest: np.ndarray, faces: np.ndarray,
                    frames: np.ndarray, rate: float, uv: np.ndarray | None = None,
                    head: tuple[np.ndarray, np.ndarray] | None = None, takes: Sequence[Take] = (),
                    first_frame: int = 0, tolerance_mm: float = TOLERANCE_MM,
                    materials: np.ndarray | None = None,
                    force: bool = True) -> tuple[Path, dict[str, object]]:
    """Atomically write the animation ``frames`` (F, V, 3) mm (NaN frames: neutral) of the mesh
    ``rest`` (V, 3) mm, ``faces`` (T, 3) at ``rate`` Hz; ``uv`` (V, 2) its texture coordinates
    (V up); ``head`` ``(R (F, 3, 3), t (F, 3))`` the head pose (frames = R y + t for
    head-relative y; NaN: held); ``takes`` the clips (default one); ``first_frame`` the
    capture's; ``materials`` (T,) each triangle's
    (:data:`~mocaptk.retarget.face_materials.MATERIALS`; with ``uv``, None: all skin). Returns
    the path and a summary (targets, largest error)."""
    data, summary = morph_glb_bytes(rest=rest, faces=faces, frames=frames, rate=rate, uv=uv,
                                    head=head, takes=takes, first_frame=first_frame,
                                    tolerance_mm=tolerance_mm, materials=materials)
    return write_bytes(path, data, force=force), summary


def morph_glb_bytes(*, rest: np.ndarray, faces: np.ndarray, frames: np.ndarray, rate: float,
                    uv: np.ndarray | None = None,
                    head: tuple[np.ndarray, np.ndarray] | None = None,
                    takes: Sequence[Take] = (), first_frame: int = 0,
                    tolerance_mm: float = TOLERANCE_MM,
                    materials: np.ndarray | None = None) -> tuple[bytes, dict[str, object]]:
    """The .glb file (deterministic bytes) and its summary; see :func:`write_morph_glb`."""
    import pygltflib  # ~0.2 s to import: only when writing glTF

    n_frames = len(frames)
    if n_frames == 0:
        raise OptionError("a mesh animation needs at least one frame")
    rest = np.asarray(rest, dtype=np.float64)
    rotations, translations = _held_pose(head, n_frames)
    displacement = _Relative(frames, rest, rotations, translations)
    basis = morph_basis(displacement, tolerance_mm=tolerance_mm)
    # weights in [0, 1] (Blender's importer clamps a shape key to [0, 1] unless the first key is
    # outside it): target k = 2 a_k x shape k, weight (w + a_k) / 2 a_k, the base moved by
    # -sum a_k shape k, so the default weights 0.5 give the neutral
    half = np.maximum(np.abs(basis.weights).max(axis=0, initial=0.0), 1e-12)
    base = rest - np.einsum("k,kvc->vc", half, basis.targets)
    builder = _BufferBuilder()
    attributes = pygltflib.Attributes(
        POSITION=builder.add((base * MM_TO_M).astype(np.float32), target=_ARRAY_BUFFER, bounds=True),
        NORMAL=builder.add(_unit_normals(rest, faces), target=_ARRAY_BUFFER),
        JOINTS_0=builder.add(np.zeros((len(rest), 4), np.uint16), target=_ARRAY_BUFFER),
        WEIGHTS_0=builder.add(np.tile(np.float32([1, 0, 0, 0]), (len(rest), 1)),
                              target=_ARRAY_BUFFER))
    if uv is not None:  # glTF's V runs down
        attributes.TEXCOORD_0 = builder.add((np.asarray(uv) * (1.0, -1.0) + (0.0, 1.0))
                                            .astype(np.float32), target=_ARRAY_BUFFER)
    index_type = np.uint16 if len(rest) <= 65535 else np.uint32
    faces = np.asarray(faces)
    used = groups(materials, len(faces)) if uv is not None else [(None, np.arange(len(faces)))]
    indices = [builder.add(faces[tris].astype(index_type).ravel(), target=_ELEMENT_ARRAY_BUFFER)
               for _, tris in used]  # one primitive per material
    targets = [{"POSITION": builder.add((shape * 2.0 * a * MM_TO_M).astype(np.float32),
                                        target=_ARRAY_BUFFER, bounds=True)}
               for shape, a in zip(basis.targets, half)]
    weights = np.clip((basis.weights + half) / (2.0 * half), 0.0, 1.0).astype(np.float32)
    quaternions = continuous(rotation_to_quaternion(rotations)).astype(np.float32)
    metres = (translations * MM_TO_M).astype(np.float32)
    animations = []
    for take in (tuple(takes) or (Take("solve", 0, n_frames),)):
        rows = slice(take.start, take.end)
        times = builder.add(np.arange(take.end - take.start, dtype=np.float32) / np.float32(rate),
                            bounds=True)  # the clip's own time, from 0
        outputs = [(0, "weights", np.ascontiguousarray(weights[rows]).ravel()),
                   (1, "translation", metres[rows]), (1, "rotation", quaternions[rows])]
        animations.append(pygltflib.Animation(
            name=take.name, extras={"first_frame": int(first_frame + take.start)},
            samplers=[pygltflib.AnimationSampler(input=times, output=builder.add(values),
                                                 interpolation="LINEAR")
                      for _, _, values in outputs],
            channels=[pygltflib.AnimationChannel(sampler=k, target=pygltflib.AnimationChannelTarget(
                node=node, path=path)) for k, (node, path, _) in enumerate(outputs)]))
    ibm = builder.add(np.eye(4, dtype=np.float32).reshape(1, 16))
    gltf = pygltflib.GLTF2(
        asset=pygltflib.Asset(version="2.0", generator=f"mocaptk {__version__}"),
        scene=0,
        scenes=[pygltflib.Scene(name="solve", nodes=[0, 1], extras={
            "frames_per_second": float(rate), "first_frame": int(first_frame),
            "morph_basis_max_error_mm": basis.max_error_mm})],
        nodes=[pygltflib.Node(name="face_mesh", mesh=0, skin=0),
               pygltflib.Node(name="head")],
        skins=[pygltflib.Skin(name="head_skin", joints=[1], skeleton=1, inverseBindMatrices=ibm)],
        meshes=[pygltflib.Mesh(name="face_mesh", weights=[0.5] * len(targets),
                               extras={"targetNames": [f"component_{k:03d}"
                                                       for k in range(len(targets))]},
                               primitives=[pygltflib.Primitive(
                                   attributes=attributes, indices=index, mode=_TRIANGLES,
                                   material=None if uv is None else k, targets=targets)
                                   for k, index in enumerate(indices)])],
        **(face_materials(builder, [m for m, _ in used]) if uv is not None else {}),
        animations=animations,
        accessors=[pygltflib.Accessor(**a) for a in builder.accessors],
        bufferViews=[pygltflib.BufferView(**v) for v in builder.views],
        buffers=[pygltflib.Buffer(byteLength=len(builder.blob))],
    )
    gltf.set_binary_blob(bytes(builder.blob))
    return b"".join(gltf.save_to_bytes()), {"morph_targets": len(targets),
                                           "max_error_mm": basis.max_error_mm,
                                           "tolerance_mm": tolerance_mm}


class _Relative:
    """``frames`` (F, V, 3) taken head-relative, minus ``rest``: indexable like an array."""

    def __init__(self, frames, rest, rotations, translations) -> None:
        self.frames, self.rest, self.rotations, self.translations = frames, rest, rotations, translations
        self.shape = frames.shape

    def __getitem__(self, index) -> np.ndarray:
        block = np.asarray(self.frames[index], dtype=np.float64)
        rot, trans = self.rotations[index], self.translations[index]
        return np.einsum("fji,fvj->fvi", rot, block - trans[:, None]) - self.rest


def _held_pose(head: tuple[np.ndarray, np.ndarray] | None, frames: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """The head pose (F, 3, 3), (F, 3); frames without one hold the previous (else the next, else
    identity)."""
    if head is None:
        return np.tile(np.eye(3), (frames, 1, 1)), np.zeros((frames, 3))
    rotations = np.array(head[0], dtype=np.float64)
    translations = np.array(head[1], dtype=np.float64)
    ok = np.isfinite(rotations).all(axis=(1, 2)) & np.isfinite(translations).all(axis=1)
    if not ok.any():
        return np.tile(np.eye(3), (frames, 1, 1)), np.zeros((frames, 3))
    source = np.maximum.accumulate(np.where(ok, np.arange(frames), -1))
    source = np.where(source < 0, np.argmax(ok), source)
    return rotations[source], translations[source]


def _unit_normals(rest: np.ndarray, faces: np.ndarray) -> np.ndarray:
    normals = vertex_normals(rest, faces)
    normals[~np.any(normals, axis=1)] = (0.0, 0.0, 1.0)
    return normals.astype(np.float32)
