"""The files ``mocaptk solve`` writes (format ``mocaptk.solve``, version 1; see docs/solve.md).

``dense.c3d`` (every dense marker; capture rate, first frame and takes kept; each point's residual
= the frame's expected error, mm), ``solve_frames.csv`` (per frame: solved, expected error, the
layout markers lost), ``solve.json`` (summary), ``model.npz`` (when trained here), and the mesh:
``mesh_neutral.obj``, ``mesh_frames.npy`` ((F, V, 3) float32 mm, NaN = unsolved; streamed to disk
chunk by chunk), ``mesh.usd``, ``mesh.glb`` (morph targets; clips up to ``GLB_FRAME_CAP`` frames).
Everything is written into a staging folder and moved into place at the end.
"""

from __future__ import annotations

import io
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.atomic import reserve, write_text
from mocaptk.clustering.reconstruction_models import save_model
from mocaptk.errors import OptionError
from mocaptk.jsonio import write_json
from mocaptk.trajectories import Trajectories

from .solve import CHUNK_FRAMES, FaceSolver, MeshMap, head_poses, layout_frames, solve_chunks

__all__ = ["SOLVE_FORMATS", "user_mesh", "write_solve_outputs"]

SOLVE_FORMAT, SOLVE_VERSION = "mocaptk.solve", 1
#: Output kinds ``--formats`` chooses from (``c3d``, the per-frame CSV and solve.json are always written).
SOLVE_FORMATS = ("npz", "usd", "glb")


