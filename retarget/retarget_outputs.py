"""``mocaptk retarget``'s pipeline and files (format ``mocaptk.retarget``, version 1; docs/retarget.md).

Fit (:func:`fit_retargeter`): the character placed on the actor's dense neutral
(:mod:`.correspondence`), the actor calibrated on the dense session (:mod:`.rom_calibration`).
Solve (:func:`retarget_capture`): the capture's layout markers, head pose removed with
``solve``'s machinery (:func:`mocaptk.retarget.solve.head_poses`), displacements from the
actor's neutral, weights chunk by chunk (:mod:`.weight_solve`). Files
(:func:`write_retarget_outputs`): ``weights.npz``, ``retarget.json``, ``blendshapes.csv``,
``calibration.npz`` and the character files.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk import __version__
from mocaptk.acquisition.stabilize import in_head_frame
from mocaptk.atomic import write_bytes, write_text
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.errors import InputFileError
from mocaptk.jsonio import dumps, write_json
from mocaptk.npz import npz_bytes
from mocaptk.trajectories import Trajectories

from .character import ARKIT_NAMES, Character
from .correspondence import Correspondence, correspond
from .gaze import eye_labels, gaze_angles
from .livelink_csv import livelink_csv, yaw_pitch_roll
from .motion_correspondence import refine_by_motion
from .rom_calibration import DEFAULT_PRIOR, Calibration, calibrate, side_ties
from .solve import CHUNK_FRAMES, POSE_FROM_LAYOUT, FaceSolver, head_poses, layout_frames, to_head_frame
from .weight_solve import DEFAULT_L1, DEFAULT_SMOOTH, solve_weights

__all__ = ["RETARGET_FORMAT", "Retargeter", "RetargetResult", "fit_retargeter", "load_calibration",
           "retarget_capture", "unseen_shapes", "write_retarget_outputs"]

RETARGET_FORMAT, RETARGET_VERSION = "mocaptk.retarget", 1
CALIBRATION_FORMAT = "mocaptk.retarget-calibration"
#: Character files ``--formats`` chooses from.
CHARACTER_FORMATS = ("glb", "usd", "fbx")
#: A shape moving no layout marker by this much (mm) is unseen by the layout (2.5x the 0.2 mm
#: marker noise of our captures): its weight cannot come from the capture.
UNSEEN_MM = 0.5


@dataclass(frozen=True, eq=False)
class Retargeter:
    """The character, where the actor's dense markers ``labels`` sit on it, and the actor's
    calibration (rows = ``labels``); ``axes`` (3, 3) the character's left, up, forward (columns)
    in the actor's head frame (None: unknown, no gaze)."""

    character: Character
    correspondence: Correspondence | None
    calibration: Calibration
    labels: tuple[str, ...]
    axes: np.ndarray | None = None


@dataclass(frozen=True)
class RetargetResult:
    """``weights`` (F, S); ``head`` (F, 3) yaw/pitch/roll radians (0 without a rigid set);
    ``residual_mm`` (F,); ``lost`` (F,) lost layout markers; ``layout_labels`` the markers used;
    ``eyes`` (F, 6) left then right eye yaw/pitch/roll radians (0 without eye markers) and
    ``eye_labels`` the eye markers used (:mod:`.gaze`); ``layout_motion_mm`` (S,) and
    ``dense_motion_mm`` (S,) each shape's largest marker motion at weight 1 over the layout's
    markers and over the session's (for :func:`unseen_shapes`)."""

    weights: np.ndarray
    head: np.ndarray
    residual_mm: np.ndarray
    lost: np.ndarray
    layout_labels: tuple[str, ...]
    eyes: np.ndarray
    eye_labels: dict[str, str]
    layout_motion_mm: np.ndarray
    dense_motion_mm: np.ndarray


