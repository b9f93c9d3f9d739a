"""The unlabelled 2-D detections file (``mocaptk detect`` -> ``mocaptk reconstruct``).

A numpy ``.npz`` with ``format`` = ``mocaptk.detections``, ``version`` 1, ``points2d (C, F, B, 2)``
float px (NaN-padded: B = most blobs in any image), ``merged (C, F, B)`` bool, ``area (C, F, B)``
px and ``camera_names (C,)``; optional ``rate`` (Hz).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_open
from mocaptk.errors import InputFileError

FORMAT, VERSION = "mocaptk.detections", 1


@dataclass
class Detections:
    points2d: np.ndarray
    merged: np.ndarray
    area: np.ndarray
    camera_names: list[str]
    rate: float | None = None


def pack(per_image: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]],
         camera_names: list[str], rate: float | None = None) -> Detections:
    """``per_image[c][f] = (centres (B, 2), merged (B,), area (B,))`` -> padded arrays."""
    most = max((len(b[0]) for row in per_image for b in row), default=0)
    shape = (len(per_image), len(per_image[0]) if per_image else 0, most)
    points, merged, area = np.full(shape + (2,), np.nan), np.zeros(shape, bool), np.zeros(shape)
    for c, row in enumerate(per_image):
        for f, (centres, flags, sizes) in enumerate(row):
            points[c, f, :len(centres)] = centres
            merged[c, f, :len(centres)] = flags
            area[c, f, :len(centres)] = sizes
    return Detections(points, merged, area, list(camera_names), rate)


def save_detections(detections: Detections, path: str | os.PathLike[str], *, force: bool) -> None:
    extra = {} if detections.rate is None else {"rate": np.float64(detections.rate)}
    with atomic_open(path, "wb", force=force) as handle:
        np.savez_compressed(handle, format=np.array(FORMAT), version=np.int64(VERSION),
                            points2d=detections.points2d, merged=detections.merged,
                            area=detections.area, camera_names=np.array(detections.camera_names),
                            **extra)


def load_detections(path: str | os.PathLike[str]) -> Detections:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputFileError(path, f"cannot read detections .npz ({exc})") from None
    if str(arrays.get("format", "")) != FORMAT:
        raise InputFileError(path, f"not a detections file (format {FORMAT!r}; made by mocaptk detect)")
    if int(arrays.get("version", -1)) != VERSION:
        raise InputFileError(path, f"unsupported detections version {arrays.get('version')}")
    points = np.asarray(arrays.get("points2d"), dtype=np.float64)
    if points.ndim != 4 or points.shape[-1] != 2:
        raise InputFileError(path, f"points2d must have shape (cameras, frames, blobs, 2), got {points.shape}")
    merged = np.asarray(arrays.get("merged"), dtype=bool)
    area = np.asarray(arrays.get("area"), dtype=np.float64)
    names = [str(n) for n in np.asarray(arrays.get("camera_names")).ravel()]
    if merged.shape != points.shape[:3] or area.shape != points.shape[:3] or len(names) != len(points):
        raise InputFileError(path, "merged, area and camera_names do not match points2d")
    rate = float(arrays["rate"]) if "rate" in arrays else None
    return Detections(points, merged, area, names, rate)
