"""A layout's capture plan for a rig (``mocaptk plan``): per layout marker, how the rig sees it and
what losing it costs.

Per layout marker (mirrored twins included, captured as the mirror image of their source's
motion): visibility (% of frames seen by >= 2 cameras) and expected triangulation error (mm) from
:mod:`.camera_cost`, the held-out RMSE of the face when that marker is lost
(:mod:`.lost_marker`; a mirrored twin: its source's, by symmetry), and a **risk**: the expected
increase of the face's held-out RMSE (mm) from capturing that marker with this rig,
``sqrt(intact² + (1 - visibility)·(lost² - intact²) + error² / N) - intact`` — its gaps cost the
lost-marker error in the frames it is unseen, its triangulation error lands on its own position
(one of the N dense markers scored).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.acquisition.cameras import RIG_PRESETS
from mocaptk.trajectories import Take, Trajectories

from .camera_cost import DEFAULT_NOISE_MM, MIRROR_PREFIX, session_costs
from .evaluation import holdout_splits
from .figures import _front, _legend_text, _pyplot, _save
from .layout import Layout, measured_indices
from .lost_marker import heldout_folds, lost_marker_rmse
from .symmetry import SagittalPlane

PLAN_FORMAT = "mocaptk.plan"
PLAN_VERSION = 1


def layout_plane(layout: Layout) -> SagittalPlane | None:
    """The sagittal plane of a mirrored layout (None: not mirrored)."""
    info = layout.extra.get("sagittal_plane")
    if not info or not any(c.mirrored_from for c in layout.clusters):
        return None
    return SagittalPlane(np.asarray(info["point"], dtype=np.float64), np.asarray(info["normal"], dtype=np.float64))


def layout_plan(session: Trajectories, layout: Layout, rig_spec: str, *, stabilized: np.ndarray,
                takes: Sequence[Take] = (), noise_mm: float = DEFAULT_NOISE_MM, layout_path: str | None = None,
                session_name: str = "the session") -> dict[str, Any]:
    """The plan (a JSON-ready dict) of ``layout`` for the rig ``rig_spec`` (``cara``, ``room`` or a
    rig file) over ``session``'s motion as filmed; lost-marker errors on ``stabilized`` (F, N, 3)
    mm, the session with head motion removed, held out by ``takes`` as ``mocaptk evaluate``."""
    measured = measured_indices(layout, session.labels, layout_path=layout_path, session_name=session_name)
    costs = session_costs(session.positions, session.labels, rig_spec, plane=layout_plane(layout),
                          noise_mm=noise_mm)
    cloud_index = {label: i for i, label in enumerate(costs.labels)}

    from mocaptk.threads import one_thread

    layout_idx = np.unique(measured)
    with one_thread():  # many small solves: BLAS threads only contend
        folds = heldout_folds(stabilized, holdout_splits(session.n_frames, takes))
        intact = folds.rmse(layout_idx)
        lost = dict(zip((session.labels[i] for i in layout_idx), lost_marker_rmse(folds, layout_idx).tolist()))
    markers = []
    for cluster in layout.clusters:
        origin = cluster.mirrored_from or cluster.representative
        filmed = cloud_index.get(origin if cluster.mirrored_from is None else MIRROR_PREFIX + origin,
                                 cloud_index[origin])  # a midline twin is its source
        visibility = float(costs.visibility[filmed])
        error = float(costs.triangulation_error_mm[filmed])
        lost_rmse = lost.get(origin, float("nan"))
        risk = marker_risk(intact, lost_rmse, visibility, error, session.n_markers)
        markers.append({"label": cluster.representative, "region": cluster.region,
                        "mirrored_from": cluster.mirrored_from, "visibility_percent": 100.0 * visibility,
                        "triangulation_error_mm": error, "lost_rmse_mm": lost_rmse, "risk_mm": risk})
    return {"format": PLAN_FORMAT, "version": PLAN_VERSION, "units": "mm",
            "rig": {"name": costs.rig, "from": rig_spec if rig_spec in RIG_PRESETS else Path(rig_spec).name,
                    "cameras": list(costs.cameras)},
            "capture": {"frames": costs.frames, "noise_mm": noise_mm, "pixel_noise": costs.pixel_noise},
            "intact_rmse_mm": intact, "dense_markers": session.n_markers,
            "protocol": "visibility and triangulation error: the session's motion captured again through "
                        "the rig (no dropouts or ghosts); lost-marker RMSE: held-out ridge reconstruction of "
                        "the face from the layout without that marker (gap-free frames, as evaluate)",
            "markers": markers}


def marker_risk(intact: float, lost: float, visibility: float, error: float, n_points: int) -> float:
    """Expected increase (mm) of the face's held-out RMSE from capturing one layout marker (see the
    module docstring); NaN error (never seen) counts as lost in every frame."""
    lost_term = (1.0 - visibility) * max(lost ** 2 - intact ** 2, 0.0) if np.isfinite(lost) else 0.0
    noise_term = error ** 2 / n_points if np.isfinite(error) else 0.0
    return float(np.sqrt(intact ** 2 + lost_term + noise_term) - intact)


#: Colour scales of plan.png: fixed where a value has a meaning of its own (visibility), else from 0
#: to a round ceiling no lower than the floor, so that trivial spreads (0.001-0.003 mm) stay green.
PLAN_SCALES = {"risk_mm": ("risk: added face RMSE (mm)", "RdYlGn_r", 0.1),
               "visibility_percent": ("seen by ≥ 2 cameras (% of frames)", "RdYlGn", None),
               "triangulation_error_mm": ("triangulation error (mm RMS)", "RdYlGn_r", 0.5),
               "lost_rmse_mm": ("face RMSE with this marker lost (mm)", "RdYlGn_r", 1.0)}
#: Markers named in each panel: the worst few by its value.
PLAN_NAMED = 5


def _round_ceiling(value: float, floor: float) -> float:
    """The smallest of 1, 2, 5 x 10^k at or above ``value`` (at least ``floor``)."""
    if not np.isfinite(value) or value <= floor:
        return floor
    power = 10.0 ** np.floor(np.log10(value))
    return float(next(m * power for m in (1, 2, 5, 10) if m * power >= value))


def plan_picture(plan: dict[str, Any], neutral: dict[str, np.ndarray], layout_positions: dict[str, np.ndarray],
                 *, frame: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Front views (``frame``: rows lateral, up, forward) of the layout markers coloured by risk,
    visibility, triangulation error and lost-marker RMSE on the scales of :data:`PLAN_SCALES`
    (dense markers grey; mirrored twins drawn as squares; the worst markers of each panel named)."""
    plt = _pyplot()
    dense = _front(np.array(list(neutral.values())), frame)
    rows = plan["markers"]
    xy = _front(np.array([layout_positions[m["label"]] for m in rows]), frame)
    mirrored = np.array([m["mirrored_from"] is not None for m in rows])
    fig, axes = plt.subplots(2, 2, figsize=(12, 12.6))
    for ax, (key, (title, cmap, floor)) in zip(axes.ravel(), PLAN_SCALES.items()):
        values = np.array([m[key] for m in rows], dtype=np.float64)
        finite = values[np.isfinite(values)]
        worst_value = (finite.min() if key == "visibility_percent" else finite.max()) if finite.size else np.nan
        low, high = (50.0, 100.0) if floor is None else (0.0, _round_ceiling(worst_value, floor))
        ax.scatter(dense[:, 0], dense[:, 1], s=8, c="lightgrey")
        for shape, chosen in (("o", ~mirrored), ("s", mirrored)):
            if chosen.any():
                drawn = ax.scatter(xy[chosen, 0], xy[chosen, 1], c=np.nan_to_num(values[chosen], nan=high),
                                   cmap=cmap, vmin=low, vmax=high, s=120, marker=shape, edgecolors="k",
                                   linewidths=0.8, zorder=3)
        fig.colorbar(drawn, ax=ax, shrink=0.8, extend="min" if floor is None else "max")
        order = np.argsort(values if key == "visibility_percent" else -np.nan_to_num(values, nan=-np.inf),
                           kind="stable")
        middle = np.nanmedian(xy[:, 0]) if np.isfinite(xy[:, 0]).any() else 0.0
        for n, i in enumerate(order[:PLAN_NAMED]):  # name the worst markers of this panel, outwards
            if np.isfinite(values[i]) and np.isfinite(xy[i]).all():
                right = xy[i, 0] >= middle
                ax.annotate(_legend_text(rows[i]["label"], width=24), xy[i], xytext=(-8 if right else 8, 8 - 5 * (n % 2)),
                            textcoords="offset points", fontsize=7, zorder=4, ha="right" if right else "left",
                            annotation_clip=False,
                            bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
        intact = f" (intact {plan['intact_rmse_mm']:.3g})" if key == "lost_rmse_mm" else ""
        ax.set_title(f"{title}\nworst: {worst_value:.3g}{intact}" + ("" if floor is None else f"; scale 0-{high:g}"))
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
    from matplotlib.lines import Line2D

    shapes = [Line2D([], [], ls="", marker="o", ms=4, mfc="lightgrey", mec="none", label="dense marker"),
              Line2D([], [], ls="", marker="o", ms=10, mfc="white", mec="k", label="layout marker"),
              Line2D([], [], ls="", marker="s", ms=10, mfc="white", mec="k",
                     label="mirrored twin (placed like its source)")]
    fig.legend(handles=shapes, loc="lower center", ncol=3, frameon=False,
               title=f"named: the {PLAN_NAMED} worst markers of each panel (plan.json lists all)")
    worst = max(rows, key=lambda m: m["risk_mm"])
    fig.suptitle(f"{len(rows)} layout markers through the {plan['rig']['name']} rig "
                 f"({len(plan['rig']['cameras'])} cameras); highest risk {_legend_text(worst['label'])} "
                 f"(+{worst['risk_mm']:.3f} mm); intact face RMSE {plan['intact_rmse_mm']:.3f} mm")
    fig.tight_layout(rect=(0, 0.05, 1, 0.97), h_pad=3.0)
    return _save(fig, path)


def plan_table(plan: dict[str, Any], *, rows: int = 12) -> str:
    """The riskiest ``rows`` markers as a text table, and the layout's worst figures."""
    markers = sorted(plan["markers"], key=lambda m: (-m["risk_mm"], m["label"]))
    lines = [f"{'marker':<24}{'seen %':>8}{'tri. mm':>9}{'lost mm':>9}{'risk mm':>9}"]
    for m in markers[:rows]:
        lines.append(f"{m['label'][:23]:<24}{m['visibility_percent']:>8.1f}{m['triangulation_error_mm']:>9.3f}"
                     f"{m['lost_rmse_mm']:>9.3f}{m['risk_mm']:>9.4f}")
    seen = min(m["visibility_percent"] for m in markers)
    error = np.nanmax([m["triangulation_error_mm"] for m in markers])
    lines.append(f"{len(markers)} layout markers through {plan['rig']['name']}: least seen {seen:.1f} % of "
                 f"frames, largest triangulation error {error:.3f} mm; intact face RMSE "
                 f"{plan['intact_rmse_mm']:.3f} mm")
    return "\n".join(lines) + "\n"


def layout_neutral(layout: Layout) -> dict[str, np.ndarray]:
    """Layout marker label -> its neutral position (3,) mm, as the layout records it."""
    return {c.representative: np.asarray(c.position, dtype=np.float64) for c in layout.clusters}


__all__ = ["layout_neutral", "layout_plane", "layout_plan", "marker_risk", "plan_picture", "plan_table"]