def fit_retargeter(character: Character, session: Trajectories, *, prior: float = DEFAULT_PRIOR,
                   l1: float = DEFAULT_L1, reach: float | None = None, by_motion: bool = True) -> Retargeter:
    """Place ``character`` on the head-relative dense ``session`` and calibrate the actor on it
    (``reach``: the ROM's reach for the range alignment, :func:`.rom_calibration.calibrate`;
    ``by_motion``: the markers' places refined by their ROM motion, :mod:`.motion_correspondence`;
    False: the geometric places alone, as before)."""
    neutral = neutral_pose(session.positions)
    corr = correspond(character, neutral)
    if by_motion:
        corr = refine_by_motion(corr, character, session.positions, neutral, l1=l1)
    basis = corr.shape_basis(character)
    calibration = calibrate(session.positions, neutral, basis, side_ties(character.names, basis),
                            strength=prior, l1=l1, reach=reach)
    return Retargeter(character, corr, calibration, tuple(session.labels), corr.rotation)


def retarget_capture(retargeter: Retargeter, solver: FaceSolver, capture: Trajectories, path: str, *,
                     l1: float = DEFAULT_L1, smooth: float = DEFAULT_SMOOTH, stabilize: bool = True,
                     chunk: int = CHUNK_FRAMES, hold_unseen: bool = True) -> RetargetResult:
    """Weights of every frame of ``capture`` (its file ``path``, for messages).

    A shape that moves no layout marker by :data:`UNSEEN_MM` at weight 1 (:func:`unseen_shapes`:
    gaze without eye markers, lids without lid markers) is held at 0 (``hold_unseen``): its weight
    would only fit noise and what other shapes leave over.

    Poses from the layout's least-moving markers (no stabilization markers) take part of the
    expression for head motion (on the sample's still performance, 20 layout markers: up to 2.6°
    and 4 mm): they are refined with the expression (:func:`_joint_poses`), and dropped when the
    rig explains the capture better without them (:func:`_posed_fits_better`)."""
    x = layout_frames(solver, capture, path)  # raises when layout markers are missing
    poses = head_poses(solver, capture) if stabilize else None
    joint = poses is not None and poses.source == POSE_FROM_LAYOUT and not poses.still
    rows = np.array([retargeter.labels.index(label) for label in solver.layout_labels])
    basis, inverse = retargeter.calibration.tied_basis(rows)
    seen_motion = _largest_motion(basis)
    if hold_unseen:  # unobservable: held at 0 (a zero column keeps its start weight, 0)
        basis[seen_motion < UNSEEN_MM] = 0.0
    neutral = retargeter.calibration.neutral[rows]
    n_frames = capture.n_frames
    weights = np.zeros((n_frames, len(basis)))
    residual, lost = np.full(n_frames, np.nan), np.zeros(n_frames, dtype=np.int64)
    rotations = None if poses is None else np.array(poses.rotations, dtype=np.float64)
    translations = None if poses is None else np.array(poses.translations, dtype=np.float64)
    if joint and not _posed_fits_better(basis, neutral, x, rotations, translations, l1=l1):
        poses = replace(poses, rotations=np.broadcast_to(np.eye(3), rotations.shape).copy(),
                        translations=np.zeros_like(translations), still=True)
        rotations, translations, joint = poses.rotations, poses.translations, False
    previous = None
    for start in range(0, n_frames, chunk):
        part = slice(start, start + chunk)
        world = np.array(x[part], dtype=np.float64)
        if joint:
            rotations[part], translations[part] = _joint_poses(
                basis, neutral, world, rotations[part], translations[part], l1=l1, smooth=smooth,
                previous=previous)
        frames = world if poses is None else in_head_frame(world, rotations[part], translations[part])
        solved = solve_weights(basis, frames - neutral, l1=l1, smooth=smooth, previous=previous)
        weights[part], residual[part], lost[part] = solved.weights, solved.residual_mm, solved.lost
        previous = solved.weights[-1] if len(solved.weights) else previous
    head = np.zeros((n_frames, 3)) if poses is None else yaw_pitch_roll(rotations)
    if joint:  # the head-frame eye markers follow the refined poses
        poses = replace(poses, rotations=rotations, translations=translations)
    eyes, eye_markers = _gaze(retargeter, capture, poses)
    dense, _ = retargeter.calibration.tied_basis()
    return RetargetResult(weights[:, inverse], head, residual, lost, solver.layout_labels, eyes, eye_markers,
                          seen_motion[inverse], _largest_motion(dense)[inverse])


