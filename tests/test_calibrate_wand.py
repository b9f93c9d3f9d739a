"""The calibration wand: its ends matched across cameras, and what it adds to the bundle
adjustment (each camera's distance, which board views facing one camera leave coupled to its
focal length)."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from mocaptk.acquisition.calibration import (View, bundle_adjust, calibrate_intrinsics,
                                             chained_stereo, pose_errors, rig_from_poses)
from mocaptk.acquisition.boards import Board
from mocaptk.acquisition.cameras import load_rig, room_rig
from mocaptk.acquisition.detections_file import pack, save_detections
from mocaptk.acquisition.image_sequences import ImageSource
from mocaptk.acquisition.synth_board_views import PRESET_BOARDS, board_poses, write_board_views
from mocaptk.acquisition.synth_wand import wand_pixels, wand_positions, write_wand_views
from mocaptk.acquisition.wand import wand_from_blobs


def _wand_blobs(rig, ends, rng, noise_px):
    """``(C, N, 2, 2)`` blobs of the wand's ends in each camera, in a random order per image."""
    blobs = np.stack([wand_pixels(camera, ends)[0] for camera in rig])
    blobs = blobs + rng.normal(0, noise_px, blobs.shape)
    swap = rng.random(blobs.shape[:2]) < 0.5
    blobs[swap] = blobs[swap][:, ::-1]
    return blobs


def test_wand_ends_are_matched_across_cameras():
    rig, rng = room_rig(n_cameras=6), np.random.default_rng(0)
    ends = wand_positions(rig, 40, seed=3)
    blobs = _wand_blobs(rig, ends, rng, 0.05)
    blobs[:, 5, 1] = np.nan  # one end hidden everywhere: a frame that cannot count
    wand = wand_from_blobs(blobs, rig, 400.0)
    assert wand.n_frames == 39
    kept = np.delete(np.arange(40), 5)
    for n, f in enumerate(kept):
        seen = np.isfinite(wand.pixels[:, n, 0, 0])
        # camera by camera the same end is called A: its pixels are the projection of one true end
        truth = np.stack([wand_pixels(camera, ends[f:f + 1])[0][0] for camera in rig])
        direct = np.linalg.norm(wand.pixels[seen, n] - truth[seen], axis=-1).max()
        crossed = np.linalg.norm(wand.pixels[seen, n] - truth[seen][:, ::-1], axis=-1).max()
        assert min(direct, crossed) < 0.5, (f, direct, crossed)


def _board_views(rig, board, poses, rng, noise_px):
    """Board corners as each camera sees them (exact projections + noise), ``views[c][v]``."""
    objects = board.object_points()
    views = []
    for camera in rig:
        row = []
        for v, pose in enumerate(poses):
            world = objects @ cv2.Rodrigues(pose[:3])[0].T + pose[3:]
            depth = world @ camera.rotation[2] + camera.tvec[2]
            normal = cv2.Rodrigues(pose[:3])[0][:, 2]
            pixels = cv2.projectPoints(world, camera.rvec, camera.tvec, camera.matrix,
                                       camera.distortion)[0].reshape(-1, 2)
            inside = np.all((pixels >= 0) & (pixels < camera.image_size), axis=1) & (depth > 0)
            facing = normal @ (camera.center - world.mean(0)) < -0.2 * np.linalg.norm(camera.center - world.mean(0))
            ids = np.flatnonzero(inside) if facing else np.zeros(0, int)
            row.append(View(f"v{v}", ids, pixels[ids] + rng.normal(0, noise_px, (len(ids), 2))))
        views.append(row)
    return views


def test_wand_pins_the_camera_distances_that_board_views_leave_loose():
    """On a ring of narrow-lens cameras, board views (0.1 px noise) leave each camera's focal
    length and distance coupled; the wand (0.05 px) seen by all at once pins them."""
    rig, board, rng = room_rig(n_cameras=4), PRESET_BOARDS["room"], np.random.default_rng(1)
    poses = board_poses(rig, board, 16, seed=1, max_tilt_deg=30.0, spread_mm=600)
    views = _board_views(rig, board, poses, rng, 0.1)
    fits = [calibrate_intrinsics(board, v, cam.image_size) for v, cam in zip(views, rig)]
    start = chained_stereo(board, views, fits)
    sizes = [c.image_size for c in rig]
    boards_only = bundle_adjust(board, views, fits, start)
    wand = wand_from_blobs(_wand_blobs(rig, wand_positions(rig, 100, seed=2), rng, 0.05),
                           rig_from_poses(rig.names, [(f.matrix, f.distortion) for f in fits], start, sizes),
                           400.0)
    assert wand.n_frames >= 90
    with_wand = bundle_adjust(board, views, fits, start, wand=wand)
    before, _ = pose_errors(rig_from_poses(rig.names, boards_only.intrinsics, boards_only.rig_poses, sizes),
                            rig, align=True)
    after, after_deg = pose_errors(rig_from_poses(rig.names, with_wand.intrinsics, with_wand.rig_poses, sizes),
                                   rig, align=True)
    assert after.max() < 0.5 * before.max(), (before, after)
    assert after.max() < 0.5 and after_deg.max() < 0.05, (after, after_deg)
    # the wand is weighed by the noise measured on the fit's own residuals (0.1 and 0.05 px made)
    assert 0.085 < with_wand.corner_sd_px < 0.115 and 0.0425 < with_wand.wand_sd_px < 0.0575, (
        with_wand.corner_sd_px, with_wand.wand_sd_px)
    assert boards_only.wand_weight is None


