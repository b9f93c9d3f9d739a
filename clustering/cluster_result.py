"""What clustering a session returns: the layout, the session it was computed on and what the
figures and summary need (shared by the pipeline and the layout methods that re-choose it)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mocaptk.trajectories import Trajectories

from .layout import Layout


@dataclass
class RegionMatrix:
    """The consolidated correlation of one region (for heatmaps): labels in matrix order."""

    labels: list[str]
    matrix: np.ndarray
    clusters: np.ndarray  # (M,) cluster number of each marker


@dataclass
class ClusterResult:
    """A computed layout plus what the figures and summary need."""

    layout: Layout
    trajectories: Trajectories  # the (stabilized) session the layout was computed on
    neutral: np.ndarray  # (M, 3) mm, neutral pose of ``trajectories``
    matrices: dict[str, RegionMatrix]
    frame: np.ndarray  # (3, 3) rows lateral, up, forward of the face (for front views)
    notes: list[str] = field(default_factory=list)
