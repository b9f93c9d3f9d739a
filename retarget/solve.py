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

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mocaptk.acquisition.filtering import lowpass
from mocaptk.acquisition.stabilize import POSE_CUTOFF_HZ, kabsch
from mocaptk.clustering.layout import Layout
from mocaptk.clustering.reconstruction_models import DEFAULT_KIND, DEFAULT_RIDGE, FaceModel, fit_model
from mocaptk.errors import InputFileError, OptionError
from mocaptk.trajectories import Trajectories

from .mesh_map import MeshMap

__all__ = ["FaceSolver", "MeshMap", "SolvedChunk", "head_poses", "layout_frames", "solve_chunks",
           "train_solver"]

#: Frames solved at once (bounded memory for any capture length).
CHUNK_FRAMES = 4096


@dataclass(frozen=True)
class FaceSolver:
    """A trained model with what the solve needs to read captures.

    ``labels`` the dense markers (model columns); ``layout_labels`` the model's layout markers
    (in ``model.layout`` order); ``rigid_labels`` / ``rigid_reference`` (R, 3) mm the rigid set
    and its head-relative neutral shape when head motion is solved (else empty / None);
    ``session`` the training session's identity (``path``, ``sha256``, ``frames``, ``markers``).
    """

    model: FaceModel
    labels: tuple[str, ...]
    layout_labels: tuple[str, ...]
    rigid_labels: tuple[str, ...]
    rigid_reference: np.ndarray | None
    session: dict[str, Any]

    def header(self) -> dict[str, Any]:
        """The JSON header of the saved model (see ``save_model``)."""
        return {"session": self.session, "labels": list(self.labels),
                "layout_labels": list(self.layout_labels), "rigid_labels": list(self.rigid_labels),
                "rigid_reference": None if self.rigid_reference is None else self.rigid_reference,
                "units": "mm"}

    @classmethod
    def from_header(cls, model: FaceModel, header: Mapping[str, Any]) -> FaceSolver:
        reference = header.get("rigid_reference")
        return cls(model, tuple(header["labels"]), tuple(header["layout_labels"]),
                   tuple(header.get("rigid_labels") or ()),
                   None if reference is None else np.asarray(reference, dtype=np.float64),
                   dict(header["session"]))


def train_solver(layout: Layout, session: Trajectories, source: Mapping[str, Any], *,
                 kind: str = DEFAULT_KIND, ridge: float = DEFAULT_RIDGE,
                 rigid_labels: Sequence[str] = ()) -> FaceSolver:
    """Fit the model of ``kind`` on ``session`` (already head-relative: stabilized on
    ``rigid_labels`` if the layout was) for ``layout``'s markers present in it.

    ``source``: ``{"path", "sha256"}`` of the session file (its identity in the model file).
    """
    known = set(session.labels)
    layout_labels = tuple(label for label in layout.labels if label in known)
    if not layout_labels:
        raise OptionError("none of the layout's markers is in the session")
    model = fit_model(session.positions, session.index(layout_labels), kind=kind, ridge=ridge)
    # fit_model sorts the layout columns: keep the labels in the model's order
    layout_labels = tuple(session.labels[i] for i in model.layout)
    reference = None
    if rigid_labels:
        reference = model.neutral[session.index(rigid_labels)]
    identity = {"path": source.get("path"), "sha256": source.get("sha256"),
                "frames": session.n_frames, "markers": session.n_markers}
    return FaceSolver(model, tuple(session.labels), layout_labels, tuple(rigid_labels), reference,
                      identity)


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


def head_poses(solver: FaceSolver, capture: Trajectories) -> tuple[np.ndarray, np.ndarray] | None:
    """Per capture frame ``(R (F, 3, 3), t (F, 3))`` with ``x_capture = R x_head + t`` (NaN where
    fewer than 3 rigid markers are seen), or ``None`` when the solver has no rigid set."""
    if solver.rigid_reference is None:
        return None
    missing = [label for label in solver.rigid_labels if label not in set(capture.labels)]
    if missing:
        raise OptionError(f"the capture lacks rigid markers {', '.join(missing[:5])} needed to "
                          "remove head motion; use --no-stabilize for head-relative captures")
    rigid = capture.select(list(solver.rigid_labels))
    if POSE_CUTOFF_HZ < capture.rate / 2:
        rigid = lowpass(rigid, cutoff_hz=POSE_CUTOFF_HZ)
    seen = np.isfinite(rigid.positions).all(axis=2)
    return kabsch(solver.rigid_reference, rigid.positions, seen.astype(float))


@dataclass(frozen=True)
class SolvedChunk:
    """Frames ``[start, start + len)`` solved: ``positions`` (f, M, 3) mm in the capture frame,
    ``expected_error_mm`` (f,), ``missing`` (f, L) lost layout markers, ``solved`` (f,) bool."""

    start: int
    positions: np.ndarray
    expected_error_mm: np.ndarray
    missing: np.ndarray
    solved: np.ndarray


def solve_chunks(solver: FaceSolver, layout_positions: np.ndarray,
                 poses: tuple[np.ndarray, np.ndarray] | None = None, *,
                 chunk: int = CHUNK_FRAMES) -> Iterator[SolvedChunk]:
    """Solve ``layout_positions`` (F, L, 3) mm chunk by chunk.

    ``poses`` from :func:`head_poses`: frames are taken into head coordinates, solved, and put
    back; a frame without a pose is not solved.
    """
    n_frames = layout_positions.shape[0]
    for start in range(0, n_frames, chunk):
        x = np.array(layout_positions[start:start + chunk], dtype=np.float64)
        if poses is not None:
            rot, trans = poses[0][start:start + chunk], poses[1][start:start + chunk]
            x = np.einsum("fji,fmj->fmi", rot, x - trans[:, None])  # R^T (x - t)
        result = solver.model.predict(x)
        positions = result.positions
        if poses is not None:
            positions = np.einsum("fij,fmj->fmi", rot, positions) + trans[:, None]
        solved = np.isfinite(positions).all(axis=2).any(axis=1)
        error = np.where(solved, result.expected_error_mm, np.nan)
        yield SolvedChunk(start, positions, error, result.missing, solved)
