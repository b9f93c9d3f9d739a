"""Offscreen pyvista pictures of a rig: influence regions shaded, layout markers numbered.

Colours: each facial region has a hue (:data:`REGION_COLOURS`); the influence regions of its
markers alternate between lighter and darker tints of it, so cluster borders show. Markers are
drawn over the render (matplotlib) as dots in the region's strong colour with their guide number,
every label shown (VTK's own label placer hides overlapping ones), none overlapping another; past
:data:`MAX_NUMBERED` markers in a view, dots only and a line saying where the numbers are.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path
from mocaptk.clustering.regions import REGION_COLOURS, region_colour

__all__ = ["REGION_COLOURS", "VIEWS", "region_colour", "render_view"]

#: Pixels per label-placement unit: the guide's placer works in page mm (dot radius 1.5).
LABEL_UNIT_PX = 3.0

#: Camera direction (from the face towards the camera) and up vector per view, rig frame.
VIEWS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "front": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "profile": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
}


#: A view with more layout markers than this shows them as dots without numbers: on a
#: 1050 x 1200 px view their labels overlap into a blot (and cost ~50 ms of matplotlib each).
MAX_NUMBERED = 200


def cluster_shades(regions: list[str]) -> np.ndarray:
    """RGB (C, 3) per cluster: its region's hue, alternating tints within the region."""
    count: dict[str, int] = {}
    out = []
    for region in regions:
        k = count.get(region, 0)
        count[region] = k + 1
        out.append(region_colour(region, tint=(0.55, 0.30, 0.70, 0.42)[k % 4]))
    return np.array(out)


def render_view(vertices: np.ndarray, faces: np.ndarray, vertex_cluster: np.ndarray,
                cluster_regions: list[str], marker_positions: np.ndarray, numbers: Sequence[int | str],
                path: str | os.PathLike[str], *, view: str = "front",
                size: tuple[int, int] = (1050, 1200), force: bool = True) -> Path:
    """Render one view to a PNG and return its path.

    Parameters
    ----------
    vertices, faces : (V, 3) mm rig frame, (T, 3)
    vertex_cluster : (V,) int
        Main influence region (cluster index) of each vertex, -1 for none (drawn grey).
    cluster_regions : list of str, length C
        Facial region of each cluster.
    marker_positions : (C, 3) mm
        Layout markers, same order as the clusters; ``numbers`` their guide names. The view is
        framed on the markers (the face), not the whole mesh (a production head has a neck,
        ears, the back of the head).
    """
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    pv.OFF_SCREEN = True
    # VTK logs its X-display probe on headless machines; it then renders offscreen anyway
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    direction, up = VIEWS[view]
    shades = cluster_shades(cluster_regions)
    colours = np.full((len(vertices), 3), 0.8)
    known = vertex_cluster >= 0
    colours[known] = shades[vertex_cluster[known]]
    mesh = pv.PolyData(np.asarray(vertices, float),
                       np.column_stack([np.full(len(faces), 3), faces]).ravel())
    mesh.point_data["rgb"] = (colours * 255).astype(np.uint8)
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    plotter.set_background("white")
    plotter.add_mesh(mesh, scalars="rgb", rgb=True, smooth_shading=True, ambient=0.35,
                     diffuse=0.7, specular=0.0)
    markers = np.asarray(marker_positions, float)
    centre = (markers.min(axis=0) + markers.max(axis=0)) / 2
    extent = float(np.ptp(vertices, axis=0).max())
    right = np.cross(np.asarray(up, float), np.asarray(direction, float))
    half_h = np.ptp(markers @ np.asarray(up, float)) / 2
    half_w = np.ptp(markers @ right) / 2
    plotter.enable_parallel_projection()
    plotter.camera.focal_point = centre
    plotter.camera.position = centre + np.asarray(direction) * extent * 4.0
    plotter.camera.up = up
    plotter.camera.parallel_scale = 1.2 * max(half_h, half_w * size[1] / size[0]) + 8.0  # mm margin
    plotter.reset_camera_clipping_range()
    image = plotter.screenshot(return_img=True)
    pixels = _display_points(plotter, marker_positions, image.shape[0])
    plotter.close()
    visible = np.ones(len(marker_positions), bool)
    if view == "profile":  # only the side facing the camera; the far side would show through
        visible = marker_positions[:, 0] >= np.median(vertices[:, 0]) - 1.0
    _draw_markers(image, pixels, visible, cluster_regions, numbers, path, force=force)
    return Path(path)


