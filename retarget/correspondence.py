"""Where each of the actor's markers sits on the character: a triangle and barycentrics.

1. **Similarity**: the character's neutral is brought onto the actor's dense neutral markers by
   ICP with scale (:func:`mocaptk.retarget.align.align_mesh_to_markers`, as ``rig --mesh``).
2. **Non-rigid**: a smooth displacement field (thin-plate spline with smoothing, over the
   markers' closest points) bends the placed character onto the markers; the markers are
   projected again on the bent surface, :data:`NONRIGID_ROUNDS` times. The projection then
   follows the actor's own proportions (a lip corner lands on the character's lip corner even
   when the mouths differ in width), not just the nearest point of a rigidly placed face.
3. Each marker keeps its triangle and barycentrics; the same point on the unbent character is
   its surface point there, and the character's shapes are read at it.

A character the markers do not cover is refused: the fit residual must be below
:data:`MAX_FIT_SPACINGS` marker spacings (RMS), and the markers must reach
:data:`MIN_MOTION_COVERAGE` of the character's moving surface (a body mesh, or a face whose
shapes move far from every marker, fails).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mocaptk.errors import MocaptkError, OptionError

from .align import SurfaceProximity, align_mesh_to_markers
from .character import Character

__all__ = ["Correspondence", "barycentric_of", "correspond"]

#: Rounds of non-rigid bending and re-projection.
NONRIGID_ROUNDS = 3
#: Thin-plate-spline smoothing of the bending field (mm², per marker).
NONRIGID_SMOOTHING = 10.0
#: Largest fit residual (RMS, in marker spacings) of the similarity fit.
MAX_FIT_SPACINGS = 0.5
#: Fraction of the character's moving vertices (area-blind) that must lie within
#: :data:`COVER_SPACINGS` marker spacings of a marker (half a face covers about half).
MIN_MOTION_COVERAGE = 0.25
COVER_SPACINGS = 2.0
#: A vertex "moves" when some shape moves it by this fraction of the largest shape motion.
MOVING_FRACTION = 0.1


@dataclass(frozen=True, eq=False)
class Correspondence:
    """``triangles`` (M,) and ``barycentric`` (M, 3) of each actor marker on the character
    (unseen markers: triangle -1); ``scale``, ``rotation`` (3, 3): the character → actor
    similarity (mm per character mm); ``fit_rms_mm`` the similarity fit residual; ``bent_rms_mm``
    after bending; ``coverage`` fraction of the moving surface near a marker."""

    triangles: np.ndarray
    barycentric: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    fit_rms_mm: float
    bent_rms_mm: float
    coverage: float

    def points(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The markers' surface points (M, 3) on a mesh with the character's topology (NaN unseen)."""
        out = np.full((len(self.triangles), 3), np.nan)
        ok = self.triangles >= 0
        out[ok] = np.einsum("mk,mkc->mc", self.barycentric[ok], vertices[faces[self.triangles[ok]]])
        return out

    def shape_basis(self, character: Character) -> np.ndarray:
        """The character's shapes at the markers, in the actor's frame and units: (S, M, 3) mm
        (0 at unseen markers)."""
        ok = self.triangles >= 0
        corners = character.faces[self.triangles[ok]]  # (m, 3)
        deltas = np.einsum("mk,smkc->smc", self.barycentric[ok],
                           character.deltas[:, corners].astype(np.float64))
        out = np.zeros((len(character.names), len(self.triangles), 3))
        out[:, ok] = self.scale * deltas @ self.rotation.T
        return out


def correspond(character: Character, neutral: np.ndarray) -> Correspondence:
    """Correspondence of the actor's neutral markers ``neutral`` (M, 3) mm (NaN unseen) on
    ``character``. Raises :class:`OptionError` when the markers do not cover its face."""
    seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
    if seen.size < 4:
        raise OptionError("the actor's neutral has fewer than 4 markers")
    points = neutral[seen]
    spacing = float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))
    try:
        fit = align_mesh_to_markers(character.vertices, character.faces, points)
    except MocaptkError as exc:
        raise OptionError(f"the character's face cannot be fitted to the markers ({exc})") from None
    if not fit.rms_mm <= MAX_FIT_SPACINGS * spacing:
        raise OptionError(f"the markers do not fit the character's face (residual RMS "
                          f"{fit.rms_mm:.1f} mm, over {MAX_FIT_SPACINGS} x the {spacing:.1f} mm "
                          "marker spacing): is it a face?")
    placed = fit.transform.apply(character.vertices)
    triangle, bary, rms = _bend(placed, character.faces, points)
    coverage = _motion_coverage(character, placed, points, spacing)
    if coverage < MIN_MOTION_COVERAGE:
        raise OptionError(f"the markers cover {100 * coverage:.0f} % of the character's moving "
                          f"face (need {100 * MIN_MOTION_COVERAGE:.0f} %): not this actor's face region")
    triangles = np.full(len(neutral), -1, dtype=np.int64)
    barycentric = np.zeros((len(neutral), 3))
    triangles[seen], barycentric[seen] = triangle, bary
    return Correspondence(triangles, barycentric, fit.transform.scale, fit.transform.rotation,
                          fit.transform.translation, fit.rms_mm, rms, coverage)


def _bend(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, float]:
    """Bend the placed mesh onto ``points``; their triangles, barycentrics and the RMS residual."""
    from scipy.interpolate import RBFInterpolator

    bent = vertices
    for _ in range(NONRIGID_ROUNDS):
        closest, _, _ = SurfaceProximity(bent, faces).query(points)
        field = RBFInterpolator(closest, points - closest, kernel="thin_plate_spline",
                                smoothing=NONRIGID_SMOOTHING, degree=1)
        bent = bent + field(bent)
    closest, dist, triangle = SurfaceProximity(bent, faces).query(points)
    corners = bent[faces[triangle]]
    return triangle, barycentric_of(closest, corners), float(np.sqrt(np.mean(dist ** 2)))


def barycentric_of(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of ``points`` (N, 3) in triangles ``corners`` (N, 3, 3)."""
    import igl

    bary = np.asarray(igl.barycentric_coordinates(
        np.ascontiguousarray(points), *(np.ascontiguousarray(corners[:, k]) for k in range(3))))
    return np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(axis=1, keepdims=True)


def _motion_coverage(character: Character, placed: np.ndarray, points: np.ndarray,
                     spacing: float) -> float:
    """Fraction of the character's moving vertices within COVER_SPACINGS spacings of a marker."""
    motion = np.linalg.norm(character.deltas, axis=2).max(axis=0)  # (V,)
    if not motion.max() > 0:
        return 0.0
    moving = placed[motion >= MOVING_FRACTION * motion.max()]
    near = cKDTree(points).query(moving, distance_upper_bound=COVER_SPACINGS * spacing)[0]
    return float(np.isfinite(near).mean())
