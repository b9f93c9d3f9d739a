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
4. **Mesh** (:class:`MeshMap`): a sparse linear map takes dense markers to mesh vertices: the
   marker surface through the dense neutral (vertices = dense markers), optionally
   midpoint-subdivided; a given mesh following the markers by thin-shell weights; or a map learned
   from training frames of the mesh itself.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from mocaptk.clustering.layout import Layout
from mocaptk.clustering.pipeline import HEAD_RELATIVE_RMS_MM
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.clustering.reconstruction_models import (DEFAULT_KIND, DEFAULT_RIDGE, FaceModel, load_model,
                                                      batched_ridge, fit_model)
from mocaptk.errors import InputFileError, OptionError
from mocaptk.surface_mesh import marker_surface_mesh
from mocaptk.trajectories import Trajectories

from .actor_adaptation import Adaptation
from .align import Alignment, SurfaceProximity, align_mesh_to_markers
from .consistency import LayoutGaussian, Screen, screen_frames, training_consistency
from .head_pose import HeadPoses, least_moving_markers, robust_head_poses
from .influence import anchor_vertices

__all__ = ["FaceSolver", "MeshMap", "SolvedChunk", "head_poses", "layout_frames", "solve_chunks",
           "load_solver", "to_head_frame", "train_solver"]

#: ``HeadPoses.source`` values: the layout's stabilization markers, or its least-moving markers.
POSE_FROM_RIGID = "stabilization markers"
POSE_FROM_LAYOUT = "least-moving layout markers"
#: Frames solved at once (bounded memory for any capture length).
CHUNK_FRAMES = 4096
#: Dense markers each vertex of a learned mesh map is regressed from (:meth:`MeshMap.learned`).
MESH_NEIGHBOURS = 8
#: A dense marker farther than this from a user's aligned mesh is not pinned to it (mm).
ANCHOR_REACH_MM = 5.0


