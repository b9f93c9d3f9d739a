"""The blendshape character as binary FBX 7.4: mesh, one ``BlendShape`` deformer with one
``BlendShapeChannel`` per shape (its ``Shape`` geometry: sparse deltas), and one take whose
``DeformPercent`` curves (0–100, linear) key every capture frame.

Conventions and file machinery as :mod:`.export_fbx` (centimetres, Y up, +Z front; deterministic
ids and bytes). Blender imports the channels as shape keys with animated values.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from .character import Character
from .export_fbx import (_KEY_DATA, _LINEAR_KEY_FLAGS, MM_TO_CM, _creator, _documents,
                         _global_settings, _header_extension, _material, _model, _p, definitions,
                         ktime)
from .fbx_binary import CREATION_TIME, FILE_ID, Int64, Node, encode_fbx

__all__ = ["character_fbx_bytes"]

MESH_NAME = "character"
TAKE_NAME = "retarget"
_GEOMETRY_ID, _MODEL_ID, _MATERIAL_ID, _BLEND_ID, _DOCUMENT_ID = 1000, 1001, 1005, 1006, 1004
_STACK_ID, _LAYER_ID = 1007, 1008
_CHANNEL_BASE, _SHAPE_BASE, _NODE_BASE, _CURVE_BASE = 100_000, 200_000, 300_000, 400_000


def character_fbx_bytes(character: Character, weights: np.ndarray, rate: float) -> bytes:
    """The FBX file (deterministic bytes) of ``character`` animated by ``weights`` (F, S)."""
    n_frames, n_shapes = len(weights), len(character.names)
    names = _unique_names(character.names)
    times = ktime(np.arange(max(n_frames, 1)), rate)
    percent = np.clip(np.asarray(weights, dtype=np.float32), 0, 1) * 100 if n_frames else \
        np.zeros((1, n_shapes), np.float32)
    objects = Node("Objects", [], [_geometry(character), _model(_MODEL_ID, MESH_NAME, "Mesh"), _material(),
                                   Node("Deformer", [Int64(_BLEND_ID), f"{MESH_NAME}\x00\x01Deformer",
                                                     "BlendShape"], [Node("Version", [100])])])
    links = [("OO", _MODEL_ID, 0), ("OO", _GEOMETRY_ID, _MODEL_ID), ("OO", _MATERIAL_ID, _MODEL_ID),
             ("OO", _BLEND_ID, _GEOMETRY_ID)]
    stack = Node("AnimationStack", [Int64(_STACK_ID), f"{TAKE_NAME}\x00\x01AnimStack", ""], [
        Node("Properties70", [], [_p(key, "KTime", "Time", "", Int64(int(t))) for key, t in (
            ("LocalStart", times[0]), ("LocalStop", times[-1]), ("ReferenceStart", times[0]),
            ("ReferenceStop", times[-1]))])], block=True)
    layer = Node("AnimationLayer", [Int64(_LAYER_ID), "BaseLayer\x00\x01AnimLayer", ""], [], block=True)
    objects.children += [stack, layer]
    links.append(("OO", _LAYER_ID, _STACK_ID))
    for k, (name, delta) in enumerate(zip(names, character.deltas)):
        moving = np.flatnonzero(np.abs(delta).max(axis=1) > 0)
        if moving.size == 0:
            moving = np.zeros(1, dtype=np.int64)  # a zero shape still needs one (zero) point
        channel, shape, node, curve = (_CHANNEL_BASE + k, _SHAPE_BASE + k, _NODE_BASE + k, _CURVE_BASE + k)
        objects.children += [
            Node("Geometry", [Int64(shape), f"{name}\x00\x01Geometry", "Shape"], [
                Node("Version", [100]), Node("Indexes", [moving.astype(np.int32)]),
                Node("Vertices", [delta[moving].astype(np.float64).ravel() * MM_TO_CM]),
                Node("Normals", [np.zeros(3 * moving.size)])]),
            Node("Deformer", [Int64(channel), f"{name}\x00\x01SubDeformer", "BlendShapeChannel"], [
                Node("Version", [100]), Node("DeformPercent", [0.0]),
                Node("FullWeights", [np.array([100.0])]),
                Node("Properties70", [], [_p("DeformPercent", "Number", "", "A", 0.0)])]),
            Node("AnimationCurveNode", [Int64(node), "DeformPercent\x00\x01AnimCurveNode", ""], [
                Node("Properties70", [], [_p("d|DeformPercent", "Number", "", "A",
                                             float(percent[0, k]))])], block=True),
            Node("AnimationCurve", [Int64(curve), "\x00\x01AnimCurve", ""], [
                Node("Default", [float(percent[0, k])]), Node("KeyVer", [4008]),
                Node("KeyTime", [times]), Node("KeyValueFloat", [np.ascontiguousarray(percent[:, k])]),
                Node("KeyAttrFlags", [np.array([_LINEAR_KEY_FLAGS], dtype=np.int32)]),
                Node("KeyAttrDataFloat", [_KEY_DATA]),
                Node("KeyAttrRefCount", [np.array([len(times)], dtype=np.int32)])], block=True)]
        links += [("OO", channel, _BLEND_ID), ("OO", shape, channel), ("OO", node, _LAYER_ID),
                  ("OP", node, channel, "DeformPercent"), ("OP", curve, node, "d|DeformPercent")]
    timing = SimpleNamespace(rate=float(rate), frame_count=max(n_frames, 1),  # one clip from frame 0
                             takes=[SimpleNamespace(start=0, end=max(n_frames, 1))])
    return encode_fbx([
        _header_extension(), Node("FileId", [FILE_ID]), Node("CreationTime", [CREATION_TIME]),
        Node("Creator", [_creator()]), _global_settings(timing), _documents(TAKE_NAME),
        Node("References"), _definitions(n_shapes), objects,
        Node("Connections", [], [Node("C", [kind, Int64(child), Int64(parent), *prop])
                                 for kind, child, parent, *prop in links]),
        Node("Takes", [], [Node("Current", [TAKE_NAME]), Node("Take", [TAKE_NAME], [
            Node("FileName", [f"{TAKE_NAME}.tak"]),
            Node("LocalTime", [Int64(int(times[0])), Int64(int(times[-1]))]),
            Node("ReferenceTime", [Int64(int(times[0])), Int64(int(times[-1]))])])]),
    ])


def _definitions(n_shapes: int) -> Node:
    return definitions([("GlobalSettings", 1), ("Geometry", 1 + n_shapes), ("Model", 1), ("Material", 1),
                        ("Deformer", 1 + n_shapes), ("AnimationStack", 1), ("AnimationLayer", 1),
                        ("AnimationCurveNode", n_shapes), ("AnimationCurve", n_shapes)])


def _geometry(character: Character) -> Node:
    from mocaptk.surface_mesh import vertex_normals

    polygon_index = np.asarray(character.faces, dtype=np.int32).copy()
    polygon_index[:, 2] = ~polygon_index[:, 2]  # a polygon's last corner is stored as -(i+1)
    normals = Node("LayerElementNormal", [0], [
        Node("Version", [101]), Node("Name", [""]), Node("MappingInformationType", ["ByVertice"]),
        Node("ReferenceInformationType", ["Direct"]),
        Node("Normals", [vertex_normals(character.vertices, character.faces).astype(np.float64).ravel()])])
    material = Node("LayerElementMaterial", [0], [
        Node("Version", [101]), Node("Name", [""]), Node("MappingInformationType", ["AllSame"]),
        Node("ReferenceInformationType", ["IndexToDirect"]), Node("Materials", [np.zeros(1, dtype=np.int32)])])
    layer = Node("Layer", [0], [Node("Version", [100])] + [
        Node("LayerElement", [], [Node("Type", [kind]), Node("TypedIndex", [0])])
        for kind in ("LayerElementNormal", "LayerElementMaterial")])
    return Node("Geometry", [Int64(_GEOMETRY_ID), f"{MESH_NAME}\x00\x01Geometry", "Mesh"], [
        Node("Properties70"), Node("GeometryVersion", [124]),
        Node("Vertices", [np.asarray(character.vertices, dtype=np.float64).ravel() * MM_TO_CM]),
        Node("PolygonVertexIndex", [polygon_index.ravel()]), normals, material, layer])


def _unique_names(names: tuple[str, ...]) -> list[str]:
    """Printable, unique FBX object names (the \\x00\\x01 separator cannot occur in them)."""
    out: list[str] = []
    for name in names:
        base = "".join(c if c.isprintable() else "_" for c in name) or "shape"
        unique, n = base, 2
        while unique in out:
            unique, n = f"{base}_{n}", n + 1
        out.append(unique)
    return out
