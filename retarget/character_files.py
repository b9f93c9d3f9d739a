"""Reading a blendshape character (:class:`~mocaptk.retarget.character.Character`): ``load_character(spec)`` reads

- ``arkit``: the generic ARKit-52 rig bundled with the package: ICT-FaceKit's face region (MIT,
  ``data/ict_face_neutral.npz``) and its expressions as ARKit's 52 shapes
  (``data/ict_face_shapes.npz``, written by ``scripts/bundle_ict_face.py``). ICT splits
  ``browInnerUp`` and ``cheekPuff`` into ``_L``/``_R``: their deltas are summed; ICT has no
  ``tongueOut``: a zero shape.
- a glTF / GLB: the first mesh with morph targets (first such primitive), names from the
  mesh's ``extras.targetNames``; metres → mm;
- a binary FBX: the mesh a ``BlendShape`` deformer is attached to, its channels' shapes;
- a USD: the first ``UsdSkelBindingAPI`` mesh with ``skel:blendShapes`` (offsets and optional
  point indices); ``metersPerUnit`` → mm.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

from .character import Character
from .character_fbx import read_fbx_character
from .character_gltf import read_gltf_character
from .character_usd import read_usd_character
from .face_template import template_face

__all__ = ["generic_arkit", "load_character"]

#: The bundled generic rig's shapes (deltas on ``face_template.TEMPLATE_FILE``'s vertices).
SHAPES_FILE = "data/ict_face_shapes.npz"


def load_character(spec: str | os.PathLike[str]) -> Character:
    """``arkit`` (the bundled generic rig) or a glTF/GLB/USD file with blend shapes.

    Raises :class:`InputFileError` for a missing/unreadable file or one without shapes.
    """
    if os.fspath(spec) == "arkit":
        return generic_arkit()
    path = Path(spec)
    if not path.is_file():
        raise InputFileError(path, "character file not found (give arkit, a .glb/.gltf, .fbx or .usd)")
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        character = read_gltf_character(path)
    elif suffix == ".fbx":
        character = read_fbx_character(path)
    elif suffix in (".usd", ".usda", ".usdc"):
        character = read_usd_character(path)
    else:
        raise InputFileError(path, f"unsupported character format {path.suffix!r} "
                             "(use arkit, .glb, .gltf, .fbx, .usd, .usda, .usdc)")
    if not character.names:
        raise InputFileError(path, "the character has no blend shapes (morph targets)")
    if not (np.isfinite(character.vertices).all() and np.isfinite(character.deltas).all()):
        raise InputFileError(path, "the character's vertices or shapes contain NaN or inf")
    return character


def generic_arkit() -> Character:
    """The bundled ICT-FaceKit (MIT) ARKit-52 face."""
    vertices, faces = template_face()
    with resources.files(__package__).joinpath(SHAPES_FILE).open("rb") as handle:
        with np.load(handle, allow_pickle=False) as data:
            names, deltas = tuple(str(n) for n in data["names"]), data["deltas"]
    return Character(np.asarray(vertices, dtype=np.float64), faces, names, deltas,
                     "arkit (ICT-FaceKit, MIT)")
