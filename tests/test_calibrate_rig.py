"""Rig extrinsics by bundle adjustment on rendered ChArUco views of the Cara-like rig, against
the true cameras and OpenCV's chained stereoCalibrate in the same run."""

from __future__ import annotations

import pytest

from mocaptk.acquisition.calibration import (View, calibrate_intrinsics, chained_stereo,
                                             pose_errors, rig_from_poses)
from mocaptk.acquisition.cameras import cara_rig, load_rig
from mocaptk.acquisition.image_sequences import ImageSource
from mocaptk.acquisition.synth_board_views import PRESET_BOARDS, write_board_views


@pytest.mark.slow
def test_bundle_adjusted_cara_rig_beats_chained_stereo(tmp_path, run_cli):
    truth, board = cara_rig(), PRESET_BOARDS["cara"]
    write_board_views(tmp_path, truth, board, n_views=16, seed=1)
    folders = [tmp_path / name for name in truth.names]
    out = tmp_path / "rig.json"
    result = run_cli("calibrate", *folders, "--board", "charuco", "--corners", "6x4", "--square", "20",
                     "--marker", "10", "--synced", "--out", out)
    assert result.exit_code == 0, result.stderr
    centre_mm, angle_deg = pose_errors(load_rig(out), truth)
    # the OpenCV-only baseline on the same detections
    views = [[View(name, *board.detect(image)) for name, image in ImageSource(f).frames()] for f in folders]
    fits = [calibrate_intrinsics(board, v, cam.image_size) for v, cam in zip(views, truth)]
    baseline = rig_from_poses(truth.names, [(f.matrix, f.distortion) for f in fits],
                              chained_stereo(board, views, fits), [c.image_size for c in truth])
    base_mm, base_deg = pose_errors(baseline, truth)
    assert centre_mm.max() <= 0.5, centre_mm
    assert centre_mm.mean() < base_mm.mean() and angle_deg.mean() < base_deg.mean(), (
        centre_mm, base_mm, angle_deg, base_deg)
