"""The plain data of a report page: face mesh, dense and layout markers, clusters, replay clips.

Everything is in the rig frame (X = subject's left, Y up, Z forward, mm), so the page opens on
the front view like the guide. Tracks of markers mirrored from the other half are not stored:
the page mirrors their source marker across the sagittal plane.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping, Sequence

import numpy as np

from mocaptk.clustering.layout import Layout
from mocaptk.clustering.symmetry import mirror_label

from ..build import DenseCloud, RigBuild
from ..guide import pair_names
from ..renders import cluster_shades, region_colour

__all__ = ["MAX_REPLAY_HZ", "REPLAY_BUDGET_BYTES", "hex_colour", "replay_clips", "replay_step",
           "scene_data"]

#: Replay rate cap (Hz): smooth enough to judge the motion, half the sample's 60 Hz.
MAX_REPLAY_HZ = 30.0
#: Track bytes of all clips together (keeps the sample's page well under 20 MB).
REPLAY_BUDGET_BYTES = 4_000_000
#: Track resolution (mm): positions are stored as int16 offsets from the neutral pose.
TRACK_MM = 0.05
_GAP = -32768
#: Decimals (mm) of the positions stored in the page.
DIGITS = 2
#: How far (mm) markers are drawn off the skin, so the surface never hides half of each dot.
LIFT_MM = 1.5


def hex_colour(rgb: Sequence[float]) -> str:
    """``(r, g, b)`` in 0-1 → ``"#rrggbb"``."""
    return "#" + "".join(f"{int(round(min(max(c, 0.0), 1.0) * 255)):02x}" for c in rgb)


def replay_step(rate_hz: float, frames: int, markers: int, *, budget_bytes: int) -> int:
    """Every how many frames a clip of ``frames`` x ``markers`` is kept: at most
    :data:`MAX_REPLAY_HZ`, and within ``budget_bytes`` of int16 positions."""
    step = max(1, math.ceil(rate_hz / MAX_REPLAY_HZ - 1e-9))
    per_frame = markers * 3 * 2
    return max(step, math.ceil(frames * per_frame / max(budget_bytes, per_frame)))


def replay_clips(clips: Sequence[tuple[str, np.ndarray]], rate_hz: float, neutral: np.ndarray, *,
                 budget_bytes: int = REPLAY_BUDGET_BYTES,
                 sampled: tuple[int, int] | None = None) -> list[dict]:
    """Replay clips ``[(name, positions (F, N, 3) mm rig frame of the captured markers)]``, all
    subsampled by one :func:`replay_step` over their total length; stored as base64 little-endian
    int16 offsets from ``neutral`` (N, 3) in :data:`TRACK_MM` steps, -32768 in gaps (and beyond
    ±1.6 m). ``sampled`` (step, frames): the one clip is already every step-th of its frames
    (:func:`replay_step` of them)."""
    neutral = np.round(np.asarray(neutral, dtype=float), DIGITS)  # the page adds its stored neutral
    arrays = [np.asarray(p, dtype=float) for _, p in clips]
    if not arrays:
        return []
    if sampled is None:
        step = replay_step(rate_hz, sum(a.shape[0] for a in arrays), arrays[0].shape[1],
                           budget_bytes=budget_bytes)
        stride, lengths = step, [a.shape[0] for a in arrays]
    else:
        step, stride, lengths = sampled[0], 1, [sampled[1]]
    out = []
    for (name, _), positions, source_frames in zip(clips, arrays, lengths):
        steps = np.round((positions[::stride] - neutral[None]) / TRACK_MM)
        kept = np.where(np.isfinite(steps) & (np.abs(steps) <= 32767), steps, _GAP).astype("<i2")
        out.append({"name": name, "source_rate_hz": float(rate_hz), "step": step,
                    "rate_hz": float(rate_hz) / step, "source_frames": int(source_frames),
                    "frames": int(kept.shape[0]), "resolution_mm": TRACK_MM,
                    "positions": base64.b64encode(kept.tobytes()).decode("ascii")})
    return out


def scene_data(cloud: DenseCloud, *, layout: Layout | None = None, build: RigBuild | None = None,
               regions: Mapping[str, Sequence[str]] | None = None) -> dict:
    """Markers, clusters, mirror plane and face mesh of a report (JSON-ready).

    ``cloud``: the dense markers in the rig frame (mirrored ones after the captured ones, as
    :func:`~mocaptk.retarget.build.dense_cloud` makes them). ``layout``: clusters to show (none
    for a page without a chosen layout). ``build``: the rig whose mesh and skin weights move the
    face; without one the face is the surface through the dense markers, each vertex following
    its marker. ``regions`` {name: labels} where there is no layout.
    """
    labels = list(cloud.labels)
    n = len(labels)
    region_of = {m: r.name for r in layout.regions for m in r.markers} if layout else {}
    if regions:
        region_of.update({m: name for name, members in regions.items() for m in members})
    cluster_of = np.full(n, -1)
    correlation = [None] * n
    clusters = []
    lookup = {label: i for i, label in enumerate(labels)}
    if layout is not None:
        shades = cluster_shades([c.region for c in layout.clusters])
        names = pair_names([c.representative for c in layout.clusters], [c.side for c in layout.clusters],
                           [c.mirrored_from for c in layout.clusters])
        for k, c in enumerate(layout.clusters):
            for m in c.members:
                region_of.setdefault(m, c.region)
                if m in lookup:
                    cluster_of[lookup[m]] = k
                    correlation[lookup[m]] = c.member_correlation.get(m)
            clusters.append({"number": k + 1, "name": names[k], "label": c.representative, "region": c.region,
                             "side": c.side, "marker": lookup[c.representative],
                             "members": [lookup[m] for m in c.members if m in lookup],
                             "mirrored_from": c.mirrored_from, "shade": hex_colour(shades[k]),
                             "colour": hex_colour(region_colour(c.region, tint=-0.45)),
                             "dense_colour": hex_colour(np.asarray(shades[k]) * 0.8)})
    captured = np.asarray(cloud.captured, bool)
    sources = {mirror_label(labels[i]): i for i in np.flatnonzero(captured)}
    mirror_of = [-1 if captured[i] else sources[labels[i]] for i in range(n)]
    region_names = [region_of.get(m, "other") for m in labels]
    data = {
        "markers": {"labels": labels, "regions": region_names, "sides": [_side(m) for m in labels],
                    "neutral": np.round(cloud.neutral, DIGITS), "mirror_of": mirror_of,
                    "cluster": cluster_of, "correlation": correlation,
                    "captured": int(captured.sum())},
        "clusters": clusters,
        "regions": sorted(set(region_names), key=_region_order),
        "region_colours": {r: hex_colour(region_colour(r)) for r in set(region_names)},
        "mirror_plane": _rig_plane(layout, cloud) if not captured.all() else None,
        "mesh": _mesh(cloud, build, cluster_of, clusters),
        "stabilization": _stabilization(layout, lookup),
    }
    return data


def _stabilization(layout: Layout | None, lookup: dict[str, int]) -> list[dict]:
    """The layout's stabilization markers as the guide names them (``H1``, ``H2`` ...)."""
    labels = ((layout.extra.get("stabilization") or {}).get("rigid_labels") or ()) if layout else ()
    return [{"name": f"H{k + 1}", "label": label, "marker": lookup[label]}
            for k, label in enumerate(labels) if label in lookup]


