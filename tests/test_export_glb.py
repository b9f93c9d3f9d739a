"""rig.glb: skinned mesh read back with pygltflib (metres, weights, inverse bind matrices) and
0 errors / 0 warnings from the Khronos glTF validator."""

from __future__ import annotations

import numpy as np
import pytest
from readers import installed
from readers.glb_reader import read_skinned_glb
from readers.sample_rig import sample_rig

from mocaptk.errors import OutputError
from mocaptk.retarget import write_rig_glb


@pytest.fixture(scope="module", params=[(4, ()), (6, ()), (4, ("face_root", "Chin_C"))],
                ids=["k4", "k6", "k4_unused_joints"])
def exported(request, tmp_path_factory):
    k, silent = request.param
    rig = sample_rig(k=k, silent_joints=silent)
    return rig, write_rig_glb(rig, tmp_path_factory.mktemp("glb") / "rig.glb")


def test_read_back(exported):
    rig, path = exported
    glb = read_skinned_glb(path)
    np.testing.assert_allclose(glb.positions, rig.vertices * 1e-3, rtol=1e-7, atol=1e-9)
    np.testing.assert_array_equal(glb.triangles, rig.faces)
    assert glb.joint_names == list(rig.joint_names)
    weight_error = np.abs(glb.weights - rig.dense_weights()).max()
    print(f"glTF: max weight error {weight_error:.3g} (k={rig.max_influences})")
    assert weight_error <= 1e-6
    for joint, name in enumerate(rig.joint_names):
        parent = rig.joint_parents[joint]
        assert glb.parents[name] == (rig.joint_names[parent] if parent >= 0 else None)
    identity = np.tile(np.eye(4), (rig.joint_count, 1, 1))
    np.testing.assert_allclose(glb.joint_world[:, :3, 3], rig.joint_positions * 1e-3, atol=1e-9)
    np.testing.assert_allclose(glb.joint_world[:, :3, :3], identity[:, :3, :3])
    np.testing.assert_allclose(glb.inverse_bind @ glb.joint_world, identity, atol=1e-6)
    attributes = glb.gltf.meshes[0].primitives[0].attributes
    assert (getattr(attributes, "JOINTS_1", None) is not None) == (rig.max_influences > 4)
    assert glb.gltf.nodes[0].name == "face_mesh" and glb.gltf.nodes[0].skin == 0
    assert attributes.TEXCOORD_0 is not None and glb.gltf.meshes[0].primitives[0].material == 0
    assert [m.name for m in glb.gltf.materials] == ["face_skin"]


def test_khronos_validator_is_clean(exported):
    _, path = exported
    report = installed.run_validator(path)
    issues = report["issues"]
    print(f"gltf-validator {report['validatorVersion']}: {issues['numErrors']} errors, "
          f"{issues['numWarnings']} warnings, {issues['numInfos']} infos, "
          f"{issues['numHints']} hints")
    assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), \
        issues["messages"]  # the texture uses TEXCOORD_0 (it was an UNUSED_OBJECT info)
    assert report["info"]["hasSkins"] and report["info"]["totalVertexCount"] == 99


def test_bad_output_paths(tmp_path):
    rig = sample_rig()
    path = write_rig_glb(rig, tmp_path / "rig.glb")
    with pytest.raises(OutputError, match="already exists"):
        write_rig_glb(rig, path, force=False)
    with pytest.raises(OutputError, match="cannot write"):
        write_rig_glb(rig, path / "rig.glb")
