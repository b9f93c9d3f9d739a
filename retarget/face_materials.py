"""The exports' materials (issue 30): a face mesh's triangles each get one of :data:`MATERIALS`,
so eyes, teeth and a user head's lash cards do not render as skin.

- the default face: its skin, then its parts' own (:mod:`~mocaptk.retarget.face_parts`: sclera,
  iris, teeth, mouth);
- a user's ``--mesh`` (:func:`mesh_materials`): its skin, then each other part by its kind
  (:func:`~mocaptk.retarget.mesh_parts.parts`): a closed piece above the nose tip an eye's
  ``sclera``, below it ``teeth``; an open piece below the nose tip (gums, tongue) ``mouth``;
  an open piece above it (lash cards, eye-occlusion and wet-rim shells, made for alpha or
  transparent materials) a translucent ``card``.

``rig.fbx``/``rig.glb`` and ``solve``'s ``mesh.usd``/``mesh.glb`` write one material per kind
used, with :data:`LOOKS` (glTF ``alphaMode`` BLEND, USD ``opacity``, FBX
``TransparencyFactor`` for the card).
"""

from __future__ import annotations

import numpy as np

__all__ = ["LOOKS", "MATERIALS", "groups", "material_name", "mesh_materials"]

#: The materials, by index (the skin first: a mesh without materials is all skin).
MATERIALS = ("skin", "sclera", "iris", "teeth", "mouth", "card")
#: Each material's base colour (linear RGB) and opacity (1: opaque).
LOOKS = {"skin": ((0.80, 0.62, 0.52), 1.0), "sclera": ((0.86, 0.85, 0.82), 1.0),
         "iris": ((0.16, 0.22, 0.30), 1.0), "teeth": ((0.90, 0.87, 0.78), 1.0),
         "mouth": ((0.36, 0.08, 0.08), 1.0), "card": ((0.06, 0.05, 0.04), 0.3)}


def material_name(index: int) -> str:
    """The exported name of material ``index``: ``face_skin``, ``face_sclera``..."""
    return f"face_{MATERIALS[int(index)]}"


def groups(materials: np.ndarray | None, count: int) -> list[tuple[int, np.ndarray]]:
    """``(material, triangles (k,))`` for each material used by ``materials`` (T,) (None: all
    ``count`` triangles skin), in :data:`MATERIALS` order."""
    if materials is None:
        return [(0, np.arange(count))]
    materials = np.asarray(materials)
    return [(int(m), np.flatnonzero(materials == m)) for m in np.unique(materials)]


def mesh_materials(vertices: np.ndarray, faces: np.ndarray, skin: int) -> np.ndarray:
    """Each triangle's material (T,) of a user's mesh whose first ``skin`` triangles are its skin
    (rig frame, Y up): the others by their part's kind, as the module says."""
    from .mesh_parts import nose_height, parts

    faces = np.asarray(faces, dtype=np.int64)
    materials = np.zeros(len(faces), dtype=np.int64)
    nose_y = nose_height(vertices, faces, skin)
    owner = np.full(len(vertices), -1, dtype=np.int64)
    found = parts(vertices, faces, skin, nose_y=nose_y)
    kinds = []
    for k, (members, kind) in enumerate(found):
        owner[members] = k
        if kind == "rigid":
            kinds.append(MATERIALS.index("sclera" if vertices[members, 1].mean() > nose_y else "teeth"))
        else:
            kinds.append(MATERIALS.index("card" if kind == "lid" else "mouth"))
    others = owner[faces[skin:, 0]]
    materials[skin:] = np.asarray(kinds, dtype=np.int64)[others] if len(others) else 0
    return materials
