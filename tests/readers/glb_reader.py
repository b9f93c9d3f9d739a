"""Read back a skinned .glb (ours, or FBX2glTF's) into plain arrays for the export tests."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib

_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
           5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


@dataclass
class SkinnedGlb:
    """World-space vertex positions (N, 3), triangles (T, 3), per-vertex weights by joint name
    (N, J) in ``joint_names`` order, joint world matrices (J, 4, 4) and inverse bind matrices
    (J, 4, 4), both row-major with column vectors; glTF units (metres)."""

    positions: np.ndarray
    triangles: np.ndarray
    joint_names: list[str]
    weights: np.ndarray
    joint_world: np.ndarray
    inverse_bind: np.ndarray
    parents: dict[str, str | None]
    gltf: pygltflib.GLTF2


def read_skinned_glb(path: str | Path) -> SkinnedGlb:
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()

    def accessor(index: int) -> np.ndarray:
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        dtype = np.dtype(_DTYPES[acc.componentType]).newbyteorder("<")
        width = _WIDTH[acc.type]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        stride = view.byteStride or dtype.itemsize * width
        rows = [np.frombuffer(blob, dtype=dtype, count=width, offset=start + i * stride)
                for i in range(acc.count)]
        return np.array(rows).reshape(acc.count, width)

    world = _node_world_matrices(gltf)
    parents = {gltf.nodes[c].name: n.name for n in gltf.nodes for c in (n.children or [])}
    mesh_node = next(i for i, n in enumerate(gltf.nodes) if n.mesh is not None)
    primitive = gltf.meshes[gltf.nodes[mesh_node].mesh].primitives[0]
    skin = gltf.skins[gltf.nodes[mesh_node].skin]
    local = accessor(primitive.attributes.POSITION).astype(np.float64)
    positions = local @ world[mesh_node][:3, :3].T + world[mesh_node][:3, 3]
    triangles = accessor(primitive.indices).reshape(-1, 3).astype(np.int64)
    names = [gltf.nodes[j].name for j in skin.joints]
    weights = np.zeros((len(positions), len(names)))
    for pair in range(2):
        joints_at = getattr(primitive.attributes, f"JOINTS_{pair}", None)
        if joints_at is None:
            continue
        joints = accessor(joints_at).astype(np.int64)
        values = accessor(getattr(primitive.attributes, f"WEIGHTS_{pair}")).astype(np.float64)
        rows = np.repeat(np.arange(len(positions)), joints.shape[1])
        np.add.at(weights, (rows, joints.ravel()), values.ravel())
    inverse = accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    return SkinnedGlb(positions=positions, triangles=triangles, joint_names=names, weights=weights,
                      joint_world=np.array([world[j] for j in skin.joints]),
                      inverse_bind=inverse.astype(np.float64),
                      parents={n.name: parents.get(n.name) for n in gltf.nodes}, gltf=gltf)


def _node_world_matrices(gltf: pygltflib.GLTF2) -> list[np.ndarray]:
    local = []
    for node in gltf.nodes:
        if node.matrix is not None:
            local.append(np.array(node.matrix, dtype=np.float64).reshape(4, 4).T)
            continue
        t = np.array(node.translation or [0.0, 0.0, 0.0])
        x, y, z, w = node.rotation or [0.0, 0.0, 0.0, 1.0]
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        m = np.eye(4)
        m[:3, :3] = r * np.array(node.scale or [1.0, 1.0, 1.0])
        m[:3, 3] = t
        local.append(m)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    world: list[np.ndarray | None] = [None] * len(gltf.nodes)

    def resolve(i: int) -> np.ndarray:
        if world[i] is None:
            world[i] = local[i] if i not in parent else resolve(parent[i]) @ local[i]
        return world[i]

    return [resolve(i) for i in range(len(gltf.nodes))]
