"""The ICT-FaceKit morphable face model (MIT, USC ICT) as numpy arrays in millimetres.

Reads the neutral mesh, the 53 ARKit-like expression blendshapes and the identity shapes
from the ICT-FaceKit ``FaceXModel`` OBJ files (a ``.tar.xz`` of them, or their folder) and
keeps the **face** (vertices ``[0, 9409)``, polygons ``[0, 9230)``, per the ICT-FaceKit README
"Face Model Topology" table) plus the **head and neck** (vertices ``[9409, 11248)``, polygons
``[9230, 11144)``), which a rigid head needs; mouth socket, teeth, eyeballs etc. are dropped.
ICT-FaceKit stores centimetres (face ≈ 18 cm wide); we convert to mm. Quads are split into
triangles. Parsed arrays are cached as a compressed ``.npz`` keyed by the source's sha256.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tarfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_open
from mocaptk.errors import InputFileError, OutputError

#: Face region and head+neck (ICT-FaceKit README, "Face Model Topology").
FACE_VERTEX_COUNT = 9409
FACE_POLYGON_COUNT = 9230
KEPT_VERTEX_COUNT = 11248
KEPT_POLYGON_COUNT = 11144
#: ICT-FaceKit OBJ coordinates are centimetres.
CM_TO_MM = 10.0

DEFAULT_TARBALL = "ict_facekit_FaceXModel_subset.tar.xz"
_CACHE_VERSION = 1
_WHERE_TO_GET = ("get ICT-FaceKit (MIT) from https://github.com/ICT-VGL/ICT-FaceKit (folder "
                 "FaceXModel) and pass its path or set MOCAPTK_ICT_FACEKIT")


@dataclass(frozen=True, eq=False)
class FaceModel:
    """A linear face model: ``neutral + identities·id_coeffs + blendshapes·weights``.

    Attributes
    ----------
    neutral : (V, 3) float64
        Generic neutral mesh, mm (+X = character's left, +Y up, +Z forward).
    faces : (T, 3) int64
        Triangles; those of the face region come first (``face_triangle_count`` of them).
    blendshape_names : tuple of str, length B
        ICT/ARKit expression names (``jawOpen``, ``mouthSmile_L`` ...).
    blendshapes : (B, V, 3) float64
        Expression deltas from ``neutral``, mm.
    identity_names : tuple of str, length I
    identities : (I, V, 3) float64
        Identity deltas from ``neutral``, mm.
    face_vertex_count : int
        Vertices ``[0, face_vertex_count)`` are the face region (9,409).
    face_triangle_count : int
        Triangles ``[0, face_triangle_count)`` use only face-region vertices.
    landmarks : (68,) int64
        Multi-PIE 68-point landmark vertex indices (ICT-FaceKit ``idx_to_landmark_verts``).
    source : str
        Where the model was read from.
    """

    neutral: np.ndarray
    faces: np.ndarray
    blendshape_names: tuple[str, ...]
    blendshapes: np.ndarray
    identity_names: tuple[str, ...]
    identities: np.ndarray
    face_vertex_count: int
    face_triangle_count: int
    landmarks: np.ndarray
    source: str = ""

    @property
    def face_triangles(self) -> np.ndarray:
        """(T_face, 3) triangles of the face region (indices < ``face_vertex_count``)."""
        return self.faces[:self.face_triangle_count]

    def blendshape_index(self, names: list[str] | tuple[str, ...]) -> np.ndarray:
        """Indices of the blendshapes called ``names``."""
        lookup = {name: i for i, name in enumerate(self.blendshape_names)}
        unknown = [n for n in names if n not in lookup]
        if unknown:
            raise KeyError(f"unknown blendshapes: {', '.join(unknown)}")
        return np.array([lookup[n] for n in names], dtype=np.intp)

    def identity_mesh(self, identity_coefficients: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) neutral mesh of an identity, mm (``None``: the generic neutral)."""
        if identity_coefficients is None:
            return self.neutral.copy()
        coeffs = np.asarray(identity_coefficients, dtype=np.float64)
        if coeffs.shape != (len(self.identity_names),):
            raise ValueError(f"expected {len(self.identity_names)} identity coefficients, "
                             f"got shape {coeffs.shape}")
        return self.neutral + np.tensordot(coeffs, self.identities, axes=1)

    def deform(self, weights: np.ndarray, *, base: np.ndarray | None = None) -> np.ndarray:
        """Meshes for blendshape ``weights`` ``(B,)`` or ``(F, B)`` → ``(V, 3)`` or ``(F, V, 3)`` mm.

        ``base`` is the neutral to deform (e.g. from :meth:`identity_mesh`); default ``neutral``.
        """
        base = self.neutral if base is None else base
        w = np.asarray(weights, dtype=np.float64)
        return base + np.tensordot(w, self.blendshapes, axes=(w.ndim - 1, 0))


def default_model_path() -> Path:
    """``$MOCAPTK_ICT_FACEKIT``, else ``../shared/data/face_mesh/ict_facekit/<tarball>`` of the repo."""
    env = os.environ.get("MOCAPTK_ICT_FACEKIT")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[1]
    return repo.parent / "shared" / "data" / "face_mesh" / "ict_facekit" / DEFAULT_TARBALL


def cache_dir() -> Path:
    """``$MOCAPTK_CACHE`` or ``~/.cache/mocaptk``."""
    env = os.environ.get("MOCAPTK_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "mocaptk"


def load_face_model(path: str | os.PathLike[str] | None = None, *,
                    use_cache: bool = True) -> FaceModel:
    """Load ICT-FaceKit from a ``FaceXModel`` tarball (``.tar.xz``) or folder.

    Parameters
    ----------
    path : path, optional
        Default :func:`default_model_path`.
    use_cache : bool
        Read/write the parsed arrays in :func:`cache_dir` (keyed by the source's sha256).

    Raises
    ------
    InputFileError
        The model is absent or malformed (the message says where to get it).
    """
    source = Path(path) if path is not None else default_model_path()
    if not source.exists():
        raise InputFileError(source, f"ICT-FaceKit face model not found; {_WHERE_TO_GET}")
    cached = cache_dir() / f"ict_facekit_{_source_sha256(source)[:20]}_v{_CACHE_VERSION}.npz"
    if use_cache and cached.is_file():
        try:
            with np.load(cached, allow_pickle=False) as data:
                return _build({key: data[key] for key in data.files}, source)
        except (OSError, KeyError, ValueError):
            pass  # a stale or broken cache is rebuilt below
    with _model_files(source) as (members, read):
        arrays = _parse(source, members, read)
    if use_cache:
        try:
            with atomic_open(cached, "wb") as handle:
                np.savez_compressed(handle, **arrays)
        except (OSError, OutputError):
            pass  # the cache is an optimisation; a read-only home must not break loading
    return _build(arrays, source)


def _source_sha256(source: Path) -> str:
    """sha256 of a tarball, or of a folder's model files (names and contents)."""
    sha = hashlib.sha256()
    if source.is_dir():
        for file in sorted(_model_folder(source).glob("*")):
            if file.suffix in (".obj", ".json"):
                sha.update(file.name.encode())
                sha.update(file.read_bytes())
    else:
        sha.update(source.read_bytes())
    return sha.hexdigest()


def _model_folder(source: Path) -> Path:
    return source / "FaceXModel" if (source / "FaceXModel").is_dir() else source


@contextlib.contextmanager
def _model_files(source: Path) -> Iterator[tuple[set[str], Callable[[str], bytes]]]:
    """Yield the model's file names and a reader ``name -> bytes`` (tarball or folder)."""
    if source.is_dir():
        files = {p.name: p for p in _model_folder(source).iterdir() if p.is_file()}
        yield set(files), lambda name: files[name].read_bytes()
        return
    try:
        archive = tarfile.open(source, "r:*")
    except (tarfile.TarError, OSError) as exc:
        raise InputFileError(source, f"not a readable ICT-FaceKit tarball ({exc})") from None
    with archive:
        by_name = {Path(m.name).name: m for m in archive.getmembers() if m.isfile()}

        def read(name: str) -> bytes:
            handle = archive.extractfile(by_name[name])
            assert handle is not None  # regular files always have a handle
            return handle.read()

        yield set(by_name), read


def _parse(source: Path, members: set[str],
           read: Callable[[str], bytes]) -> dict[str, np.ndarray]:
    for needed in ("vertex_indices.json", "generic_neutral_mesh.obj"):
        if needed not in members:
            raise InputFileError(source, f"no {needed} in the ICT-FaceKit model; {_WHERE_TO_GET}")
    config = json.loads(read("vertex_indices.json"))
    names = [str(n) for n in config["expressions"]]
    missing = [n for n in names if f"{n}.obj" not in members]
    if missing:
        raise InputFileError(source, f"missing expression meshes: {', '.join(missing[:5])}")
    neutral_text = read("generic_neutral_mesh.obj")
    neutral = _obj_vertices(neutral_text, source)
    faces = _obj_triangles(neutral_text, KEPT_POLYGON_COUNT)
    face_triangles = _obj_triangles(neutral_text, FACE_POLYGON_COUNT)
    if faces.max() >= KEPT_VERTEX_COUNT or face_triangles.max() >= FACE_VERTEX_COUNT:
        raise InputFileError(source, "unexpected ICT-FaceKit topology (face/head vertex ranges)")
    identity_names = sorted(n[:-4] for n in members
                            if n.startswith("identity") and n.endswith(".obj"))
    blendshapes = np.stack([_obj_vertices(read(f"{n}.obj"), source) - neutral for n in names])
    identities = (np.stack([_obj_vertices(read(f"{n}.obj"), source) - neutral
                            for n in identity_names])
                  if identity_names else np.zeros((0, KEPT_VERTEX_COUNT, 3)))
    return {
        "neutral": neutral * CM_TO_MM,
        "faces": faces,
        "face_triangle_count": np.array(len(face_triangles)),
        "blendshape_names": np.array(names),
        "blendshapes": (blendshapes * CM_TO_MM).astype(np.float32),
        "identity_names": np.array(identity_names, dtype=str),
        "identities": (identities * CM_TO_MM).astype(np.float32),
        "landmarks": np.asarray(config["idx_to_landmark_verts"], dtype=np.int64),
    }


def _obj_vertices(text: bytes, source: Path) -> np.ndarray:
    """The first ``KEPT_VERTEX_COUNT`` ``v x y z`` rows of an OBJ, (V, 3) float64 (file units)."""
    # ICT OBJs list their vertices in one block: split only that block (C speed)
    start = 0 if text.startswith(b"v ") else text.find(b"\nv ") + 1
    rows = text[start:].split(b"\n", KEPT_VERTEX_COUNT)[:KEPT_VERTEX_COUNT]
    if not all(row.startswith(b"v ") for row in rows):
        rows = [line for line in text.split(b"\n") if line.startswith(b"v ")]
    rows = [row[2:] for row in rows]
    if len(rows) < KEPT_VERTEX_COUNT:
        raise InputFileError(source, f"an OBJ has {len(rows)} vertices, expected ≥ {KEPT_VERTEX_COUNT}")
    values = np.array(b" ".join(rows[:KEPT_VERTEX_COUNT]).split(), dtype=np.float64)
    return values.reshape(KEPT_VERTEX_COUNT, 3)


def _obj_triangles(text: bytes, polygon_count: int) -> np.ndarray:
    """Triangles (fan split) of the first ``polygon_count`` ``f`` rows, 0-based, (T, 3) int64."""
    triangles: list[tuple[int, int, int]] = []
    count = 0
    for line in text.split(b"\n"):
        if not line.startswith(b"f "):
            continue
        if count == polygon_count:
            break
        corners = [int(token.split(b"/")[0]) - 1 for token in line.split()[1:]]
        triangles.extend((corners[0], corners[k], corners[k + 1]) for k in range(1, len(corners) - 1))
        count += 1
    return np.array(triangles, dtype=np.int64)


def _build(arrays: dict[str, np.ndarray], source: Path) -> FaceModel:
    return FaceModel(
        neutral=np.asarray(arrays["neutral"], dtype=np.float64),
        faces=np.asarray(arrays["faces"], dtype=np.int64),
        blendshape_names=tuple(str(n) for n in arrays["blendshape_names"]),
        blendshapes=np.asarray(arrays["blendshapes"], dtype=np.float64),
        identity_names=tuple(str(n) for n in arrays["identity_names"]),
        identities=np.asarray(arrays["identities"], dtype=np.float64),
        face_vertex_count=FACE_VERTEX_COUNT,
        face_triangle_count=int(arrays["face_triangle_count"]),
        landmarks=np.asarray(arrays["landmarks"], dtype=np.int64),
        source=os.fspath(source),
    )