def _largest_motion(basis: np.ndarray) -> np.ndarray:
    """(S,) each shape's largest marker displacement (mm) in ``basis`` (S, M, 3), NaN rows skipped."""
    return np.nan_to_num(np.linalg.norm(basis, axis=2)).max(axis=1, initial=0.0)


def unseen_shapes(names: Sequence[str], result: RetargetResult) -> list[str]:
    """The shapes that move no layout marker by :data:`UNSEEN_MM` (a shape that moves no marker
    at all, a zero shape such as the generic rig's ``tongueOut``, left out), most-moving over the
    session's markers first: their weights cannot come from the capture (held at 0)."""
    unseen = [k for k in range(len(names)) if result.layout_motion_mm[k] < UNSEEN_MM and result.dense_motion_mm[k] > 0]
    return [names[k] for k in sorted(unseen, key=lambda k: -result.dense_motion_mm[k])]


def _unseen_note(names: Sequence[str], result: RetargetResult) -> list[str]:
    """A note naming :func:`unseen_shapes` (the first 3 with their motion), or none."""
    unseen = unseen_shapes(names, result)
    if not unseen:
        return []
    index = {name: k for k, name in enumerate(names)}
    listed = ", ".join(f"{n} {result.layout_motion_mm[index[n]]:.2f} mm (session {result.dense_motion_mm[index[n]]:.1f})"
                       for n in unseen[:3]) + (f" and {len(unseen) - 3} more" if len(unseen) > 3 else "")
    hint = (" (a layout with markers there can: cluster --method set-cover --character)"
            if any(result.dense_motion_mm[index[n]] >= UNSEEN_MM for n in unseen) else "")
    return [f"{len(unseen)} shapes move no layout marker by {UNSEEN_MM} mm: {listed}; the capture cannot show "
            f"them, so they are held at 0{hint}"]


#: Rounds of :func:`_joint_poses` (pose, then expression, then pose ...).
JOINT_POSE_ROUNDS = 3
#: Frames (evenly spread) on which :func:`_posed_fits_better` compares the two hypotheses.
POSE_TEST_FRAMES = 1000


def _posed_fits_better(basis: np.ndarray, neutral: np.ndarray, x: np.ndarray, rotations: np.ndarray,
                       translations: np.ndarray, *, l1: float) -> bool:
    """Whether the rig fits the capture's layout markers ``x`` (F, L, 3) better (median RMS
    residual) with the refined poses than with none: a head that did not move, seen through a few
    expression-moving markers, is better left unposed."""
    test = np.linspace(0, len(x) - 1, min(len(x), POSE_TEST_FRAMES)).astype(np.int64)
    world = np.array(x[test], dtype=np.float64)
    rot, trans = _joint_poses(basis, neutral, world, rotations[test].copy(), translations[test].copy(),
                              l1=l1, smooth=0.0, previous=None)
    posed = solve_weights(basis, in_head_frame(world, rot, trans) - neutral, l1=l1, smooth=0.0).residual_mm
    unposed = solve_weights(basis, world - neutral, l1=l1, smooth=0.0).residual_mm
    return bool(np.nanmedian(posed) < np.nanmedian(unposed))


