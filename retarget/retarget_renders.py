"""Pictures of a retarget (offscreen pyvista): the actor beside the character at telling frames,
and the actor's markers on the character's face.

- ``retarget_frames.png``: top row the actor (the solved dense markers' surface, layout markers
  as dots), bottom row the character at the same frames: rest (the frame with the smallest total
  weight), the widest jaw opening, the strongest smile and the strongest blink.
- ``correspondence.png``: the character's neutral, front and profile, with every dense marker's
  surface point (layout markers larger).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path

from .character import Character

__all__ = ["pick_frames", "render_correspondence", "render_frames"]

SKIN = (0.85, 0.70, 0.62)
ACTOR = (0.70, 0.78, 0.88)


def pick_frames(names: tuple[str, ...], weights: np.ndarray) -> dict[str, int]:
    """``{"rest", "widest jaw", "strongest smile", "blink"}`` → frame, from the shape ``names``
    (S,) and ``weights`` (F, S): a shape counts when its name (lower case, letters only)
    contains ``jawopen``, ``smile`` or ``blink`` (ARKit's and most rigs' names); a moment the rig
    has no shape for shows the rest frame."""
    keys = [re.sub(r"[^a-z]", "", name.lower()) for name in names]
    rest = int(np.argmin(weights.sum(axis=1)))
    picks = {"rest": rest}
    for title, word in (("widest jaw", "jawopen"), ("strongest smile", "smile"), ("blink", "blink")):
        cols = [i for i, key in enumerate(keys) if word in key]
        score = weights[:, cols].sum(axis=1) if cols else np.zeros(len(weights))
        picks[title] = int(np.argmax(score)) if score.max() > 0 else rest
    return picks


def render_frames(path: str | os.PathLike[str], *, actor_faces: np.ndarray, actor: np.ndarray,
                  layout: np.ndarray, character: Character, weights: np.ndarray,
                  titles: list[str], size: tuple[int, int] = (1600, 900)) -> Path:
    """Actor (``actor`` (K, M, 3) mm dense frames on ``actor_faces``, ``layout`` (K, L, 3) mm)
    above the character driven by ``weights`` (K, S), one column per title."""
    plotter = _plotter((2, len(titles)), size)
    for k, title in enumerate(titles):
        plotter.subplot(0, k)
        seen = np.isfinite(actor[k]).all(axis=1)
        faces = actor_faces[seen[actor_faces].all(axis=1)]
        plotter.add_mesh(_polydata(np.nan_to_num(actor[k]), faces), color=ACTOR, smooth_shading=True)
        dots = layout[k][np.isfinite(layout[k]).all(axis=1)]
        if len(dots):
            plotter.add_points(dots, color=(0.8, 0.1, 0.1), point_size=7, render_points_as_spheres=True)
        plotter.add_text(f"actor: {title}", font_size=9, color="black")
        _front(plotter, np.nan_to_num(actor[k][seen]))
        plotter.subplot(1, k)
        moved = character.deform(weights[k])
        plotter.add_mesh(_polydata(moved, character.faces), color=SKIN, smooth_shading=True)
        plotter.add_text(f"character: {title}", font_size=9, color="black")
        _front(plotter, moved)
    return _save(plotter, path)


def render_correspondence(path: str | os.PathLike[str], *, character: Character, points: np.ndarray,
                          layout: np.ndarray, size: tuple[int, int] = (1200, 700)) -> Path:
    """The character's neutral, front and profile, with the markers' surface points ``points``
    (M, 3) (character frame, NaN unseen) and the layout's ``layout`` (L, 3)."""
    plotter = _plotter((1, 2), size)
    for k, view in enumerate(("front", "profile")):
        plotter.subplot(0, k)
        plotter.add_mesh(_polydata(character.vertices, character.faces), color=SKIN, smooth_shading=True)
        ok = points[np.isfinite(points).all(axis=1)]
        direction = np.array([0.0, 0.0, 1.0]) if view == "front" else np.array([1.0, 0.0, 0.0])
        lift = direction * 0.5  # just off the skin so the dots are not buried in it
        plotter.add_points(ok + lift, color=(0.15, 0.35, 0.85), point_size=6, render_points_as_spheres=True)
        plotter.add_points(layout + lift, color=(0.85, 0.1, 0.1), point_size=11, render_points_as_spheres=True)
        plotter.add_text(f"markers on the character ({view}): blue dense, red layout", font_size=9,
                         color="black")
        _front(plotter, character.vertices, direction=direction)
    return _save(plotter, path)


def _plotter(shape: tuple[int, int], size: tuple[int, int]):
    import pyvista as pv
    from vtkmodules.vtkCommonCore import vtkLogger

    pv.OFF_SCREEN = True
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)  # headless X probe noise
    plotter = pv.Plotter(off_screen=True, shape=shape, window_size=list(size), border=False)
    plotter.set_background("white")
    return plotter


def _polydata(vertices: np.ndarray, faces: np.ndarray):
    import pyvista as pv

    return pv.PolyData(np.asarray(vertices, float), np.column_stack([np.full(len(faces), 3), faces]).ravel())


def _front(plotter, points: np.ndarray, *, direction: np.ndarray | None = None) -> None:
    """Parallel camera looking along -``direction`` (default +Z: the face) framing ``points``."""
    direction = np.array([0.0, 0.0, 1.0]) if direction is None else direction
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    plotter.enable_parallel_projection()
    plotter.camera.focal_point = centre
    plotter.camera.position = centre + direction * 1000.0
    plotter.camera.up = (0.0, 1.0, 0.0)
    plotter.camera.parallel_scale = 0.6 * float(np.ptp(points[:, 1])) + 5.0
    plotter.reset_camera_clipping_range()


def _save(plotter, path: str | os.PathLike[str]) -> Path:
    from PIL import Image

    image = plotter.screenshot(return_img=True)
    plotter.close()
    with atomic_path(path, force=True) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return Path(path)
