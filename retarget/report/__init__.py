"""Self-contained ``report.html`` pages: the layout on the face in 3-D, replay, held-out errors."""

from .page import report_html, write_report
from .pages import (cluster_report, compare_report, error_map, evaluation_report, per_marker_rmse,
                    retarget_report, session_clips, solve_report)
from .scene import replay_clips, replay_step, scene_data

__all__ = ["cluster_report", "compare_report", "error_map", "evaluation_report", "per_marker_rmse", "replay_clips", "replay_step", "report_html", "retarget_report", "scene_data",
           "session_clips", "solve_report", "write_report"]