#: The method's region order (top of the face to the bottom), others after.
_ORDER = ("forehead_brow", "eye", "nose", "cheek", "mouth", "chin")


def _region_order(name: str) -> tuple[int, str]:
    return (_ORDER.index(name) if name in _ORDER else len(_ORDER), name)


def _side(label: str) -> str:
    tail = label.rsplit("_", 1)[-1].upper()
    return tail if tail in ("L", "R", "C") else ""


def _rig_plane(layout: Layout | None, cloud: DenseCloud) -> dict | None:
    plane = (layout.extra.get("sagittal_plane") if layout is not None else None) or {}
    if "point" not in plane or "normal" not in plane:
        return None
    point = cloud.rotation @ np.asarray(plane["point"], float)
    normal = cloud.rotation @ np.asarray(plane["normal"], float)
    return {"point": np.round(point, 4), "normal": np.round(normal / np.linalg.norm(normal), 6)}


def _mesh(cloud: DenseCloud, build: RigBuild | None, cluster_of: np.ndarray,
          clusters: list[dict]) -> dict:
    """Vertices, triangles, per-vertex colour / nearest marker / mirrored flag, and the skin:
    per vertex up to k (marker index, weight) pairs moving it with those markers."""
    if build is not None:
        rig = build.rig
        vertices = np.asarray(rig.vertices, float)
        faces = np.asarray(rig.faces, np.int64)
        joint_marker = np.full(rig.joint_count, -1)  # the root and the lid joints: no marker
        joint_marker[build.marker_joints] = cloud.index(build.layout.labels)
        skin_index = joint_marker[np.asarray(rig.weight_index)]
        skin_weight = np.where(skin_index >= 0, np.asarray(rig.weight_value, float), 0.0)
        vertex_cluster = np.asarray(build.regions)
    else:
        from mocaptk.surface_mesh import marker_surface_mesh

        vertices, faces = marker_surface_mesh(cloud.neutral)
        skin_index = np.arange(len(vertices))[:, None]
        skin_weight = np.ones((len(vertices), 1))
        vertex_cluster = cluster_of[: len(vertices)]
    nearest = _nearest(vertices, cloud.neutral)
    mirrored = ~np.asarray(cloud.captured, bool)[nearest]
    base = hex_colour(region_colour("other", tint=0.6))
    colours = [clusters[c]["shade"] if c >= 0 else base for c in vertex_cluster]
    lift = LIFT_MM * _outward_normals(vertices, faces)[_nearest(cloud.neutral, vertices)]
    return {"vertices": np.round(vertices, DIGITS), "faces": faces, "colours": colours,
            "nearest_marker": nearest, "mirrored": mirrored.astype(int),
            "marker_lift": np.round(lift, 3),
            "skin_marker": np.where(skin_index >= 0, skin_index, 0), "skin_weight": np.round(skin_weight, 4)}


def _nearest(points: np.ndarray, targets: np.ndarray, *, shortlist: int = 8) -> np.ndarray:
    """(P,) index of the nearest of ``targets`` (T, 3) to each of ``points`` (P, 3), first on a
    tie: a k-d tree's ``shortlist`` nearest, then the exact distances among them (O(P log T))."""
    from scipy.spatial import cKDTree

    k = min(shortlist, len(targets))
    near = cKDTree(targets).query(points, k=k)[1].reshape(len(points), k)
    near = np.sort(near, axis=1)  # lowest index first, so argmin keeps the first of a tie
    dist = np.linalg.norm(points[:, None] - targets[near], axis=2)
    return near[np.arange(len(points)), np.argmin(dist, axis=1)]


def _outward_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3) pointing away from a point behind the face (rig frame: -Z)."""
    tri = vertices[faces]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], face_normals)
    centre = vertices.mean(axis=0) - np.array([0.0, 0.0, np.ptp(vertices[:, 0])])
    normals *= np.sign(np.sum(normals * (vertices - centre), axis=1))[:, None]
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