def _scale_error(estimate, truth) -> float:
    """How much longer ``estimate``'s camera-to-camera distances are than ``truth``'s, summed."""
    i, j = np.triu_indices(len(truth), k=1)

    def distances(rig):
        centres = np.stack([cam.center for cam in rig])
        return np.linalg.norm(centres[i] - centres[j], axis=1).sum()
    return distances(estimate) / distances(truth) - 1


def test_the_wand_length_sets_the_scale_a_misprinted_board_gets_wrong():
    """A board printed 0.05 % too large gives the boards alone a rig 0.18 % too small here; the
    wand, a rigid 400 mm with its pixels weighed by their measured noise, brings it within
    7.5e-5 (free ends with a 0.05 mm length term left 1.0e-4)."""
    rig, board, rng = room_rig(n_cameras=4), PRESET_BOARDS["room"], np.random.default_rng(2)
    printed = Board("charuco", board.corners, board.square * (1 + 5e-4), marker=board.marker)
    views = _board_views(rig, printed, board_poses(rig, board, 16, seed=2, max_tilt_deg=30.0, spread_mm=600),
                         rng, 0.1)
    fits = [calibrate_intrinsics(board, v, cam.image_size) for v, cam in zip(views, rig)]
    start = chained_stereo(board, views, fits)
    sizes = [c.image_size for c in rig]
    wand = wand_from_blobs(_wand_blobs(rig, wand_positions(rig, 100, seed=2), rng, 0.05),
                           rig_from_poses(rig.names, [(f.matrix, f.distortion) for f in fits], start, sizes),
                           400.0)
    alone, with_wand = (bundle_adjust(board, views, fits, start, wand=w) for w in (None, wand))
    alone_scale, wand_scale = (_scale_error(rig_from_poses(rig.names, r.intrinsics, r.rig_poses, sizes), rig)
                               for r in (alone, with_wand))
    assert alone_scale < -1e-3, alone_scale
    assert abs(wand_scale) < 7.5e-5, wand_scale


def test_a_wand_never_seen_is_refused_with_what_was_seen():
    rig, rng = room_rig(n_cameras=4), np.random.default_rng(0)
    blobs = _wand_blobs(rig, wand_positions(rig, 20, seed=3), rng, 0.05)
    with pytest.raises(ValueError, match=r"the wand was not found: 20 of 20 frames .* median length is (39\d|40\d)\.\d mm"):
        wand_from_blobs(blobs, rig, 500.0)  # the wrong length
    blobs[:, :, 1] = np.nan  # one blob per image: a glint, never the wand
    with pytest.raises(ValueError, match="the wand was not found: 0 of 20 frames show two blobs"):
        wand_from_blobs(blobs, rig, 400.0)


# -- calibrate --wand on the command line: rendered board and wand footage -> detect -> calibrate

BOARD_ARGS = ("--board", "charuco", "--corners", "6x4", "--square", "100", "--marker", "50", "--synced")


@pytest.fixture(scope="module")
def room_footage(tmp_path_factory):
    """A 6-camera room ring at half resolution (1024x544 px, focal 1500 px: the same view as
    the room preset): 16 ChArUco views and a 400 mm wand waved 24 times, rendered as PNGs."""
    rig = room_rig(n_cameras=6, image_size=(1024, 544), focal_px=1500.0)
    folder = tmp_path_factory.mktemp("room_wand")
    (folder / "boards").mkdir()
    (folder / "wand").mkdir()
    write_board_views(folder / "boards", rig, PRESET_BOARDS["room"], n_views=16, seed=1)
    write_wand_views(folder / "wand", rig, n_frames=24, seed=1)
    return rig, folder


