"""Write a :class:`Rig` as binary FBX 7.4 (pure Python): skinned mesh, LimbNode joints, BindPose,
and optionally its baked animation.

Conventions (see docs/rig-format.md): centimetres (UnitScaleFactor 1), Y up, +Z front, +X right
axis; geometry written in place with identity object transforms; joints at their bind positions
with identity rotation; one Skin deformer with one Cluster per joint; each joint's marker label,
side and region as user properties (``marker``/``side``/``region``). An animation
(:class:`~mocaptk.retarget.bake.RigAnimation`) becomes one AnimationStack per take with one
layer, linear keys on every joint's ``Lcl Translation`` and on the rotating joints' ``Lcl Rotation``
(Euler XYZ degrees, unwrapped), at the capture's frame rate (``TimeMode``: the standard rate
when there is one, else custom with ``CustomFrameRate``). Every take starts at time 0, as in
the glTF; the scene's time span is the longest take's.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocaptk import __version__
from mocaptk.atomic import write_bytes

from .bake import RigAnimation
from .face_materials import LOOKS, MATERIALS, groups, material_name
from .fbx_binary import CREATION_TIME, FILE_ID, Int64, Node, Property, encode_fbx
from .rig import Rig

#: Millimetres to FBX centimetres.
MM_TO_CM = 0.1
MESH_NAME = "face_mesh"

# Fixed object ids: files are deterministic and ids stay readable in a dump.
_GEOMETRY_ID, _MESH_MODEL_ID, _SKIN_ID, _POSE_ID, _DOCUMENT_ID = 1000, 1001, 1002, 1003, 1004
_MATERIAL_ID = 1005
_JOINT_MODEL_BASE, _ATTRIBUTE_BASE, _CLUSTER_BASE = 100_000, 200_000, 300_000
_ANIMATION_BASE = 1_000_000  # stacks, layers, curve nodes and curves: counted up from here
#: FBX time units per second (KTime).
KTIME_PER_SECOND = 46_186_158_000
#: FBX TimeMode of the standard frame rates (FbxTime::EMode); others use 14 (custom).
TIME_MODES = {120.0: 1, 100.0: 2, 60.0: 3, 50.0: 4, 48.0: 5, 30.0: 6, 25.0: 10, 24.0: 11,
              1000.0: 12, 96.0: 15, 72.0: 16}
_CUSTOM_TIME_MODE = 14
# Linear interpolation, as the FBX SDK writes it (eInterpolationLinear | tangent flags), and the
# SDK's default tangent data (weights 1/3, encoded as four 32-bit words).
_LINEAR_KEY_FLAGS = 24836
# Property templates the FBX SDK needs to see animation (a curve node's channels live under the
# compound "d"; without it the SDK finds no curves).
_TEMPLATES: dict[str, tuple[str, list[tuple]]] = {
    "AnimationStack": ("FbxAnimStack", [
        ("Description", "KString", "", "", ""),
        *((key, "KTime", "Time", "", Int64(0))
          for key in ("LocalStart", "LocalStop", "ReferenceStart", "ReferenceStop"))]),
    "AnimationLayer": ("FbxAnimLayer", [
        ("Weight", "Number", "", "A", 100.0), ("Mute", "bool", "", "", 0),
        ("Solo", "bool", "", "", 0), ("Lock", "bool", "", "", 0),
        ("Color", "ColorRGB", "Color", "", 0.8, 0.8, 0.8), ("BlendMode", "enum", "", "", 0),
        ("RotationAccumulationMode", "enum", "", "", 0),
        ("ScaleAccumulationMode", "enum", "", "", 0),
        ("BlendModeBypass", "ULongLong", "", "", Int64(0))]),
    "AnimationCurveNode": ("FbxAnimCurveNode", [("d", "Compound", "", "")]),
}
_KEY_DATA = np.array([0, 0, 255790911, 0], dtype=np.int32).view(np.float32)


def write_rig_fbx(rig: Rig, path: str | os.PathLike[str], *, animation: RigAnimation | None = None,
                  force: bool = True) -> Path:
    """Atomically write ``rig`` (and ``animation``) as a binary FBX 7.4 file; returns the path."""
    return write_bytes(path, rig_fbx_bytes(rig, animation=animation), force=force)


def rig_fbx_bytes(rig: Rig, *, animation: RigAnimation | None = None) -> bytes:
    """The binary FBX 7.4 file for ``rig`` and its optional ``animation`` (deterministic)."""
    if animation is not None:
        animation.check_rig(rig)
    anim = _Animation(rig, animation) if animation is not None else None
    objects, links = _objects(rig), _links(rig)
    if anim is not None:
        objects.children += anim.objects
        links += anim.links
    return encode_fbx([
        _header_extension(),
        Node("FileId", [FILE_ID]),
        Node("CreationTime", [CREATION_TIME]),
        Node("Creator", [_creator()]),
        _global_settings(animation),
        _documents(anim.stack_names[0] if anim else ""),
        Node("References"),
        _definitions(rig, anim),
        objects,
        Node("Connections", [], [Node("C", [kind, Int64(child), Int64(parent), *prop])
                                 for kind, child, parent, *prop in links]),
        _takes(anim),
    ])


def ktime(frames: np.ndarray, rate: float) -> np.ndarray:
    """FBX times (int64 KTime) of frame numbers at ``rate`` frames per second."""
    return np.round(np.asarray(frames, dtype=np.float64) * (KTIME_PER_SECOND / rate)).astype(np.int64)


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


def _global_settings(animation: RigAnimation | None) -> Node:
    rate = 24.0 if animation is None else animation.rate
    mode = TIME_MODES.get(rate, _CUSTOM_TIME_MODE)
    longest = max((t.end - t.start for t in animation.takes), default=1) if animation else 25
    stop = ktime(np.array([longest - 1]), rate)[0]
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
        _p("TimeMode", "enum", "", "", mode),
        _p("TimeSpanStart", "KTime", "Time", "", Int64(0)),
        _p("TimeSpanStop", "KTime", "Time", "", Int64(int(stop))),
        _p("CustomFrameRate", "double", "Number", "", rate),
    ])
    return Node("GlobalSettings", [], [Node("Version", [1000]), props])


def _documents(active_stack: str) -> Node:
    document = Node("Document", [Int64(_DOCUMENT_ID), "", "Scene"], [
        Node("Properties70", [], [
            _p("SourceObject", "object", "", ""),
            _p("ActiveAnimStackName", "KString", "", "", active_stack),
        ]),
        Node("RootNode", [Int64(0)]),
    ])
    return Node("Documents", [], [Node("Count", [1]), document])


def _definitions(rig: Rig, anim: _Animation | None) -> Node:
    joints = rig.joint_count
    counts = [("GlobalSettings", 1), ("Geometry", 1), ("Model", 1 + joints),
              ("NodeAttribute", joints), ("Deformer", 1 + joints), ("Pose", 1),
              ("Material", len(groups(rig.materials, len(rig.faces))))]
    if anim is not None:
        counts += list(anim.counts.items())
    return definitions(counts)


def definitions(counts: list[tuple[str, int]]) -> Node:
    """The ``Definitions`` node: object counts per type, with the property templates the SDK needs."""
    node = Node("Definitions", [], [Node("Version", [100]),
                                    Node("Count", [sum(c for _, c in counts)])])
    for kind, count in counts:
        entry = Node("ObjectType", [kind], [Node("Count", [count])])
        if kind in _TEMPLATES:
            template, props = _TEMPLATES[kind]
            entry.children.append(Node("PropertyTemplate", [template],
                                       [Node("Properties70", [], [_p(*p) for p in props])]))
        node.children.append(entry)
    return node


def _objects(rig: Rig) -> Node:
    world_cm = rig.joint_positions * MM_TO_CM
    objects = Node("Objects", [], [_geometry(rig), _model(_MESH_MODEL_ID, MESH_NAME, "Mesh"),
                                   *_materials(rig)])
    for joint, name in enumerate(rig.joint_names):
        parent = int(rig.joint_parents[joint])
        local = world_cm[joint] - (world_cm[parent] if parent >= 0 else 0.0)
        kind = _skeleton_kind(rig, joint)
        flags = ["Null", "Skeleton", "Root"] if kind == "Root" else ["Skeleton"]
        objects.children.append(Node(
            "NodeAttribute", [Int64(_ATTRIBUTE_BASE + joint), f"{name}\x00\x01NodeAttribute", kind],
            [Node("Properties70", [], [_p("Size", "double", "Number", "", 1.0)]),
             Node("TypeFlags", flags)]))
        user = {"marker": rig.joint_markers[joint], "side": rig.joint_sides[joint],
                "region": rig.joint_regions[joint]}
        objects.children.append(_model(_JOINT_MODEL_BASE + joint, name, kind,
                                       translation=local, user=user))
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


def _skeleton_kind(rig: Rig, joint: int) -> str:
    """``Root`` for a root joint no vertex is weighted to, else ``LimbNode``.

    A skeleton Root becomes Blender's armature object (its motion: object animation) and its
    children leaf bones of 1 cm; as a LimbNode with 80 children spread over the face, Blender
    would make every bone as long as their mean distance (6 cm on a 14 cm face). A root with
    influences must stay a bone to deform the mesh.
    """
    if rig.joint_parents[joint] >= 0 or len(rig.joint_influences(joint)[0]):
        return "LimbNode"
    return "Root"


def _geometry(rig: Rig) -> Node:
    polygon_index = rig.faces.astype(np.int32).copy()
    polygon_index[:, 2] = ~polygon_index[:, 2]  # a polygon's last corner is stored as -(i+1)
    normals = Node("LayerElementNormal", [0], [
        Node("Version", [101]), Node("Name", [""]),
        Node("MappingInformationType", ["ByVertice"]),
        Node("ReferenceInformationType", ["Direct"]),
        Node("Normals", [rig.vertex_normals().astype(np.float64)]),
    ])
    uv = Node("LayerElementUV", [0], [
        Node("Version", [101]), Node("Name", ["UVMap"]),
        Node("MappingInformationType", ["ByVertice"]),
        Node("ReferenceInformationType", ["Direct"]),
        Node("UV", [rig.uv().astype(np.float64)]),
    ])
    used = groups(rig.materials, len(rig.faces))
    per_polygon = np.zeros(len(rig.faces), dtype=np.int32)  # the k-th material linked to the model
    for k, (_, tris) in enumerate(used):
        per_polygon[tris] = k
    material = Node("LayerElementMaterial", [0], [
        Node("Version", [101]), Node("Name", [""]),
        Node("MappingInformationType", ["AllSame" if len(used) == 1 else "ByPolygon"]),
        Node("ReferenceInformationType", ["IndexToDirect"]),
        Node("Materials", [per_polygon[:1] if len(used) == 1 else per_polygon]),
    ])
    layer = Node("Layer", [0], [Node("Version", [100])] + [
        Node("LayerElement", [], [Node("Type", [kind]), Node("TypedIndex", [0])])
        for kind in ("LayerElementNormal", "LayerElementMaterial", "LayerElementUV")])
    return Node("Geometry", [Int64(_GEOMETRY_ID), f"{MESH_NAME}\x00\x01Geometry", "Mesh"], [
        Node("Properties70"),
        Node("GeometryVersion", [124]),
        Node("Vertices", [rig.vertices.astype(np.float64) * MM_TO_CM]),
        Node("PolygonVertexIndex", [polygon_index]),
        normals, uv, material, layer,
    ])


def _materials(rig: Rig) -> list[Node]:
    """The mesh's materials (:mod:`~mocaptk.retarget.face_materials`), one per kind used."""
    return [_material(_material_id(k), m) for k, (m, _) in enumerate(groups(rig.materials, len(rig.faces)))]


