"""Read a character face mesh (OBJ, PLY, glTF/GLB, STL, OFF) into vertices and triangles.

Reading goes through trimesh (MIT), which handles the file formats; scenes with several
meshes are merged into one. Vertices keep the file's order and units (``process=False``):
alignment to the session (:mod:`mocaptk.retarget.align`) estimates the scale, so a mesh in
metres, centimetres or millimetres all work.
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
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "mesh file not found")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputFileError(path, f"unsupported mesh format {path.suffix!r} "
                             f"(use one of {', '.join(MESH_SUFFIXES)})")
    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise InputFileError(path, f"cannot read mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geometries = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        loaded = trimesh.util.concatenate(geometries) if geometries else None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InputFileError(path, "the file holds no triangle mesh")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    faces = np.asarray(loaded.faces, dtype=np.int64)
    if not np.all(np.isfinite(vertices)):
        raise InputFileError(path, "mesh vertices contain NaN or inf")
    return SurfaceMesh(vertices, faces)
