"""Marker blob detection on rendered frames (true 2-D positions known): sub-pixel centres,
recall, false blobs, merged flags; ``mocaptk detect`` end to end and its bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mocaptk.acquisition.blob_detection import detect_blobs
from mocaptk.acquisition.cameras import cara_rig
from mocaptk.acquisition.detections_file import load_detections
from mocaptk.acquisition.projection import ellipsoid_markers
from mocaptk.acquisition.synth_images import (marker_truth, render_markers, score_detections,
                                              skin_shading, write_marker_images)


@pytest.fixture(scope="module")
def rendered():
    """4 Cara cameras x 3 frames of 139 markers spread over a face-sized ellipsoid."""
    rig = cara_rig()
    points, normals = ellipsoid_markers(3, 139, max_yaw=1.1, seed=1)
    truth = marker_truth(rig, points, normals)
    rng = np.random.default_rng(0)
    images = [[render_markers(skin_shading(cam, c), truth.pixels[c, f], truth.radius[c, f], rng=rng)[0]
               for f in range(3)] for c, cam in enumerate(rig)]
    return truth, images


def test_isolated_markers_are_found_to_a_tenth_of_a_pixel(rendered):
    truth, images = rendered
    score = None
    for c, row in enumerate(images):
        for f, image in enumerate(row):
            blobs = detect_blobs(image)
            one = score_detections(truth.pixels[c, f], truth.radius[c, f], truth.merged[c, f],
                                   blobs.centres, blobs.merged)
            score = one if score is None else score + one
    assert score.isolated > 1000
    assert score.rms_px <= 0.1
    assert score.recall >= 0.995
    assert score.false_rate < 0.005
    # merged blobs are flagged, and a flag is (almost) always on markers that did merge
    assert score.merged_blobs > 20 and score.merged_flagged >= 0.95 * score.merged_blobs


def test_a_merged_pair_is_one_flagged_blob():
    background = np.full((60, 80), 100.0, np.float32)
    pixels = np.array([[30.0, 30.0], [37.0, 30.5], [60.0, 20.0]])
    image, _ = render_markers(background, pixels, np.full(3, 4.0), rng=np.random.default_rng(0), glints=0)
    blobs = detect_blobs(image)
    assert len(blobs.centres) == 2
    pair = np.argmin(blobs.centres[:, 0])
    assert blobs.merged[pair] and not blobs.merged[1 - pair]
    assert np.linalg.norm(blobs.centres[1 - pair] - pixels[2]) < 0.1
    halves = detect_blobs(image, split=True)
    assert len(halves.centres) == 3 and halves.merged.sum() == 2
    split = halves.centres[halves.merged]
    gaps = np.linalg.norm(split[:, None] - pixels[None, :2], axis=2)
    assert gaps.min(axis=1).max() < 1.0 and set(gaps.argmin(axis=1)) == {0, 1}


def test_detect_command_writes_unlabelled_detections(tmp_path, run_cli):
    rig = cara_rig()
    points, normals = ellipsoid_markers(2, 60, max_yaw=1.1, seed=2)
    folder = tmp_path / "markers"
    folder.mkdir()
    truth = write_marker_images(folder, rig, points, normals, labels=[f"M{i}" for i in range(60)])
    out = tmp_path / "det.npz"
    result = run_cli("detect", folder, "--out", out)
    assert result.exit_code == 0, result.stderr
    detections = load_detections(out)
    assert detections.camera_names == sorted(rig.names)  # sub-folders in name order
    assert detections.points2d.shape[:2] == (4, 2)
    c = rig.names.index(detections.camera_names[0])
    seen = np.isfinite(truth.pixels[c, 0, :, 0]).sum()
    found = np.isfinite(detections.points2d[0, 0, :, 0]).sum()
    assert found <= seen and found >= seen - 2 * truth.merged[c, 0].sum()
    assert cv2.imread(str(tmp_path / "det_overlay.png")) is not None


def test_cameras_with_different_frame_counts(tmp_path, run_cli):
    for name, count in (("a", 2), ("b", 3)):
        (tmp_path / name).mkdir()
        for i in range(count):
            cv2.imwrite(str(tmp_path / name / f"{i}.png"), np.full((20, 30), 90, np.uint8))
    result = run_cli("detect", tmp_path / "a", tmp_path / "b", "--out", tmp_path / "d.npz")
    assert result.exit_code == 2 and "one image per frame" in result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "d.npz").exists()


def test_images_of_different_sizes_within_a_camera(tmp_path, run_cli):
    (tmp_path / "a").mkdir()
    cv2.imwrite(str(tmp_path / "a" / "0.png"), np.full((20, 30), 90, np.uint8))
    cv2.imwrite(str(tmp_path / "a" / "1.png"), np.full((24, 30), 90, np.uint8))
    result = run_cli("detect", tmp_path / "a", "--out", tmp_path / "d.npz")
    assert result.exit_code == 2 and "must share one size" in result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "d.npz").exists()


def test_a_video_that_cannot_be_decoded(tmp_path, run_cli):
    video = tmp_path / "cam1.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    result = run_cli("detect", video, "--out", tmp_path / "d.npz")
    assert result.exit_code == 2 and "cannot decode" in result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "d.npz").exists()


def test_synth_images_needs_a_rig(tmp_path, run_cli):
    result = run_cli("synth", tmp_path / "s.c3d", "--rig", "none", "--images", tmp_path / "img")
    assert result.exit_code == 2 and "--images needs a camera rig" in result.stderr
    assert not (tmp_path / "img").exists() and not (tmp_path / "s.c3d").exists()


def test_synth_images_refuses_a_full_folder_before_writing(tmp_path, run_cli):
    (tmp_path / "img").mkdir()
    (tmp_path / "img" / "old.txt").write_text("x")
    result = run_cli("synth", tmp_path / "s.c3d", "--images", tmp_path / "img")
    assert result.exit_code == 2 and "not empty" in result.stderr
    assert not (tmp_path / "s.c3d").exists()
