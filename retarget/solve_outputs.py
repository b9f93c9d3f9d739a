"""The files ``mocaptk solve`` writes (format ``mocaptk.solve``, version 1; see docs/solve.md).

``dense.c3d`` (every dense marker; capture rate, first frame and takes kept; each point's residual
= the frame's expected error, mm), ``solve_frames.csv`` (per frame: solved, expected error, the
layout markers lost), ``solve.json`` (summary), ``model.npz`` (when trained here), and the mesh:
``mesh_neutral.obj``, ``mesh_frames.npy`` ((F, V, 3) float32 mm, NaN = unsolved; streamed to disk
chunk by chunk), ``mesh.usd`` (time codes = the capture's frame numbers; a long take's samples in value clips,
``mesh_clips/``), ``mesh.glb`` (a morph basis keyed per
frame and the head pose on one joint; any length; one clip per take from time 0).
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
from mocaptk.clustering.layout import Layout
from mocaptk.clustering.reconstruction_models import save_model
from mocaptk.errors import OptionError
from mocaptk.jsonio import write_json
from mocaptk.trajectories import Trajectories

from .actor_adaptation import NeutralMismatch, adapt_to_capture, neutral_mismatch, neutral_offset
from .consistency import capture_screen, stabilization_residuals
from .head_pose import HeadPoses
from .build import check_surface
from .solve import (CHUNK_FRAMES, POSE_FROM_RIGID, FaceSolver, MeshMap, head_poses, layout_frames,
                    solve_chunks, to_head_frame)

__all__ = ["SOLVE_FORMATS", "user_mesh", "write_solve_outputs"]

SOLVE_FORMAT, SOLVE_VERSION = "mocaptk.solve", 2
#: Output kinds ``--formats`` chooses from (``c3d``, the per-frame CSV and solve.json are always written).
SOLVE_FORMATS = ("npz", "usd", "glb")
#: How much of the layout markers' excess inconsistency (over the training session's) shows in
#: the dense markers' error (see :func:`estimated_error`).
CONSISTENCY_WEIGHT = 1.0
#: Bytes of float64 vertices mapped at once: a 9,000-vertex face over a whole chunk of frames
#: would hold ~3 GB of temporaries (72,000 frames then peaked at 3.2 GB anonymous memory).
MESH_BLOCK_BYTES = 1 << 26
#: Bytes of mesh.usd time samples held in memory at once: above this the samples go into value clips
#: (``mesh_clips/``), since usd-core keeps a layer's samples until it saves (72,000 frames of the
#: default face held 10.1 GB).
MESH_USD_CLIP_BYTES = 1 << 28


def write_solve_outputs(solver: FaceSolver, capture: Trajectories, capture_source: Mapping[str, Any],
                        staging: Path, *, formats: Sequence[str] = SOLVE_FORMATS,
                        subdivisions: int = 0, mesh_path: str | os.PathLike[str] | None = None,
                        landmarks: Mapping[str, int] | None = None,
                        layout: Layout | None = None, surface: str = "face", face_parts: bool = True,
                        stabilize: bool = True, save_trained: bool = True,
                        chunk: int = CHUNK_FRAMES, notes: Sequence[str] = (),
                        adapt: bool = False, rest_frames: np.ndarray | None = None,
                        progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Solve ``capture`` and write every output into ``staging`` (a fresh folder); returns the
    summary written to ``solve.json`` (``notes`` go into it). The mesh is the mesh file
    ``mesh_path`` aligned to the dense neutral, else ``surface``: ``"face"`` the default face
    (:meth:`MeshMap.face`; the whole face for a half-face ``layout``; with its eyeballs and mouth
    interior unless ``face_parts`` is False) or ``"markers"`` the marker surface
    (``subdivisions``; also where the face does not fit)."""
    say = progress or (lambda _: None)
    unknown = [f for f in formats if f not in SOLVE_FORMATS]
    if unknown:
        raise OptionError(f"unknown --formats {', '.join(unknown)} (choose from {', '.join(SOLVE_FORMATS)})")
    path = str(capture_source.get("path", "capture"))
    x = layout_frames(solver, capture, path)
    notes = list(notes)
    poses = head_poses(solver, capture) if stabilize else None
    if stabilize and poses is None:
        notes.append("head motion not removed: the capture has neither the layout's stabilization "
                     "markers nor its least-moving layout markers")
    if poses is not None and poses.source != POSE_FROM_RIGID:
        notes.append(f"warning: the capture lacks the layout's stabilization markers "
                     f"({', '.join(solver.rigid_labels) or 'none recorded'}): head motion taken from the "
                     f"least-moving layout markers {', '.join(poses.labels)}, refined on all of them "
                     "(see pose_residual_mm in solve_frames.csv)")
    if poses is not None and poses.still:
        fixed = bool(np.any(poses.translations)) or not np.allclose(poses.rotations, np.eye(3))
        notes.append(f"the capture's head does not move (its {poses.source} "
                     f"{', '.join(poses.labels)} move {poses.motion_rms_mm:.2f} mm RMS"
                     + ("" if np.isnan(solver.rigid_motion_mm) or poses.source != POSE_FROM_RIGID
                        else f", {solver.rigid_motion_mm:.2f} mm in the session") + "): "
                     + ("one fixed pose lays its frame onto the session's head frame" if fixed
                        else "already in the session's head frame, head motion not removed"))
    head = to_head_frame(x, poses)
    screen = adaptation = None
    mismatch = None
    if solver.gaussian is not None:
        screen = capture_screen(solver.gaussian, head, training_mm=solver.training_consistency_mm)
        neutral = solver.model.neutral[solver.model.layout]
        offset = neutral_offset(neutral, solver.gaussian.cov, head, rest=rest_frames)
        mismatch = neutral_mismatch(neutral, offset)
        if adapt:
            adaptation = adapt_to_capture(neutral, offset)
            screen = capture_screen(solver.gaussian, adaptation.to_session(head),
                                    training_mm=solver.training_consistency_mm)
        elif mismatch.mismatch:
            notes.append(f"warning: the capture's neutral differs from the session's by "
                         f"{mismatch.shift_rms_mm:.1f} mm RMS (size x{mismatch.scale:.3f}): another "
                         "actor, another scale or other units? --adapt-neutral solves relative to the "
                         "capture's own neutral")
    del head
    n_frames, n_dense = capture.n_frames, len(solver.labels)
    check_surface(surface)
    mesh = None
    if mesh_path is not None:
        say(f"aligning {Path(mesh_path).name} to the dense neutral")
        mesh, mesh_info = user_mesh(mesh_path, solver.model.neutral, layout=layout,
                                    landmarks=landmarks, labels=solver.labels,
                                    head=parts_head(solver))
    elif surface == "face":
        say("fitting the face to the dense neutral")
        mesh = face_mesh(solver, layout, parts=face_parts)
        mesh_info = {"kind": "face", "whole_face_mirrored": mesh is not None and mesh.mirror is not None,
                     "parts": mesh is not None and mesh.materials is not None}
    if mesh is None:
        mesh = MeshMap.marker_surface(solver.model.neutral, subdivisions=subdivisions)
        mesh_info = {"kind": "marker surface", "subdivisions": subdivisions}
    dense = np.full((n_frames, n_dense, 3), np.nan)
    error = np.full(n_frames, np.nan)
    consistency = np.full(n_frames, np.nan)
    missing = np.zeros((n_frames, len(solver.layout_labels)), bool)
    flagged = np.zeros((n_frames, len(solver.layout_labels)), bool)
    frames_file = None
    if "npz" in formats or "usd" in formats or "glb" in formats:
        frames_file = np.lib.format.open_memmap(staging / "mesh_frames.npy", mode="w+", dtype=np.float32,
                                                shape=(n_frames, mesh.vertices.shape[0], 3))
        reserve(staging / "mesh_frames.npy", frames_file.offset + frames_file.nbytes)  # full disk: no SIGBUS
    step = max(1, MESH_BLOCK_BYTES // (24 * mesh.vertices.shape[0]))  # frames mapped at once
    for part in solve_chunks(solver, x, poses, screen=screen, adaptation=adaptation, chunk=chunk):
        say(f"solving frames {part.start}-{part.start + len(part.positions)} of {n_frames}")
        rows = slice(part.start, part.start + len(part.positions))
        dense[rows], error[rows], missing[rows] = part.positions, part.expected_error_mm, part.missing
        if part.flagged is not None:
            flagged[rows], consistency[rows] = part.flagged, part.consistency_mm
        if frames_file is not None:
            for first in range(rows.start, rows.stop, step):
                block = slice(first, min(first + step, rows.stop))
                frames_file[block] = mesh.apply(dense[block], None if poses is None else
                                                (poses.rotations[block], poses.translations[block]))
    measured, measured_labels = measured_error(solver, capture, dense, poses)
    estimated = estimated_error(error, consistency, solver.training_consistency_mm, measured=measured,
                                n_outside=len(solver.labels) - len(solver.layout_labels))
    measured_rms = np.full(n_frames, np.nan) if measured is None else _rms_rows(measured)
    solved = np.isfinite(dense).all(axis=2).any(axis=1)
    written = ["dense.c3d", "solve_frames.csv", "solve.json"]
    say("writing dense.c3d")
    from mocaptk.acquisition.c3d_write import write_c3d

    residual = np.where(np.isfinite(dense).all(axis=2), estimated[:, None], np.nan)
    meta = {"takes": capture.takes, "source": path}
    write_c3d(Trajectories(dense, solver.labels, capture.rate, capture.first_frame, residual, meta),
              staging / "dense.c3d")
    write_text(staging / "solve_frames.csv",
               _frames_csv(solved, error, estimated, consistency, measured_rms, missing & ~flagged,
                           flagged, poses, solver.layout_labels))
    if save_trained:
        save_model(solver.model, staging / "model.npz", header=solver.header(), extra=solver.extra_arrays())
        written.append("model.npz")
    if frames_file is not None:
        frames_file.flush()
        _write_obj(staging / "mesh_neutral.obj", mesh.vertices, mesh.faces, uv=mesh.uv)
        written += ["mesh_neutral.obj"] + (["mesh_frames.npy"] if "npz" in formats else [])
    if "usd" in formats:
        say("writing mesh.usd")
        from .export_usd import write_mesh_usd

        clip_frames = max(1, MESH_USD_CLIP_BYTES // (12 * mesh.vertices.shape[0]))
        write_mesh_usd(staging / "mesh.usd", rest=mesh.vertices, faces=mesh.faces, n_frames=n_frames,
                       frames=(frames_file[s:s + chunk] for s in range(0, n_frames, chunk)),
                       rate=capture.rate, uv=mesh.uv, first_frame=capture.first_frame,
                       takes=capture.takes, clip_frames=clip_frames, materials=mesh.materials)
        written += ["mesh.usd"] + (["mesh_clips/"] if n_frames > clip_frames else [])
    if "glb" in formats:
        say("writing mesh.glb")
        from .export_morph_glb import write_morph_glb

        _, mesh_info["glb"] = write_morph_glb(
            staging / "mesh.glb", rest=mesh.vertices, faces=mesh.faces, frames=frames_file,
            rate=capture.rate, uv=mesh.uv, takes=capture.takes, first_frame=capture.first_frame,
            head=None if poses is None else (poses.rotations, poses.translations),
            materials=mesh.materials)
        written.append("mesh.glb")
    if frames_file is not None:
        del frames_file
        if "npz" not in formats:
            (staging / "mesh_frames.npy").unlink()
    mesh_info.update(vertices=int(mesh.vertices.shape[0]), triangles=int(mesh.faces.shape[0]))
    summary = _summary(solver, capture, capture_source, solved=solved, error=error, estimated=estimated,
                       consistency=consistency, measured=measured_rms, measured_labels=measured_labels,
                       missing=missing, flagged=flagged, poses=poses,
                       mismatch=mismatch, adapted=adaptation is not None, mesh=mesh_info,
                       outputs=sorted(written), notes=notes)
    write_json(staging / "solve.json", summary)
    return summary


def face_mesh(solver: FaceSolver, layout: Layout | None, *, parts: bool = True) -> MeshMap | None:
    """The default face on ``solver``'s dense neutral (:meth:`MeshMap.face`), mirrored to the
    whole face when ``layout`` has mirrored markers, its lip markers each on its own lip
    (:func:`jaw_following`); None where it does not fit. With ``parts`` and ``layout``, its
    eyeballs and mouth interior move with the jaw and the head's marker (:func:`parts_head`)."""
    plane = None if layout is None else layout.extra.get("sagittal_plane")
    plane = None if not isinstance(plane, dict) else (np.asarray(plane["point"], float),
                                                      np.asarray(plane["normal"], float))
    mirrored = layout is not None and any(c.mirrored_from for c in layout.clusters)
    index = {label: i for i, label in enumerate(solver.labels)}
    head = index.get(parts_head(solver))
    regions = None
    if parts and layout is not None and head is not None:
        region_of = {m: c.region for c in layout.clusters for m in c.members}
        regions = [region_of.get(label, "") for label in solver.labels]
    return MeshMap.face(solver.model.neutral, plane=plane, mirrored=mirrored, head=head, regions=regions,
                        jaw_following=None if layout is None else jaw_following(
                            solver, layout, lateral=None if plane is None else plane[1]))


#: How far (mm) :func:`jaw_following` drops the jaw's layout markers (the model's response to it).
JAW_PROBE_MM = 5.0


def jaw_following(solver: FaceSolver, layout: Layout, *,
                  lateral: np.ndarray | None = None) -> np.ndarray | None:
    """Which dense markers (M,) bool drop with the jaw, as the rig's (at least
    :data:`~.build.JAW_FOLLOWING` of the jaw's drop), from the solver instead of the session:
    the layout pose the session's layout Gaussian expects when the jaw's layout markers
    (:func:`~.rig_hierarchy.jaw_members`) drop :data:`JAW_PROBE_MM` on average (rig frame,
    ``lateral`` the subject's left if known), through the model. None for a model file without
    the Gaussian."""
    from .build import JAW_FOLLOWING, rig_frame_rotation
    from .rig_hierarchy import jaw_members

    model, gaussian = solver.model, solver.gaussian
    if gaussian is None:
        return None
    seen = np.isfinite(model.neutral).all(axis=1)
    rotation = rig_frame_rotation(model.neutral[seen], np.zeros(int(seen.sum())), lateral=lateral)
    rest = model.neutral[model.layout]
    region = {c.representative: c.region for c in layout.clusters}
    jaw = jaw_members([region.get(label, "") for label in solver.layout_labels], rest @ rotation.T)
    signal = (np.outer(jaw, -rotation[1]) / max(int(jaw.sum()), 1)).ravel()  # the jaw's mean drop
    along = gaussian.cov @ signal  # the layout's regression on that drop
    dropped = rest + (JAW_PROBE_MM / float(signal @ along)) * along.reshape(rest.shape)
    moved = np.diff(model.predict_positions(np.stack([rest, dropped])), axis=0)[0]
    return -(moved @ rotation.T)[:, 1] >= JAW_FOLLOWING * JAW_PROBE_MM


def parts_head(solver: FaceSolver) -> str | None:
    """The layout marker a ``--mesh``'s parts take as the head's (``rig --mesh`` takes the one
    that moves least): the first fallback pose marker (:func:`~.head_pose.least_moving_markers`),
    else, where the layout has no 3 of them apart, the one whose positions spread least over
    the session (the layout markers' Gaussian); None without either (an old model file)."""
    if solver.fallback_labels:
        return solver.fallback_labels[0]
    if solver.gaussian is None:
        return None
    spread = np.diagonal(solver.gaussian.cov).reshape(-1, 3).sum(axis=1)
    return solver.layout_labels[int(np.argmin(spread))]


def user_mesh(path: str | os.PathLike[str], neutral: np.ndarray, *, layout: Layout | None = None,
              landmarks: Mapping[str, int] | None = None, labels: Sequence[str] = (),
              head: str | None = None) -> tuple[MeshMap, dict[str, Any]]:
    """The mesh file ``path`` (OBJ, PLY, glTF/GLB, STL, OFF; any unit, Y up, facing +Z) aligned
    to the dense neutral (M, 3) mm (dense marker ``labels``), opened as ``rig --mesh`` opens it
    and following the dense markers (:meth:`MeshMap.fitted`), and its summary for
    ``solve.json``. ``landmarks`` as ``rig --landmarks``: {marker label: vertex} pairs start the
    alignment, the :data:`~mocaptk.retarget.mesh_openings.CORNERS` keys steer the openings.
    ``head``: the layout marker that moves least (:func:`parts_head`); with
    it and ``layout``, the mesh's teeth, eyeballs, lashes and gums move as ``rig --mesh`` moves
    them (with the head, the jaw or the lids)."""
    from .mesh_io import load_mesh
    from .mesh_openings import CORNERS

    loaded = load_mesh(path)
    plane = None if layout is None else layout.extra.get("sagittal_plane")
    lateral = np.asarray(plane["normal"], float) if isinstance(plane, dict) else None
    corners = {k: v for k, v in (landmarks or {}).items() if k in CORNERS}
    index = {label: i for i, label in enumerate(labels)}
    pairs = {k: v for k, v in (landmarks or {}).items() if k not in CORNERS}
    unknown = [k for k in pairs if k not in index]
    if unknown:
        raise OptionError(f"--landmarks: not dense markers of the model: {', '.join(unknown[:6])}")
    region_of = {} if layout is None else {m: c.region for c in layout.clusters for m in c.members}
    mesh, alignment, pinned, opened = MeshMap.fitted(
        loaded.vertices, loaded.faces, neutral, lateral=lateral, corners=corners,
        landmarks={index[k]: v for k, v in pairs.items()} or None,
        head=index.get(head) if head is not None else None,
        regions=[region_of.get(label, "") for label in labels] if layout is not None else None)
    return mesh, {"kind": "user mesh", "source": str(path), "pinned_markers": pinned,
                  "alignment": {"method": alignment.method, "scale": alignment.transform.scale,
                                "rms_residual_mm": alignment.rms_mm,
                                "max_residual_mm": alignment.max_mm},
                  "opening_edges_cut": [] if opened.lip_cut is None else opened.lip_cut.edges.tolist(),
                  "eye_openings": opened.eye_report}


def _frames_csv(solved: np.ndarray, error: np.ndarray, estimated: np.ndarray, consistency: np.ndarray,
                measured: np.ndarray, lost: np.ndarray, flagged: np.ndarray, poses: HeadPoses | None,
                labels: Sequence[str]) -> str:
    names = np.asarray(labels, dtype=object)
    out = io.StringIO()
    out.write("frame,solved,expected_error_mm,estimated_error_mm,consistency_mm,pose_residual_mm,"
              "missing_count,missing_markers,flagged_count,flagged_markers,measured_error_mm\n")
    pose = poses.residual_mm if poses is not None else np.full(len(solved), np.nan)
    for f in range(len(solved)):
        values = ",".join(f"{v:.3f}" if np.isfinite(v) else "" for v in
                          (error[f], estimated[f], consistency[f], pose[f]))
        lost_names = ";".join(names[lost[f]]) if lost[f].any() else ""
        ghost_names = ";".join(names[flagged[f]]) if flagged[f].any() else ""
        measured_text = f"{measured[f]:.3f}" if np.isfinite(measured[f]) else ""
        out.write(f"{f},{int(solved[f])},{values},{int(lost[f].sum())},{lost_names},"
                  f"{int(flagged[f].sum())},{ghost_names},{measured_text}\n")
    return out.getvalue()


def measured_error(solver: FaceSolver, capture: Trajectories, dense: np.ndarray,
                   poses: HeadPoses | None) -> tuple[np.ndarray | None, list[str]]:
    """The solve's error (F, R) mm measured at the capture's stabilization markers outside the
    layout (:func:`~.consistency.stabilization_residuals`; ``dense`` (F, M, 3) the solved markers),
    and their labels; None when the capture has none of them, or when its head poses were fitted
    to them frame by frame (their distance from the solve is then the pose fit's residual)."""
    layout = set(solver.layout_labels)
    labels = [label for label in solver.rigid_labels if label not in layout and label in capture.labels]
    if not labels or (poses is not None and not poses.still):
        return None, []
    solved = dense[:, [solver.labels.index(label) for label in labels]]
    return stabilization_residuals(solved, capture.positions[:, capture.index(labels)]), labels


def estimated_error(expected: np.ndarray, consistency: np.ndarray, training_mm: float, *,
                    measured: np.ndarray | None = None, n_outside: int = 0) -> np.ndarray:
    """Per frame the error the solve reports (mm) over the ``n_outside`` dense markers outside
    the layout: the model's expected error, raised where the layout markers agree less with each
    other than on the training session (consistency above ``training_mm``: a face or expression
    the model does not explain); where the error is ``measured`` (F, R) mm at some of those
    markers (:func:`measured_error`; NaN = not measured), their measured squares replace that
    estimate for their share of the markers."""
    excess = np.where(np.isfinite(consistency), consistency ** 2 - training_mm ** 2, 0.0) \
        if np.isfinite(training_mm) else np.zeros_like(expected)
    sq = expected ** 2 + CONSISTENCY_WEIGHT ** 2 * np.maximum(excess, 0.0)
    if measured is not None and n_outside >= measured.shape[1]:
        seen = np.isfinite(measured)
        total = np.where(seen, measured, 0.0) ** 2
        sq = (total.sum(axis=1) + (n_outside - seen.sum(axis=1)) * sq) / n_outside
    return np.sqrt(sq)


def _rms_rows(values: np.ndarray) -> np.ndarray:
    """Per row the RMS of the finite ``values`` (F, R) (NaN where none)."""
    seen = np.isfinite(values)
    total = np.where(seen, values, 0.0) ** 2
    count = seen.sum(axis=1)
    return np.where(count > 0, np.sqrt(total.sum(axis=1) / np.maximum(count, 1)), np.nan)


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, *,
               uv: np.ndarray | None = None) -> None:
    """The neutral mesh as OBJ (mm) with vertex normals, and texture coordinates when given."""
    from mocaptk.surface_mesh import vertex_normals

    normals = vertex_normals(vertices, faces)
    normals[~np.any(normals, axis=1)] = (0.0, 0.0, 1.0)
    lines = ["# mocaptk solve: neutral face mesh, mm"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in vertices]
    lines += [f"vn {x:.5f} {y:.5f} {z:.5f}" for x, y, z in normals]
    if uv is None:
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in np.asarray(faces) + 1]
    else:
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv]
        lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in np.asarray(faces) + 1]
    write_text(path, "\n".join(lines) + "\n")