@dataclass(frozen=True)
class FaceSolver:
    """A trained model with what the solve needs to read captures.

    ``labels`` the dense markers (model columns); ``layout_labels`` the model's layout markers
    (in ``model.layout`` order); ``rigid_labels`` / ``rigid_reference`` (R, 3) mm the layout's
    stabilization markers and their neutral shape in the session's head frame (empty / None for
    a layout without them); ``fallback_labels`` / ``fallback_reference`` (K, 3) mm the
    least-moving layout markers a capture without stabilization markers is posed from;
    ``gaussian`` the layout markers' Gaussian (ghosts, consistency; None in old model files) and
    ``training_consistency_mm`` its consistency on the session; ``session`` the training
    session's identity (``path``, ``sha256``, ``frames``, ``markers``).
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

    def header(self) -> dict[str, Any]:
        """The JSON header of the saved model (see ``save_model``); the numbers the solve uses go
        in :meth:`extra_arrays` (JSON rounds them)."""
        return {"session": self.session, "labels": list(self.labels),
                "layout_labels": list(self.layout_labels), "rigid_labels": list(self.rigid_labels),
                "fallback_labels": list(self.fallback_labels), "units": "mm"}

    def extra_arrays(self) -> dict[str, np.ndarray]:
        """Arrays saved beside the model: ``solver_rigid_reference``, ``solver_fallback_reference``,
        ``solver_mean``, ``solver_cov`` (the Gaussian), ``solver_training_consistency``."""
        out = {"solver_training_consistency": np.array(self.training_consistency_mm)}
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
                   float(extra.get("solver_training_consistency", float("nan"))))


def load_solver(path: str | os.PathLike[str], *, session: Mapping[str, Any] | None = None) -> FaceSolver:
    """A solver saved by ``mocaptk solve`` (``model.npz``: the model, its header and the layout
    Gaussian); ``session`` as in :func:`~mocaptk.clustering.reconstruction_models.load_model`."""
    model, header = load_model(path, session=session)
    with np.load(path, allow_pickle=False) as data:  # readable: load_model just read it
        extra = {k: data[k] for k in data.files if k.startswith("solver_")}
    try:
        return FaceSolver.from_header(model, header, extra)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed model header ({exc})") from None


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
                      gaussian, training_consistency(gaussian, train_layout))


def layout_frames(solver: FaceSolver, capture: Trajectories, path: str) -> np.ndarray:
    """The capture's layout markers (F, L, 3) mm in the model's order; extra markers ignored.

    Raises :class:`InputFileError` naming ``path`` when layout markers are missing.
    """
    known = set(capture.labels)
    missing = [label for label in solver.layout_labels if label not in known]
    if missing:
        raise InputFileError(path, f"lacks {len(missing)} of the layout's {len(solver.layout_labels)} "
                             f"markers: {', '.join(missing[:5])}" + (" ..." if len(missing) > 5 else ""))
    return capture.positions[:, capture.index(solver.layout_labels)]


def head_poses(solver: FaceSolver, capture: Trajectories) -> HeadPoses | None:
    """The capture's head poses in the session's head frame: from the layout's stabilization
    markers, or, when the capture has fewer than 3 of them, from the least-moving layout markers
    (``HeadPoses.source`` says which); identity poses (``still``) when those markers already sit
    within ``HEAD_RELATIVE_RMS_MM`` RMS of their session shape; None when the solver has neither."""
    known = set(capture.labels)
    present = [k for k, label in enumerate(solver.rigid_labels) if label in known]
    if solver.rigid_reference is not None and len(present) >= 3:
        poses = robust_head_poses(solver.rigid_reference[present], capture,
                                  [solver.rigid_labels[k] for k in present], source=POSE_FROM_RIGID)
    elif solver.fallback_reference is not None and all(label in known for label in solver.fallback_labels):
        poses = robust_head_poses(solver.fallback_reference, capture, solver.fallback_labels,
                                  source=POSE_FROM_LAYOUT)
    else:
        return None
    if poses.motion_rms_mm < HEAD_RELATIVE_RMS_MM:  # skin sliding on the pose markers is not head motion
        n = len(poses.rotations)
        return replace(poses, rotations=np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
                       translations=np.zeros((n, 3)), still=True)
    return poses


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
    rot, trans = poses.rotations[rows], poses.translations[rows]
    return np.einsum("fji,fmj->fmi", rot, x - trans[:, None])


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


def _motion_p95(frames: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """Per marker the 95th percentile distance (mm) from ``neutral`` (L, 3) over ``frames``
    (F, L, 3) (every k-th frame, at most 8,192; inf for a marker never seen)."""
    sample = frames[::max(1, -(-len(frames) // 8192))]
    dist = np.linalg.norm(sample - neutral, axis=2)
    out = np.full(dist.shape[1], np.inf)
    seen = np.isfinite(dist).any(axis=0)
    out[seen] = [np.percentile(d[np.isfinite(d)], 95) for d in dist[:, seen].T]
    return out


def _array_or_none(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


@dataclass(frozen=True)
class MeshMap:
    """The animated mesh: ``vertices`` (V, 3) mm neutral, ``faces`` (T, 3), ``matrix`` the linear
    map and ``offset`` (V, 3) mm: vertex positions = matrix @ dense markers + offset (unseen dense
    markers have no column weight). ``matrix`` is (V, M) dense float32 when x, y and z share the
    weights (one GEMM per chunk: ~15x a sparse product of the same map), else (3V, 3M) sparse on
    the flattened coordinates (x, y, z per point)."""

    vertices: np.ndarray
    faces: np.ndarray
    matrix: np.ndarray | sp.csr_matrix
    offset: np.ndarray | None = None

    @classmethod
    def marker_surface(cls, neutral: np.ndarray, *, subdivisions: int = 0) -> MeshMap:
        """The marker surface through the dense neutral ``neutral`` (M, 3) mm (NaN = unseen),
        midpoint-subdivided ``subdivisions`` times (each splits a triangle into 4)."""
        if subdivisions < 0 or subdivisions > 4:
            raise OptionError(f"--subdivisions must be 0..4, got {subdivisions}")
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        _, faces = marker_surface_mesh(neutral[seen])
        faces = np.asarray(faces, dtype=np.int64)
        matrix = sp.csr_matrix((np.ones(seen.size), (np.arange(seen.size), seen)),
                               shape=(seen.size, neutral.shape[0]))
        for _ in range(subdivisions):
            matrix, faces = _midpoint_subdivide(matrix, faces)
        return cls(matrix @ np.nan_to_num(neutral), faces, _per_axis(matrix))

    @classmethod
    def anchored(cls, vertices: np.ndarray, faces: np.ndarray, anchors: np.ndarray,
                 neutral: np.ndarray, *, min_weight: float = 1e-4) -> MeshMap:
        """A given mesh ``vertices`` (V, 3) mm, ``faces`` (T, 3) following the dense markers pinned
        at vertices ``anchors`` (M,) (-1: not pinned; neutral ``neutral`` (M, 3) mm) by
        thin-shell interpolation (Le et al.'s ``W = Â⁻¹B̂``). A vertex several markers are
        pinned to moves by their mean displacement (a coarse mesh); weights below
        ``min_weight`` are dropped (sparse, fast)."""
        from mocaptk.clustering.reconstruction_models import KB, KS, TIKHONOV
        from mocaptk.thin_shell import interpolation_weights, thin_shell_operator

        anchors = np.asarray(anchors, dtype=np.intp)
        pinned = np.flatnonzero(anchors >= 0)
        if pinned.size == 0:
            raise OptionError("no dense marker is pinned to the mesh")
        held, slot = np.unique(anchors[pinned], return_inverse=True)
        share = np.bincount(slot)
        mean = sp.csr_matrix((1.0 / share[slot], (slot, pinned)), shape=(held.size, len(anchors)))
        op = thin_shell_operator(vertices, faces, ks=KS, kb=KB)
        op = op + TIKHONOV * float(np.abs(op.diagonal()).mean()) * sp.identity(op.shape[0])
        weights = interpolation_weights(op, held)
        weights[np.abs(weights) < min_weight] = 0.0
        matrix = sp.csr_matrix(sp.csr_matrix(weights) @ mean)
        offset = (np.asarray(vertices, dtype=np.float64)
                  - matrix @ np.nan_to_num(np.asarray(neutral, dtype=np.float64)))
        return cls(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                   _per_axis(matrix), offset)

    @classmethod
    def fitted(cls, vertices: np.ndarray, faces: np.ndarray, neutral: np.ndarray, *,
               reach_mm: float = ANCHOR_REACH_MM) -> tuple[MeshMap, Alignment, int]:
        """A user's mesh ``vertices`` (V, 3) (any unit, Y up, facing +Z), ``faces`` (T, 3) aligned
        onto the dense neutral ``neutral`` (M, 3) mm (NaN = unseen) by ICP with scale, as
        ``mocaptk rig --mesh`` does; each seen dense marker is pinned at the vertex nearest to
        its closest surface point unless it is more than ``reach_mm`` from the surface (beyond
        the mesh's border), then :meth:`anchored`. Returns the map, the alignment and how many
        markers were pinned."""
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        alignment = align_mesh_to_markers(vertices, faces, neutral[seen])
        placed = alignment.transform.apply(vertices)
        nearest, dist = anchor_vertices(placed, faces, neutral[seen],
                                        proximity=SurfaceProximity(placed, faces))
        anchors = np.full(len(neutral), -1, dtype=np.intp)
        close = dist <= reach_mm
        anchors[seen[close]] = nearest[close]
        return cls.anchored(placed, faces, anchors, neutral), alignment, int(close.sum())

    @classmethod
    def learned(cls, vertices: np.ndarray, faces: np.ndarray, markers: np.ndarray,
                positions: np.ndarray, *, neighbours: int = MESH_NEIGHBOURS,
                ridge: float = DEFAULT_RIDGE, block: int = 256) -> MeshMap:
        """A mesh seen moving with the dense markers: per vertex, ridge regression of its position
        from the 3 coordinates of its ``neighbours`` nearest dense markers (neutral pose).

        ``vertices`` (V, 3) mm the neutral mesh, ``faces`` (T, 3); ``markers`` (F, M, 3) mm
        training frames of the dense markers (NaN gaps; the frames without any gap are used, as
        the ridge models do) and ``positions`` (F, V, 3) mm the mesh in those frames (a synthetic
        session's ground truth, or registered scans). Unlike :meth:`anchored` it learns how
        vertices beyond the markers move (the neck with the jaw, the inner lips).
        """
        n_verts, n_markers = len(vertices), markers.shape[1]
        neutral = neutral_pose(markers)
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        rows = np.isfinite(markers[:, seen]).all(axis=(1, 2)) & np.isfinite(positions).all(axis=(1, 2))
        k = min(int(neighbours), seen.size)
        if rows.sum() < 2 * 3 * k or k < 1:
            raise OptionError(f"a learned mesh map needs at least {2 * 3 * k} training frames "
                              f"without gaps, got {int(rows.sum())}")
        x = markers[rows].reshape(int(rows.sum()), -1)
        x_mean = x.mean(axis=0)
        x -= x_mean
        near = seen[cKDTree(neutral[seen]).query(vertices, k=k)[1].reshape(n_verts, k)]
        cols = (3 * near[..., None] + np.arange(3)).reshape(n_verts, 3 * k)  # (V, 3k)
        coef = np.empty((n_verts, 3 * k, 3))
        offset = np.empty((n_verts, 3))
        for start in range(0, n_verts, block):  # bounded memory: (frames, block, 3k) at a time
            part = slice(start, start + block)
            xs = x[:, cols[part]].transpose(1, 0, 2)  # (b, F, 3k)
            ys = np.asarray(positions[rows, part], dtype=np.float64).transpose(1, 0, 2)  # (b, F, 3)
            y_mean = ys.mean(axis=1)
            coef[part] = batched_ridge(xs.transpose(0, 2, 1) @ xs,
                                       xs.transpose(0, 2, 1) @ (ys - y_mean[:, None]), ridge)
            offset[part] = y_mean - np.einsum("bk,bkc->bc", x_mean[cols[part]], coef[part])
        matrix = sp.csr_matrix((coef.transpose(0, 2, 1).ravel().astype(np.float32),
                                (np.repeat(np.arange(3 * n_verts), 3 * k),
                                 np.repeat(cols, 3, axis=0).ravel())),
                               shape=(3 * n_verts, 3 * n_markers))
        return cls(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                   matrix, offset)

    def apply(self, dense: np.ndarray) -> np.ndarray:
        """Vertex positions (f, V, 3) float32 mm from dense markers (f, M, 3) (unsolved frames NaN)."""
        f, m, _ = dense.shape
        x = np.nan_to_num(dense).astype(np.float32)  # unseen: weight 0
        if isinstance(self.matrix, np.ndarray):
            verts = (x.transpose(0, 2, 1).reshape(3 * f, m) @ self.matrix.T).reshape(f, 3, -1)
            verts = verts.transpose(0, 2, 1)
        else:
            verts = np.asarray(self.matrix @ x.reshape(f, 3 * m).T).T.reshape(f, -1, 3)
        verts = verts + (0.0 if self.offset is None else self.offset.astype(np.float32))
        verts[~np.isfinite(dense).all(axis=2).any(axis=1)] = np.nan
        return verts


def _per_axis(matrix: sp.spmatrix) -> np.ndarray:
    """A (V, M) map applied to x, y and z alike, as a dense float32 array."""
    return np.asarray(matrix.toarray(), dtype=np.float32)


def _midpoint_subdivide(matrix: sp.csr_matrix, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """One midpoint subdivision of a mesh given as rows of a linear map: each edge gets its
    midpoint row (the mean of its ends), each triangle becomes 4 (orientation kept)."""
    n = matrix.shape[0]
    corners = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)  # (T, 3, 2)
    edges, inverse = np.unique(np.sort(corners.reshape(-1, 2), axis=1), axis=0, return_inverse=True)
    mid = n + inverse.reshape(-1, 3)  # midpoint of edge ab, bc, ca per face
    half = sp.csr_matrix((np.full(2 * len(edges), 0.5),
                          (np.repeat(np.arange(len(edges)), 2), edges.ravel())), shape=(len(edges), n))
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack(t, axis=1) for t in
                                ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return sp.csr_matrix(sp.vstack([matrix, half @ matrix])), new_faces
