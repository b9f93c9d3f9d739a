"""An independent test bed for mocaptk: ICT-FaceKit sessions made without mocaptk's synth.

See README.md. Nothing here imports ``mocaptk.acquisition.synth_session``, ``synth_layout`` or
``face_model``; mocaptk is used only to write C3D files (writing is not generation).
"""

from .ict import IctFace, load_ict
from .session import (Actor, TestbedSession, apply_pose, head_motion, load_truth, make_actor,
                      performance_session, rom_session, save_truth, truth_positions, write_set)

__all__ = ["Actor", "IctFace", "TestbedSession", "apply_pose", "head_motion", "load_ict", "load_truth",
           "make_actor", "performance_session", "rom_session", "save_truth", "truth_positions", "write_set"]