def _summary(solver: FaceSolver, capture: Trajectories, source: Mapping[str, Any], *,
             solved: np.ndarray, error: np.ndarray, estimated: np.ndarray, consistency: np.ndarray,
             measured: np.ndarray, measured_labels: list[str], missing: np.ndarray,
             flagged: np.ndarray, poses: HeadPoses | None, mismatch: NeutralMismatch | None,
             adapted: bool, mesh: dict[str, Any], outputs: list[str], notes: list[str]) -> dict[str, Any]:
    lost_rate = missing.mean(axis=0) if len(missing) else np.zeros(missing.shape[1])
    head: dict[str, Any] = {"removed_and_restored": poses is not None and not poses.still,
                            "rigid_labels": list(solver.rigid_labels)}
    if poses is not None:
        head.update(pose_from=poses.source, pose_labels=list(poses.labels), still=poses.still,
                    pose_residual_mm=_stats(poses.residual_mm),
                    frames_without_pose=int((~np.isfinite(poses.rotations[:, 0, 0])).sum()),
                    pose_markers_dropped=int(poses.dropped.sum()))
    return {
        "format": SOLVE_FORMAT, "version": SOLVE_VERSION, "units": "mm",
        "capture": {"path": source.get("path"), "sha256": source.get("sha256"),
                    "frames": capture.n_frames, "rate": capture.rate},
        "session": solver.session,
        "model": {"kind": solver.model.kind, "layout_markers": list(solver.layout_labels),
                  "dense_markers": len(solver.labels),
                  "expected_error_all_present_mm": solver.model.error_base,
                  "training_consistency_mm": solver.training_consistency_mm},
        "head_motion": head,
        "frames": {"solved": int(solved.sum()), "unsolved": int((~solved).sum()),
                   "with_lost_markers": int(missing.any(axis=1).sum()),
                   "with_flagged_markers": int(flagged.any(axis=1).sum()),
                   "unsolved_frames": np.flatnonzero(~solved)[:100].tolist()},
        "missing_rate": {label: float(r) for label, r in zip(solver.layout_labels, lost_rate) if r > 0},
        "flagged_markers": int(flagged.sum()),
        "expected_error_mm": _stats(error),
        "consistency_mm": _stats(consistency),
        "estimated_error_mm": _stats(estimated),
        "measured_error_mm": {**_stats(measured), "markers": measured_labels},
        "neutral": {**(mismatch.as_dict() if mismatch is not None else {}), "adapted": adapted},
        "mesh": mesh,
        "outputs": outputs, "notes": notes,
    }


def _stats(values: np.ndarray) -> dict[str, float | None]:
    finite = values[np.isfinite(values)]
    return {"mean": float(finite.mean()) if finite.size else None,
            "p95": float(np.percentile(finite, 95)) if finite.size else None,
            "max": float(finite.max()) if finite.size else None}
