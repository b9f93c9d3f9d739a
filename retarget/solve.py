"""From a production capture with only the layout's markers back to the whole face.

The pure pipeline behind ``mocaptk solve``:

1. **Train** (:func:`train_solver`): a reconstruction model
   (:mod:`mocaptk.clustering.reconstruction_models`) of every dense marker of the layout's
   session from the layout markers, on the head-relative session. Layout markers the session
   never captured (mirrored twins of a half-face layout) take no part.
2. **Head motion** (:func:`head_poses`): when the layout was made on stabilized data, each
   capture frame's head pose is the rigid fit (Kabsch, rigid markers low-passed at 12 Hz as in
   stabilization) of the layout's rigid set from its head-relative session neutral onto the
   capture; the frame is solved head-relative and the head motion is put back on the result.
3. **Solve** (:func:`solve_chunks`): chunks of frames, each frame from the layout markers present
   in it (lost ones are NaN, never filled first); per frame the missing markers and the expected
   error are kept. A frame without any layout marker (or without a head pose) is not solved.
4. **Mesh** (:class:`~mocaptk.retarget.mesh_map.MeshMap`, in its own module): a sparse linear
   map takes dense markers to mesh vertices.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from mocaptk.acquisition.stabilize import in_head_frame
from mocaptk.clustering.layout import Layout
from mocaptk.clustering.pipeline import HEAD_RELATIVE_RMS_MM
from mocaptk.clustering.reconstruction_models import DEFAULT_KIND, DEFAULT_RIDGE, FaceModel, fit_model, load_model
from mocaptk.errors import InputFileError, OptionError
from mocaptk.trajectories import Trajectories

from .actor_adaptation import Adaptation
from .consistency import LayoutGaussian, Screen, capture_screen, screen_frames, training_consistency
from .head_pose import (HeadPoses, fixed_pose, least_moving_markers, refine_poses, robust_head_poses,
                        skin_following_poses)
from .mesh_map import MeshMap

__all__ = ["FaceSolver", "MeshMap", "SolvedChunk", "head_poses", "layout_frames", "solve_chunks",
           "in_head_frame", "load_solver", "to_head_frame", "train_solver"]

#: ``HeadPoses.source`` values: the layout's stabilization markers, or its least-moving markers.
POSE_FROM_RIGID = "stabilization markers"
POSE_FROM_LAYOUT = "least-moving layout markers"
#: Frames solved at once (bounded memory for any capture length).
CHUNK_FRAMES = 4096
#: Pose fits following the stabilization markers' skin motion (:func:`_following_skin`): the
#: second fits again with the expression read through the first's poses (fixed beforehand, not tuned).
SKIN_ROUNDS = 2


@dataclass(frozen=True)
class FaceSolver:
    """A trained model with what the solve needs to read captures.

    ``labels`` the dense markers (model columns); ``layout_labels`` the model's layout markers
    (in ``model.layout`` order); ``rigid_labels`` / ``rigid_reference`` (R, 3) mm the layout's
    stabilization markers and their neutral shape in the session's head frame (empty / None for
    a layout without them); ``fallback_labels`` / ``fallback_reference`` (K, 3) mm the
    least-moving layout markers a capture without stabilization markers is posed from;
    ``gaussian`` the layout markers' Gaussian (ghosts, consistency; None in old model files) and
    ``training_consistency_mm`` its consistency on the session; ``rigid_motion_mm`` the RMS
    distance of the stabilization markers from ``rigid_reference`` over the session (their own
    skin motion in the head frame: facial markers chosen on a head-relative session move with
    the expressions; NaN in old model files); ``session`` the training session's identity
    (``path``, ``sha256``, ``frames``, ``markers``).
    """

    model: FaceModel
    labels: tuple[str, ...]
    layout_labels: tuple[str, ...]
    rigid_labels: tuple[str, ...]
    rigid_reference: np.ndarray | None
    session: dict[str, Any]
    fallback_labels: tuple[str, ...] = ()
    fallback_reference: np.ndarray | None = None
    gaussian: LayoutGaussian | None = None
    training_consistency_mm: float = float("nan")
    rigid_motion_mm: float = float("nan")

    def header(self) -> dict[str, Any]:
        """The JSON header of the saved model (see ``save_model``); the numbers the solve uses go
        in :meth:`extra_arrays` (JSON rounds them)."""
        return {"session": self.session, "labels": list(self.labels),
                "layout_labels": list(self.layout_labels), "rigid_labels": list(self.rigid_labels),
                "fallback_labels": list(self.fallback_labels), "units": "mm"}

    def extra_arrays(self) -> dict[str, np.ndarray]:
        """Arrays saved beside the model: ``solver_rigid_reference``, ``solver_fallback_reference``,
        ``solver_mean``, ``solver_cov`` (the Gaussian), ``solver_training_consistency``,
        ``solver_rigid_motion``."""
        out = {"solver_training_consistency": np.array(self.training_consistency_mm),
               "solver_rigid_motion": np.array(self.rigid_motion_mm)}
        for name, value in (("rigid_reference", self.rigid_reference),
                            ("fallback_reference", self.fallback_reference)):
            if value is not None:
                out[f"solver_{name}"] = value
        if self.gaussian is not None:
            out.update({f"solver_{k}": v for k, v in self.gaussian.arrays().items()})
        return out

    @classmethod
    def from_header(cls, model: FaceModel, header: Mapping[str, Any],
                    extra: Mapping[str, np.ndarray] | None = None) -> FaceSolver:
        extra = extra or {}
        gaussian = None
        if "solver_mean" in extra and "solver_cov" in extra:
            gaussian = LayoutGaussian.from_arrays({"mean": extra["solver_mean"], "cov": extra["solver_cov"]})
        rigid = tuple(header.get("rigid_labels") or ())
        fallback = tuple(header.get("fallback_labels") or ())
        return cls(model, tuple(header["labels"]), tuple(header["layout_labels"]),
                   rigid if "solver_rigid_reference" in extra else (),
                   _array_or_none(extra.get("solver_rigid_reference")), dict(header["session"]),
                   fallback if "solver_fallback_reference" in extra else (),
                   _array_or_none(extra.get("solver_fallback_reference")), gaussian,
                   float(extra.get("solver_training_consistency", float("nan"))),
                   float(extra.get("solver_rigid_motion", float("nan"))))


def load_solver(path: str | os.PathLike[str], *, session: Mapping[str, Any] | None = None) -> FaceSolver:
    """A solver saved by ``mocaptk solve`` (``model.npz``: the model, its header and the layout
    Gaussian); ``session`` as in :func:`~mocaptk.clustering.reconstruction_models.load_model`."""
    model, header = load_model(path, session=session, labelled=True)
    with np.load(path, allow_pickle=False) as data:  # readable: load_model just read it
        extra = {k: data[k] for k in data.files if k.startswith("solver_")}
    problem = _extra_problem(header, extra)
    if problem:
        raise InputFileError(path, f"malformed model file: {problem}")
    try:
        return FaceSolver.from_header(model, header, extra)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed model header ({exc})") from None


def _extra_problem(header: Mapping[str, Any], extra: Mapping[str, np.ndarray]) -> str | None:
    """What is wrong with the ``solver_*`` arrays of a model file (shapes against the header's
    labels, real finite numbers), or None."""
    fallback = header.get("fallback_labels") or []
    if not isinstance(fallback, list) or not all(isinstance(v, str) for v in fallback) \
            or not set(fallback) <= set(header["layout_labels"]):
        return "header fallback_labels must be among its layout_labels"
    n = len(header["layout_labels"])
    expected = {"solver_rigid_reference": (len(header.get("rigid_labels") or ()), 3),
                "solver_fallback_reference": (len(fallback), 3),
                "solver_mean": (3 * n,), "solver_cov": (3 * n, 3 * n), "solver_training_consistency": ()}
    for name, value in extra.items():
        if name not in expected:
            continue
        if value.dtype.kind not in "iuf" or value.shape != expected[name]:
            return f"{name} must be {expected[name]} numbers, not {value.shape} {value.dtype}"
        value = value.astype(np.float64)  # a float16 compared with 1e12 overflows
        finite = np.isfinite(value) | (name == "solver_training_consistency")  # NaN: not measured
        if not (finite.all() and (np.abs(np.nan_to_num(value)) < 1e12).all()):
            return f"{name} has values out of range"
    for name in ("solver_rigid_reference", "solver_fallback_reference"):
        points = extra.get(name)
        if points is not None and len(points) >= 3:  # head poses are fitted to them
            spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
            if spread[1] < 1e-3 * max(spread[0], 1.0):
                return f"{name}: its markers coincide or lie on one line"
    if "solver_cov" in extra:
        try:  # the ghost screen inverts it: a fitted Gaussian's (ridge added) is positive definite
            np.linalg.cholesky(extra["solver_cov"].astype(np.float64))
        except np.linalg.LinAlgError:
            return "solver_cov is not a covariance (not positive definite)"
    return None


def train_solver(layout: Layout, session: Trajectories, source: Mapping[str, Any], *,
                 kind: str = DEFAULT_KIND, ridge: float = DEFAULT_RIDGE,
                 rigid_labels: Sequence[str] = ()) -> FaceSolver:
    """Fit the model of ``kind`` on ``session`` (head-relative: stabilized on ``rigid_labels``
    when it needed it) for ``layout``'s markers present in it, with the layout markers' Gaussian
    and the fallback pose markers.

    ``source``: ``{"path", "sha256"}`` of the session file (its identity in the model file).
    """
    known = set(session.labels)
    layout_labels = tuple(label for label in layout.labels if label in known)
    if not layout_labels:
        raise OptionError("none of the layout's markers is in the session")
    model = fit_model(session.positions, session.index(layout_labels), kind=kind, ridge=ridge)
    # fit_model sorts the layout columns: keep the labels in the model's order
    layout_labels = tuple(session.labels[i] for i in model.layout)
    rigid_labels = tuple(label for label in rigid_labels if label in known)
    reference = model.neutral[session.index(rigid_labels)] if len(rigid_labels) >= 3 else None
    rigid_motion = float("nan") if reference is None else \
        _rms_distance(session.positions[:, session.index(rigid_labels)], reference)
    train_layout = session.positions[:, model.layout]
    neutral = model.neutral[model.layout]
    motion = _motion_p95(train_layout, neutral)
    fallback = least_moving_markers(neutral, motion, layout_labels)
    gaussian = LayoutGaussian.fit(train_layout, ridge=ridge)
    identity = {"path": source.get("path"), "sha256": source.get("sha256"),
                "frames": session.n_frames, "markers": session.n_markers}
    return FaceSolver(model, tuple(session.labels), layout_labels,
                      rigid_labels if reference is not None else (), reference, identity,
                      fallback, model.neutral[session.index(fallback)] if fallback else None,
                      gaussian, training_consistency(gaussian, train_layout), rigid_motion)


def layout_frames(solver: FaceSolver, capture: Trajectories, path: str) -> np.ndarray:
    """The capture's layout markers (F, L, 3) mm in the model's order; extra markers ignored.

    Raises :class:`InputFileError` naming ``path`` when layout markers are missing.
    """
    known = set(capture.labels)
    missing = [label for label in solver.layout_labels if label not in known]
    if missing:
        from mocaptk.acquisition.labelling import is_unnamed

        hint = ("; its points are unlabelled (*N): give --label" if all(map(is_unnamed, capture.labels))
                else "")
        raise InputFileError(path, f"lacks {len(missing)} of the layout's {len(solver.layout_labels)} "
                             f"markers: {', '.join(missing[:5])}" + (" ..." if len(missing) > 5 else "") + hint)
    return capture.positions[:, capture.index(solver.layout_labels)]


def head_poses(solver: FaceSolver, capture: Trajectories) -> HeadPoses | None:
    """The capture's head poses in the session's head frame: from the layout's stabilization
    markers, or, when the capture has fewer than 3 of them, from the least-moving layout markers
    (``HeadPoses.source`` says which); identity poses (``still``) when those markers already sit
    within ``HEAD_RELATIVE_RMS_MM`` RMS of their session shape, beyond the stabilization markers'
    own motion in the session (:func:`still_limit_mm`); one fixed pose for every frame (also
    ``still``) when the stabilization markers move no more than that about their own median
    (a head-relative capture in another frame); None when the solver has neither."""
    known = set(capture.labels)
    present = [k for k, label in enumerate(solver.rigid_labels) if label in known]
    if solver.rigid_reference is not None and len(present) >= 3:
        poses = robust_head_poses(solver.rigid_reference[present], capture,
                                  [solver.rigid_labels[k] for k in present], source=POSE_FROM_RIGID)
    elif solver.fallback_reference is not None and all(label in known for label in solver.fallback_labels):
        poses = robust_head_poses(solver.fallback_reference, capture, solver.fallback_labels,
                                  source=POSE_FROM_LAYOUT)
        if solver.gaussian is not None and all(label in known for label in solver.layout_labels):
            poses = _refined(solver, poses, capture.positions[:, capture.index(solver.layout_labels)])
    else:
        return None
    limit = still_limit_mm(solver, poses)
    n = len(poses.rotations)
    if poses.motion_rms_mm < limit:  # skin motion of the pose markers is not head motion
        return replace(poses, rotations=np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
                       translations=np.zeros((n, 3)), still=True)
    if poses.source == POSE_FROM_RIGID:
        fixed = fixed_pose(solver.rigid_reference[present], capture, poses.labels)
        if fixed is not None and fixed[2] < limit:
            return replace(poses, rotations=np.broadcast_to(fixed[0], (n, 3, 3)).copy(),
                           translations=np.broadcast_to(fixed[1], (n, 3)).copy(), still=True,
                           motion_rms_mm=fixed[2])
        if all(label in known for label in solver.layout_labels):
            poses = _following_skin(solver, poses, solver.rigid_reference[present],
                                    capture.positions[:, capture.index(solver.layout_labels)], capture)
    return poses


def still_limit_mm(solver: FaceSolver, poses: HeadPoses) -> float:
    """The pose markers' RMS motion (mm) below which a capture is already in the head frame:
    ``HEAD_RELATIVE_RMS_MM``, plus, for the stabilization markers, their own motion in the
    session's head frame. A layout made on a head-relative session (blenderFace) may have chosen
    facial markers as its stabilization set; a capture of the same kind moves them as much as
    the session did, and posing it on them would turn expressions into head motion (and leave
    the frames where fewer than 3 of them are seen unsolved)."""
    own = solver.rigid_motion_mm if poses.source == POSE_FROM_RIGID else float("nan")
    return HEAD_RELATIVE_RMS_MM + (own if np.isfinite(own) else 0.0)


@dataclass(frozen=True)
class SolvedChunk:
    """Frames ``[start, start + len)`` solved: ``positions`` (f, M, 3) mm in the capture frame,
    ``expected_error_mm`` (f,) the model's expected error for the markers used,
    ``missing`` (f, L) layout markers not used (lost, or ``flagged``: present but contradicted by
    the others, ghosts), ``consistency_mm`` (f,) the RMS leave-one-out residual of the markers
    used, ``solved`` (f,) bool."""

    start: int
    positions: np.ndarray
    expected_error_mm: np.ndarray
    missing: np.ndarray
    solved: np.ndarray
    flagged: np.ndarray | None = None
    consistency_mm: np.ndarray | None = None


def to_head_frame(x: np.ndarray, poses: HeadPoses | None, rows: slice = slice(None)) -> np.ndarray:
    """Capture points (f, K, 3) mm of frames ``rows`` in the head frame: ``R^T (x - t)``."""
    if poses is None:
        return np.array(x, dtype=np.float64)
    return in_head_frame(x, poses.rotations[rows], poses.translations[rows])


def solve_chunks(solver: FaceSolver, layout_positions: np.ndarray, poses: HeadPoses | None = None, *,
                 screen: Screen | None = None, adaptation: Adaptation | None = None,
                 chunk: int = CHUNK_FRAMES) -> Iterator[SolvedChunk]:
    """Solve ``layout_positions`` (F, L, 3) mm chunk by chunk.

    ``poses`` from :func:`head_poses`: frames are taken into head coordinates, solved, and put
    back; a frame without a pose is not solved. ``screen`` (from :func:`capture_screen` on the
    head-relative frames): layout markers the others contradict are dropped before the solve.
    ``adaptation``: another actor's neutral offsets (:mod:`.actor_adaptation`).
    """
    n_frames = layout_positions.shape[0]
    for start in range(0, n_frames, chunk):
        rows = slice(start, start + chunk)
        x = to_head_frame(layout_positions[rows], poses, rows)
        if adaptation is not None:
            x = adaptation.to_session(x)
        flagged = consistency = None
        if screen is not None and solver.gaussian is not None:
            flagged, consistency = screen_frames(solver.gaussian, screen, x)
            x[flagged] = np.nan
        result = solver.model.predict(x)
        positions = result.positions
        if adaptation is not None:
            positions = adaptation.to_capture(positions)
        if poses is not None:
            positions = np.einsum("fij,fmj->fmi", poses.rotations[rows], positions) \
                + poses.translations[rows][:, None]
        solved = np.isfinite(positions).all(axis=2).any(axis=1)
        error = np.where(solved, result.expected_error_mm, np.nan)
        yield SolvedChunk(start, positions, error, result.missing, solved, flagged, consistency)


def _following_skin(solver: FaceSolver, poses: HeadPoses, reference: np.ndarray, x: np.ndarray,
                    capture: Trajectories) -> HeadPoses:
    """Stabilization-marker poses fitted again with each pose marker where the model puts it in
    that frame (:func:`~.head_pose.skin_following_poses`), :data:`SKIN_ROUNDS` times.

    A head-relative session's stabilization set holds the markers that moved least in it, skin
    ones among them (a forehead, a nose bridge); the expressions of a capture move them, and a
    pose fitted to a fixed shape turns that into head motion, which the solve then passes to
    every dense marker (the model, trained without head motion, does not follow a rigid offset
    of its layout markers). The layout markers in the head frame give each frame's expression,
    the model the pose markers' skin motion in it. A pose marker that is itself a layout marker
    keeps its fixed shape (the model copies it: no prediction). Ghosts are screened first."""
    layout = set(solver.layout_labels)
    movable = [k for k, label in enumerate(poses.labels) if label not in layout]
    if not movable or solver.gaussian is None:
        return poses
    columns = [solver.labels.index(poses.labels[k]) for k in movable]
    x = _without_ghosts(solver, poses, x)
    for _ in range(SKIN_ROUNDS):
        moved = np.full((len(x), len(columns), 3), np.nan)
        for start in range(0, len(x), CHUNK_FRAMES):
            rows = slice(start, start + CHUNK_FRAMES)
            moved[rows] = solver.model.predict_markers(to_head_frame(x[rows], poses, rows), columns)
        seen = np.isfinite(moved).any(axis=0)  # a marker never solved keeps its fixed shape
        centre = np.full(seen.shape, np.nan)
        centre[seen] = np.nanmedian(moved[:, seen], axis=0)
        skin = np.zeros((len(x), len(poses.labels), 3))
        skin[:, movable] = moved - centre
        poses = skin_following_poses(poses, reference, capture, skin)
    return poses


def _without_ghosts(solver: FaceSolver, poses: HeadPoses, x: np.ndarray) -> np.ndarray:
    """Layout positions ``x`` (F, L, 3) mm with the points the layout Gaussian flags as ghosts in
    the head frame of ``poses`` set to NaN (before a pose fit leans on them)."""
    head = to_head_frame(x, poses)
    flagged, _ = screen_frames(solver.gaussian, capture_screen(
        solver.gaussian, head, training_mm=solver.training_consistency_mm), head)
    return np.where(flagged[..., None], np.nan, x)


def _refined(solver: FaceSolver, poses: HeadPoses, x: np.ndarray) -> HeadPoses:
    """Few-marker poses refined on every layout marker (ghosts screened out first): a brow raise
    tilts a head posed from a few forehead markers. ``motion_rms_mm`` becomes the RMS distance the
    poses move the layout's neutral (a still capture's expressions no longer count as motion)."""
    poses = refine_poses(poses, solver.gaussian, _without_ghosts(solver, poses, x))
    neutral = solver.model.neutral[solver.model.layout]
    moved = np.einsum("fij,lj->fli", poses.rotations, neutral) + poses.translations[:, None] - neutral
    sq = np.sum(moved ** 2, axis=2)
    sq = sq[np.isfinite(sq)]
    return replace(poses, motion_rms_mm=float(np.sqrt(sq.mean())) if sq.size else float("nan"))


def _motion_p95(frames: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Per marker the 95th percentile distance (mm) from ``neutral`` (L, 3) over ``frames``
    (F, L, 3) (every k-th frame, at most 8,192; inf for a marker never seen)."""
    sample = frames[::max(1, -(-len(frames) // 8192))]
    dist = np.linalg.norm(sample - neutral, axis=2)
    out = np.full(dist.shape[1], np.inf)
    seen = np.isfinite(dist).any(axis=0)
    out[seen] = [np.percentile(d[np.isfinite(d)], 95) for d in dist[:, seen].T]
    return out


def _rms_distance(points: np.ndarray, reference: np.ndarray) -> float:
    """RMS distance (mm) of ``points`` (F, K, 3) from ``reference`` (K, 3) over the seen ones."""
    sq = np.sum((points - reference) ** 2, axis=2)
    sq = sq[np.isfinite(sq)]
    return float(np.sqrt(sq.mean())) if sq.size else float("nan")


def _array_or_none(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)
