"""Write retarget/data/ict_face_neutral.npz: the ICT-FaceKit (MIT) neutral face region that the
default face is made of (fitted to the markers, see retarget/default_face.py), so it does not
depend on a data folder beside the repo. Arrays: ``vertices`` (9409, 3) mm, ``triangles``
(T, 3), ``uv`` (9409, 2) the model's texture coordinates (one per vertex on the face region).
Also retarget/data/ict_face_shapes.npz: the generic ARKit-52 rig of ``mocaptk retarget
--character arkit``, ICT's expressions as float32 deltas (mm) on the same face-region vertices.
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
    np.savez_compressed(OUT / "ict_face_neutral.npz",
                        vertices=np.ascontiguousarray(model.neutral[:count], dtype=np.float64),
                        triangles=np.ascontiguousarray(model.face_triangles, dtype=np.int32),
                        uv=np.ascontiguousarray(face_uv(obj, count, FACE_POLYGON_COUNT)))


if __name__ == "__main__":
    main(sys.argv[1:])
