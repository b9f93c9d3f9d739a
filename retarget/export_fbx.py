"""Write a :class:`Rig` as binary FBX 7.4 (pure Python): skinned mesh, LimbNode joints, BindPose.

Conventions (see docs/rig-format.md): centimetres (UnitScaleFactor 1), Y up, +Z front, +X right
axis; geometry written in place with identity object transforms; joints at their bind positions
with identity rotation; one Skin deformer with one Cluster per joint.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import write_bytes

from .fbx_binary import CREATION_TIME, FILE_ID, Int64, Node, Property, encode_fbx
from .rig import Rig

#: Millimetres to FBX centimetres.
MM_TO_CM = 0.1
MESH_NAME = "face_mesh"

# Fixed object ids: files are deterministic and ids stay readable in a dump.
_GEOMETRY_ID, _MESH_MODEL_ID, _SKIN_ID, _POSE_ID, _DOCUMENT_ID = 1000, 1001, 1002, 1003, 1004
_JOINT_MODEL_BASE, _ATTRIBUTE_BASE, _CLUSTER_BASE = 100_000, 200_000, 300_000


def write_rig_fbx(rig: Rig, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Atomically write ``rig`` as a binary FBX 7.4 file at ``path``; returns the path."""
    return write_bytes(path, rig_fbx_bytes(rig), force=force)


def rig_fbx_bytes(rig: Rig) -> bytes:
    """The binary FBX 7.4 file for ``rig`` (deterministic)."""
    return encode_fbx([
        _header_extension(),
        Node("FileId", [FILE_ID]),
        Node("CreationTime", [CREATION_TIME]),
        Node("Creator", [_creator()]),
        _global_settings(),
        _documents(),
        Node("References"),
        _definitions(rig),
        _objects(rig),
        _connections(rig),
        Node("Takes", [], [Node("Current", [""])]),
    ])


def translation_matrix(translation: np.ndarray) -> np.ndarray:
    """A 4x4 FBX matrix as 16 doubles (column-major, translation at 12-14)."""
    matrix = np.eye(4)
    matrix[3, :3] = translation
    return matrix.ravel()


def _creator() -> str:
    return f"mocaptk {__version__}"


def _p(name: str, kind: str, label: str, flags: str, *values: Property) -> Node:
    return Node("P", [name, kind, label, flags, *values])


def _header_extension() -> Node:
    stamp = Node("CreationTimeStamp", [], [
        Node("Version", [1000]), Node("Year", [1970]), Node("Month", [1]), Node("Day", [1]),
        Node("Hour", [10]), Node("Minute", [0]), Node("Second", [0]), Node("Millisecond", [0]),
    ])
    return Node("FBXHeaderExtension", [], [
        Node("FBXHeaderVersion", [1003]), Node("FBXVersion", [7400]),
        Node("EncryptionType", [0]), stamp, Node("Creator", [_creator()]),
    ])


def _global_settings() -> Node:
    props = Node("Properties70", [], [
        _p("UpAxis", "int", "Integer", "", 1), _p("UpAxisSign", "int", "Integer", "", 1),
        _p("FrontAxis", "int", "Integer", "", 2), _p("FrontAxisSign", "int", "Integer", "", 1),
        _p("CoordAxis", "int", "Integer", "", 0), _p("CoordAxisSign", "int", "Integer", "", 1),
        _p("OriginalUpAxis", "int", "Integer", "", 1),
        _p("OriginalUpAxisSign", "int", "Integer", "", 1),
        _p("UnitScaleFactor", "double", "Number", "", 1.0),
        _p("OriginalUnitScaleFactor", "double", "Number", "", 1.0),
        _p("AmbientColor", "ColorRGB", "Color", "", 0.0, 0.0, 0.0),
        _p("DefaultCamera", "KString", "", "", "Producer Perspective"),
        _p("TimeMode", "enum", "", "", 11),
        _p("TimeSpanStart", "KTime", "Time", "", Int64(0)),
        _p("TimeSpanStop", "KTime", "Time", "", Int64(46186158000)),
        _p("CustomFrameRate", "double", "Number", "", -1.0),
    ])
    return Node("GlobalSettings", [], [Node("Version", [1000]), props])


def _documents() -> Node:
    document = Node("Document", [Int64(_DOCUMENT_ID), "", "Scene"], [
        Node("Properties70", [], [
            _p("SourceObject", "object", "", ""),
            _p("ActiveAnimStackName", "KString", "", "", ""),
        ]),
        Node("RootNode", [Int64(0)]),
    ])
    return Node("Documents", [], [Node("Count", [1]), document])


def _definitions(rig: Rig) -> Node:
    joints = rig.joint_count
    counts = [("GlobalSettings", 1), ("Geometry", 1), ("Model", 1 + joints),
              ("NodeAttribute", joints), ("Deformer", 1 + joints), ("Pose", 1)]
    node = Node("Definitions", [], [Node("Version", [100]),
                                    Node("Count", [sum(c for _, c in counts)])])
    for kind, count in counts:
        node.children.append(Node("ObjectType", [kind], [Node("Count", [count])]))
    return node


