"""The report data of each command: what ``cluster``, ``evaluate``, ``compare`` put on the page."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mocaptk.clustering.layout import Layout
from mocaptk.trajectories import Trajectories

from ..build import DenseCloud, RigBuild, dense_cloud
from .scene import REPLAY_BUDGET_BYTES, replay_clips, replay_step, scene_data

__all__ = ["cluster_report", "compare_report", "error_map", "evaluation_report", "per_marker_rmse",
           "retarget_report", "session_clips", "solve_report"]


def session_clips(cloud: DenseCloud, rate_hz: float, *, labels: Sequence[str] = (),
                  performance: np.ndarray | None = None) -> list[dict]:
    """Replay clips of the cloud's session and, where given, a held-out ``performance``
    (F, M, 3) mm in the session frame with markers ``labels`` (matched to the cloud by label)."""
    captured = int(np.sum(cloud.captured))
    clips = [("session", cloud.trajectories[:, :captured])]
    if performance is not None:
        clips.append(("held-out performance", _in_cloud(cloud, labels, performance) @ cloud.rotation.T))
    return replay_clips(clips, rate_hz, cloud.neutral[:captured])


def _in_cloud(cloud: DenseCloud, labels: Sequence[str], values: np.ndarray) -> np.ndarray:
    """``values`` (..., M, ...) over ``labels`` → the cloud's captured markers (NaN where absent)."""
    lookup = {label: i for i, label in enumerate(labels)}
    captured = int(np.sum(cloud.captured))
    out = np.full((values.shape[0], captured) + values.shape[2:], np.nan)
    for i, label in enumerate(cloud.labels[:captured]):
        if label in lookup:
            out[:, i] = values[:, lookup[label]]
    return out


def per_marker_rmse(errors: np.ndarray) -> np.ndarray:
    """RMSE (M,) mm over frames of held-out errors (F, M) (NaN: never tested)."""
    squared = np.asarray(errors, float) ** 2
    counts = np.isfinite(squared).sum(axis=0)
    total = np.nansum(squared, axis=0)
    return np.sqrt(np.divide(total, counts, out=np.full(total.shape, np.nan), where=counts > 0))


def error_map(cloud: DenseCloud, labels: Sequence[str], rmse: np.ndarray, *, name: str,
              layout: Sequence[str] | None = None) -> dict:
    """One colour map of the page: per-marker RMSE (M,) over ``labels`` on the cloud's markers
    (mirrored ones unmeasured), with its own ``layout`` labels (None: the page's clusters)."""
    values = np.full(len(cloud.labels), np.nan)
    values[: int(np.sum(cloud.captured))] = _in_cloud(cloud, labels, np.asarray(rmse)[None])[0]
    return {"name": name, "values": np.round(values, 3),
            "layout": None if layout is None else [int(i) for i in cloud.index(layout)]}


def evaluation_report(layout: Layout, session: Trajectories, *, rmse: np.ndarray, result: dict,
                      performance: np.ndarray | None, summary: str, title: str) -> dict:
    """Page data of ``mocaptk evaluate``: the layout's clusters on the dense marker surface,
    coloured by each marker's held-out RMSE ``rmse`` (M,) mm, the method table, the session
    and the held-out ``performance`` (session frame, session markers) replays."""
    cloud = dense_cloud(layout, session)
    data = scene_data(cloud, layout=layout)
    name = str(layout.parameters.get("method", "layout"))
    data["errors"] = [error_map(cloud, session.labels, rmse, name=f"held-out RMSE, {name}")]
    rows, picks = [], []
    for method, s in result["methods"].items():
        rows.append([method, s["count"], _mm(s, "rmse_mm"), _mm(s, "p95_mm")])
        picks.append(0 if method == name else None)
    protocol = result.get("protocol", {})
    data.update(kind="evaluate", title=title, summary=summary,
                clips=session_clips(cloud, session.rate, labels=session.labels, performance=performance),
                tables=[{"title": "Held-out reconstruction error (mm)", "rows": rows, "picks": picks,
                         "columns": ["method", "markers", "RMSE", "p95"],
                         "note": f"test: {protocol.get('test', '')}; random: mean ± sd of "
                                 f"{protocol.get('random_seeds', '')} layouts. Click the layout's row "
                                 "to colour the face by its per-marker RMSE."}])
    return data