def _display_points(plotter, points: np.ndarray, height: int) -> np.ndarray:
    """Pixel coordinates (N, 2) (x right, y down) of world points in the rendered image."""
    renderer = plotter.renderer
    out = np.empty((len(points), 2))
    for i, p in enumerate(np.asarray(points, float)):
        renderer.SetWorldPoint(*p, 1.0)
        renderer.WorldToDisplay()
        x, y, _ = renderer.GetDisplayPoint()
        out[i] = (x, height - y)
    return out


def _draw_markers(image: np.ndarray, pixels: np.ndarray, visible: np.ndarray,
                  cluster_regions: list[str], numbers: list[int],
                  path: str | os.PathLike[str], *, force: bool) -> np.ndarray:
    """Markers (region colour) and their numbers over the render, every label drawn where it
    overlaps no other label or dot (:func:`~mocaptk.retarget.guide.place_labels`; a leader line
    joins a label moved away from a crowded marker). Returns the label boxes (N, 4) pixels
    ``x0, y0, x1, y1`` (y down; NaN for hidden markers)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .guide import place_labels

    height, width = image.shape[:2]
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(image)
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    ax.axis("off")
    if visible.sum() > MAX_NUMBERED:  # one artist for all dots; numbers only on the guide's pages
        shown = np.flatnonzero(visible)
        ax.scatter(pixels[shown, 0], pixels[shown, 1], s=49,
                   c=[region_colour(cluster_regions[i], tint=-0.35) for i in shown],
                   edgecolors="white", linewidths=1.2)
        ax.text(12, 24, f"{len(shown)} markers, too many to number legibly here: guide.pdf names "
                "them (1:1 page, marker table)", fontsize=10, color="black",
                bbox={"boxstyle": "round,pad=0.3", "fc": "white", "ec": "none", "alpha": 0.8})
        visible = np.zeros_like(visible)
    shown = np.flatnonzero(visible)
    texts = [ax.text(0, 0, str(numbers[k]), fontsize=9, fontweight="bold", color="black",
                     ha="left", va="bottom", bbox={"boxstyle": "square,pad=0.12", "fc": "white",
                                                   "ec": "none", "alpha": 0.7})
             for k in shown]
    renderer = fig.canvas.get_renderer()
    pad = 0.12 * 9 * 100 / 72  # the bbox pad, pixels
    sizes = np.array([[t.get_window_extent(renderer).width + 2 * pad,
                       t.get_window_extent(renderer).height + 2 * pad] for t in texts]).reshape(-1, 2)
    # place_labels works in page millimetres: one unit = LABEL_UNIT_PX pixels here
    boxes, leader = place_labels(pixels[shown] / LABEL_UNIT_PX, sizes / LABEL_UNIT_PX,
                                 bounds=(0.0, 0.0, width / LABEL_UNIT_PX, height / LABEL_UNIT_PX))
    boxes *= LABEL_UNIT_PX
    for k, text, box, long in zip(shown, texts, boxes, leader):
        x, y = pixels[k]
        if long:  # from the dot to the nearest point of its label
            near = np.clip([x, y], box[:2], box[2:])
            ax.plot([x, near[0]], [y, near[1]], "-", color="black", lw=0.8, alpha=0.8)
        ax.plot(x, y, "o", ms=7, mfc=region_colour(cluster_regions[k], tint=-0.35), mec="white",
                mew=1.2)
        text.set_position((box[0] + pad, box[3] - pad))
    out = np.full((len(pixels), 4), np.nan)
    out[shown] = boxes
    with atomic_path(path, force=force) as tmp:
        fig.savefig(tmp, dpi=100, format="png", metadata={"Software": None})
    plt.close(fig)
    return out
