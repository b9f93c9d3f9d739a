"""What a camera rig makes of every marker: how often it is seen and how well it is triangulated.

The session's own motion is captured again through the rig with the synthetic capture of
:mod:`mocaptk.acquisition` (projection with back-facing and field-of-view occlusion, Gaussian
detection noise, robust triangulation; no random dropouts or ghosts, which hit every marker
alike). Per marker:

* **visibility** — the fraction of frames in which at least 2 cameras see it (what
  triangulation needs);
* **triangulation error** — RMS distance (mm) of the triangulated point from the true one over
  the frames where it is seen.

Surface normals come from a mesh through the neutral markers (:func:`surface_normals`), deformed
with them frame by frame, so any session works without a face model. A preset rig (``cara``,
``room``) is placed on the session's face (:func:`place_preset`); a rig file is taken as
calibrated in the session's coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from mocaptk.acquisition.cameras import FACE_CENTER_MM, RIG_PRESETS, CameraRig, load_rig
from mocaptk.errors import InputFileError, OptionError

from .neutral import max_displacement, neutral_pose
from .regions import face_frame
from .symmetry import SagittalPlane

#: Where the presets aim (``FACE_CENTER_MM``) relative to the centroid of a dense full-face marker
#: set on the ICT-FaceKit face of ``mocaptk synth`` (seed 7: (0, 11.2, 93.4) mm), face axes, mm.
PRESET_AIM_OFFSET_MM = (0.0, -11.2, -23.4)
#: A session whose estimated face axes are within this angle (degrees) of Y up / +Z forward is taken
#: to be in that frame already (the axes estimate tilts ≈ 6° with the forehead's slope).
ALIGNED_FRAME_DEG = 20.0
#: Detection noise of one marker (mm) the costs assume: ``mocaptk synth``'s default.
DEFAULT_NOISE_MM = 0.3
#: Prefix of the internal labels of mirrored session markers (never a real label: it has spaces).
MIRROR_PREFIX = "mirror of "
#: Frames of the session captured again (evenly subsampled): enough for stable per-marker figures.
COST_FRAMES = 600


@dataclass(frozen=True)
class CaptureCosts:
    """Per marker: visibility ``(N,)`` (fraction of frames seen by >= 2 cameras) and triangulation
    error ``(N,)`` mm (RMS over the frames it is seen in; NaN if never seen), for ``labels``."""

    labels: tuple[str, ...]
    visibility: np.ndarray
    triangulation_error_mm: np.ndarray
    rig: str
    cameras: tuple[str, ...]
    frames: int
    pixel_noise: float

    def select(self, labels: Sequence[str]) -> CaptureCosts:
        """The costs of ``labels`` only, in that order."""
        index = {label: i for i, label in enumerate(self.labels)}
        idx = np.array([index[label] for label in labels], dtype=np.intp)
        return CaptureCosts(tuple(labels), self.visibility[idx], self.triangulation_error_mm[idx],
                            self.rig, self.cameras, self.frames, self.pixel_noise)


def place_preset(rig: CameraRig, positions: np.ndarray) -> CameraRig:
    """A preset rig (built around ``FACE_CENTER_MM`` in the face model's frame) moved onto the face
    of ``positions`` (F, N, 3) mm: aimed at :data:`PRESET_AIM_OFFSET_MM` from the neutral centroid
    along the face's axes (:func:`~mocaptk.clustering.regions.face_frame`), or along X, Y, Z when
    those are within :data:`ALIGNED_FRAME_DEG` of the face's lateral, up and forward axes."""
    neutral = neutral_pose(positions)
    frame = face_frame(neutral, max_displacement(positions, neutral))
    angle = np.degrees(np.arccos(np.clip((np.trace(frame) - 1.0) / 2.0, -1.0, 1.0)))
    axes = np.eye(3) if angle <= ALIGNED_FRAME_DEG else frame.T  # columns: face axes in session coordinates
    aim = neutral.mean(axis=0) + axes @ np.asarray(PRESET_AIM_OFFSET_MM)
    return rig.moved(axes, aim - axes @ np.asarray(FACE_CENTER_MM))


def resolve_rig(spec: str, positions: np.ndarray) -> CameraRig:
    """``cara`` / ``room`` (placed on the face of ``positions``, see :func:`place_preset`) or a rig
    file (:func:`read_rig_file`)."""
    if spec in RIG_PRESETS:
        return place_preset(RIG_PRESETS[spec](), positions)
    return read_rig_file(spec)


def read_rig_file(spec: str) -> CameraRig:
    """The rig in file ``spec`` (mocaptk JSON or Qualisys ``.qca.txt``, calibrated in the session's
    coordinates); OptionError / InputFileError when it is no preset name, no file or no rig."""
    path = Path(spec)
    if not path.is_file():
        raise OptionError(f"--rig must be {', '.join(RIG_PRESETS)} or a rig file, got {spec!r} "
                          "(no such file)")
    rig = load_rig(path)
    if len(rig) < 2:
        raise InputFileError(path, f"a rig needs at least 2 cameras to triangulate, it has {len(rig)}")
    return rig


def surface_normals(positions: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Outward unit normals ``(F, N, 3)`` of the marker surface (a mesh through ``neutral`` (N, 3)
    mm, deformed with ``positions`` (F, N, 3) mm, no NaN): area-weighted per frame; a marker the
    mesh leaves out (its rim peeled) takes the normal of the nearest marker in the mesh."""
    from mocaptk.surface_mesh import marker_surface_mesh

    try:
        faces = marker_surface_mesh(neutral)[1]
    except ValueError as exc:
        raise OptionError(f"cannot build a surface through the markers: {exc}") from None
    n_points = neutral.shape[0]
    corners = np.asarray(faces, dtype=np.intp)
    owner = corners.T.ravel()  # vertex of each (corner, triangle) entry
    gather = sp.csr_matrix((np.ones(owner.size), (owner, np.tile(np.arange(len(corners)), 3))),
                           shape=(n_points, len(corners)))
    tri = positions[:, corners]  # (F, T, 3, 3)
    tri_normals = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])  # 2 x area
    summed = (gather @ tri_normals.transpose(1, 0, 2).reshape(len(corners), -1))
    summed = summed.reshape(n_points, positions.shape[0], 3).transpose(1, 0, 2)
    in_mesh = np.zeros(n_points, dtype=bool)
    in_mesh[owner] = True
    if not in_mesh.all():
        inside = np.flatnonzero(in_mesh)
        near = inside[np.argmin(np.linalg.norm(neutral[:, None] - neutral[inside][None], axis=2), axis=1)]
        summed = summed[:, near]
    length = np.linalg.norm(summed, axis=2, keepdims=True)
    return summed / np.maximum(length, 1e-300)


def capture_costs(rig: CameraRig, positions: np.ndarray, *, labels: Sequence[str],
                  noise_mm: float = DEFAULT_NOISE_MM, frames: int = COST_FRAMES, seed: int = 0) -> CaptureCosts:
    """Visibility and triangulation error of every marker of ``positions`` (F, N, 3) mm (gaps NaN)
    captured through ``rig`` with ``noise_mm`` of detection noise (in px as ``mocaptk synth``)."""
    from mocaptk.acquisition.projection import project_markers
    from mocaptk.acquisition.synth_session import MAX_VIEW_NORMAL_DEG, detection_noise_px
    from mocaptk.acquisition.triangulate import triangulate

    if not noise_mm >= 0:
        raise OptionError(f"--noise must be >= 0 mm, got {noise_mm}")
    positions = np.asarray(positions, dtype=np.float64)
    neutral = neutral_pose(positions)
    if not np.isfinite(neutral).all():
        raise OptionError("a marker is never seen in the session: no position to capture")
    step = -(-positions.shape[0] // frames)
    points = positions[::step]
    points = np.where(np.isfinite(points), points, neutral[None])  # a gap: the marker is still there
    normals = surface_normals(points, neutral)
    pixel_noise = detection_noise_px(rig, points, noise_mm)
    observations = project_markers(rig, points, normals=normals, pixel_noise=pixel_noise,
                                   min_view_cos=np.cos(np.deg2rad(MAX_VIEW_NORMAL_DEG)),
                                   rng=np.random.default_rng([seed, 6]))
    seen = np.isfinite(observations[..., 0]).sum(axis=0) >= 2  # (F, N)
    traj = triangulate(rig, observations, labels=list(labels))
    squared = np.sum((traj.positions - points) ** 2, axis=2)
    solved = np.isfinite(squared)
    with np.errstate(invalid="ignore", divide="ignore"):
        error = np.sqrt(np.where(solved, squared, 0.0).sum(axis=0) / solved.sum(axis=0))
    return CaptureCosts(tuple(labels), seen.mean(axis=0), np.where(solved.any(axis=0), error, np.nan),
                        rig.name, tuple(rig.names), int(points.shape[0]), pixel_noise)



def captured_cloud(positions: np.ndarray, labels: Sequence[str], plane: SagittalPlane | None = None,
                   ) -> tuple[np.ndarray, list[str]]:
    """The markers a rig films: the session's ``(F, N, 3)`` mm and, for a half face (``plane``: its
    sagittal plane), the mirror image of every off-midline marker (labels ``"mirror of <label>"``)."""
    labels = list(labels)
    if plane is None:
        return positions, labels
    neutral = neutral_pose(positions)
    off_midline = np.flatnonzero(np.linalg.norm(plane.mirror(neutral) - neutral, axis=1) > 1.0)
    return (np.concatenate([positions, plane.mirror(positions[:, off_midline])], axis=1),
            labels + [MIRROR_PREFIX + labels[i] for i in off_midline])


def session_costs(positions: np.ndarray, labels: Sequence[str], rig_spec: str, *,
                  plane: SagittalPlane | None = None, noise_mm: float = DEFAULT_NOISE_MM) -> CaptureCosts:
    """The costs of every marker of a session (``positions`` (F, N, 3) mm) and, for a half face, of
    its mirror images (:func:`captured_cloud`), through the rig ``rig_spec`` (:func:`resolve_rig`)."""
    cloud, cloud_labels = captured_cloud(positions, labels, plane)
    return capture_costs(resolve_rig(rig_spec, cloud), cloud, labels=cloud_labels, noise_mm=noise_mm)