def _joint_poses(basis: np.ndarray, neutral: np.ndarray, world: np.ndarray, rotations: np.ndarray,
                 translations: np.ndarray, *, l1: float, smooth: float, previous: np.ndarray | None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Head poses refined with the expression: alternately the weights in the current head frame,
    then each frame's pose as the rigid fit (all seen layout markers) of the rig's prediction
    ``neutral + A w`` onto the capture ``world`` (f, L, 3) mm. What the rig's shapes explain stays
    expression; only the rigid remainder is head motion. Frames the fit cannot pose keep theirs."""
    from mocaptk.acquisition.stabilize import kabsch

    seen = np.isfinite(world).all(axis=2)
    for _ in range(JOINT_POSE_ROUNDS):
        frames = in_head_frame(world, rotations, translations)
        w = solve_weights(basis, frames - neutral, l1=l1, smooth=smooth, previous=previous).weights
        predicted = neutral + np.einsum("fs,smc->fmc", w, basis)
        rot, trans = kabsch(predicted, np.where(seen[..., None], world, 0.0), seen.astype(float))
        ok = np.isfinite(rot).all(axis=(1, 2))
        rotations[ok], translations[ok] = rot[ok], trans[ok]
    return rotations, translations


def _gaze(retargeter: Retargeter, capture: Trajectories, poses) -> tuple[np.ndarray, dict[str, str]]:
    """(F, 6) eye yaw/pitch/roll from the capture's eye markers (:mod:`.gaze`), and their labels."""
    eyes = np.zeros((capture.n_frames, 6))
    found = eye_labels(capture.labels) if retargeter.axes is not None else {}
    for side, label in found.items():
        x = to_head_frame(capture.positions[:, capture.index([label])], poses)[:, 0]
        eyes[:, (0 if side == "left" else 3) + np.arange(2)] = gaze_angles(x, retargeter.axes)
    return eyes, found


def save_calibration(path: str | os.PathLike[str], retargeter: Retargeter,
                     session: Mapping[str, Any]) -> Path:
    """``calibration.npz``: the actor's shapes, neutral and ranges, for ``--calibration``."""
    cal = retargeter.calibration
    header = {"format": CALIBRATION_FORMAT, "version": RETARGET_VERSION, "session": dict(session),
              "shapes": list(retargeter.character.names), "labels": list(retargeter.labels)}
    return write_bytes(path, npz_bytes({
        "header": np.frombuffer(dumps(header).encode(), dtype=np.uint8),
        "basis": cal.basis.astype(np.float64), "neutral": cal.neutral, "ties": cal.ties.astype(np.int64),
        "rom_extreme": cal.rom_extreme, "stretch": cal.stretch,
        **({} if retargeter.axes is None else {"axes": np.asarray(retargeter.axes, dtype=np.float64)})}))


def load_calibration(path: str | os.PathLike[str], character: Character,
                     session_labels: Sequence[str]) -> Retargeter:
    """A saved calibration for ``character``; refused (InputFileError) when its shapes or
    markers differ."""
    import json

    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(bytes(data["header"]).decode())
            arrays = {k: data[k] for k in ("basis", "neutral", "ties", "rom_extreme", "stretch")}
            axes = data["axes"] if "axes" in data.files else None
    except (OSError, KeyError, ValueError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"not a mocaptk retarget calibration ({type(exc).__name__})") from None
    if header.get("format") != CALIBRATION_FORMAT:
        raise InputFileError(path, "not a mocaptk retarget calibration")
    shapes = header.get("shapes", [])
    if len(shapes) != len(character.names) or arrays["basis"].shape[0] != len(character.names):
        raise InputFileError(path, f"calibrated for {len(shapes)} shapes, the character has "
                             f"{len(character.names)}")
    if list(shapes) != list(character.names):
        raise InputFileError(path, "calibrated for other shape names than the character's")
    labels = tuple(header.get("labels", []))
    if arrays["basis"].shape[1] != len(labels) or not set(session_labels) <= set(labels):
        raise InputFileError(path, "calibrated on other markers than the session's")
    return Retargeter(character, None, Calibration(**arrays), labels, axes)


def arkit_columns(character: Character, weights: np.ndarray) -> np.ndarray:
    """(F, 52) weights in ARKit order (0 for ARKit shapes the character lacks)."""
    out = np.zeros((len(weights), len(ARKIT_NAMES)))
    for i, name in enumerate(character.arkit):
        if name is not None:
            out[:, ARKIT_NAMES.index(name)] = weights[:, i]
    return out


def write_retarget_outputs(retargeter: Retargeter, result: RetargetResult, capture: Trajectories,
                           capture_source: Mapping[str, Any], session: Mapping[str, Any],
                           staging: Path, *, options: Mapping[str, Any],
                           formats: Sequence[str] = CHARACTER_FORMATS, extra_outputs: Sequence[str] = (),
                           notes: Sequence[str] = (),
                           progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write the outputs into ``staging``; returns the summary written to ``retarget.json``."""
    say = progress or (lambda _: None)
    character = retargeter.character
    weights = result.weights.astype(np.float32)
    say("writing weights.npz, blendshapes.csv")
    write_bytes(staging / "weights.npz", npz_bytes({
        "format": np.array(RETARGET_FORMAT), "version": np.array(RETARGET_VERSION),
        "names": np.array(character.names), "weights": weights, "rate": np.array(capture.rate),
        "head_yaw_pitch_roll": result.head.astype(np.float32),
        "eyes_yaw_pitch_roll": result.eyes.astype(np.float32),
        "residual_mm": result.residual_mm.astype(np.float32), "lost": result.lost}))
    write_text(staging / "blendshapes.csv", livelink_csv(arkit_columns(character, weights), capture.rate,
                                                          head=result.head, eyes=result.eyes))
    save_calibration(staging / "calibration.npz", retargeter, session)
    written = ["weights.npz", "blendshapes.csv", "calibration.npz", "retarget.json", *extra_outputs]
    if formats:
        from .export_character import write_character_files
        written += write_character_files(staging, character, weights, capture.rate, formats=formats,
                                         progress=say)
    summary = _summary(retargeter, result, capture, capture_source, session, options=options,
                       outputs=sorted(written), notes=notes)
    write_json(staging / "retarget.json", summary)
    return summary


def write_renders(staging: Path, retargeter: Retargeter, solver: FaceSolver, capture: Trajectories,
                  result: RetargetResult, *, stabilize: bool = True) -> list[str]:
    """``retarget_frames.png`` (actor = solved dense markers, beside the character at rest, widest
    jaw, strongest smile, blink) and ``correspondence.png``; returns the names written."""
    from mocaptk.surface_mesh import marker_surface_mesh

    from .retarget_renders import pick_frames, render_correspondence, render_frames
    from .solve import solve_chunks

    character = retargeter.character
    picks = pick_frames(character.names, result.weights)
    frames = np.array(list(picks.values()))
    x = layout_frames(solver, capture, "capture")[frames]
    poses = head_poses(solver, capture) if stabilize else None
    sub = None if poses is None else poses.select(frames)
    dense = next(solve_chunks(solver, x, sub)).positions
    if sub is not None:  # show the actor head-relative, as the character is
        dense, x = to_head_frame(dense, sub), to_head_frame(x, sub)
    neutral = retargeter.calibration.neutral
    seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
    _, faces = marker_surface_mesh(neutral[seen])
    render_frames(staging / "retarget_frames.png", actor_faces=np.asarray(faces), actor=dense[:, seen],
                  layout=x, character=character, weights=result.weights[frames],
                  titles=[f"{title} (frame {frame})" for title, frame in picks.items()])
    written = ["retarget_frames.png"]
    if retargeter.correspondence is not None:
        points = retargeter.correspondence.points(character.vertices, character.faces)
        rows = [retargeter.labels.index(label) for label in result.layout_labels]
        render_correspondence(staging / "correspondence.png", character=character, points=points,
                              layout=points[rows])
        written.append("correspondence.png")
    return written


def write_report_page(path: Path, retargeter: Retargeter, solver: FaceSolver, layout, capture: Trajectories,
                      result: RetargetResult, *, summary: str, title: str,
                      stabilize: bool = True) -> tuple[Path, int, list[dict]]:
    """``report.html``: the actor (the capture's solved dense markers, head-relative) beside the
    character driven by the weights, replayed, and the weights as curves. Returns (path, bytes,
    the page's clips)."""
    from .report import replay_step, retarget_report, write_report
    from .report.scene import REPLAY_BUDGET_BYTES
    from .solve import solve_chunks

    step = replay_step(capture.rate, capture.n_frames, len(solver.labels), budget_bytes=REPLAY_BUDGET_BYTES)
    frames = np.arange(0, capture.n_frames, step)
    x = layout_frames(solver, capture, "capture")[frames]
    poses = head_poses(solver, capture) if stabilize else None
    sub = None if poses is None else poses.select(frames)
    dense = np.concatenate([c.positions for c in solve_chunks(solver, x, sub)])
    if sub is not None:  # the actor head-relative, as the character is
        dense = to_head_frame(dense, sub)
    solved = Trajectories(dense, solver.labels, capture.rate, metadata={"replay": (step, capture.n_frames)})
    cal = retargeter.calibration
    table = [["character", retargeter.character.source],
             ["shapes", f"{len(retargeter.character.names)} ({sum(1 for w in result.weights.max(axis=0, initial=0) if w > 0.1)} above 0.1)"],
             ["layout markers", len(result.layout_labels)],
             ["frames with lost markers", int((result.lost > 0).sum())],
             ["fit residual mean", f"{np.nanmean(result.residual_mm):.2f} mm" if np.isfinite(result.residual_mm).any() else "–"],
             ["shapes stretched by the ROM", int(np.sum(np.abs(cal.stretch - 1) > 1e-9))],
             ["eye markers", ", ".join(f"{k}: {v}" for k, v in sorted(result.eye_labels.items())) or "none (gaze 0)"]]
    data = retarget_report(layout, solved, character=retargeter.character, weights=result.weights, table=table,
                           summary=summary, title=title)
    written, size = write_report(path, data)
    return written, size, data["clips"]


def _summary(retargeter: Retargeter, result: RetargetResult, capture: Trajectories,
             capture_source: Mapping[str, Any], session: Mapping[str, Any], *,
             options: Mapping[str, Any], outputs: list[str], notes: Sequence[str]) -> dict[str, Any]:
    character, cal, corr = retargeter.character, retargeter.calibration, retargeter.correspondence
    unseen = set(unseen_shapes(character.names, result))
    shapes = [{"name": name, "arkit": arkit, "rom_extreme": float(cal.rom_extreme[i]),
               "stretch": float(cal.stretch[i]),
               "layout_motion_mm": round(float(result.layout_motion_mm[i]), 4), "observed": name not in unseen,
               "follows": None if cal.ties[i] == i else character.names[int(cal.ties[i])],
               "max_weight": float(result.weights[:, i].max()) if len(result.weights) else 0.0}
              for i, (name, arkit) in enumerate(zip(character.names, character.arkit))]
    return {
        "format": RETARGET_FORMAT, "version": RETARGET_VERSION, "generator": f"mocaptk {__version__}",
        "capture": {"path": capture_source.get("path"), "sha256": capture_source.get("sha256"),
                    "frames": capture.n_frames, "rate": capture.rate},
        "session": dict(session),
        "character": {"source": character.source, "vertices": int(len(character.vertices)),
                      "triangles": int(len(character.faces)), "shapes": len(character.names)},
        "correspondence": None if corr is None else {
            "scale": corr.scale, "fit_rms_mm": corr.fit_rms_mm, "bent_rms_mm": corr.bent_rms_mm,
            "motion_coverage": corr.coverage},
        "options": dict(options),
        "layout_markers": list(result.layout_labels),
        "eye_markers": dict(sorted(result.eye_labels.items())),
        "shapes": shapes,
        "frames": {"lost_markers": result.lost.tolist(),
                   "residual_mm": [None if not np.isfinite(r) else round(float(r), 4)
                                   for r in result.residual_mm],
                   "with_lost_markers": int((result.lost > 0).sum()),
                   "without_markers": int((~np.isfinite(result.residual_mm)).sum())},
        "outputs": outputs,
        "notes": [*notes, *_unseen_note(character.names, result)],
    }
