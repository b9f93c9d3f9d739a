"""Retarget: influence regions to joint weights on a face mesh, rig exports, marker guides."""

__all__: list[str] = []

from .export_fbx import write_rig_fbx  # noqa: E402
from .export_glb import write_rig_glb  # noqa: E402
from .export_json import read_rig_json, write_rig_json  # noqa: E402
from .rig import Rig, RigError, joint_names_from_markers  # noqa: E402
from .build import (RigBuild, RigOptions, build_rig, ground_truth_error,  # noqa: E402
                    write_rig_outputs)

__all__ += ["Rig", "RigError", "joint_names_from_markers", "read_rig_json", "write_rig_fbx",
            "write_rig_glb", "write_rig_json"]
__all__ += ["RigBuild", "RigOptions", "build_rig", "ground_truth_error", "write_rig_outputs"]
