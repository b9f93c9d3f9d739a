"""The calibration wand: its ends matched across cameras, and what it adds to the bundle
adjustment (each camera's distance, which board views facing one camera leave coupled to its
focal length)."""

from __future__ import annotations

import cv2
import numpy as np

from mocaptk.acquisition.calibration import (View, bundle_adjust, calibrate_intrinsics,
                                             chained_stereo, pose_errors, rig_from_poses)
from mocaptk.acquisition.cameras import room_rig
from mocaptk.acquisition.synth_board_views import PRESET_BOARDS, board_poses
from mocaptk.acquisition.synth_wand import wand_pixels, wand_positions
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
