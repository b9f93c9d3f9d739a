"""rig.fbx: structure the FBX SDK demands, and read-back through ufbx, the Autodesk FBX SDK
(FBX2glTF) and Blender — weights within 1e-6, joints, bind matrices, geometry in centimetres."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
from readers import installed
from readers.fbx_dom import parse_fbx
from readers.glb_reader import read_skinned_glb
from readers.sample_rig import sample_rig
from scipy.spatial import cKDTree

from mocaptk.errors import OutputError
from mocaptk.retarget import write_rig_fbx, write_rig_json

WEIGHT_TOL = 1e-6


@pytest.fixture(scope="module", params=[(4, ()), (6, ()), (4, ("face_root", "Chin_C"))],
                ids=["k4", "k6", "k4_unused_joints"])
def exported(request, tmp_path_factory):
    """(rig, rig.fbx path) for 4 and 6 influences per vertex, and with joints that have no
    influence (empty clusters)."""
    k, silent = request.param
    rig = sample_rig(k=k, silent_joints=silent)
    folder = tmp_path_factory.mktemp(f"fbx_k{k}")
    write_rig_json(rig, folder / "rig.json")
    return rig, write_rig_fbx(rig, folder / "rig.fbx")


def _props70(record) -> dict:
    return {p.props[0]: p.props[4:] for p in record.first("Properties70").find("P")}


def test_structure_the_fbx_sdk_needs(exported):
    rig, path = exported
    data = path.read_bytes()
    version, root = parse_fbx(data)
    assert version == 7400
    assert data.endswith(bytes.fromhex("f85a8c6adef5d97eece90ce3758f290b"))
    names = [r.name for r in root.children]
    assert names == ["FBXHeaderExtension", "FileId", "CreationTime", "Creator", "GlobalSettings",
                     "Documents", "References", "Definitions", "Objects", "Connections", "Takes"]
    settings = _props70(root.first("GlobalSettings"))
    assert settings["UnitScaleFactor"] == [1.0]
    assert (settings["UpAxis"], settings["FrontAxis"], settings["CoordAxis"]) == ([1], [2], [0])
    counts = {o.props[0]: o.first("Count").props[0]
              for o in root.first("Definitions").find("ObjectType")}
    joints = rig.joint_count
    assert counts == {"GlobalSettings": 1, "Geometry": 1, "Model": 1 + joints,
                      "NodeAttribute": joints, "Deformer": 1 + joints, "Pose": 1, "Material": 1}

    objects = root.first("Objects")
    models = objects.find("Model")
    # a root no vertex is weighted to is the skeleton's Root (Blender: the armature object)
    root_kind = "LimbNode" if len(rig.joint_influences(0)[0]) else "Root"
    assert [m.props[2] for m in models] == ["Mesh", root_kind] + ["LimbNode"] * (joints - 1)
    for joint, model in enumerate(models[1:]):
        props = _props70(model)
        assert props["DefaultAttributeIndex"] == [0] and props["InheritType"] == [1]
        assert (props["marker"], props["side"], props["region"]) == (
            [rig.joint_markers[joint]], [rig.joint_sides[joint]], [rig.joint_regions[joint]])
    flags = [a.first("TypeFlags").props for a in objects.find("NodeAttribute")]
    assert flags[0] == (["Skeleton"] if root_kind == "LimbNode" else ["Null", "Skeleton", "Root"])
    assert all(f == ["Skeleton"] for f in flags[1:])
    geometry = objects.first("Geometry")
    np.testing.assert_allclose(geometry.first("Vertices").props[0].reshape(-1, 3),
                               rig.vertices * 0.1)
    clusters = [d for d in objects.find("Deformer") if d.props[2] == "Cluster"]
    assert len(clusters) == joints
    for joint, cluster in enumerate(clusters):
        link = cluster.first("TransformLink").props[0].reshape(4, 4).T
        transform = cluster.first("Transform").props[0].reshape(4, 4).T
        np.testing.assert_allclose(link[:3, 3], rig.joint_positions[joint] * 0.1)
        np.testing.assert_allclose(transform @ link, np.eye(4), atol=1e-12)
        vertices, weights = rig.joint_influences(joint)
        np.testing.assert_array_equal(cluster.first("Indexes").props[0], vertices)
        np.testing.assert_array_equal(cluster.first("Weights").props[0], weights)
    pose = objects.first("Pose")
    assert pose.props[2] == "BindPose" and pose.first("NbPoseNodes").props == [1 + joints]
    assert len(root.first("Connections").find("C")) == 4 + 4 * joints
    # UVs (front projection into [0, 1]) and one material
    uv = geometry.first("LayerElementUV").first("UV").props[0].reshape(-1, 2)
    np.testing.assert_allclose(uv, rig.uv())
    assert uv.min() == 0.0 and uv.max() == 1.0
    assert [m.props[1].split("\x00")[0] for m in objects.find("Material")] == ["face_skin"]


def _dense_from_clusters(rig, clusters: dict) -> np.ndarray:
    dense = np.zeros((rig.vertex_count, rig.joint_count))
    for joint, name in enumerate(rig.joint_names):
        dense[clusters[name]["vertices"], joint] = clusters[name]["weights"]
    return dense


def test_ufbx_reads_the_rig(exported):
    rig, path = exported
    scene = installed.run_ufbx(path)
    assert scene["version"] == 7400
    assert scene["unit_meters"] == pytest.approx(0.01)
    assert scene["axes"] == ["POSITIVE_X", "POSITIVE_Y", "POSITIVE_Z"]
    np.testing.assert_allclose(scene["vertices"], rig.vertices * 0.1, atol=1e-9)
    np.testing.assert_array_equal(scene["faces"], rig.faces)
    np.testing.assert_allclose(scene["mesh_node_to_world"], np.eye(4), atol=1e-12)

    weight_error = np.abs(_dense_from_clusters(rig, scene["clusters"]) - rig.dense_weights()).max()
    print(f"ufbx: max weight error {weight_error:.3g}")
    assert weight_error <= WEIGHT_TOL

    assert set(scene["joints"]) == set(rig.joint_names)
    for joint, name in enumerate(rig.joint_names):
        parent = rig.joint_parents[joint]
        assert scene["joints"][name]["parent"] == (rig.joint_names[parent] if parent >= 0 else None)
        expected = np.eye(4)
        expected[:3, 3] = rig.joint_positions[joint] * 0.1
        cluster = scene["clusters"][name]
        np.testing.assert_allclose(scene["joints"][name]["node_to_world"], expected, atol=1e-9)
        np.testing.assert_allclose(cluster["bind_to_world"], expected, atol=1e-9)
        np.testing.assert_allclose(np.array(cluster["geometry_to_bone"]) @ expected, np.eye(4),
                                   atol=1e-9)
        np.testing.assert_allclose(scene["bind_pose"][name], expected, atol=1e-9)
    np.testing.assert_allclose(scene["bind_pose"]["face_mesh"], np.eye(4))


def test_autodesk_fbx_sdk_reads_the_rig(exported, tmp_path):
    """FBX2glTF (FBX SDK) converts to glTF in metres; compare what it saw with the rig."""
    rig, path = exported
    binary = installed.fbx2gltf()
    done = subprocess.run([str(binary), "-b", "-i", str(path), "-o", str(tmp_path / "sdk")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    sdk = read_skinned_glb(tmp_path / "sdk.glb")

    # FBX2glTF may split/reorder vertices: match each to the rig vertex at the same place.
    distance, original = cKDTree(rig.vertices * 1e-3).query(sdk.positions)
    assert distance.max() < 1e-6
    assert set(original) == set(range(rig.vertex_count))
    triangles = {tuple(sorted(t)) for t in original[sdk.triangles].tolist()}
    assert triangles == {tuple(sorted(t)) for t in rig.faces.tolist()}

    order = [rig.joint_names.index(n) for n in sdk.joint_names]
    assert sorted(order) == list(range(rig.joint_count))
    expected = rig.dense_weights()[original][:, order]
    compare = np.ones(len(expected), dtype=bool)
    if rig.max_influences > 4:
        # FBX2glTF 0.9.7 keeps the 4 strongest influences the SDK reports and renormalizes;
        # where the 4th and 5th strongest tie, which one it keeps is its choice.
        ranked = np.sort(expected, axis=1)[:, ::-1]
        compare = ranked[:, 3] - ranked[:, 4] > 1e-9
        weakest = np.argsort(-expected, axis=1, kind="stable")[:, 4:]
        np.put_along_axis(expected, weakest, 0.0, axis=1)
        expected /= expected.sum(axis=1, keepdims=True)
        np.testing.assert_allclose(np.sort(sdk.weights, axis=1), np.sort(expected, axis=1),
                                   atol=WEIGHT_TOL)
    weight_error = np.abs(sdk.weights - expected)[compare].max()
    print(f"FBX SDK (FBX2glTF): max weight error {weight_error:.3g} (k={rig.max_influences})")
    assert weight_error <= WEIGHT_TOL

    for joint_index, name in zip(order, sdk.joint_names):
        parent = rig.joint_parents[joint_index]
        if parent >= 0:
            assert sdk.parents[name] == rig.joint_names[parent]
    bind_m = rig.joint_positions[order] * 1e-3
    np.testing.assert_allclose(sdk.joint_world[:, :3, 3], bind_m, atol=1e-6)
    np.testing.assert_allclose(sdk.joint_world[:, :3, :3], np.tile(np.eye(3), (len(order), 1, 1)),
                               atol=1e-6)
    np.testing.assert_allclose(sdk.inverse_bind @ sdk.joint_world,
                               np.tile(np.eye(4), (len(order), 1, 1)), atol=1e-6)


def test_blender_reads_the_rig(exported):
    """Blender (PyPI bpy in its own venv) via scripts/check_fbx_blender.py."""
    rig, path = exported
    python = installed.blender_python()
    script = installed.REPO / "scripts" / "check_fbx_blender.py"
    done = subprocess.run([str(python), str(script), str(path), str(path.with_name("rig.json"))],
                          capture_output=True, text=True, timeout=300)
    report = json.loads(done.stdout[done.stdout.index("{"):])
    print("Blender:", json.dumps(report, sort_keys=True))
    assert done.returncode == 0 and report["ok"], report
    assert report["max_weight_error"] <= WEIGHT_TOL


def test_bad_output_paths(tmp_path):
    rig = sample_rig()
    path = write_rig_fbx(rig, tmp_path / "rig.fbx")
    with pytest.raises(OutputError, match="already exists"):
        write_rig_fbx(rig, path, force=False)
    with pytest.raises(OutputError, match="cannot write"):
        write_rig_fbx(rig, path / "rig.fbx")
    assert [p.name for p in tmp_path.iterdir()] == ["rig.fbx"]
