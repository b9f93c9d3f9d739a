"""Write :class:`mocaptk.Trajectories` to a C3D file with ezc3d (atomic)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.atomic import atomic_path
from mocaptk.errors import OutputError
from mocaptk.trajectories import Trajectories

from .c3d_read import TAKES_GROUP


def write_c3d(traj: Trajectories, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``traj`` to the C3D file ``path`` (Intel, float storage, units ``mm``).

    Gaps (NaN) are written as invalid points (residual −1, coordinates 0), never as valid
    zeros. Labels past 255 go to POINT:LABELS2, LABELS3...; more than 65,535 frames are
    written whole (the header field saturates, TRIAL:ACTUAL_START_FIELD/ACTUAL_END_FIELD hold
    the 32-bit frame range); ``first_frame`` is stored in the header and TRIAL fields; takes go
    to the ``MOCAPTK`` parameter group (TAKE_NAMES, TAKE_STARTS, TAKE_ENDS, TAKE_REGIONS;
    0-based frames, end exclusive) so :func:`.c3d_read.read_c3d` restores them. Residuals are
    stored as the C3D standard allows: whole multiples of the scale (1 mm).

    The file is written to a temporary sibling and renamed into place; an existing ``path``
    is refused unless ``force``.
    """
    import ezc3d

    if traj.n_frames == 0 or traj.n_markers == 0:
        raise OutputError(f"{path}: nothing to write ({traj.n_frames} frames, "
                          f"{traj.n_markers} markers)")
    c3d = ezc3d.c3d()
    params = c3d["parameters"]
    params["POINT"]["RATE"]["value"] = np.array([traj.rate])
    params["POINT"]["UNITS"]["value"] = ["mm"]
    params["POINT"]["LABELS"]["value"] = list(traj.labels)
    descriptions = traj.metadata.get("descriptions") or {}
    if descriptions:
        params["POINT"]["DESCRIPTIONS"]["value"] = [str(descriptions.get(lb, "")) for lb in traj.labels]
    n_frames, n_markers = traj.n_frames, traj.n_markers
    first = traj.first_frame
    c3d["header"]["points"]["first_frame"] = min(max(first, 1), 0xFFFF) - 1  # ezc3d is 0-based
    last = first + n_frames - 1
    _set(params, "TRIAL", "ACTUAL_START_FIELD", _words(first), "INT")
    _set(params, "TRIAL", "ACTUAL_END_FIELD", _words(max(last, first)), "INT")
    takes = traj.takes
    if takes:
        _set(params, TAKES_GROUP, "TAKE_NAMES", [t.name for t in takes], "CHAR")
        _set(params, TAKES_GROUP, "TAKE_STARTS", np.array([float(t.start) for t in takes]), "FLOAT")
        _set(params, TAKES_GROUP, "TAKE_ENDS", np.array([float(t.end) for t in takes]), "FLOAT")
        _set(params, TAKES_GROUP, "TAKE_REGIONS", [t.region or "" for t in takes], "CHAR")

    missing = ~np.isfinite(traj.positions).all(axis=2)  # (frames, markers)
    points = np.zeros((4, n_markers, n_frames))
    points[:3] = np.where(missing[..., None], 0.0, traj.positions).transpose(2, 1, 0)
    points[3] = 1.0
    residual = np.zeros((n_frames, n_markers)) if traj.residuals is None else traj.residuals
    # a valid point without a residual (e.g. gap-filled) gets 0, C3D's "interpolated" residual
    residual = np.where(missing, -1.0, np.where(np.isfinite(residual), np.clip(residual, 0, 255), 0.0))
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {
        "residuals": residual.T[None].astype(np.float64),
        "camera_masks": np.zeros((7, n_markers, n_frames), dtype=bool)}
    with atomic_path(path, force=force) as tmp:
        # ezc3d appends ".c3d" to any other file name
        target = tmp if tmp.name.endswith(".c3d") else tmp.with_name(tmp.name + ".c3d")
        try:
            c3d.write(str(target))
            if target != tmp:
                os.replace(target, tmp)
        except (RuntimeError, ValueError, OSError) as exc:
            target.unlink(missing_ok=True)
            raise OutputError(f"{path}: cannot write C3D ({exc})") from None
    return Path(path)


def _words(value: int) -> np.ndarray:
    """A 32-bit unsigned frame number as the two 16-bit words of a TRIAL ``*_FIELD``."""
    value = max(int(value), 0)
    return np.array([value & 0xFFFF, value >> 16])


def _set(params: dict[str, Any], group: str, name: str, value: Any, kind: str) -> None:
    import ezc3d

    if group not in params:
        params[group] = {"__METADATA__": {"DESCRIPTION": "", "IS_LOCKED": False}}
    params[group][name] = {"type": getattr(ezc3d.ezc3d, kind), "value": value,
                           "description": "", "is_locked": False}
