"""Pictures of a clustering: per-region correlation heatmaps, the layout, the regions (matplotlib, Agg)."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path

from .layout import Layout
from .regions import region_colour


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams["svg.hashsalt"] = "mocaptk"
    return plt


def _save(fig, path: str | os.PathLike[str]) -> Path:
    plt = _pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, metadata={"Software": None})
    plt.close(fig)
    return Path(path)


#: Heatmaps of larger regions are drawn as block means on a grid of at most this many cells a
#: side (a 10,000-marker region: 512 x 512, not a 10,000 x 10,000 image of 3 GB RGBA).
HEATMAP_MAX_CELLS = 512


def correlation_heatmap(labels: Sequence[str], matrix: np.ndarray, clusters: np.ndarray, *, title: str,
                        path: str | os.PathLike[str], representatives: Sequence[str] = ()) -> Path:
    """Heatmap of one region's consolidated correlation (−3..3), markers ordered by cluster
    (``clusters`` (N,) ints: one box each; block means for more than :data:`HEATMAP_MAX_CELLS`
    markers; axes in marker positions); ``representatives`` are labelled in bold."""
    plt = _pyplot()
    order = np.argsort(clusters, kind="stable")
    n = len(labels)
    size = min(4 + 0.18 * n, 16)
    fig, ax = plt.subplots(figsize=(size + 1.5, size))
    image = ax.imshow(_ordered_cells(matrix, order, HEATMAP_MAX_CELLS), cmap="RdBu_r", vmin=-3,
                      vmax=3, interpolation="nearest", extent=(-0.5, n - 0.5, n - 0.5, -0.5))
    if n <= 60:
        ax.set_xticks(range(n), [labels[i] for i in order], rotation=90, fontsize=6)
        ax.set_yticks(range(n), [labels[i] for i in order], fontsize=6)
        for tick in [*ax.get_xticklabels(), *ax.get_yticklabels()]:
            if tick.get_text() in representatives:
                tick.set_fontweight("bold")
    bounds = np.flatnonzero(np.diff(clusters[order])) + 0.5
    if 0 < len(bounds) <= HEATMAP_MAX_CELLS:  # more cluster lines than cells would be a black square
        ax.hlines(bounds, -0.5, n - 0.5, color="k", lw=0.6)  # one artist for all lines: cheap to draw
        ax.vlines(bounds, -0.5, n - 0.5, color="k", lw=0.6)
    fig.colorbar(image, ax=ax, label="consolidated correlation Cx+Cy+Cz")
    if n > HEATMAP_MAX_CELLS:  # say that a cell is not one marker pair
        title += (f"\n{n} markers drawn as block means on a {HEATMAP_MAX_CELLS} x "
                  f"{HEATMAP_MAX_CELLS} grid (~{n / HEATMAP_MAX_CELLS:.1f} markers a cell side)")
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)


def _ordered_cells(matrix: np.ndarray, order: np.ndarray, cells: int) -> np.ndarray:
    """``matrix[order][:, order]``, or for more than ``cells`` rows its means over a
    ``cells`` x ``cells`` grid of consecutive blocks (rows read in chunks: no n x n copy)."""
    n = len(order)
    if n <= cells:
        return matrix[np.ix_(order, order)]
    starts = (np.arange(cells) * n) // cells  # first ordered position of each cell
    cell_of = np.searchsorted(starts, np.arange(n), side="right") - 1
    sums = np.zeros((cells, cells))
    for lo in range(0, n, 1024):
        rows = np.take(matrix[order[lo:lo + 1024]], order, axis=1)  # np.take: 2x a fancy index
        # row by row into its cell, as np.add.at adds them (same order), ~20x faster
        for cell, row in zip(cell_of[lo:lo + 1024], np.add.reduceat(rows, starts, axis=1)):
            sums[cell] += row
    sizes = np.diff(np.append(starts, n)).astype(float)
    return sums / sizes[:, None] / sizes[None, :]


#: Front-view coordinates beyond this (mm) are not drawn: matplotlib's transforms overflow or turn
#: singular on them (10 km is no face; such a session got its warning before).
PLOT_LIMIT_MM = 1e7


def _front(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(lateral, up) coordinates ``(N, 2)``: a front view of the face; NaN (not drawn) for points
    that are not finite or lie beyond :data:`PLOT_LIMIT_MM`."""
    with np.errstate(over="ignore", invalid="ignore"):
        xy = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ np.asarray(frame)[:2].T
        xy[~(np.abs(xy) < PLOT_LIMIT_MM).all(axis=1)] = np.nan
    return xy


