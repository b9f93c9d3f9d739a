"""``mocaptk calibrate`` on the real Pose2Sim demo photos (4 cameras, 7 photos each of a 4x7
checkerboard with 60 mm squares) against the same cameras' Qualisys calibration, and its
one-line errors for bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from conftest import shared_path
from mocaptk.acquisition.boards import Board
from mocaptk.acquisition.calibration import View, calibrate_intrinsics
from mocaptk.acquisition.cameras import load_rig
from mocaptk.acquisition.image_sequences import ImageSource

BOARD = Board("checkerboard", (4, 7), 60.0)


def calibration_dir():
    return shared_path("multicam", "pose2sim_demo", "calibration")


@pytest.fixture(scope="module")
def cam01_views():
    source = ImageSource(calibration_dir() / "intrinsics" / "int_cam01_img")
    views, size = [], None
    for name, image in source.frames():
        size = image.shape[1], image.shape[0]
        views.append(View(name, *BOARD.detect(image)))
    return views, size


@pytest.mark.slow
def test_calibrate_real_photos_matches_qualisys(tmp_path, run_cli):
    folder = calibration_dir()
    sources = [folder / "intrinsics" / f"int_cam0{i}_img" for i in range(1, 5)]
    out = tmp_path / "rig.json"
    result = run_cli("calibrate", *sources, "--board", "checkerboard", "--corners", "4x7",
                     "--square", "60", "--out", out)
    assert result.exit_code == 0, result.stderr
    rig, truth = load_rig(out), load_rig(folder / "Calib.qca.txt")
    report = json.loads(out.read_text())["metadata"]["calibration"]
    for camera, qualisys in zip(rig, truth):
        focal_error = np.abs(np.diag(camera.matrix)[:2] / np.diag(qualisys.matrix)[:2] - 1)
        assert focal_error.max() < 0.015, (camera.name, focal_error)
        assert camera.image_size == qualisys.image_size == (1088, 1920)
        entry = report[camera.name]
        assert entry["rms_px"] <= 0.3
        assert entry["views_kept"] >= 6 and entry["views_kept"] + len(entry["dropped"]) == 7
    # two photos show no full board: named as dropped, not silently skipped
    assert "cam02_06_int.jpg" in report["int_cam02_img"]["dropped"]
    assert "views kept" in result.stdout
    picture = cv2.imread(str(tmp_path / "rig_corners.png"))
    assert picture is not None and picture.shape[1] > 4 * 400


def test_checkerboard_corners_match_the_board_geometry(cam01_views):
    """Fitted board poses put the 60 mm grid onto the detected corners to a fraction of a px."""
    views, size = cam01_views
    assert sum(v.found for v in views) == 7
    fit = calibrate_intrinsics(BOARD, views, size)
    assert fit.rms < 0.2 and not fit.dropped
    # adjacent corners of the object grid are 60 mm apart
    points = BOARD.object_points()
    assert np.allclose(np.linalg.norm(points[1] - points[0]), 60.0)


def test_an_outlier_view_is_dropped_with_its_error(cam01_views):
    views, size = cam01_views
    rng = np.random.default_rng(0)
    broken = views[2]
    noisy = View(broken.name, broken.ids, broken.pixels + rng.normal(0, 3.0, broken.pixels.shape))
    fit = calibrate_intrinsics(BOARD, [*views[:2], noisy, *views[3:]], size)
    assert list(fit.dropped) == [broken.name] and "outlier" in fit.dropped[broken.name]
    assert fit.rms < 0.2 and len(fit.view_rms) == 6



def test_a_view_whose_corners_lie_on_one_line_is_dropped(cam01_views):
    """A partial board of one row has no homography: dropped with its reason, not an OpenCV
    assertion (found on rendered room-rig views)."""
    views, size = cam01_views
    column = views[0].ids % BOARD.corners[0] == 0  # the first column of corners only (7)
    line = View("one-column", views[0].ids[column], views[0].pixels[column])
    assert line.found
    fit = calibrate_intrinsics(BOARD, [*views, line], size)
    assert fit.dropped == {"one-column": "corners on one line"} and len(fit.view_rms) == 7


def test_images_of_different_sizes_in_one_camera(tmp_path, run_cli):
    folder = tmp_path / "cam1"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((40, 60), np.uint8))
    cv2.imwrite(str(folder / "b.png"), np.zeros((50, 60), np.uint8))
    result = run_cli("calibrate", folder, "--out", tmp_path / "rig.json")
    assert result.exit_code == 2
    assert result.stderr.strip().count("\n") == 0 and "must share one size" in result.stderr
    assert not (tmp_path / "rig.json").exists()


def test_a_board_that_is_never_found(tmp_path, run_cli):
    scene = calibration_dir() / "extrinsics"  # real scene photos without the checkerboard
    folder = tmp_path / "cam1"
    folder.mkdir()
    image = cv2.imread(str(scene / "cam01_ext.png"), cv2.IMREAD_GRAYSCALE)
    for i in range(3):
        cv2.imwrite(str(folder / f"{i}.png"), image)
    result = run_cli("calibrate", folder, "--corners", "9x6", "--out", tmp_path / "rig.json")
    assert result.exit_code == 2, result.stderr
    assert "found in 0 usable view" in result.stderr and result.stderr.count("\n") == 1


def test_a_video_that_cannot_be_decoded(tmp_path, run_cli):
    video = tmp_path / "cam1.mp4"
    video.write_bytes(b"not a video" * 100)
    result = run_cli("calibrate", video, "--out", tmp_path / "rig.json")
    assert result.exit_code == 2
    assert "cannot decode" in result.stderr and result.stderr.count("\n") == 1


def test_synced_needs_charuco(tmp_path, run_cli):
    result = run_cli("calibrate", tmp_path, "--synced", "--out", tmp_path / "rig.json")
    assert result.exit_code == 2 and "--synced needs --board charuco" in result.stderr


def test_intrinsics_from_a_video(tmp_path, run_cli):
    """A ChArUco video (rendered through a known Cara camera, MJPG-compressed) sampled frame by frame."""
    from mocaptk.acquisition.cameras import cara_rig
    from mocaptk.acquisition.synth_board_views import (PRESET_BOARDS, board_poses, render_views,
                                                       texture_resolution)

    rig, board = cara_rig(), PRESET_BOARDS["cara"]
    camera = rig[0]
    poses = board_poses(rig, board, 16, seed=2, max_tilt_deg=30.0)
    video = tmp_path / "cam.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, camera.image_size)
    for image in render_views(camera, board, poses, px_per_mm=texture_resolution(rig, board, poses)):
        if image is not None:
            writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    out = tmp_path / "rig.json"
    result = run_cli("calibrate", video, "--board", "charuco", "--corners", "6x4", "--square", "20",
                     "--marker", "10", "--step", "1", "--out", out)
    assert result.exit_code == 0, result.stderr
    fitted = load_rig(out)[0]
    assert abs(fitted.focal_px / camera.focal_px - 1) < 0.005
    assert np.abs(fitted.matrix[:2, 2] - camera.matrix[:2, 2]).max() < 3.0


@pytest.mark.parametrize("preset, px_per_mm", [("room", 8.6709), ("room", 9.1646), ("cara", 57.1429)])
def test_rendered_board_squares_sit_where_the_renderer_samples_them(preset, px_per_mm):
    """The texture's square edges lie at whole multiples of its texels per square, the scale the
    renderer samples it at (width / board width): OpenCV draws whole-texel squares, and a
    fractional square drew the room board 1.65e-4 small at 8.6709 texels per mm."""
    from mocaptk.acquisition.synth_board_views import PRESET_BOARDS, board_texture

    board = PRESET_BOARDS[preset]  # texels per mm of the room bench's seeds 2 and 4 and of Cara's
    texture = board_texture(board, px_per_mm)
    square = texture.shape[1] / board.size_mm()[0] * board.square  # texels per square as sampled
    row, column = texture[int(0.1 * square)] > 120, texture[:, int(0.1 * square)] > 120
    across = np.flatnonzero(np.diff(row)) + 1  # the first row and column: squares, no markers
    down = np.flatnonzero(np.diff(column)) + 1
    assert len(across) == board.corners[0] and len(down) == board.corners[1]
    assert np.array_equal(across, np.arange(1, len(across) + 1) * square)
    assert np.array_equal(down, np.arange(1, len(down) + 1) * square)
