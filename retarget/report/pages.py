"""The report data of each command: what ``cluster``, ``evaluate``, ``compare`` put on the page."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mocaptk.clustering.layout import Layout
from mocaptk.trajectories import Trajectories

from ..build import DenseCloud, RigBuild, dense_cloud
from .scene import replay_clips, scene_data

__all__ = ["cluster_report", "session_clips"]


def session_clips(cloud: DenseCloud, rate_hz: float, *,
                  performance: Trajectories | None = None) -> list[dict]:
    """Replay clips of the cloud's session and, where given, a held-out ``performance`` (its
    markers matched by label, rotated into the cloud's rig frame)."""
    captured = int(np.sum(cloud.captured))
    clips = [("session", cloud.trajectories[:, :captured])]
    if performance is not None:
        lookup = {label: i for i, label in enumerate(performance.labels)}
        perf = np.full((performance.n_frames, captured, 3), np.nan)
        for i, label in enumerate(cloud.labels[:captured]):
            if label in lookup:
                perf[:, i] = performance.positions[:, lookup[label]]
        clips.append(("held-out performance", perf @ cloud.rotation.T))
    return replay_clips(clips, rate_hz, cloud.neutral[:captured])


def cluster_report(layout: Layout, session: Trajectories, *, build: RigBuild | None,
                   summary: str, title: str) -> dict:
    """Page data of ``mocaptk cluster``: the layout on its rig's face (or the dense marker
    surface without a rig), the session replay and the clustering summary."""
    cloud = build.cloud if build is not None else dense_cloud(layout, session)
    data = scene_data(cloud, layout=layout, build=build)
    data.update(kind="cluster", title=title, summary=summary,
                clips=session_clips(cloud, session.rate), tables=_rig_tables(build))
    return data


def _rig_tables(build: RigBuild | None) -> list[dict]:
    if build is None:
        return []
    check = build.check
    rows: list[Sequence] = [
        ["joints", build.rig.joint_count - 1],
        ["mesh", f"{build.report['mesh']['kind']}, {build.rig.vertex_count} vertices"],
        ["weights", build.report["weights"]["method"]],
        ["skinning check RMSE", f"{check.rmse_mm:.2f} mm"],
        ["skinning check p95", f"{check.p95_mm:.2f} mm"],
    ]
    return [{"title": "Rig (rig.json / rig.fbx / rig.glb)", "columns": ["", ""], "rows": rows}]
