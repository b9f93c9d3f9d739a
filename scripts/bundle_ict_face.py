"""Write retarget/data/ict_face_neutral.npz: the ICT-FaceKit (MIT) neutral face region that the
default rig mesh fits to the markers to open the eyes, so that cut does not depend on a data
folder beside the repo; and retarget/data/ict_face_shapes.npz: the generic ARKit-52 rig of
``mocaptk retarget --character arkit``, ICT's expressions as float32 deltas (mm) on the same
face-region vertices. Usage: python scripts/bundle_ict_face.py [FaceXModel tarball or folder]
"""

from __future__ import annotations

import sys
import tarfile
from pathlib import Path

import numpy as np

from mocaptk.acquisition.face_model import default_model_path, load_face_model
from mocaptk.retarget.character import ARKIT_NAMES, ict_to_arkit

OUT = Path(__file__).resolve().parents[1] / "retarget" / "data"


def main(argv: list[str]) -> None:
    source = Path(argv[0]) if argv else default_model_path()
    model = load_face_model(source, use_cache=False)
    count = model.face_vertex_count
    np.savez_compressed(OUT / "ict_face_neutral.npz",
                        vertices=np.ascontiguousarray(model.neutral[:count], dtype=np.float64),
                        triangles=np.ascontiguousarray(model.face_triangles, dtype=np.int32))
    deltas = ict_to_arkit(model.blendshape_names, model.blendshapes[:, :count])
    np.savez_compressed(OUT / "ict_face_shapes.npz", names=np.array(ARKIT_NAMES),
                        deltas=np.ascontiguousarray(deltas, dtype=np.float32))
    with tarfile.open(source) as tar:  # the licence travels with the data (MIT: keep the notice)
        (OUT / "ICT-FaceKit-LICENSE.txt").write_bytes(tar.extractfile("ICT-FaceKit/LICENSE").read())


if __name__ == "__main__":
    main(sys.argv[1:])