def compare_report(session: Trajectories, *, rows: Sequence[dict], performance: np.ndarray | None,
                   summary: str, title: str, note: str) -> dict:
    """Page data of ``mocaptk compare``: one colour map per method x count, each with its own
    layout (``rows``: dicts with ``method``, ``count``, ``rmse_mm``, ``p95_mm``, ``lost_rmse_mm``, ``layout``
    (labels) and ``rmse`` (M,) mm per session marker, or ``error``), the table, the
    session and held-out ``performance`` replays. Regions come from the label prefixes."""
    from mocaptk.clustering.neutral import max_displacement, neutral_pose
    from mocaptk.clustering.regions import regions_from_prefixes
    from mocaptk.clustering.symmetry import estimate_sagittal_plane, is_half_capture

    neutral = neutral_pose(session.positions)
    plane = estimate_sagittal_plane(session.labels, neutral, max_displacement(session.positions, neutral),
                                    half=is_half_capture(session.labels))  # orients the front view
    cloud = dense_cloud(Layout(source={}, parameters={}, regions=(), clusters=(),
                               extra={"sagittal_plane": {"point": plane.point, "normal": plane.normal}}),
                        session)
    data = scene_data(cloud, regions=regions_from_prefixes(cloud.labels))
    table, picks, maps = [], [], []
    for row in rows:
        table.append([row["method"], row["count"], *(["–"] * 3 if row.get("error") else
                     [f"{row['rmse_mm']:.3f}", f"{row['p95_mm']:.3f}", f"{row['lost_rmse_mm']:.3f}"])])
        picks.append(None if row.get("error") else len(maps))
        if not row.get("error"):
            maps.append(error_map(cloud, session.labels, row["rmse"], name=f"{row['method']} × {row['count']}",
                                  layout=row["layout"]))
    data.update(kind="compare", title=title, summary=summary, errors=maps,
                clips=session_clips(cloud, session.rate, labels=session.labels, performance=performance),
                tables=[{"title": "Held-out reconstruction error (mm)",
                         "columns": ["method", "markers", "RMSE", "p95", "1 lost"], "rows": table,
                         "picks": picks, "note": note}])
    return data


def _mm(summary: dict, key: str) -> str:
    sd = summary.get(key.replace("_mm", "_sd_mm"))
    return f"{summary[key]:.3f}" + (f" ± {sd:.3f}" if sd is not None else "")


def cluster_report(layout: Layout, session: Trajectories, *, build: RigBuild | None,
                   summary: str, title: str, neutral: np.ndarray | None = None) -> dict:
    """Page data of ``mocaptk cluster``: the layout on its rig's face (or the dense marker
    surface without a rig), the session replay and the clustering summary (``neutral``: the
    session's neutral pose, if known)."""
    if build is not None:
        cloud = build.cloud
        clips = session_clips(cloud, session.rate)
    else:  # a cloud of the replayed frames only
        if neutral is None:
            from mocaptk.clustering.neutral import neutral_pose
            neutral = neutral_pose(session.positions)
        captured = int(np.isfinite(neutral).all(axis=1).sum())
        step = replay_step(session.rate, session.n_frames, captured, budget_bytes=REPLAY_BUDGET_BYTES)
        cloud = dense_cloud(layout, session, neutral=neutral, frames=slice(None, None, step))
        clips = replay_clips([("session", cloud.trajectories[:, :captured])], session.rate,
                             cloud.neutral[:captured], sampled=(step, session.n_frames))
    data = scene_data(cloud, layout=layout, build=build)
    data.update(kind="cluster", title=title, summary=summary, clips=clips, tables=_rig_tables(build))
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


