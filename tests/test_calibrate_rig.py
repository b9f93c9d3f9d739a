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


def test_camera_1_frame_spreads_camera_1s_own_error_and_pairwise_errors_do_not():
    """One camera of a room ring (5 m across) turned by 0.02 deg about its centre: in camera 1's
    frame every other centre seems ~1 mm off; the gauge-free pairwise errors put the fault on
    camera 1's pairs' rotations alone and move no centre distance."""
    import cv2
    import numpy as np

    from mocaptk.acquisition.calibration import pairwise_errors
    from mocaptk.acquisition.cameras import Camera, CameraRig, room_rig

    truth = room_rig()
    turn = cv2.Rodrigues(np.radians(0.02) * np.array([0.0, 1.0, 0.0]))[0]
    first = truth[0]
    rotation = turn @ first.rotation
    turned = Camera(name=first.name, matrix=first.matrix, distortion=first.distortion,
                    rvec=cv2.Rodrigues(rotation)[0].ravel(), tvec=-rotation @ first.center,
                    image_size=first.image_size)
    estimate = CameraRig((turned, *truth.cameras[1:]), name="turned")
    centre_mm, angle_deg = pose_errors(estimate, truth)
    assert centre_mm.max() > 1.0 and np.allclose(angle_deg[1:], 0.02, atol=1e-6), (centre_mm, angle_deg)
    distance_mm, relative_deg = pairwise_errors(estimate, truth)
    assert distance_mm.max() < 1e-6
    pairs = np.array(np.triu_indices(len(truth), k=1)).T
    assert np.allclose(relative_deg[pairs[:, 0] == 0], 0.02, atol=1e-4)
    assert relative_deg[pairs[:, 0] > 0].max() < 1e-4  # arccos near 1: ~1e-6 deg of rounding
