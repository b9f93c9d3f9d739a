"""Cameras, rig presets, rig files (JSON, Qualisys .qca.txt) and simulated 2-D detections."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_path
from mocaptk.acquisition.cameras import (
    FACE_CENTER_MM, Camera, CameraRig, cara_rig, load_rig, read_qca, room_rig, save_rig)
from mocaptk.acquisition.projection import project_markers, project_points
from mocaptk.errors import InputFileError


def test_look_at_puts_target_on_principal_point_and_recovers_center():
    cam = Camera.look_at("c", position=(100.0, 200.0, 900.0), target=(0.0, 0.0, 0.0),
                         focal_px=800.0, image_size=(640, 480))
    pixels, depth = project_points(cam, np.array([[0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(pixels[0], [319.5, 239.5], atol=1e-9)
    np.testing.assert_allclose(depth[0], np.linalg.norm([100.0, 200.0, 900.0]))
    np.testing.assert_allclose(cam.center, [100.0, 200.0, 900.0], atol=1e-9)
    np.testing.assert_allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-12)
    # world +Y (up) appears toward the top of the image (smaller row)
    above, _ = project_points(cam, np.array([[0.0, 50.0, 0.0]]))
    assert above[0, 1] < 239.5


def test_cara_preset_geometry():
    rig = cara_rig()
    assert len(rig) == 4 and rig.rate == 60.0
    center = np.array(FACE_CENTER_MM)
    for cam in rig:
        assert sorted(cam.image_size) == [720, 1280]
        assert cam.tvec @ cam.tvec > 0
        # aimed at the face centre, 25 cm from it (~15 cm from the nose tip at z=131 mm)
        pixels, depth = project_points(cam, center[None])
        np.testing.assert_allclose(pixels[0], (np.array(cam.image_size) - 1) / 2, atol=1e-6)
        assert 150 <= np.linalg.norm(cam.center - center) <= 260
        assert 130 <= np.linalg.norm(cam.center - [0, 0, 131.0]) <= 250
    heights = [cam.center[1] - center[1] for cam in rig]
    assert sum(h > 0 for h in heights) == 2 and sum(h < 0 for h in heights) == 2
    assert all(cam.center[2] > center[2] for cam in rig)  # all in front of the face (+Z)


def test_room_preset_ring():
    rig = room_rig(n_cameras=12, radius=2800.0)
    assert len(rig) == 12
    centers = np.array([cam.center for cam in rig]) - np.array(FACE_CENTER_MM)
    np.testing.assert_allclose(np.hypot(centers[:, 0], centers[:, 2]), 2800.0, rtol=1e-9)
    assert np.ptp(centers[:, 1]) > 500  # various heights


def test_rig_json_round_trip_is_exact_and_deterministic(tmp_path):
    rig = cara_rig()
    first = save_rig(rig, tmp_path / "rig.json")
    loaded = load_rig(first)
    second = save_rig(loaded, tmp_path / "again.json")
    assert first.read_bytes() == second.read_bytes()
    assert loaded.names == rig.names and loaded.rate == rig.rate
    points = np.random.default_rng(0).normal([0, 0, 70], 40, (50, 3))
    for a, b in zip(rig, loaded):
        np.testing.assert_allclose(project_points(a, points)[0], project_points(b, points)[0],
                                   atol=1e-6)


def test_load_rig_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something else"}')
    with pytest.raises(InputFileError, match="not a camera rig"):
        load_rig(bad)
    bad.write_text("not json")
    with pytest.raises(InputFileError):
        load_rig(bad)
    with pytest.raises(InputFileError, match="no such file"):
        load_rig(tmp_path / "missing.json")
    xml = tmp_path / "empty.qca.txt"
    xml.write_text("<calibration><cameras/></calibration>")
    with pytest.raises(InputFileError, match="no <cameras>"):
        load_rig(xml)


def test_qualisys_calibration_parse():
    path = shared_path("multicam", "pose2sim_demo", "Calib.qca.txt")
    rig = read_qca(path)
    assert rig.names == ["cam_01", "cam_02", "cam_03", "cam_04"]
    assert load_rig(path).names == rig.names  # dispatch by content
    cam = rig[0]
    assert cam.image_size == (1088, 1920)
    # sub-pixel units (1/64 px): focalLengthU=107599.67 -> 1681.2 px, centre 533.0, 948.1 px
    np.testing.assert_allclose(cam.matrix[0, 0], 107599.671875 / 64)
    np.testing.assert_allclose(cam.matrix[:2, 2], [34110.316406 / 64, 60680.792969 / 64])
    np.testing.assert_allclose(cam.distortion[:2], [-0.046183 / 64, 0.139983 / 64])
    # the camera centre is the transform position (mm)
    np.testing.assert_allclose(cam.center, [1460.2323709212087, -1909.1590482454608,
                                            1896.5058524092062], atol=1e-6)
    for cam in rig:
        assert np.isclose(np.linalg.det(cam.rotation), 1.0)
        # the capture volume (world origin, subject ~1 m up) is in front of every camera,
        # inside its image
        pixels, depth = project_points(cam, np.array([[0.0, 0.0, 1000.0]]))
        assert depth[0] > 1000
        assert 0 <= pixels[0, 0] < cam.image_size[0] and 0 <= pixels[0, 1] < cam.image_size[1]


@pytest.fixture(scope="module")
def sphere():
    """Points on a 60 mm sphere in front of a camera (+ outward normals)."""
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(20, 300, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return 60.0 * normals, normals


def test_projection_visibility_rules(sphere):
    points, normals = sphere
    cam = Camera.look_at("front", position=(0, 0, 400), target=(0, 0, 0), focal_px=600,
                         image_size=(640, 480))
    rig = CameraRig((cam,))
    obs = project_markers(rig, points, normals=normals)
    seen = np.isfinite(obs[0, ..., 0])
    facing = np.einsum("fmk,fmk->fm", normals, cam.center - points) > 0
    assert seen.sum() > 0.3 * seen.size
    assert not np.any(seen & ~facing)  # back-facing markers are never seen
    # without normals, the far side is seen too; points behind the camera never are
    assert np.isfinite(project_markers(rig, points)[..., 0]).sum() > seen.sum()
    behind = points + np.array([0.0, 0.0, 800.0])
    assert np.isnan(project_markers(rig, behind)).all()
    # out of frame: shift sideways beyond the image edge
    aside = points + np.array([600.0, 0.0, 0.0])
    assert np.isnan(project_markers(rig, aside)).all()
    assert np.isnan(project_markers(rig, np.full((2, 3, 3), np.nan))).all()


def test_projection_noise_dropout_and_ghosts(sphere):
    points, normals = sphere
    rig = cara_rig(center=(0, 0, 0))
    clean = project_markers(rig, points, normals=normals)
    noisy = project_markers(rig, points, normals=normals, pixel_noise=0.5, rng=1)
    diff = (noisy - clean)[np.isfinite(clean)]
    assert abs(diff.std() - 0.5) < 0.02 and abs(diff.mean()) < 0.02
    visible = np.isfinite(clean[..., 0]).sum()
    dropped = project_markers(rig, points, normals=normals, dropout=0.2, rng=2)
    assert abs(np.isfinite(dropped[..., 0]).sum() / visible - 0.8) < 0.02
    ghosts = project_markers(rig, points, normals=normals, ghost_rate=0.1, rng=4)
    moved = np.linalg.norm(ghosts - clean, axis=-1) > 1.0
    assert np.array_equal(np.isfinite(ghosts[..., 0]), np.isfinite(clean[..., 0]))
    assert abs(moved.sum() / visible - 0.1) < 0.015
    # same seed, same detections
    again = project_markers(rig, points, normals=normals, ghost_rate=0.1, rng=4)
    np.testing.assert_array_equal(ghosts, again)


def test_pixels_from_normalized_matches_opencv_projection():
    cam = Camera.look_at("d", position=(30, 40, 300), target=(0, 0, 0), focal_px=700,
                         image_size=(720, 1280), distortion=(-0.2, 0.05, 0.002, -0.001, 0.01))
    points = np.random.default_rng(1).uniform(-80, 80, (500, 3))
    expected, _ = project_points(cam, points)
    local = points @ cam.rotation.T + cam.tvec
    u, v = cam.pixels_from_normalized(local[:, 0] / local[:, 2], local[:, 1] / local[:, 2])
    np.testing.assert_allclose(np.column_stack([u, v]), expected, atol=1e-8)