def _legend_text(name: str, *, width: int = 40) -> str:
    """A name matplotlib draws without warnings: control characters, undecodable bytes (surrogates)
    and scripts beyond its DejaVu font escaped, not starting with ``_`` (hidden from legends), at
    most ``width`` characters."""
    text = "".join(c if c.isprintable() and ord(c) < 0x2000 else f"\\u{ord(c):04x}" for c in name)
    text = text if len(text) <= width else text[:width - 1] + "..."
    return f" {text}" if text.startswith("_") or not text else text


def layout_picture(layout: Layout, neutral: Mapping[str, np.ndarray], *, frame: np.ndarray,
                   path: str | os.PathLike[str]) -> Path:
    """Front view: every neutral marker coloured by its cluster; representatives large, mirrored hollow."""
    plt = _pyplot()
    cmap = plt.get_cmap("tab20")
    fig, ax = plt.subplots(figsize=(8, 9))
    clustered = {m for c in layout.clusters for m in c.members if c.mirrored_from is None}
    others = np.array([p for label, p in neutral.items() if label not in clustered])
    if others.size:
        xy = _front(others, frame)
        ax.scatter(xy[:, 0], xy[:, 1], s=10, c="lightgrey", label="not clustered")
    colours = [cmap(k % 20) for k in range(len(layout.clusters))]
    measured = [k for k, c in enumerate(layout.clusters) if c.mirrored_from is None]
    if measured:  # one scatter for all members, one for all representatives: few artists to draw
        members = np.array([neutral[m] for k in measured for m in layout.clusters[k].members])
        xy = _front(members, frame)
        ax.scatter(xy[:, 0], xy[:, 1], s=14, color=[colours[k] for k in measured
                                                    for _ in layout.clusters[k].members])
    if layout.clusters:
        reps = _front(np.array([c.position for c in layout.clusters]), frame)
        faces = ["none" if c.mirrored_from else colour for c, colour in zip(layout.clusters, colours)]
        ax.scatter(reps[:, 0], reps[:, 1], s=150, facecolors=faces, edgecolors="k", linewidths=1.2, zorder=3)
    ax.set_aspect("equal")
    ax.set_xlabel("lateral (mm, + = subject's left)")
    ax.set_ylabel("up (mm)")
    n_mirrored = sum(c.mirrored_from is not None for c in layout.clusters)
    ax.set_title(f"{len(layout.clusters)} layout markers (large; {n_mirrored} mirrored, hollow), "
                 f"factor {layout.parameters.get('factor')}")
    fig.tight_layout()
    return _save(fig, path)


def regions_picture(regions: Mapping[str, Sequence[str]], neutral: Mapping[str, np.ndarray], *,
                    frame: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Front view of the markers coloured by region."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 9), layout="constrained")  # room for the legend and both labels
    for name, members in regions.items():
        pts = np.array([neutral[m] for m in members if m in neutral])
        if pts.size:  # the region's colour in the guide and the report
            xy = _front(pts, frame)
            ax.scatter(xy[:, 0], xy[:, 1], s=30, color=region_colour(name),
                       label=f"{_legend_text(name)} ({len(pts)})")
    ax.set_aspect("equal")
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False)  # off the markers
    ax.set_xlabel("lateral (mm, + = subject's left)")
    ax.set_ylabel("up (mm)")
    ax.set_title("regions (front view)")
    return _save(fig, path)


def sweep_plot(factors: Sequence[float], counts: Sequence[int], errors: Sequence[float], *,
               path: str | os.PathLike[str]) -> Path:
    """Marker count and held-out RMSE against the refinement factor."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(factors, counts, "o-", color="tab:blue")
    ax.set_xlabel("refinement factor")
    ax.set_ylabel("layout markers", color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(factors, errors, "s--", color="tab:red")
    ax2.set_ylabel("held-out RMSE (mm)", color="tab:red")
    ax.set_title("factor sweep")
    fig.tight_layout()
    return _save(fig, path)