def _material(object_id: int = _MATERIAL_ID, material: int = 0) -> Node:
    """Material ``material`` (:data:`~mocaptk.retarget.face_materials.MATERIALS`; default the
    skin): Lambert, its colour; a translucent one (lash cards) with its opacity."""
    colour, opacity = LOOKS[MATERIALS[material]]
    see_through = [_p("TransparentColor", "Color", "", "A", 1.0, 1.0, 1.0),
                   _p("TransparencyFactor", "Number", "", "A", 1.0 - opacity),
                   _p("Opacity", "Number", "", "A", opacity)] if opacity < 1 else []
    return Node("Material", [Int64(object_id), f"{material_name(material)}\x00\x01Material", ""], [
        Node("Version", [102]), Node("ShadingModel", ["lambert"]), Node("MultiLayer", [0]),
        Node("Properties70", [], [
            _p("DiffuseColor", "Color", "", "A", *colour),
            _p("DiffuseFactor", "Number", "", "A", 1.0), *see_through])])


def _material_id(k: int) -> int:
    """The object id of the mesh's ``k``-th material (the first: :data:`_MATERIAL_ID`)."""
    return _MATERIAL_ID + 100 * k


def _model(model_id: int, name: str, kind: str, *, translation: np.ndarray | None = None,
           user: dict[str, str] | None = None) -> Node:
    """A Model; ``user``: string user properties (flag ``U``: custom properties in DCC tools)."""
    t = np.zeros(3) if translation is None else translation
    props = Node("Properties70", [], [
        _p("Lcl Translation", "Lcl Translation", "", "A", *(float(v) for v in t)),
        _p("Lcl Rotation", "Lcl Rotation", "", "A", 0.0, 0.0, 0.0),
        _p("Lcl Scaling", "Lcl Scaling", "", "A", 1.0, 1.0, 1.0),
        _p("DefaultAttributeIndex", "int", "Integer", "", 0),
        _p("InheritType", "enum", "", "", 1),
        *(_p(key, "KString", "", "U", value) for key, value in sorted((user or {}).items())),
    ])
    return Node("Model", [Int64(model_id), f"{name}\x00\x01Model", kind], [
        Node("Version", [232]), props, Node("MultiLayer", [0]), Node("MultiTake", [0]),
        Node("Shading", [True]), Node("Culling", ["CullingOff"]),
    ])


