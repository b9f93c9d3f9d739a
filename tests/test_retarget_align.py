"""Mesh alignment: similarity transforms and ICP with scale recover known placements."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaptk.errors import InputFileError, OptionError
from mocaptk.retarget.align import Similarity, align_mesh_to_markers, similarity_transform
from mocaptk.retarget.mesh_io import load_mesh


def test_similarity_transform_recovers_scale_rotation_translation():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3)) * 50
    truth = Similarity(0.001, Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_matrix(),
                       np.array([0.1, -0.2, 0.3]))
    est = similarity_transform(src, truth.apply(src))
    assert est.scale == pytest.approx(0.001, rel=1e-9)
    np.testing.assert_allclose(est.rotation, truth.rotation, atol=1e-9)
    np.testing.assert_allclose(est.translation, truth.translation, atol=1e-9)
    np.testing.assert_allclose(est.then(Similarity(1.0, np.eye(3), np.ones(3))).apply(src),
                               truth.apply(src) + 1, atol=1e-9)
    with pytest.raises(OptionError):
        similarity_transform(src[:2], src[:2])
    with pytest.raises(OptionError):
        similarity_transform(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [1, 2, 3]))


@pytest.fixture(scope="module")
def face():
    """A real face mesh (MediaPipe canonical face, cm -> mm, looking down +Z) and markers on it."""
    from conftest import shared_path

    mesh = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    vertices = mesh.vertices * 10.0
    markers = vertices[::5]
    return vertices, mesh.faces, markers


@pytest.mark.parametrize("half", [False, True])
def test_icp_with_scale_recovers_a_mesh_in_metres(face, half):
    vertices, faces, markers = face
    if half:
        markers = markers[markers[:, 0] > -2]
    truth = Similarity(1e-3, Rotation.from_euler("xyz", [5, -7, 3], degrees=True).as_matrix(),
                       np.array([0.02, -0.01, 0.04]))
    mesh_in_metres = truth.apply(vertices)
    result = align_mesh_to_markers(mesh_in_metres, faces, markers)
    assert result.rms_mm < 0.5
    # the aligned mesh is back where it was (mm)
    assert np.abs(result.transform.apply(mesh_in_metres) - vertices).max() < 2.0
    assert result.transform.scale == pytest.approx(1000, rel=0.01)


def test_landmarks_alone_give_the_exact_transform(face):
    vertices, faces, _ = face
    truth = Similarity(2.0, Rotation.from_euler("y", 40, degrees=True).as_matrix(), np.ones(3))
    picks = np.array([1, 50, 200, 400])
    result = align_mesh_to_markers(truth.apply(vertices), faces, vertices[picks],
                                   landmarks={k: int(v) for k, v in enumerate(picks)},
                                   iterations=0)
    assert result.method == "landmarks"
    assert result.max_mm < 1e-6


def test_load_mesh_reads_obj_and_rejects_bad_files(face, tmp_path):
    import trimesh

    vertices, faces, _ = face
    path = tmp_path / "face.obj"
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    mesh = load_mesh(path)
    np.testing.assert_allclose(mesh.vertices, vertices, atol=1e-5)
    np.testing.assert_array_equal(mesh.faces, faces)
    (tmp_path / "bad.obj").write_text("this is not a mesh\n")
    for bad in (tmp_path / "missing.obj", tmp_path / "bad.obj", tmp_path / "face.xyz"):
        if bad.suffix == ".xyz":
            bad.write_text("1 2 3\n")
        with pytest.raises(InputFileError):
            load_mesh(bad)
