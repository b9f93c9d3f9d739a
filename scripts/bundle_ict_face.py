"""Write retarget/data/ict_face_neutral.npz: the ICT-FaceKit (MIT) neutral face region that the
default face is made of (fitted to the markers, see retarget/default_face.py), so it does not
depend on a data folder beside the repo. Arrays: ``vertices`` (9409, 3) mm, ``triangles``
(T, 3), ``uv`` (9409, 2) the model's texture coordinates (one per vertex on the face region).
Also retarget/data/ict_face_shapes.npz: the generic ARKit-52 rig of ``mocaptk retarget
--character arkit``, ICT's expressions as float32 deltas (mm) on the same face-region vertices.
And retarget/data/ict_face_parts.npz: the eyeballs, teeth and mouth socket of the default face
(retarget/face_parts.py), decimated (vtk's DecimatePro, topology and borders kept).
Usage: python scripts/bundle_ict_face.py [FaceXModel tarball or folder]
"""

from __future__ import annotations

import sys
import tarfile
from pathlib import Path

import numpy as np

from mocaptk.acquisition.face_model import default_model_path, load_face_model
from mocaptk.retarget.character import ARKIT_NAMES, ict_to_arkit

OUT = Path(__file__).resolve().parents[1] / "retarget" / "data"
MESH = "ICT-FaceKit/FaceXModel/generic_neutral_mesh.obj"


def face_uv(obj: str, count: int, polygons: int) -> np.ndarray:
    """Per-vertex texture coordinates (count, 2) of the first ``polygons`` faces of an OBJ (the
    face region has no UV seam: every corner of a vertex has the same ``vt``)."""
    lines = obj.splitlines()
    texcoords = np.array([line.split()[1:3] for line in lines if line.startswith("vt ")], float)
    faces = [line.split()[1:] for line in lines if line.startswith("f ")][:polygons]
    uv = np.full((count, 2), np.nan)
    for corners in faces:
        for corner in corners:
            v, t = (int(i) - 1 for i in corner.split("/")[:2])
            if np.isfinite(uv[v, 0]) and not np.allclose(uv[v], texcoords[t]):
                raise SystemExit(f"vertex {v} has two texture coordinates (a UV seam)")
            uv[v] = texcoords[t]
    if not np.isfinite(uv).all():
        raise SystemExit("a face-region vertex has no texture coordinate")
    return uv


#: ICT-FaceKit's pieces kept as the default face's parts (README "Face Model Topology": vertex
#: ranges) and how much of each DecimatePro removes: (name, first, end, reduction).
PARTS = (("eye", 21451, 24591, 0.8), ("teeth", 17039, 21451, 0.75), ("socket", 11248, 13294, 0.5))
#: The irises' vertex ranges (left, right) among the eyeballs'.
IRISES = ((22221, 23021), (23791, 24591))


def face_parts(obj: str) -> dict[str, np.ndarray]:
    """The eyeballs (sclera and iris, one closed piece each), the 32 teeth and the mouth socket
    (its triangles that reach the face region's lips keep those vertices, numbered as the face
    region's: ``attach``) as arrays: ``vertices`` (P, 3) float32 mm, ``triangles`` (Tp, 3) int32
    (indices into ``vertices``), ``material`` (Tp,) int8 (0 sclera, 1 iris, 2 teeth, 3 mouth) and ``attach``
    (P,) int32 (the face-region vertex a socket vertex is, else -1)."""
    import pyvista as pv
    from mocaptk.acquisition.face_model import CM_TO_MM, FACE_VERTEX_COUNT

    lines = obj.splitlines()
    points = np.array([line.split()[1:4] for line in lines if line.startswith("v ")], float) * CM_TO_MM
    polygons = [[int(c.split("/")[0]) - 1 for c in line.split()[1:]]
                for line in lines if line.startswith("f ")]
    triangles = np.array([[p[0], p[k], p[k + 1]] for p in polygons for k in range(1, len(p) - 1)])
    vertices, faces, material, attach = [], [], [], []
    count = 0
    for name, first, end, reduction in PARTS:
        inside = (triangles >= first) & (triangles < end)
        # the socket's triangles at the lips also use face-region vertices
        keep = inside.all(axis=1) | (inside.any(axis=1) & ((triangles < FACE_VERTEX_COUNT) | inside).all(axis=1))
        if name == "socket":  # the mouth's, not the eye sockets' sharing its range
            keep &= points[triangles, 1].mean(axis=1) < points[:FACE_VERTEX_COUNT, 1].mean()
        mesh = pv.PolyData(points, np.column_stack([np.full(int(keep.sum()), 3), triangles[keep]]))
        small = mesh.clean().decimate_pro(reduction, preserve_topology=True, boundary_vertex_deletion=False)
        tris = small.faces.reshape(-1, 4)[:, 1:]
        # decimation keeps the points it does not remove: find their source vertices
        source = _source_vertices(points, np.asarray(small.points))
        vertices.append(np.asarray(small.points))
        faces.append(tris + count)
        kind = {"eye": 0, "teeth": 2, "socket": 3}[name]
        iris = np.zeros(len(tris), bool)
        for low, high in IRISES:  # decimation keeps each triangle within its piece
            iris |= ((source[tris] >= low) & (source[tris] < high)).all(axis=1)
        material.append(np.where(iris, 1, kind))
        attach.append(np.where(source < FACE_VERTEX_COUNT, source, -1))
        count += small.n_points
    vertices, faces, material, attach = (np.concatenate(a) for a in (vertices, faces, material, attach))
    # each material's vertices together, in material order: a glTF importer that splits the
    # mesh by primitive (Blender) then keeps the vertex order
    kind = np.zeros(len(vertices), dtype=np.int64)
    kind[faces.ravel()] = np.repeat(material, 3)
    order = np.argsort(kind, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return {"vertices": vertices[order].astype(np.float32),
            "triangles": rank[faces].astype(np.int32),
            "material": material.astype(np.int8),
            "attach": attach[order].astype(np.int32)}


def _source_vertices(points: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """The index (K,) in ``points`` of each of ``kept`` (K, 3) (the lowest, where two coincide)."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(points).query(kept)
    if distance.max() > 1e-4:
        raise SystemExit("decimation moved a vertex")
    return index


def main(argv: list[str]) -> None:
    from mocaptk.acquisition.face_model import FACE_POLYGON_COUNT

    source = Path(argv[0]) if argv else default_model_path()
    model = load_face_model(source, use_cache=False)
    count = model.face_vertex_count
    deltas = ict_to_arkit(model.blendshape_names, model.blendshapes[:, :count])
    np.savez_compressed(OUT / "ict_face_shapes.npz", names=np.array(ARKIT_NAMES),
                        deltas=np.ascontiguousarray(deltas, dtype=np.float32))
    with tarfile.open(source) as tar:  # the licence travels with the data (MIT: keep the notice)
        (OUT / "ICT-FaceKit-LICENSE.txt").write_bytes(tar.extractfile("ICT-FaceKit/LICENSE").read())
        obj = tar.extractfile(MESH).read().decode()
    np.savez_compressed(OUT / "ict_face_parts.npz", **face_parts(obj))
    np.savez_compressed(OUT / "ict_face_neutral.npz",
                        vertices=np.ascontiguousarray(model.neutral[:count], dtype=np.float64),
                        triangles=np.ascontiguousarray(model.face_triangles, dtype=np.int32),
                        uv=np.ascontiguousarray(face_uv(obj, count, FACE_POLYGON_COUNT)))


if __name__ == "__main__":
    main(sys.argv[1:])