def _links(rig: Rig) -> list[tuple]:
    """Object-object connections ``("OO", child id, parent id)`` of the rig."""
    links = [(_MESH_MODEL_ID, 0), (_GEOMETRY_ID, _MESH_MODEL_ID), (_SKIN_ID, _GEOMETRY_ID)]
    links += [(_material_id(k), _MESH_MODEL_ID) for k in range(len(groups(rig.materials, len(rig.faces))))]
    for joint in range(rig.joint_count):
        parent = int(rig.joint_parents[joint])
        model = _JOINT_MODEL_BASE + joint
        links.append((model, _JOINT_MODEL_BASE + parent if parent >= 0 else 0))
        links.append((_ATTRIBUTE_BASE + joint, model))
        links.append((_CLUSTER_BASE + joint, _SKIN_ID))
        links.append((model, _CLUSTER_BASE + joint))
    return [("OO", child, parent) for child, parent in links]


def _takes(anim: _Animation | None) -> Node:
    takes = Node("Takes", [], [Node("Current", [anim.stack_names[0] if anim else ""])])
    for name, (start, stop) in zip(anim.stack_names if anim else (), anim.spans if anim else ()):
        takes.children.append(Node("Take", [name], [
            Node("FileName", [f"{name}.tak"]),
            Node("LocalTime", [Int64(start), Int64(stop)]),
            Node("ReferenceTime", [Int64(start), Int64(stop)])]))
    return takes


