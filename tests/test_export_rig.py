"""The Rig data type: validation, joint naming, construction from layout markers."""

from __future__ import annotations

import numpy as np
import pytest
from readers.sample_rig import sample_rig

from mocaptk.retarget.rig import Rig, RigError, joint_names_from_markers


def _fields(rig: Rig) -> dict:
    return {name: getattr(rig, name) for name in (
        "vertices", "faces", "joint_names", "joint_parents", "joint_positions", "joint_sides",
        "joint_regions", "joint_markers", "weight_index", "weight_value")}


def test_sample_rig_is_consistent():
    rig = sample_rig()
    dense = rig.dense_weights()
    assert dense.shape == (rig.vertex_count, rig.joint_count)
    np.testing.assert_allclose(dense.sum(axis=1), 1.0, atol=1e-12)
    assert rig.root == 0 and rig.joint_names[0] == "face_root"
    assert rig.max_influences == 4
    assert not rig.vertices.flags.writeable  # frozen data
    for joint in range(rig.joint_count):
        vertices, weights = rig.joint_influences(joint)
        np.testing.assert_array_equal(weights, dense[vertices, joint])
        assert np.all(np.diff(vertices) > 0)
        assert np.count_nonzero(dense[:, joint]) == len(vertices)


def test_unused_slots_are_stored_as_joint_zero():
    fields = _fields(sample_rig())
    index = np.array(fields["weight_index"])
    value = np.array(fields["weight_value"])
    value[0] = (1.0, 0.0, 0.0, 0.0)
    index[0] = (3, 5, 6, 2)
    rig = Rig(**{**fields, "weight_index": index, "weight_value": value})
    assert rig.weight_index[0].tolist() == [3, 0, 0, 0]


def _with(**changes) -> dict:
    fields = {k: np.array(v) if isinstance(v, np.ndarray) else v
              for k, v in _fields(sample_rig()).items()}
    fields.update(changes)
    return fields


def _weights_row0(index, value):
    fields = _with()
    fields["weight_index"][0] = index
    fields["weight_value"][0] = value
    return fields


@pytest.mark.parametrize("fields, message", [
    (_with(vertices=np.zeros((5, 2))), "vertices must have shape"),
    (_with(faces=np.array([[0, 1, 999]])), "faces index vertices outside"),
    (_with(joint_names=("face_root", "Brow_L", "Brow_L", "Nose_C", "Mouth_L", "Mouth_R",
                        "Chin_C")), "not unique"),
    (_with(joint_names=("face_root", "Brow-L", "Brow_R", "Nose_C", "Mouth_L", "Mouth_R",
                        "Chin_C")), "outside \\[A-Za-z0-9_\\]"),
    (_with(joint_names=("face_root", "L_Brow", "Brow_R", "Nose_C", "Mouth_L", "Mouth_R",
                        "Chin_C")), "side tag _L"),
    (_with(joint_sides=("C", "X", "R", "C", "L", "R", "C")), "side must be one of"),
    (_with(joint_parents=np.array([-1, -1, 0, 0, 0, 0, 0])), "exactly one root"),
    (_with(joint_parents=np.array([-1, 2, 0, 0, 0, 0, 0])), "parent must come before"),
    (_with(joint_regions=("",)), "joint_regions has 1 entries"),
    (_weights_row0((1, 2, 3, 4), (0.5, 0.5, 0.5, 0.0)), "do not sum to 1"),
    (_weights_row0((1, 2, 3, 4), (0.0, 0.0, 0.0, 0.0)), "no influence"),
    (_weights_row0((1, 1, 3, 4), (0.5, 0.5, 0.0, 0.0)), "same joint twice"),
    (_weights_row0((1, 9, 3, 4), (0.5, 0.5, 0.0, 0.0)), "outside 0..6"),
    (_weights_row0((1, 2, 3, 4), (1.5, -0.5, 0.0, 0.0)), "within \\[0, 1\\]"),
    (_with(joint_positions=np.full((7, 3), np.nan)), "finite"),
])
def test_invalid_rigs_are_refused(fields, message):
    with pytest.raises(RigError, match=message):
        Rig(**fields)


def test_joint_names_from_markers():
    names = joint_names_from_markers(
        ["Subj:LBrowIn", "mouth corner", "mouth-corner", "L_cheek", "nose.tip", "MOUTH_03_L",
         "NOSE_01_M", "LIP_01", "LBrowOuter"],
        ["L", "R", "R", "L", "C", "L", "C", "L", "R"])
    assert names == ("BrowIn_L", "mouth_corner_R", "mouth_corner_2_R", "cheek_L", "nose_tip_C",
                     "MOUTH_03_L", "NOSE_01_C", "LIP_01_L", "LBrowOuter_R")
    assert joint_names_from_markers(["LBrowOuter"], ["L"]) == ("BrowOuter_L",)
    with pytest.raises(RigError, match="side must be one of"):
        joint_names_from_markers(["a"], ["left"])
    with pytest.raises(RigError, match="2 marker labels but 1 sides"):
        joint_names_from_markers(["a", "b"], ["L"])


def test_joint_names_mirror_like_blender_flip_name():
    """Blender's bpy.utils.flip_name swaps a trailing _L/_R (and keeps _C): every L joint of a
    mirrored layout maps to an existing R joint (the rule re-stated: flip the final letter)."""
    labels = ["FOREHEAD_BROW_21_L", "FOREHEAD_BROW_21_R", "MOUTH_05_C", "LBrow", "RBrow"]
    names = joint_names_from_markers(labels, ["L", "R", "C", "L", "R"])
    assert names == ("FOREHEAD_BROW_21_L", "FOREHEAD_BROW_21_R", "MOUTH_05_C", "Brow_L", "Brow_R")
    flip = {"L": "R", "R": "L", "C": "C"}
    assert all(n[:-1] + flip[n[-1]] in names for n in names)


def test_from_markers_puts_root_first_and_shifts_indices():
    base = sample_rig()
    markers = base.joint_positions[1:]
    rig = Rig.from_markers(
        base.vertices, base.faces, marker_labels=list(base.joint_markers[1:]),
        marker_positions=markers, marker_sides=list(base.joint_sides[1:]),
        marker_regions=list(base.joint_regions[1:]),
        weight_index=np.zeros((base.vertex_count, 1), dtype=int) + 2,
        weight_value=np.ones((base.vertex_count, 1)))
    assert rig.joint_names == ("face_root", "Brow_L", "Brow_R", "Nose_C", "Mouth_L",
                               "Mouth_R", "Chin_C")
    assert rig.joint_parents.tolist() == [-1, 0, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(rig.joint_positions[0], markers.mean(axis=0))
    assert set(rig.weight_index.ravel()) == {3}  # marker 2 (Nose) is joint 3
    assert rig.joint_regions[0] == "" and rig.joint_markers[3] == "Nose"


def test_vertex_normals_face_the_camera():
    rig = sample_rig()
    normals = rig.vertex_normals()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    centre = np.argmin(np.linalg.norm(rig.vertices[:, [0, 1]] - (0.0, 1650.0), axis=1))
    np.testing.assert_allclose(normals[centre], (0.0, 0.0, 1.0), atol=1e-12)
    assert np.all(normals[:, 2] > 0.5)


def test_mesh_hash_tracks_geometry():
    rig = sample_rig()
    moved = Rig(**{**_fields(rig), "vertices": rig.vertices + (0.0, 0.0, 1e-3)})
    assert len(rig.mesh_sha256()) == 64
    assert rig.mesh_sha256() == sample_rig().mesh_sha256()
    assert moved.mesh_sha256() != rig.mesh_sha256()