def solve_report(layout: Layout, solved: Trajectories, *, marker_error: np.ndarray | None, kind: str,
                 table: Sequence[Sequence], summary: str, title: str) -> dict:
    """Page data of ``mocaptk solve``: the layout on the surface through the solved dense markers
    ``solved`` (head-relative, as the model solves them), each marker coloured by the model's
    expected error ``marker_error`` (M,) mm over ``solved.labels`` (None: unknown, no map), the
    model ``table`` rows ([name, value]) and the replay of the solved performance."""
    cloud = dense_cloud(layout, solved)
    data = scene_data(cloud, layout=layout)
    data["errors"] = [] if marker_error is None else [
        error_map(cloud, solved.labels, marker_error, name=f"expected error, {kind}")]
    captured = int(np.sum(cloud.captured))
    clips = replay_clips([("solved performance", cloud.trajectories[:, :captured])], solved.rate,
                         cloud.neutral[:captured])
    data.update(kind="solve", title=title, summary=summary, clips=clips,
                tables=[{"title": "Model and solve", "columns": ["", ""], "rows": list(table)}])
    return data


#: Gap (mm) between the actor's face and the character beside it on the page.
CHARACTER_GAP_MM = 25.0
#: A weight curve is drawn for the shapes whose weight exceeds this somewhere.
CURVE_MIN_WEIGHT = 0.1


def retarget_report(layout: Layout, solved: Trajectories, *, character, weights: np.ndarray,
                    table: Sequence[Sequence], summary: str, title: str) -> dict:
    """Page data of ``mocaptk retarget``: the actor (the solved dense markers ``solved``,
    head-relative, at the replay's frames: every ``step``-th of ``weights``' F, given in
    ``solved.metadata["replay"]`` as (step, F)) with the layout, the ``character``
    (:class:`~mocaptk.retarget.character.Character`) beside it driven by ``weights`` (F, S) at the
    same frames, the weights as curves, and ``table`` rows ([name, value])."""
    step, frames = solved.metadata["replay"]
    cloud = dense_cloud(layout, solved)
    data = scene_data(cloud, layout=layout)
    captured = int(np.sum(cloud.captured))
    clips = replay_clips([("performance: actor and character", cloud.trajectories[:, :captured])], solved.rate,
                         cloud.neutral[:captured], sampled=(step, frames))
    data.update(kind="retarget", title=title, summary=summary, clips=clips,
                character=character_scene(character, weights[::step], cloud.neutral),
                tables=[{"title": "Retarget", "columns": ["", ""], "rows": list(table)}])
    return data


def character_scene(character, weights: np.ndarray, actor: np.ndarray) -> dict:
    """The character beside the ``actor``'s markers (N, 3) mm rig frame: its neutral scaled to the
    actor's height, shapes as int16 offsets (:data:`~.scene.TRACK_MM` steps, base64), the
    replayed ``weights`` (f, S) and which shapes get a curve."""
    import base64

    from .scene import DIGITS, TRACK_MM

    rest = np.asarray(character.vertices, dtype=float)
    finite = actor[np.isfinite(actor).all(axis=1)]
    scale = np.ptp(finite[:, 1]) / max(np.ptp(rest[:, 1]), 1e-9)
    lo, hi = rest.min(axis=0) * scale, rest.max(axis=0) * scale
    centre = (finite.min(axis=0) + finite.max(axis=0)) / 2
    shift = np.array([finite[:, 0].max() + CHARACTER_GAP_MM - lo[0], centre[1] - (lo[1] + hi[1]) / 2,
                      centre[2] - hi[2] + (finite[:, 2].max() - centre[2])])
    shapes = np.clip(np.round(np.asarray(character.deltas, dtype=float) * scale / TRACK_MM), -32767, 32767)
    curves = [int(k) for k in np.flatnonzero(np.asarray(weights).max(axis=0, initial=0) > CURVE_MIN_WEIGHT)]
    return {"names": list(character.names), "vertices": np.round(rest * scale + shift, DIGITS),
            "faces": np.asarray(character.faces, dtype=np.int64), "resolution_mm": TRACK_MM,
            "shapes": base64.b64encode(shapes.astype("<i2").tobytes()).decode("ascii"),
            "weights": np.round(np.asarray(weights, dtype=float), 3), "curves": curves}