class _Animation:
    """The FBX objects and connections of a :class:`RigAnimation`: per take an AnimationStack
    with one AnimationLayer, per joint a ``T`` curve node (3 curves, cm), and an ``R`` curve
    node (Euler XYZ degrees) on each rotating joint."""

    def __init__(self, rig: Rig, animation: RigAnimation) -> None:
        from scipy.spatial.transform import Rotation

        self.objects: list[Node] = []
        self.links: list[tuple] = []
        self.stack_names: list[str] = []
        self.spans: list[tuple[int, int]] = []
        self.counts = {"AnimationStack": 0, "AnimationLayer": 0, "AnimationCurveNode": 0,
                       "AnimationCurve": 0}
        self._next_id = _ANIMATION_BASE
        translation = animation.translations * MM_TO_CM
        # 'xyz' (extrinsic) = FBX eEulerXYZ: X applied first; unwrapped so keys never jump 360°
        euler = {joint: np.degrees(np.unwrap(Rotation.from_quat(
                     animation.rotations[:, k]).as_euler("xyz"), axis=0))
                 for k, joint in enumerate(animation.rotated)}
        for take in animation.takes:
            times = ktime(np.arange(take.end - take.start), animation.rate)  # the clip's own time
            name = _safe_take_name(take.name, self.stack_names)
            self.stack_names.append(name)
            self.spans.append((int(times[0]), int(times[-1])))
            stack = self._add("AnimationStack", name, "AnimStack", [Node("Properties70", [], [
                _p(key, "KTime", "Time", "", Int64(int(t)))
                for key, t in (("LocalStart", times[0]), ("LocalStop", times[-1]),
                               ("ReferenceStart", times[0]), ("ReferenceStop", times[-1]))])])
            layer = self._add("AnimationLayer", "BaseLayer", "AnimLayer", [])
            self.links.append(("OO", layer, stack))
            for joint in range(rig.joint_count):
                model = _JOINT_MODEL_BASE + joint
                self._curve_node(layer, model, "T", "Lcl Translation", times,
                                 translation[take.start:take.end, joint])
                if joint in euler:
                    self._curve_node(layer, model, "R", "Lcl Rotation", times,
                                     euler[joint][take.start:take.end])

    def _add(self, kind: str, name: str, fbx_class: str, children: list[Node]) -> int:
        object_id = self._next_id
        self._next_id += 1
        self.counts[kind] += 1
        self.objects.append(Node(kind, [Int64(object_id), f"{name}\x00\x01{fbx_class}", ""],
                                 children, block=True))
        return object_id

    def _curve_node(self, layer: int, model: int, short: str, prop: str, times: np.ndarray,
                    values: np.ndarray) -> None:
        """Curve node ``short`` (T/R) animating ``prop`` of ``model`` with ``values`` (K, 3)."""
        node = self._add("AnimationCurveNode", short, "AnimCurveNode", [Node("Properties70", [], [
            _p(f"d|{axis}", "Number", "", "A", float(values[0, k]))
            for k, axis in enumerate("XYZ")])])
        self.links += [("OO", node, layer), ("OP", node, model, prop)]
        for k, axis in enumerate("XYZ"):
            curve = self._add("AnimationCurve", "", "AnimCurve", [
                Node("Default", [float(values[0, k])]),
                Node("KeyVer", [4008]),
                Node("KeyTime", [times]),
                Node("KeyValueFloat", [values[:, k].astype(np.float32)]),
                Node("KeyAttrFlags", [np.array([_LINEAR_KEY_FLAGS], dtype=np.int32)]),
                Node("KeyAttrDataFloat", [_KEY_DATA]),
                Node("KeyAttrRefCount", [np.array([len(times)], dtype=np.int32)])])
            self.links.append(("OP", curve, node, f"d|{axis}"))


def _safe_take_name(name: str, taken: list[str]) -> str:
    """A unique, printable stack name (FBX names cannot hold the \\x00\\x01 separator)."""
    base = "".join(c if c.isprintable() else "_" for c in name) or "take"
    unique, n = base, 2
    while unique in taken:
        unique, n = f"{base}_{n}", n + 1
    return unique
