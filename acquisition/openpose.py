"""OpenPose 2-D keypoint detections (one JSON file per frame and camera) as arrays.

Used for the real-data triangulation check (Pose2Sim demo: 4 cameras, BODY_25B keypoints).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

from .cameras import CameraRig
from .projection import project_points
from .triangulate import triangulate_points

#: Keypoint order of OpenPose's BODY_25B model (the Pose2Sim demo's ``pose_model``).
BODY_25B = ("Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow",
            "RElbow", "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle",
            "Neck", "Head", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")


def read_openpose_folder(folder: str | os.PathLike[str]) -> np.ndarray:
    """Keypoints of all people in a folder of OpenPose ``*.json`` frames (natural order).

    Returns ``(F, P, K, 3)``: x px, y px, confidence; NaN-padded to the most people in a
    frame; keypoints with confidence 0 (not detected) are NaN.
    """
    folder = Path(folder)
    files = sorted(folder.glob("*.json"), key=lambda p: [int(t) if t.isdigit() else t
                                                          for t in re.split(r"(\d+)", p.name)])
    if not files:
        raise InputFileError(folder, "no OpenPose .json files")
    frames = []
    for path in files:
        try:
            people = json.loads(path.read_text(encoding="utf-8"))["people"]
            frames.append([np.asarray(p["pose_keypoints_2d"], dtype=np.float64).reshape(-1, 3)
                           for p in people])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputFileError(path, f"not an OpenPose keypoint file ({exc})") from None
    n_people = max(1, max(len(f) for f in frames))
    n_keypoints = max((p.shape[0] for f in frames for p in f), default=len(BODY_25B))
    out = np.full((len(frames), n_people, n_keypoints, 3), np.nan)
    for i, people in enumerate(frames):
        for j, keypoints in enumerate(people):
            out[i, j, :keypoints.shape[0]] = keypoints
    out[out[..., 2] <= 0] = np.nan
    return out


def read_openpose_cameras(folders: Sequence[str | os.PathLike[str]]) -> np.ndarray:
    """Detections of several cameras, ``(C, F, P, K, 3)``, one folder per camera (same order
    as the rig); people padded to the same count; frame counts must match."""
    per_camera = [read_openpose_folder(folder) for folder in folders]
    n_frames = {d.shape[0] for d in per_camera}
    if len(n_frames) != 1:
        raise InputFileError(folders[0], f"camera folders have different frame counts "
                                         f"{sorted(n_frames)}")
    n_people = max(d.shape[1] for d in per_camera)
    return np.stack([np.pad(d, ((0, 0), (0, n_people - d.shape[1]), (0, 0), (0, 0)),
                            constant_values=np.nan) for d in per_camera])


def select_person(rig: CameraRig, detections: np.ndarray, *, min_confidence: float = 0.3,
                  outlier_threshold_px: float = 20.0) -> np.ndarray:
    """Pick, per camera and frame, the detected person who is the same across cameras.

    Starts from the most confident person in every view, triangulates robustly, then keeps
    in each view the person whose keypoints lie closest (median px) to the reprojected
    skeleton. Keypoints below ``min_confidence`` are dropped.

    Parameters
    ----------
    detections : (C, F, P, K, 3) from :func:`read_openpose_cameras`.

    Returns
    -------
    observations : (C, F, K, 2) px, NaN where not detected.
    """
    confident = detections[..., 2] >= min_confidence  # NaN compares False
    xy = np.where(confident[..., None], detections[..., :2], np.nan)
    n_cams, n_frames, _, n_keypoints, _ = xy.shape
    score = np.where(confident, detections[..., 2], 0.0).sum(axis=-1)  # (C, F, P)
    choice = score.argmax(axis=-1)
    frames = np.arange(n_frames)
    chosen = np.stack([xy[c, frames, choice[c]] for c in range(n_cams)])  # (C, F, K, 2)
    points, _ = triangulate_points(rig, chosen.reshape(n_cams, -1, 2),
                                   outlier_threshold_px=outlier_threshold_px)
    points = points.reshape(n_frames, n_keypoints, 3)
    for c, camera in enumerate(rig):
        reprojected, _ = project_points(camera, points)  # (F, K, 2)
        distance = np.linalg.norm(xy[c] - reprojected[:, None], axis=-1)  # (F, P, K)
        seen = np.isfinite(distance)
        median = np.full(distance.shape[:2], np.inf)
        has = seen.any(axis=-1)
        median[has] = np.nanmedian(distance[has], axis=-1)
        keep = np.isfinite(median).any(axis=-1)
        choice[c, keep] = median[keep].argmin(axis=-1)
        chosen[c] = xy[c, frames, choice[c]]
    return chosen
