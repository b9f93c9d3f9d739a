"""The facial rig the exporters write: a mesh, one joint per layout marker under a root, weights.

Pure data with validation; no file I/O here (see ``export_json``, ``export_fbx``, ``export_glb``).
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mocaptk.jsonio import to_plain
from mocaptk.surface_mesh import vertex_normals

#: Side tags a joint name ends with (character's left = +X when the face looks down +Z).
SIDES = ("L", "R", "C")
#: Name of the joint that parents every marker joint.
ROOT_NAME = "face_root"
#: Region of the stabilization locators (``stabilization_H1``...): like the structural joints
#: (``head``, ``jaw``: no marker) their names carry no side tag (a rigid set, not mirror pairs).
STABILIZATION_REGION = "stabilization"
#: Decimals (of a millimetre) kept for vertex positions in the mesh hash and in rig.json.
MESH_DIGITS = 6
#: Tolerance on each weight row summing to 1.
WEIGHT_SUM_TOL = 1e-6

_NAME_RE = re.compile(r"^[A-Za-z0-9_]+$")
_BAD_CHARS_RE = re.compile(r"[^A-Za-z0-9_]+")
# a side token on a marker label: suffix "_L", prefix "L_", camel-case prefix "LBrow"
_SIDE_TOKEN_RES = (re.compile(r"^(?P<stem>.+)_(?P<side>[LRCMlrcm])$"),
                   re.compile(r"^(?P<side>[LRCMlrcm])_(?P<stem>.+)$"),
                   re.compile(r"^(?P<side>[LRC])(?P<stem>[A-Z][a-z].*)$"))
_SIDE_ALIASES = {"L": "L", "R": "R", "C": "C", "M": "C"}


class RigError(ValueError):
    """The arrays handed to :class:`Rig` are inconsistent (a bug upstream, not a user mistake)."""


@dataclass(frozen=True, eq=False)
class Rig:
    """A skinned face rig.

    Parameters
    ----------
    vertices : (V, 3) float64
        Mesh vertex positions in millimetres (Y up, face looking down +Z).
    faces : (T, 3) int64
        Triangles, indices into ``vertices``.
    joint_names : sequence of str, length J
        Unique names matching ``[A-Za-z0-9_]+``; every joint except the root ends with
        ``_L``, ``_R`` or ``_C`` matching ``joint_sides`` (mirror tools pair them).
    joint_parents : (J,) int64
        Parent joint index, ``-1`` for the single root; parents come before children.
    joint_positions : (J, 3) float64
        Bind (neutral) positions in millimetres; joints have identity bind rotation.
    joint_sides : sequence of str, length J
        ``"L"``, ``"R"`` or ``"C"``.
    joint_regions : sequence of str, length J
        Facial region of the joint's marker (``""`` for the root).
    joint_markers : sequence of str, length J
        Source marker label of each joint (``""`` for the root).
    weight_index : (V, k) int64
        Joint indices of each vertex's influences.
    weight_value : (V, k) float64
        Matching weights in [0, 1]; rows sum to 1, at least one positive entry per row.
        Unused slots hold weight 0 (their index is stored as 0).
    texcoords : (V, 2) float64, optional
        Texture coordinates in [0, 1] (the default face's own layout); default: :meth:`uv`'s
        front projection.
    materials : (T,) int64, optional
        Each triangle's material, an index into
        :data:`~mocaptk.retarget.face_materials.MATERIALS` (0 skin); default: all skin.
    """

    vertices: np.ndarray
    faces: np.ndarray
    joint_names: tuple[str, ...]
    joint_parents: np.ndarray
    joint_positions: np.ndarray
    joint_sides: tuple[str, ...]
    joint_regions: tuple[str, ...]
    joint_markers: tuple[str, ...]
    weight_index: np.ndarray
    weight_value: np.ndarray
    texcoords: np.ndarray | None = None
    materials: np.ndarray | None = None

    def __post_init__(self) -> None:
        def put(name: str, value: object) -> None:
            object.__setattr__(self, name, value)

        vertices = _array(self.vertices, np.float64, "vertices", (None, 3))
        faces = _array(self.faces, np.int64, "faces", (None, 3))
        positions = _array(self.joint_positions, np.float64, "joint_positions", (None, 3))
        count = len(positions)
        parents = _array(self.joint_parents, np.int64, "joint_parents", (count,))
        names = _strings(self.joint_names, "joint_names", count)
        sides = _strings(self.joint_sides, "joint_sides", count)
        regions = _strings(self.joint_regions, "joint_regions", count)
        markers = _strings(self.joint_markers, "joint_markers", count)
        index = _array(self.weight_index, np.int64, "weight_index", (len(vertices), None))
        value = _array(self.weight_value, np.float64, "weight_value", index.shape)

        if len(vertices) == 0 or len(faces) == 0:
            raise RigError("rig mesh has no vertices or no faces")
        if not np.all(np.isfinite(vertices)) or not np.all(np.isfinite(positions)):
            raise RigError("rig vertices and joint positions must be finite")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise RigError(f"faces index vertices outside 0..{len(vertices) - 1}")
        if count == 0:
            raise RigError("rig has no joints")
        _check_hierarchy(parents)
        _check_names(names, sides, parents, regions, markers)
        if index.shape[1] == 0:
            raise RigError("weight_index has no influence columns")
        if index.min() < 0 or index.max() >= count:
            raise RigError(f"weight_index refers to joints outside 0..{count - 1}")
        if not np.all(np.isfinite(value)) or value.min() < 0 or value.max() > 1:
            raise RigError("weight_value must be finite and within [0, 1]")
        empty = ~np.any(value > 0, axis=1)
        if np.any(empty):
            raise RigError(f"{int(empty.sum())} vertices have no influence "
                           f"(first: vertex {int(np.argmax(empty))})")
        bad_sum = np.abs(value.sum(axis=1) - 1.0) > WEIGHT_SUM_TOL
        if np.any(bad_sum):
            raise RigError(f"weights of {int(bad_sum.sum())} vertices do not sum to 1 "
                           f"(first: vertex {int(np.argmax(bad_sum))})")
        used = np.where(value > 0, index, -1 - np.arange(index.shape[1]))
        if np.any(np.diff(np.sort(used, axis=1), axis=1) == 0):
            raise RigError("a vertex lists the same joint twice among its influences")

        index[value <= 0] = 0  # unused slots: weight 0, joint 0
        if self.texcoords is not None:
            uv = _array(self.texcoords, np.float64, "texcoords", (len(vertices), 2))
            if not np.all(np.isfinite(uv)):
                raise RigError("texcoords must be finite")
            uv.setflags(write=False)
            put("texcoords", uv)
        if self.materials is not None:
            kinds = _array(self.materials, np.int64, "materials", (len(faces),))
            if kinds.size and kinds.min() < 0:
                raise RigError("materials must be >= 0")
            kinds.setflags(write=False)
            put("materials", kinds)

        for name, array in (("vertices", vertices), ("faces", faces),
                            ("joint_positions", positions), ("joint_parents", parents),
                            ("weight_index", index), ("weight_value", value)):
            array.setflags(write=False)
            put(name, array)
        put("joint_names", names)
        put("joint_sides", sides)
        put("joint_regions", regions)
        put("joint_markers", markers)

    @property
    def vertex_count(self) -> int:
        return int(len(self.vertices))

    @property
    def joint_count(self) -> int:
        return int(len(self.joint_names))

    @property
    def max_influences(self) -> int:
        """k, the number of influence slots per vertex."""
        return int(self.weight_index.shape[1])

    @property
    def root(self) -> int:
        """Index of the root joint."""
        return int(np.flatnonzero(self.joint_parents < 0)[0])

    def mesh_sha256(self) -> str:
        """SHA-256 (hex) of the mesh, unchanged by a rig.json round trip (:func:`mesh_sha256`)."""
        return mesh_sha256(to_plain(self.vertices, digits=MESH_DIGITS), self.faces.tolist())

    def vertex_normals(self) -> np.ndarray:
        """Unit area-weighted vertex normals ``(V, 3)``; ``+Z`` where a vertex has none.

        Exporters need unit normals everywhere (glTF validation), hence the fallback.
        """
        normals = vertex_normals(self.vertices, self.faces)
        normals[~np.any(normals, axis=1)] = (0.0, 0.0, 1.0)
        return normals

    def uv(self) -> np.ndarray:
        """Texture coordinates (V, 2) in [0, 1], V up: :attr:`texcoords` when the rig has them,
        else the front (X, Y) projection of the mesh scaled to its bounding square, U towards
        +X (one chart, no seams: a face seen from the front)."""
        if self.texcoords is not None:
            return np.array(self.texcoords)
        xy = self.vertices[:, :2]
        low = xy.min(axis=0)
        size = max(float(np.ptp(xy, axis=0).max()), 1e-12)
        return (xy - low) / size

    def dense_weights(self) -> np.ndarray:
        """Weights as a dense ``(V, J)`` float64 matrix."""
        dense = np.zeros((self.vertex_count, self.joint_count))
        rows = np.repeat(np.arange(self.vertex_count), self.max_influences)
        np.add.at(dense, (rows, self.weight_index.ravel()), self.weight_value.ravel())
        return dense

    def joint_influences(self, joint: int) -> tuple[np.ndarray, np.ndarray]:
        """Vertices influenced by ``joint`` (ascending int64) and their weights (float64)."""
        mask = (self.weight_index == joint) & (self.weight_value > 0)
        rows, cols = np.nonzero(mask)
        order = np.argsort(rows, kind="stable")
        return rows[order].astype(np.int64), self.weight_value[rows[order], cols[order]]

    @classmethod
    def from_markers(cls, vertices: np.ndarray, faces: np.ndarray, *,
                     marker_labels: Sequence[str], marker_positions: np.ndarray,
                     marker_sides: Sequence[str], marker_regions: Sequence[str],
                     weight_index: np.ndarray, weight_value: np.ndarray,
                     root_position: np.ndarray | None = None,
                     root_name: str = ROOT_NAME, texcoords: np.ndarray | None = None,
                     materials: np.ndarray | None = None) -> Rig:
        """Build a rig with one joint per marker under a root joint.

        Parameters
        ----------
        vertices, faces : (V, 3) float mm, (T, 3) int
            The mesh.
        marker_labels, marker_sides, marker_regions : sequences of length M
            Layout marker labels, sides (``L``/``R``/``C``) and regions.
        marker_positions : (M, 3) float
            Neutral marker positions in mm (the joints' bind positions).
        weight_index, weight_value : (V, k) int, (V, k) float
            Influences with indices into the **markers** (0..M-1); the root is joint 0, so
            marker ``m`` becomes joint ``m + 1``.
        root_position : (3,) float mm, optional
            Defaults to the centroid of the markers.
        """
        positions = np.asarray(marker_positions, dtype=np.float64)
        if positions.ndim != 2 or positions.shape[1:] != (3,):
            raise RigError(f"marker_positions must have shape (M, 3), got {positions.shape}")
        root = positions.mean(axis=0) if root_position is None else root_position
        names = joint_names_from_markers(marker_labels, marker_sides)
        if root_name in names:
            raise RigError(f"a marker joint is named like the root: {root_name}")
        count = len(positions)
        return cls(
            vertices=vertices, faces=faces,
            joint_names=(root_name, *names),
            joint_parents=np.array([-1] + [0] * count),
            joint_positions=np.vstack([np.reshape(root, (1, 3)), positions]),
            joint_sides=("C", *marker_sides),
            joint_regions=("", *marker_regions),
            joint_markers=("", *marker_labels),
            weight_index=np.asarray(weight_index) + 1,
            weight_value=weight_value, texcoords=texcoords, materials=materials,
        )


def mesh_sha256(vertices: list[list[float]], faces: list[list[int]]) -> str:
    """SHA-256 (hex) of the UTF-8 text ``{"faces":[[a,b,c],...],"vertices":[[x,y,z],...]}``.

    ``vertices`` in mm already rounded to :data:`MESH_DIGITS` decimals as :mod:`mocaptk.jsonio`
    writes them (``to_plain(vertices, digits=MESH_DIGITS)``); no spaces in the text.
    """
    text = json.dumps({"faces": faces, "vertices": vertices}, sort_keys=True,
                      separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def joint_names_from_markers(labels: Sequence[str], sides: Sequence[str]) -> tuple[str, ...]:
    """Joint names ``<label>_<side>`` from marker labels and sides, unique and ``[A-Za-z0-9_]``.

    One side token, as a suffix, so Blender's ``flip_name`` and Maya's mirror tools pair
    ``BROW_21_L`` with ``BROW_21_R`` (midline: ``_C``). Subject prefixes (``Subject:``) are
    dropped, other characters become ``_``, a side token already on the label that matches the
    side is not repeated (``MOUTH_03_L``, ``L_brow``, ``LBrowOuter`` give ``MOUTH_03_L``,
    ``brow_L``, ``BrowOuter_L``), and duplicates get ``_2``, ``_3``... before the side.
    """
    if len(labels) != len(sides):
        raise RigError(f"{len(labels)} marker labels but {len(sides)} sides")
    names: list[str] = []
    taken: set[str] = set()
    for label, side in zip(labels, sides):
        if side not in SIDES:
            raise RigError(f"marker {label!r}: side must be one of {SIDES}, got {side!r}")
        stem = _BAD_CHARS_RE.sub("_", str(label).rsplit(":", 1)[-1]).strip("_") or "marker"
        stem = _strip_side(stem, side)
        name, suffix = f"{stem}_{side}", 2
        while name in taken:
            name = f"{stem}_{suffix}_{side}"
            suffix += 1
        taken.add(name)
        names.append(name)
    return tuple(names)


def _strip_side(stem: str, side: str) -> str:
    """``stem`` without a side token matching ``side`` (suffix ``_L``, prefix ``L_``, camel
    ``LBrow``; midline ``C`` or ``M``); unchanged if the token is another side's."""
    for pattern in _SIDE_TOKEN_RES:
        match = pattern.match(stem)
        if match and _SIDE_ALIASES.get(match["side"].upper()) == side:
            return match["stem"]
    return stem


def _array(value: object, dtype: type, what: str, shape: tuple[int | None, ...]) -> np.ndarray:
    array = np.array(value, dtype=dtype, copy=True)
    wrong = any(s is not None and s != n for s, n in zip(shape, array.shape))
    if array.ndim != len(shape) or wrong:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise RigError(f"{what} must have shape {want}, got {array.shape}")
    return array


def _strings(value: Sequence[str], what: str, count: int) -> tuple[str, ...]:
    items = tuple(str(v) for v in value)
    if len(items) != count:
        raise RigError(f"{what} has {len(items)} entries for {count} joints")
    return items


def _check_hierarchy(parents: np.ndarray) -> None:
    roots = np.flatnonzero(parents < 0)
    if len(roots) != 1 or parents[roots[0]] != -1:
        raise RigError(f"rig needs exactly one root joint (parent -1), found {len(roots)}")
    children = np.flatnonzero(parents >= 0)
    if np.any(parents[children] >= children):
        raise RigError("every joint's parent must come before it (parent index < joint index)")


def _check_names(names: tuple[str, ...], sides: tuple[str, ...], parents: np.ndarray,
                 regions: tuple[str, ...], markers: tuple[str, ...]) -> None:
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise RigError(f"joint names are not unique: {', '.join(dup[:5])}")
    for name, side in zip(names, sides):
        if not _NAME_RE.match(name):
            raise RigError(f"joint name {name!r} has characters outside [A-Za-z0-9_]")
        if side not in SIDES:
            raise RigError(f"joint {name!r}: side must be one of {SIDES}, got {side!r}")
    for name, side, parent, region, marker in zip(names, sides, parents, regions, markers):
        # structural joints (head, jaw: no marker) and locators carry no mirror-paired side tag
        untagged = not marker or region == STABILIZATION_REGION
        if parent >= 0 and not untagged and not name.endswith(f"_{side}"):
            raise RigError(f"joint {name!r} must end with its side tag _{side}")
