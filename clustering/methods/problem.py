"""The input every layout method takes: dense displacements from neutral, plus optional geometry."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocaptk.errors import OptionError
from mocaptk.trajectories import Trajectories

from ..neutral import max_displacement, neutral_pose
from ..regions import default_regions
from ..symmetry import FaceSides, face_sides


@dataclass(frozen=True, eq=False)
class LayoutProblem:
    """Choose ``count`` of ``N`` dense points (markers or mesh vertices) as the layout.

    Parameters
    ----------
    displacements : (frames, N, 3) float, mm
        Training displacements from ``neutral``; NaN gaps. For a blendshape model, one "frame"
        per blendshape (its delta).
    neutral : (N, 3) float, mm
    labels : tuple of str, length N (optional)
    faces : (T, 3) int, optional
        Surface mesh over the points (vertex i = point i); built on demand for dense markers.
    regions : {name: point indices}, optional
        Facial regions (the paper's per-region takes).
    segments : tuple of (start, end), optional
        Frame ranges of the takes (0-based, end exclusive): cross-validation folds, per-take shapes.
    mirror : (N,) int, optional
        Mirror partner of every point across the sagittal plane (itself on the midline).
    candidates : (K,) int, optional
        Points a layout may use (default: all), e.g. the face region of a head mesh.
    measured_error_mm : (N,) float, optional
        Expected error (mm, RMS) of each point when it is a layout marker captured by the rig
        (triangulation error, :mod:`mocaptk.clustering.camera_cost`); None: measured exactly.
    sides : tuple of str, length N (optional)
        Each point's side of the face, ``"L"``, ``"R"`` or ``"C"`` (``cluster``'s); default:
        :func:`problem_sides` finds them as ``cluster`` does.
    """

    displacements: np.ndarray
    neutral: np.ndarray
    labels: tuple[str, ...] = ()
    faces: np.ndarray | None = None
    regions: Mapping[str, np.ndarray] = field(default_factory=dict)
    segments: tuple[tuple[int, int], ...] = ()
    mirror: np.ndarray | None = None
    candidates: np.ndarray | None = None
    measured_error_mm: np.ndarray | None = None
    sides: tuple[str, ...] = ()
    #: derived arrays shared between methods (Gram matrices ...), filled on first use
    cache: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        disp = np.asarray(self.displacements, dtype=np.float64)
        neutral = np.asarray(self.neutral, dtype=np.float64)
        if disp.ndim != 3 or disp.shape[2] != 3:
            raise OptionError(f"displacements must be (frames, points, 3), got {disp.shape}")
        if neutral.shape != disp.shape[1:]:
            raise OptionError(f"neutral must be {disp.shape[1:]}, got {neutral.shape}")
        object.__setattr__(self, "displacements", disp)
        object.__setattr__(self, "neutral", neutral)
        object.__setattr__(self, "labels", tuple(self.labels))
        object.__setattr__(self, "sides", tuple(self.sides))
        if self.sides and (len(self.sides) != disp.shape[1] or not set(self.sides) <= {"L", "R", "C"}):
            raise OptionError(f"sides must be one of L, R, C per point ({disp.shape[1]})")
        object.__setattr__(self, "regions",
                           {k: np.asarray(v, dtype=np.intp) for k, v in self.regions.items()})
        object.__setattr__(self, "segments", tuple((int(a), int(b)) for a, b in self.segments))
        if self.faces is not None:
            object.__setattr__(self, "faces", np.asarray(self.faces, dtype=np.intp))
        if self.mirror is not None:
            mirror = np.asarray(self.mirror, dtype=np.intp)
            if mirror.shape != (self.n_points,) or not np.array_equal(mirror[mirror], np.arange(self.n_points)):
                raise OptionError("mirror must map every point to a partner whose partner is the point")
            object.__setattr__(self, "mirror", mirror)
        if self.candidates is not None:
            object.__setattr__(self, "candidates", np.unique(np.asarray(self.candidates, dtype=np.intp)))
        if self.measured_error_mm is not None:
            error = np.asarray(self.measured_error_mm, dtype=np.float64)
            if error.shape != (self.n_points,):
                raise OptionError(f"measured_error_mm must be ({self.n_points},), got {error.shape}")
            object.__setattr__(self, "measured_error_mm", error)

    @property
    def n_frames(self) -> int:
        return int(self.displacements.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.displacements.shape[1])

    @property
    def positions(self) -> np.ndarray:
        """(frames, N, 3) mm: neutral + displacements."""
        return self.neutral[None] + self.displacements

    def cached(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """``compute()`` once per problem and ``key``: what several methods compute alike (the
        hybrid's contenders are the k-means, QR, greedy and paper layouts of the same problem,
        which ``compare`` also runs on their own); treat the result as read-only."""
        if key not in self.cache:
            self.cache[key] = compute()
        return self.cache[key]

    def candidate_points(self) -> np.ndarray:
        """(K,) intp: the points a layout may use."""
        return np.arange(self.n_points) if self.candidates is None else self.candidates

    def complete_frames(self) -> np.ndarray:
        """(F', N, 3) the training frames where every point is present (for gap-free methods).

        Falls back to all frames with gaps set to 0 (at rest) when fewer than 2 frames are complete.
        """
        complete = np.isfinite(self.displacements).all(axis=(1, 2))
        if complete.sum() >= 2:
            return self.displacements[complete]
        return np.nan_to_num(self.displacements, nan=0.0)

    def has_surface(self) -> bool:
        """Whether :meth:`surface_faces` can give a mesh: faces given, or distinct neutral points
        (coincident markers, e.g. a duplicated label, have no marker surface)."""
        return self.faces is not None or len(np.unique(self.neutral, axis=0)) == len(self.neutral)

    def surface_faces(self) -> np.ndarray:
        """(T, 3) the surface mesh over the points (``faces``, else triangulated from ``neutral``)."""
        if self.faces is not None:
            return self.faces
        from mocaptk.surface_mesh import marker_surface_mesh
        return np.asarray(marker_surface_mesh(self.neutral)[1], dtype=np.intp)


def problem_regions(problem: LayoutProblem) -> dict[str, np.ndarray]:
    """{name: point indices}: the problem's regions, else ``cluster``'s default regions of its
    points (label prefixes, else the geometric segmentation in the face's own orientation)."""
    if problem.regions:
        return dict(problem.regions)

    def default() -> dict[str, np.ndarray]:
        labels = _point_labels(problem)
        named, _ = default_regions(labels, problem.neutral, max_displacement(problem.positions, problem.neutral),
                                   frame=_face(problem).orientation.frame)
        index = {label: i for i, label in enumerate(labels)}
        return {name: np.array([index[m] for m in members], dtype=np.intp) for name, members in named.items()}

    return problem.cached("default-regions", default)


def problem_sides(problem: LayoutProblem) -> tuple[str, ...]:
    """Each point's side (``"L"``, ``"R"``, ``"C"``): the problem's, else as ``cluster`` finds them
    (:func:`~mocaptk.clustering.symmetry.face_sides`)."""
    return problem.sides or _face(problem).sides


def _point_labels(problem: LayoutProblem) -> tuple[str, ...]:
    return problem.labels or tuple(f"P{i}" for i in range(problem.n_points))


def _face(problem: LayoutProblem) -> FaceSides:
    return problem.cached("face-sides", lambda: face_sides(_point_labels(problem), problem.positions, problem.neutral))


#: With capture costs, a point seen by >= 2 cameras in fewer than this fraction of the frames is
#: no candidate: it would be a gap in production too often.
MIN_VISIBILITY = 0.9


def camera_aware(problem: LayoutProblem, *, visibility: np.ndarray,
                 triangulation_error_mm: np.ndarray) -> LayoutProblem:
    """``problem`` for a rig: points seen in fewer than :data:`MIN_VISIBILITY` of the frames are
    left out of the candidates (unless that leaves fewer than a tenth of them), and every layout
    marker is charged its expected triangulation error (``(N,)`` each; NaN error: never seen)."""
    visibility = np.asarray(visibility, dtype=np.float64)
    error = np.asarray(triangulation_error_mm, dtype=np.float64)
    cand = problem.candidate_points()
    seen = cand[(visibility[cand] >= MIN_VISIBILITY) & np.isfinite(error[cand])]
    if seen.size >= max(1, cand.size // 10):
        cand = seen
    worst = float(np.nanmax(error)) if np.isfinite(error).any() else 0.0
    return dataclasses.replace(problem, candidates=cand, measured_error_mm=np.nan_to_num(error, nan=worst),
                               cache={})


def layout_problem(session: Trajectories, *, neutral: np.ndarray | None = None,
                   regions: Mapping[str, Sequence[int]] | None = None,
                   faces: np.ndarray | None = None, mirror: np.ndarray | None = None) -> LayoutProblem:
    """A :class:`LayoutProblem` from a dense session (neutral default: per-marker median)."""
    positions = session.positions
    rest = neutral_pose(positions) if neutral is None else np.asarray(neutral, dtype=np.float64)
    if not np.isfinite(rest).all():
        missing = [session.labels[i] for i in np.flatnonzero(~np.isfinite(rest).all(axis=1))]
        raise OptionError(f"markers never seen, no neutral position: {', '.join(missing[:5])}")
    if regions is None:
        regions = _regions_from_metadata(session)
    return LayoutProblem(positions - rest[None], rest, labels=session.labels, faces=faces,
                         regions=regions or {}, mirror=mirror,
                         segments=tuple((t.start, t.end) for t in session.takes))


def _regions_from_metadata(session: Trajectories) -> dict[str, Any]:
    regions = session.metadata.get("regions")
    if isinstance(regions, Mapping):
        return {str(k): session.index(v) for k, v in regions.items()}
    return {}
