"""Acquisition: marker files (C3D, CSV, TRC), synthetic captures, cameras, triangulation, cleaning.

Public API is listed in ``__all__``; the CLI calls only these names.
"""

__all__: list[str] = []

from .cameras import Camera, CameraRig, cara_rig, load_rig, read_qca, room_rig, save_rig  # noqa: E402
from .projection import project_markers  # noqa: E402
from .triangulate import triangulate  # noqa: E402

__all__ += ["Camera", "CameraRig", "cara_rig", "room_rig", "load_rig", "save_rig", "read_qca",
            "project_markers", "triangulate"]

from .c3d_read import read_c3d  # noqa: E402
from .c3d_write import write_c3d  # noqa: E402

__all__ += ["read_c3d", "write_c3d"]

from .formats import detect_format, read_trajectories, write_trajectories  # noqa: E402

__all__ += ["detect_format", "read_trajectories", "write_trajectories"]

from .face_model import FaceModel, load_face_model  # noqa: E402
from .synth_layout import MarkerLayout, dense_layout  # noqa: E402
from .synth_session import (GroundTruth, SyntheticSession, camera_capture,  # noqa: E402
                            dense_session, load_ground_truth, performance_session,
                            save_ground_truth)

__all__ += ["FaceModel", "load_face_model", "MarkerLayout", "dense_layout", "GroundTruth",
            "SyntheticSession", "dense_session", "performance_session", "camera_capture",
            "save_ground_truth", "load_ground_truth"]

from .filtering import lowpass  # noqa: E402
from .gapfill import FillReport, GapRecord, fill_gaps  # noqa: E402
from .stabilize import StabilizeResult, detect_rigid_markers, stabilize_head  # noqa: E402

__all__ += ["lowpass", "fill_gaps", "FillReport", "GapRecord", "stabilize_head", "StabilizeResult",
            "detect_rigid_markers"]