def write_solve_outputs(solver: FaceSolver, capture: Trajectories, capture_source: Mapping[str, Any],
                        staging: Path, *, formats: Sequence[str] = SOLVE_FORMATS,
                        subdivisions: int = 0, mesh_path: str | os.PathLike[str] | None = None,
                        stabilize: bool = True, save_trained: bool = True,
                        chunk: int = CHUNK_FRAMES, notes: Sequence[str] = (),
                        progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Solve ``capture`` and write every output into ``staging`` (a fresh folder); returns the
    summary written to ``solve.json`` (``notes`` go into it). The mesh is the marker surface
    (``subdivisions``), or the mesh file ``mesh_path`` aligned to the dense neutral."""
    say = progress or (lambda _: None)
    unknown = [f for f in formats if f not in SOLVE_FORMATS]
    if unknown:
        raise OptionError(f"unknown --formats {', '.join(unknown)} (choose from {', '.join(SOLVE_FORMATS)})")
    path = str(capture_source.get("path", "capture"))
    x = layout_frames(solver, capture, path)
    poses = head_poses(solver, capture) if stabilize else None
    n_frames, n_dense = capture.n_frames, len(solver.labels)
    if mesh_path is None:
        mesh = MeshMap.marker_surface(solver.model.neutral, subdivisions=subdivisions)
        mesh_info: dict[str, Any] = {"kind": "marker surface", "subdivisions": subdivisions}
    else:
        say(f"aligning {Path(mesh_path).name} to the dense neutral")
        mesh, mesh_info = user_mesh(mesh_path, solver.model.neutral)
    dense = np.full((n_frames, n_dense, 3), np.nan)
    error = np.full(n_frames, np.nan)
    missing = np.zeros((n_frames, len(solver.layout_labels)), bool)
    frames_file = None
    if "npz" in formats or "usd" in formats or "glb" in formats:
        frames_file = np.lib.format.open_memmap(staging / "mesh_frames.npy", mode="w+", dtype=np.float32,
                                                shape=(n_frames, mesh.vertices.shape[0], 3))
        reserve(staging / "mesh_frames.npy", frames_file.offset + frames_file.nbytes)  # full disk: no SIGBUS
    for part in solve_chunks(solver, x, poses, chunk=chunk):
        say(f"solving frames {part.start}-{part.start + len(part.positions)} of {n_frames}")
        rows = slice(part.start, part.start + len(part.positions))
        dense[rows], error[rows], missing[rows] = part.positions, part.expected_error_mm, part.missing
        if frames_file is not None:
            frames_file[rows] = mesh.apply(part.positions)
    solved = np.isfinite(dense).all(axis=2).any(axis=1)
    written = ["dense.c3d", "solve_frames.csv", "solve.json"]
    say("writing dense.c3d")
    from mocaptk.acquisition.c3d_write import write_c3d

    residual = np.where(np.isfinite(dense).all(axis=2), error[:, None], np.nan)
    meta = {"takes": capture.takes, "source": path}
    write_c3d(Trajectories(dense, solver.labels, capture.rate, capture.first_frame, residual, meta),
              staging / "dense.c3d")
    write_text(staging / "solve_frames.csv", _frames_csv(solved, error, missing, solver.layout_labels))
    if save_trained:
        save_model(solver.model, staging / "model.npz", header=solver.header())
        written.append("model.npz")
    if frames_file is not None:
        frames_file.flush()
        _write_obj(staging / "mesh_neutral.obj", mesh.vertices, mesh.faces)
        written += ["mesh_neutral.obj"] + (["mesh_frames.npy"] if "npz" in formats else [])
    notes = list(notes)
    if "usd" in formats:
        say("writing mesh.usd")
        from .export_usd import write_mesh_usd

        write_mesh_usd(staging / "mesh.usd", rest=mesh.vertices, faces=mesh.faces, n_frames=n_frames,
                       frames=(frames_file[s:s + chunk] for s in range(0, n_frames, chunk)),
                       rate=capture.rate)
        written.append("mesh.usd")
    if "glb" in formats:
        from .export_morph_glb import GLB_FRAME_CAP, write_morph_glb

        if n_frames <= GLB_FRAME_CAP:
            say("writing mesh.glb")
            write_morph_glb(staging / "mesh.glb", rest=mesh.vertices, faces=mesh.faces,
                            frames=frames_file, rate=capture.rate)
            written.append("mesh.glb")
        else:
            notes.append(f"mesh.glb not written: {n_frames} frames > the morph-target cap of "
                         f"{GLB_FRAME_CAP} (use mesh.usd or mesh_frames.npy)")
    if frames_file is not None:
        del frames_file
        if "npz" not in formats:
            (staging / "mesh_frames.npy").unlink()
    mesh_info.update(vertices=int(mesh.vertices.shape[0]), triangles=int(mesh.faces.shape[0]))
    summary = _summary(solver, capture, capture_source, solved=solved, error=error, missing=missing,
                       mesh=mesh_info, head_motion=poses is not None, outputs=sorted(written),
                       notes=notes)
    write_json(staging / "solve.json", summary)
    return summary


def user_mesh(path: str | os.PathLike[str], neutral: np.ndarray) -> tuple[MeshMap, dict[str, Any]]:
    """The mesh file ``path`` (OBJ, PLY, glTF/GLB, STL, OFF; any unit, Y up, facing +Z) aligned
    to the dense neutral (M, 3) mm and following the dense markers (:meth:`MeshMap.fitted`), and
    its summary for ``solve.json``."""
    from .mesh_io import load_mesh

    loaded = load_mesh(path)
    mesh, alignment, pinned = MeshMap.fitted(loaded.vertices, loaded.faces, neutral)
    return mesh, {"kind": "user mesh", "source": str(path), "pinned_markers": pinned,
                  "alignment": {"method": alignment.method, "scale": alignment.transform.scale,
                                "rms_residual_mm": alignment.rms_mm,
                                "max_residual_mm": alignment.max_mm}}


def _frames_csv(solved: np.ndarray, error: np.ndarray, missing: np.ndarray,
                labels: Sequence[str]) -> str:
    names = np.asarray(labels, dtype=object)
    out = io.StringIO()
    out.write("frame,solved,expected_error_mm,missing_count,missing_markers\n")
    for f in range(len(solved)):
        lost = ";".join(names[missing[f]]) if missing[f].any() else ""
        value = f"{error[f]:.3f}" if np.isfinite(error[f]) else ""
        out.write(f"{f},{int(solved[f])},{value},{int(missing[f].sum())},{lost}\n")
    return out.getvalue()


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = ["# mocaptk solve: neutral face mesh, mm"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    write_text(path, "\n".join(lines) + "\n")


def _summary(solver: FaceSolver, capture: Trajectories, source: Mapping[str, Any], *,
             solved: np.ndarray, error: np.ndarray, missing: np.ndarray, mesh: dict[str, Any],
             head_motion: bool, outputs: list[str], notes: list[str]) -> dict[str, Any]:
    finite = error[np.isfinite(error)]
    lost_rate = missing.mean(axis=0) if len(missing) else np.zeros(missing.shape[1])
    return {
        "format": SOLVE_FORMAT, "version": SOLVE_VERSION, "units": "mm",
        "capture": {"path": source.get("path"), "sha256": source.get("sha256"),
                    "frames": capture.n_frames, "rate": capture.rate},
        "session": solver.session,
        "model": {"kind": solver.model.kind, "layout_markers": list(solver.layout_labels),
                  "dense_markers": len(solver.labels),
                  "expected_error_all_present_mm": solver.model.error_base},
        "head_motion": {"removed_and_restored": head_motion, "rigid_labels": list(solver.rigid_labels)},
        "frames": {"solved": int(solved.sum()), "unsolved": int((~solved).sum()),
                   "with_lost_markers": int(missing.any(axis=1).sum()),
                   "unsolved_frames": np.flatnonzero(~solved)[:100].tolist()},
        "missing_rate": {label: float(r) for label, r in zip(solver.layout_labels, lost_rate) if r > 0},
        "expected_error_mm": {"mean": float(finite.mean()) if finite.size else None,
                              "p95": float(np.percentile(finite, 95)) if finite.size else None,
                              "max": float(finite.max()) if finite.size else None},
        "mesh": mesh,
        "outputs": outputs, "notes": notes,
    }