@pytest.mark.slow
def test_calibrate_with_a_detected_wand_beats_the_boards_alone(room_footage, run_cli, tmp_path):
    rig, folder = room_footage
    detected = run_cli("detect", folder / "wand", "--out", tmp_path / "wand.npz", "--quiet")
    assert detected.exit_code == 0, detected.stderr
    out = tmp_path / "rig.json"
    result = run_cli("calibrate", folder / "boards", *BOARD_ARGS, "--wand", tmp_path / "wand.npz",
                     "--wand-length", "400", "--out", out)
    assert result.exit_code == 0, result.stderr
    assert "wand 24 of 24 frames" in result.stdout, result.stdout
    calibrated = load_rig(out)
    assert calibrated.metadata["wand"] == {"length_mm": 400.0, "frames": 24, "frames_kept": 24}
    # the same board detections without the wand (the bundle adjustment `calibrate --synced` runs)
    board = PRESET_BOARDS["room"]
    views = [[View(name, *board.detect(image)) for name, image in ImageSource(folder / "boards" / c).frames()]
             for c in rig.names]
    fits = [calibrate_intrinsics(board, v, cam.image_size) for v, cam in zip(views, rig)]
    alone = bundle_adjust(board, views, fits, chained_stereo(board, views, fits))
    sizes = [c.image_size for c in rig]
    alone_mm, alone_deg = pose_errors(rig_from_poses(rig.names, alone.intrinsics, alone.rig_poses, sizes),
                                      rig, align=True)
    wand_mm, wand_deg = pose_errors(calibrated, rig, align=True)
    assert wand_mm.max() < alone_mm.max() and wand_deg.max() < alone_deg.max(), (
        alone_mm, wand_mm, alone_deg, wand_deg)


@pytest.mark.slow
def test_calibrate_refuses_a_wand_of_another_length(room_footage, run_cli, tmp_path):
    _, folder = room_footage
    assert run_cli("detect", folder / "wand", "--out", tmp_path / "wand.npz", "--quiet").exit_code == 0
    result = run_cli("calibrate", folder / "boards", *BOARD_ARGS, "--wand", tmp_path / "wand.npz",
                     "--wand-length", "500", "--out", tmp_path / "rig.json", "--quiet")
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines()[-1].startswith(
        f"mocaptk: error: {tmp_path / 'wand.npz'}: the wand was not found: "), result.stderr
    assert re.search(r"median length is (39\d|40\d)\.\d mm, none within 2% of 500 mm", result.stderr)
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "rig.json").exists()


def _tiny_cameras(folder, n):
    """``n`` camera folders of one blank PNG each (enough for the checks made before any work)."""
    for c in range(n):
        (folder / f"cam{c}").mkdir()
        cv2.imwrite(str(folder / f"cam{c}" / "view_000.png"), np.zeros((8, 8), np.uint8))
    return [folder / f"cam{c}" for c in range(n)]


def test_calibrate_refuses_a_wand_file_of_another_camera_count(run_cli, tmp_path):
    cameras = _tiny_cameras(tmp_path, 2)
    save_detections(pack([[(np.zeros((2, 2)), np.zeros(2, bool), np.ones(2))]] * 3, ["a", "b", "c"]),
                    tmp_path / "wand.npz", force=False)
    result = run_cli("calibrate", *cameras, *BOARD_ARGS, "--wand", tmp_path / "wand.npz", "--wand-length",
                     "400", "--out", tmp_path / "rig.json")
    assert result.exit_code == 2
    assert result.stderr.strip() == (f"mocaptk: error: {tmp_path / 'wand.npz'}: 3 cameras, but 2 are "
                                     "calibrated: detect the wand footage of the same cameras, in the same order")


@pytest.mark.parametrize("args, message", [
    (("--wand", "w.npz"), "--wand and --wand-length go together"),
    (("--wand-length", "400"), "--wand and --wand-length go together"),
    (("--wand", "w.npz", "--wand-length", "-4"), "--wand-length must be > 0 mm, got -4"),
    (("--wand", "w.npz", "--wand-length", "inf"), "--wand-length must be > 0 mm, got inf"),
])
def test_calibrate_wand_options_are_checked_first(run_cli, tmp_path, args, message):
    result = run_cli("calibrate", *_tiny_cameras(tmp_path, 2), *BOARD_ARGS, *args, "--out", tmp_path / "r.json")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith(f"mocaptk: error: {message}"), lines


def test_calibrate_wand_needs_synced(run_cli, tmp_path):
    result = run_cli("calibrate", *_tiny_cameras(tmp_path, 2), "--wand", "w.npz", "--wand-length", "400",
                     "--out", tmp_path / "r.json")
    assert result.exit_code == 2
    assert result.stderr.strip() == "mocaptk: error: --wand needs --synced: the wand refines the rig's extrinsics"
