"""A small but real face-like rig with known answers for the export tests (no weights engine)."""

from __future__ import annotations

import numpy as np

from mocaptk.retarget.rig import Rig


def sample_rig(*, rows: int = 9, cols: int = 11, k: int = 4,
               silent_joints: tuple[str, ...] = ()) -> Rig:
    """A curved 140 x 120 mm grid patch (Y up, facing +Z) with 6 marker joints under a root.

    Weights: Gaussian falloff from each joint (sigma 30 mm), top ``k`` kept, renormalised;
    the root keeps a share on the outer rows so it has influences too. Joints named in
    ``silent_joints`` get no influence at all (empty clusters in FBX).
    """
    u, v = np.meshgrid(np.linspace(-70.0, 70.0, cols), np.linspace(-60.0, 60.0, rows))
    z = 90.0 - (u ** 2 + v ** 2) / 200.0
    vertices = np.column_stack([u.ravel(), v.ravel() + 1650.0, z.ravel()])
    quads = [(r * cols + c, r * cols + c + 1, (r + 1) * cols + c + 1, (r + 1) * cols + c)
             for r in range(rows - 1) for c in range(cols - 1)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])

    labels = ["LBrow", "RBrow", "Nose", "LMouth", "RMouth", "Chin"]
    sides = ["L", "R", "C", "L", "R", "C"]
    regions = ["brow", "brow", "nose", "mouth", "mouth", "jaw"]
    anchors = [0.4 * (rows - 1), 0.4 * (rows - 1), 0.5 * (rows - 1), 0.7 * (rows - 1),
               0.7 * (rows - 1), 0.9 * (rows - 1)]
    columns = [0.75, 0.25, 0.5, 0.65, 0.35, 0.5]
    vertex_ids = [int(round(rows - 1 - a)) * cols + int(round(c * (cols - 1)))
                  for a, c in zip(anchors, columns)]
    markers = vertices[vertex_ids]

    distance = np.linalg.norm(vertices[:, None, :] - markers[None, :, :], axis=2)
    dense = np.exp(-0.5 * (distance / 30.0) ** 2)
    outer = np.abs(v.ravel()) > 50.0
    dense = np.column_stack([np.where(outer, 0.3, 0.0), dense])  # column 0: the root
    names = ("face_root", "Brow_L", "Brow_R", "Nose_C", "Mouth_L", "Mouth_R", "Chin_C")
    dense[:, [names.index(n) for n in silent_joints]] = 0.0
    order = np.argsort(-dense, axis=1, kind="stable")[:, :k]
    value = np.take_along_axis(dense, order, axis=1)
    value /= value.sum(axis=1, keepdims=True)
    value[value < 1e-3] = 0.0
    value /= value.sum(axis=1, keepdims=True)
    return Rig(
        vertices=vertices, faces=faces,
        joint_names=names,
        joint_parents=np.array([-1, 0, 0, 0, 0, 0, 0]),
        joint_positions=np.vstack([markers.mean(axis=0), markers]),
        joint_sides=("C", *sides), joint_regions=("", *regions), joint_markers=("", *labels),
        weight_index=order, weight_value=value,
    )
