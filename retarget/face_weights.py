"""How the default face follows its drivers, one code for the rig and for ``solve``'s mesh.

The rig's weights (V, J) over its layout joints and ``solve``'s linear map (V, M) over the dense
markers are both rows of the same fitted face (:mod:`~mocaptk.retarget.default_face`), and both
get the same fixes (issue 30), so the two deform the face the same way:

- each marker sits on its own lip (:func:`face_anchors`: a marker that follows the jaw on the
  lower lip, one that does not on the upper; :func:`~mocaptk.retarget.default_face.lip_anchors`);
- rows the markers hardly reach (behind the ears: ratios of tiny numbers) are the harmonic
  interpolation of the others (:func:`~mocaptk.retarget.weights.fill_unsupported`);
- around the mouth's corners the rows blend towards the corner's own
  (:func:`~mocaptk.retarget.weights.blend_corners`): the mouth parts as a lens does, not as a
  crack whose tip folds; the drivers' own vertices take most of that blend too
  (:data:`CORNER_PIN_HOLD`).
"""

from __future__ import annotations

import numpy as np

from .default_face import CORNER_PIN_FADE_MM, MOUTH_CORNER_MM, DefaultFace, lip_anchors
from .influence import anchor_vertices
from .weights import blend_corners, fill_unsupported

__all__ = ["CORNER_PIN_HOLD", "MIN_SUPPORT", "face_anchors", "face_rows"]

#: Rows with less masked thin-shell weight than this are filled harmonically from the others
#: (:func:`~mocaptk.retarget.weights.fill_unsupported`; sample, behind the ears: 2.06x -> 1.99x
#: at the widest jaw, the same at 0.02 and 0.1; 905 of 9,409 vertices).
MIN_SUPPORT = 0.05
#: How much of its own row a driver's vertex (a lip marker's) keeps against the mouth corner's
#: blend (1: all, exact at its marker). Near a corner the sample's upper and lower lip markers
#: are 11 mm apart and move 16 mm apart at the widest jaw; held exactly, that motion was forced
#: into the skin between them where the seam is closed. Sample, rig (largest stretch within
#: 20 mm of a corner / held-out mouth RMSE): 1 2.077x / 0.255 mm, 0.9 2.063x / 0.255,
#: 0.8 2.049x / 0.257, 0.5 2.007x, 0.4 1.993x / 0.274, 0.3 1.978x / 0.281, 0 1.985x / 0.306.
CORNER_PIN_HOLD = 0.3


def face_anchors(face: DefaultFace, points: np.ndarray,
                 jaw_following: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's vertex (N,) on the fitted face (before its lips close: where the markers
    are) and its distance (N,) mm from the face, for the markers ``points`` (N, 3) mm (rig
    frame); with ``jaw_following`` (N,) bool each lip marker is moved onto its own lip."""
    vertex, dist = anchor_vertices(face.fitted, face.faces, points)
    if jaw_following is not None:
        vertex = lip_anchors(face, vertex, points, jaw_following)
    return vertex, dist


def face_rows(weights: np.ndarray, face: DefaultFace, *, pinned: np.ndarray,
              support: np.ndarray | None) -> np.ndarray:
    """``weights`` (V, K) of ``face``'s vertices (the rig's joints, solve's dense markers) with
    the rows whose ``support`` (V,) is below :data:`MIN_SUPPORT` filled harmonically (None: not
    filled; :func:`~mocaptk.retarget.weights.masked_support`) and the rows within
    :data:`MOUTH_CORNER_MM` of a mouth corner blended towards the corner's; the drivers'
    ``pinned`` vertices hold :data:`CORNER_PIN_HOLD` of their rows, faded over
    :data:`CORNER_PIN_FADE_MM`."""
    if support is not None:
        weights = fill_unsupported(weights, support, face.vertices, face.faces,
                                   min_support=MIN_SUPPORT)
    return blend_corners(weights, face.vertices, np.array([face.upper_lip[0], face.upper_lip[-1]]),
                         reach_mm=MOUTH_CORNER_MM, pinned=pinned, pin_fade_mm=CORNER_PIN_FADE_MM,
                         pin_hold=CORNER_PIN_HOLD)
