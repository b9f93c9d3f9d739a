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


def test_a_png_whose_valid_header_claims_more_pixels_than_opencv_allows(tmp_path, run_cli):
    """OpenCV raises (not returns None) on a well-formed header of 60000 x 60000 px: one line, exit 2."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    (tmp_path / "cam1").mkdir()
    (tmp_path / "cam1" / "000000.png").write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 60000, 60000, 8, 0, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(bytes(10), 0)) + chunk(b"IEND", b""))
    result = run_cli("detect", tmp_path / "cam1", "--out", tmp_path / "d.npz")
    assert result.exit_code == 2 and "cannot decode this image" in result.stderr
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


def _mjpg(path, frames):
    height, width = frames[0].shape
    video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 60, (width, height), isColor=False)
    for frame in frames:
        video.write(frame)
    video.release()
    return path


def test_mjpg_frames_are_decoded_on_threads_in_frame_order(rendered, tmp_path):
    from mocaptk.acquisition.detect_images import detect_sources
    from mocaptk.acquisition.image_sequences import ImageSource, decode_jpeg

    _, images = rendered
    sources = [ImageSource(_mjpg(tmp_path / f"cam{c}.avi", images[c])) for c in range(2)]
    packets = list(sources[0].jpeg_frames())
    assert [name for name, _ in packets] == ["frame 0", "frame 1", "frame 2"]
    by_ffmpeg = [image for _, image in sources[0].frames()]  # FFmpeg, then BGR -> grey
    for (_, packet), image in zip(packets, by_ffmpeg):
        assert np.abs(decode_jpeg(packet).astype(int) - image).max() <= 1
    one, firsts = detect_sources(sources, min_area=6, max_area=2000, threads=1)
    two, _ = detect_sources(sources, min_area=6, max_area=2000, threads=2)
    assert all(np.array_equal(a.centres, b.centres) and np.array_equal(a.merged, b.merged)
               for row_a, row_b in zip(one, two) for a, b in zip(row_a, row_b))
    assert [len(row) for row in one] == [3, 3] and firsts[0].shape == images[0][0].shape
    ffmpeg = detect_blobs(by_ffmpeg[2], split=True)
    assert len(ffmpeg.centres) == len(one[0][2].centres)
    assert np.abs(ffmpeg.centres - one[0][2].centres).max() < 0.05


def test_an_mjpg_frame_that_cannot_be_decoded(rendered, tmp_path, run_cli):
    _, images = rendered
    video = _mjpg(tmp_path / "cam1.avi", images[0])
    data = bytearray(video.read_bytes())
    second = data.index(b"\xff\xd8\xff", data.index(b"\xff\xd8\xff") + 3)
    data[second:second + 3] = b"\x00\x00\x00"  # frame 1 no longer starts as a JPEG
    video.write_bytes(bytes(data))
    result = run_cli("detect", video, "--out", tmp_path / "d.npz")
    assert result.exit_code == 2 and "frame 1: cannot decode this MJPG frame" in result.stderr
    assert result.stderr.count("\n") == 1 and not (tmp_path / "d.npz").exists()


def test_components_from_runs_are_opencvs(rendered):
    """Labels, their numbering and stats as cv2.connectedComponentsWithStats (8-connected) gives
    them, on a rendered frame's bright pixels and on random masks up to nearly full."""
    from mocaptk.acquisition.blob_kernel import label_components

    rng = np.random.default_rng(5)
    image = rendered[1][0][0]
    masks = [cv2.threshold(image, 160, 255, cv2.THRESH_BINARY)[1][200:700, 100:600]]
    masks += [(rng.random((41, 67)) < p).astype(np.uint8) * 255 for p in (0.05, 0.3, 0.5, 0.7, 0.95)]
    for mask, dtype in zip(masks + masks[1:2], [np.uint16] * len(masks) + [np.int32]):
        count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
        ours = np.full(mask.shape, 7, dtype)  # not zeroed beforehand: the kernel clears it
        found, our_stats = label_components(mask, ours, cv2.countNonZero(mask))
        assert found == count and np.array_equal(our_stats[1:], stats[1:]) and np.array_equal(ours, labels)
