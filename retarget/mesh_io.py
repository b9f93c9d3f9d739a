"""Read a character face mesh (OBJ, PLY, glTF/GLB, STL, OFF) into vertices and triangles.

OBJ is read directly: its ``v`` positions in file order (so ``--landmarks`` indices are the
file's vertex numbers, 0-based) and its faces, polygons fanned into triangles, every group and
material in one index space. A UV or normal seam does not split a vertex (trimesh would, which
cut a production head into disconnected triangles), and materials are not read. The other
formats go through trimesh (MIT); scenes with several meshes are merged into one. Vertices keep
the file's units: alignment to the session (:mod:`mocaptk.retarget.align`) estimates the scale,
so a mesh in metres, centimetres or millimetres all work.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError
from mocaptk.surface_mesh import SurfaceMesh

#: File name endings trimesh reads that we accept as meshes.
MESH_SUFFIXES = (".obj", ".ply", ".gltf", ".glb", ".stl", ".off")


def load_mesh(path: str | os.PathLike[str]) -> SurfaceMesh:
    """Load a triangle mesh; vertices (V, 3) in the file's units, faces (T, 3) int64.

    Raises
    ------
    InputFileError
        Missing file, unsupported suffix, unreadable content, or no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "mesh file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputFileError(path, f"unsupported mesh format {path.suffix!r} "
                             f"(use one of {', '.join(MESH_SUFFIXES)})")
    vertices, faces = _read_obj(path) if path.suffix.lower() == ".obj" else _read_trimesh(path)
    if len(faces) == 0:
        raise InputFileError(path, "the file holds no triangle mesh")
    if not np.all(np.isfinite(vertices)):
        raise InputFileError(path, "mesh vertices contain NaN or inf")
    return SurfaceMesh(vertices, faces)


def _read_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of any trimesh format (scenes merged); empty faces if none."""
    import trimesh

    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise InputFileError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geometries = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geometries) if geometries else None
    if not isinstance(loaded, trimesh.Trimesh):
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64)


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """OBJ ``v`` positions (file order) and ``f`` polygons fanned into triangles (0-based)."""
    positions: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    try:
        with open(path, encoding="utf-8", errors="replace") as stream:
            for number, line in enumerate(stream, 1):
                parts = line.split()
                if not parts or parts[0] not in ("v", "f"):
                    continue
                if parts[0] == "v":
                    positions.append([float(x) for x in parts[1:4]])
                    if len(positions[-1]) != 3:
                        raise ValueError(f"line {number}: a vertex needs x y z")
                    continue
                corners = [int(c.split("/")[0]) for c in parts[1:]]
                # negative indices count back from the last vertex read so far
                corners = [c - 1 if c > 0 else len(positions) + c for c in corners]
                if len(corners) < 3 or min(corners) < 0 or max(corners) >= len(positions):
                    raise ValueError(f"line {number}: face with a missing vertex")
                triangles += [(corners[0], corners[k], corners[k + 1])
                              for k in range(1, len(corners) - 1)]
    except (OSError, ValueError) as exc:
        raise InputFileError(path, f"cannot read OBJ mesh ({exc})") from None
    return (np.array(positions, dtype=np.float64).reshape(-1, 3),
            np.array(triangles, dtype=np.int64).reshape(-1, 3))
