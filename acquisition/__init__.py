"""Acquisition: marker files (C3D, CSV, TRC), synthetic captures, cameras, triangulation, cleaning.

Public API is listed in ``__all__``; the CLI calls only these names. Each name is imported from
its module on first use (PEP 562), so ``mocaptk info`` does not pay for scipy.signal / scipy.stats
(filtering, synthesis) it never calls.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> the submodule that defines it.
_WHERE = {
    **dict.fromkeys(["Camera", "CameraRig", "cara_rig", "room_rig", "load_rig", "save_rig",
                     "read_qca"], "cameras"),
    "project_markers": "projection",
    "triangulate": "triangulate",
    "read_c3d": "c3d_read",
    "write_c3d": "c3d_write",
    **dict.fromkeys(["detect_format", "read_trajectories", "write_trajectories"], "formats"),
    **dict.fromkeys(["FaceModel", "load_face_model"], "face_model"),
    **dict.fromkeys(["MarkerLayout", "dense_layout"], "synth_layout"),
    **dict.fromkeys(["GroundTruth", "SyntheticSession", "dense_session", "performance_session",
                     "camera_capture", "save_ground_truth", "load_ground_truth"], "synth_session"),
    "lowpass": "filtering",
    **dict.fromkeys(["fill_gaps", "FillReport", "GapRecord"], "gapfill"),
    **dict.fromkeys(["stabilize_head", "StabilizeResult", "detect_rigid_markers"], "stabilize"),
}
__all__ = list(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
