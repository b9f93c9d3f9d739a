"""ICT-FaceKit (MIT) read on its own: the face area's neutral, expression and identity shapes.

The FaceXModel OBJs share one vertex order (26,719 vertices, cm); a shape mode is its OBJ minus
``generic_neutral_mesh.obj``. Only the face area (vertices 0..9408, ICT's README) is kept, in mm.
The parsed arrays are cached as an ``.npz`` beside nothing of mocaptk's (``TESTBED_CACHE`` or the
temp folder): the tarball costs ~20 s to read, the cache ~0.1 s.
"""

from __future__ import annotations

import os
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: ICT's "Full face area" and "Narrow face area" vertex ranges (README, Face Area Details).
FACE_VERTICES, NARROW_VERTICES = 9409, 6706
CM_TO_MM = 10.0
MEMBER = "ICT-FaceKit/FaceXModel/"


@dataclass(frozen=True)
class IctFace:
    """Face area of ICT-FaceKit in mm: ``neutral`` (V, 3), ``faces`` (T, 3) triangles,
    ``expressions`` (E, V, 3) deltas named ``expression_names``, ``identities`` (I, V, 3) deltas."""

    neutral: np.ndarray
    faces: np.ndarray
    expression_names: tuple[str, ...]
    expressions: np.ndarray
    identities: np.ndarray

    def delta(self, name: str) -> np.ndarray:
        return self.expressions[self.expression_names.index(name)]


def _vertices(text: str) -> np.ndarray:
    """(N, 3) of an OBJ's ``v`` lines."""
    rows = [line[2:] for line in text.splitlines() if line.startswith("v ")]
    return np.array(" ".join(rows).split(), dtype=np.float64).reshape(-1, 3)


def _triangles(text: str, limit: int) -> np.ndarray:
    """Polygons (``f`` lines, ``v/vt/vn`` tokens, 1-based) fanned into triangles, those whose
    vertices are all below ``limit``."""
    out = []
    for line in text.splitlines():
        if not line.startswith("f "):
            continue
        idx = [int(token.split("/")[0]) - 1 for token in line.split()[1:]]
        if max(idx) >= limit:
            continue
        out.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    return np.array(out, dtype=np.intp)


def _cache_path(tarball: Path) -> Path:
    folder = Path(os.environ.get("TESTBED_CACHE", tempfile.gettempdir()))
    stat = tarball.stat()
    return folder / f"testbed_ict_{stat.st_size}_{int(stat.st_mtime)}.npz"


def load_ict(tarball: str | os.PathLike[str]) -> IctFace:
    """Read (or the cache of) ``ict_facekit_FaceXModel_subset.tar.xz``."""
    tarball = Path(tarball)
    cache = _cache_path(tarball)
    if cache.exists():
        with np.load(cache) as data:
            return IctFace(data["neutral"], data["faces"], tuple(str(n) for n in data["names"]),
                           data["expressions"], data["identities"])
    texts: dict[str, str] = {}
    with tarfile.open(tarball, "r:xz") as archive:
        for member in archive:
            name = member.name
            if name.startswith(MEMBER) and name.endswith(".obj"):
                texts[name[len(MEMBER):-4]] = archive.extractfile(member).read().decode()
    base_text = texts.pop("generic_neutral_mesh")
    base = _vertices(base_text)[:FACE_VERTICES]
    faces = _triangles(base_text, FACE_VERTICES)
    ids = sorted(n for n in texts if n.startswith("identity"))
    exprs = sorted(n for n in texts if not n.startswith("identity") and not n.startswith("Pupil"))
    def deltas(names: list[str]) -> np.ndarray:
        return np.stack([(_vertices(texts[n])[:FACE_VERTICES] - base) * CM_TO_MM for n in names])
    face = IctFace(base * CM_TO_MM, faces, tuple(exprs), deltas(exprs).astype(np.float32),
                   deltas(ids).astype(np.float32))
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, neutral=face.neutral, faces=face.faces, names=np.array(face.expression_names),
             expressions=face.expressions, identities=face.identities)
    os.replace(tmp, cache)
    return face