def _objects(rig: Rig) -> Node:
    world_cm = rig.joint_positions * MM_TO_CM
    objects = Node("Objects", [], [_geometry(rig), _model(_MESH_MODEL_ID, MESH_NAME, "Mesh")])
    for joint, name in enumerate(rig.joint_names):
        parent = int(rig.joint_parents[joint])
        local = world_cm[joint] - (world_cm[parent] if parent >= 0 else 0.0)
        objects.children.append(Node(
            "NodeAttribute", [Int64(_ATTRIBUTE_BASE + joint), f"{name}\x00\x01NodeAttribute",
                              "LimbNode"],
            [Node("Properties70", [], [_p("Size", "double", "Number", "", 1.0)]),
             Node("TypeFlags", ["Skeleton"])]))
        objects.children.append(_model(_JOINT_MODEL_BASE + joint, name, "LimbNode",
                                       translation=local))
    objects.children.append(Node(
        "Deformer", [Int64(_SKIN_ID), f"{MESH_NAME}\x00\x01Deformer", "Skin"],
        [Node("Version", [101]), Node("Link_DeformAcuracy", [50.0]),
         Node("SkinningType", ["Linear"])]))
    for joint, name in enumerate(rig.joint_names):
        vertices, weights = rig.joint_influences(joint)
        link = translation_matrix(world_cm[joint])
        objects.children.append(Node(
            "Deformer", [Int64(_CLUSTER_BASE + joint), f"{name}\x00\x01SubDeformer", "Cluster"],
            [Node("Version", [100]), Node("UserData", ["", ""]),
             Node("Indexes", [vertices.astype(np.int32)]),
             Node("Weights", [weights.astype(np.float64)]),
             # Transform = mesh world (identity) in joint space; TransformLink = joint world.
             Node("Transform", [translation_matrix(-world_cm[joint])]),
             Node("TransformLink", [link])]))
    pose = Node("Pose", [Int64(_POSE_ID), f"{MESH_NAME}\x00\x01Pose", "BindPose"], [
        Node("Type", ["BindPose"]), Node("Version", [100]),
        Node("NbPoseNodes", [1 + rig.joint_count]),
        Node("PoseNode", [], [Node("Node", [Int64(_MESH_MODEL_ID)]),
                              Node("Matrix", [np.eye(4).ravel()])]),
    ])
    for joint in range(rig.joint_count):
        pose.children.append(Node("PoseNode", [], [
            Node("Node", [Int64(_JOINT_MODEL_BASE + joint)]),
            Node("Matrix", [translation_matrix(world_cm[joint])])]))
    objects.children.append(pose)
    return objects


def _geometry(rig: Rig) -> Node:
    polygon_index = rig.faces.astype(np.int32).copy()
    polygon_index[:, 2] = ~polygon_index[:, 2]  # a polygon's last corner is stored as -(i+1)
    normals = Node("LayerElementNormal", [0], [
        Node("Version", [101]), Node("Name", [""]),
        Node("MappingInformationType", ["ByVertice"]),
        Node("ReferenceInformationType", ["Direct"]),
        Node("Normals", [rig.vertex_normals().astype(np.float64)]),
    ])
    layer = Node("Layer", [0], [
        Node("Version", [100]),
        Node("LayerElement", [], [Node("Type", ["LayerElementNormal"]), Node("TypedIndex", [0])]),
    ])
    return Node("Geometry", [Int64(_GEOMETRY_ID), f"{MESH_NAME}\x00\x01Geometry", "Mesh"], [
        Node("Properties70"),
        Node("GeometryVersion", [124]),
        Node("Vertices", [rig.vertices.astype(np.float64) * MM_TO_CM]),
        Node("PolygonVertexIndex", [polygon_index]),
        normals, layer,
    ])


def _model(model_id: int, name: str, kind: str, *,
           translation: np.ndarray | None = None) -> Node:
    t = np.zeros(3) if translation is None else translation
    props = Node("Properties70", [], [
        _p("Lcl Translation", "Lcl Translation", "", "A", *(float(v) for v in t)),
        _p("Lcl Rotation", "Lcl Rotation", "", "A", 0.0, 0.0, 0.0),
        _p("Lcl Scaling", "Lcl Scaling", "", "A", 1.0, 1.0, 1.0),
        _p("DefaultAttributeIndex", "int", "Integer", "", 0),
        _p("InheritType", "enum", "", "", 1),
    ])
    return Node("Model", [Int64(model_id), f"{name}\x00\x01Model", kind], [
        Node("Version", [232]), props, Node("MultiLayer", [0]), Node("MultiTake", [0]),
        Node("Shading", [True]), Node("Culling", ["CullingOff"]),
    ])


def _connections(rig: Rig) -> Node:
    links = [(_MESH_MODEL_ID, 0), (_GEOMETRY_ID, _MESH_MODEL_ID), (_SKIN_ID, _GEOMETRY_ID)]
    for joint in range(rig.joint_count):
        parent = int(rig.joint_parents[joint])
        model = _JOINT_MODEL_BASE + joint
        links.append((model, _JOINT_MODEL_BASE + parent if parent >= 0 else 0))
        links.append((_ATTRIBUTE_BASE + joint, model))
        links.append((_CLUSTER_BASE + joint, _SKIN_ID))
        links.append((model, _CLUSTER_BASE + joint))
    return Node("Connections", [], [Node("C", ["OO", Int64(child), Int64(parent)])
                                    for child, parent in links])
