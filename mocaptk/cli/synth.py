"""``mocaptk synth OUT.c3d``: a synthetic dense facial capture with ground truth.

Face (ICT-FaceKit) → dense marker layout → per-region expression takes → cameras (2-D
detections with noise, occlusion, dropouts, ghosts) → triangulation → spike removal → short-gap
filling → OUT.
Beside OUT it writes ``<stem>_regions.json``, ``<stem>_takes.json``, ``<stem>_truth.npz`` and,
unless ``--performance 0``, a held-out performance ``<stem>_performance<ext>`` with its
``<stem>_performance_truth.npz``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet


def companion_paths(target: Path, *, performance: bool) -> dict[str, Path]:
    """Every file ``synth`` writes for ``target`` (by role)."""
    stem, folder = target.stem, target.parent
    paths = {"session": target, "regions": folder / f"{stem}_regions.json",
             "takes": folder / f"{stem}_takes.json", "session_truth": folder / f"{stem}_truth.npz"}
    if performance:
        paths["performance"] = folder / f"{stem}_performance{target.suffix}"
        paths["performance_truth"] = folder / f"{stem}_performance_truth.npz"
    return paths


def _parse_identity(text: str | None):
    """The --identity numbers, checked before the face model loads (its count is checked after)."""
    import numpy as np

    from mocaptk.errors import OptionError

    if text is None:
        return None
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise OptionError(f"--identity must be comma-separated numbers, got {text!r}") from None
    if not np.isfinite(values).all():
        raise OptionError(f"--identity must be finite numbers, got {text!r}")
    return values


@app.command()
def synth(
    target: Path = typer.Argument(..., metavar="OUT",
                                  help="Output session: .c3d (takes kept), .csv or .trc."),
    half: bool = typer.Option(True, "--half/--full",
                              help="Markers on one half of the face + midline (paper) or both."),
    rig: str = typer.Option("cara", "--rig", metavar="cara|room|none",
                            help="Capture through a head-mounted 4-camera rig (cara), a room "
                                 "ring (room), or directly with noise only (none)."),
    seed: int = typer.Option(0, "--seed", help="Random seed (layout, expressions, noise)."),
    layout_seed: int = typer.Option(None, "--layout-seed", help="Seed of the dense marker layout "
                                    "alone (default: --seed); one layout for several actors."),
    noise: float = typer.Option(0.3, "--noise", metavar="MM",
                                help="Detection noise in mm at the face (per camera in px "
                                     "through the rig; per axis with --rig none)."),
    head_motion: bool = typer.Option(False, "--head-motion",
                                     help="Add small rigid head motion (room rig or none; a "
                                          "head-mounted rig moves with the head)."),
    rotation: float = typer.Option(3.0, "--rotation", metavar="DEG",
                                   help="Peak head rotation per axis with --head-motion."),
    translation: float = typer.Option(5.0, "--translation", metavar="MM",
                                      help="Peak head translation per axis with --head-motion."),
    spacing: float = typer.Option(8.0, "--spacing", metavar="MM",
                                  help="Minimum marker spacing (8 mm: ≈ 140 half-face markers, "
                                       "median neighbour ≈ 9.3 mm)."),
    wide_zone: bool = typer.Option(False, "--wide-zone",
                                   help="Also place markers where rigs see badly: under the "
                                        "nose and chin, eyelids, inner lips."),
    expressions: int = typer.Option(8, "--expressions",
                                    help="Target expressions per region take."),
    rest: float = typer.Option(2.0, "--rest", metavar="S",
                               help="Neutral rest before each expression, seconds (±15%)."),
    hold: float = typer.Option(2.0, "--hold", metavar="S",
                               help="Expression duration incl. easing in/out, seconds (±15%)."),
    performance: float = typer.Option(30.0, "--performance", metavar="S",
                                      help="Length of the held-out performance; 0: none."),
    rate: float = typer.Option(0.0, "--rate", metavar="HZ",
                               help="Frame rate (0: the rig's, 60 Hz for cara and none)."),
    identity: str = typer.Option(None, "--identity", metavar="C1,C2,...",
                                 help="ICT-FaceKit identity coefficients (default generic face)."),
    gaps: float = typer.Option(1.0, "--gaps", metavar="PER_MIN",
                               help="With --rig none: random dropouts per marker per minute."),
    dropout: float = typer.Option(0.01, "--dropout",
                                  help="With a rig: fraction of 2-D detections lost."),
    ghosts: float = typer.Option(0.002, "--ghosts",
                                 help="With a rig: fraction of 2-D detections that are wrong."),
    max_gap: int = typer.Option(6, "--max-gap", metavar="FRAMES",
                                help="With a rig: fill gaps up to this long by cubic spline, "
                                     "as capture software does (0: no filling)."),
    model_path: Path = typer.Option(None, "--model", metavar="PATH",
                                    help="ICT-FaceKit FaceXModel .tar.xz or folder (default "
                                         "$MOCAPTK_ICT_FACEKIT or ../shared/data/...)."),
    images: Path = typer.Option(None, "--images", metavar="DIR",
                                help="Also render the session's first --image-frames frames per camera "
                                     "(DIR/markers, true 2-D positions beside) and ChArUco views "
                                     "(DIR/charuco); see docs/optics.md."),
    image_frames: int = typer.Option(120, "--image-frames", help="Frames rendered with --images."),
    unlabelled: Path = typer.Option(None, "--unlabelled", metavar="LABELLED",
                                    help="Instead: make a raw unlabelled capture of this labelled one "
                                         "(head motion, occlusions, ghosts, fragments; docs/label.md), "
                                         "with its truth <stem>_truth.npz."),
    clouds: bool = typer.Option(False, "--clouds", help="With --unlabelled: untracked per-frame clouds."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing outputs."),
    quiet: Quiet = False,
) -> None:
    """Simulate a dense facial marker capture (per-region takes) with ground truth."""
    if unlabelled is not None:
        return _unlabelled(unlabelled, target, seed=seed, clouds=clouds, force=force)
    from rich.console import Console

    from mocaptk.acquisition import synth_session as ss
    from mocaptk.acquisition.cameras import RIG_PRESETS
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.acquisition.gapfill import fill_gaps
    from mocaptk.acquisition.synth_layout import dense_layout
    from mocaptk.acquisition.triangulate import compile_notice
    from mocaptk.atomic import check_writable, claim_output
    from mocaptk.errors import OptionError

    if rig not in (*RIG_PRESETS, "none"):
        raise OptionError(f"--rig must be one of {', '.join((*RIG_PRESETS, 'none'))}, got {rig!r}")
    if head_motion and rig == "cara":
        raise OptionError("--head-motion needs --rig room or none: a head-mounted rig moves "
                          "with the head, so its data stay head-relative")
    if expressions < 1 or rest <= 0 or hold <= 0 or performance < 0 or rate < 0:
        raise OptionError("--expressions must be ≥ 1, --rest/--hold > 0, --performance/--rate ≥ 0")
    if noise < 0 or gaps < 0 or max_gap < 0 or not 0 <= dropout <= 1 or not 0 <= ghosts <= 1:
        raise OptionError("--noise/--gaps/--max-gap must be ≥ 0 and --dropout/--ghosts within "
                          "[0, 1]")
    if images is not None and (rig == "none" or image_frames < 1):
        raise OptionError("--images needs a camera rig (--rig cara or room) and --image-frames >= 1")
    identity_coefficients = _parse_identity(identity)
    fmt = output_format(target)
    paths = companion_paths(target, performance=performance > 0)
    for path in paths.values():
        check_writable(path, force=force)
    if images is not None:  # refused before the slow part, not after the session is written
        claim_output(images, force=force, folder=True)

    console = Console(stderr=True, quiet=quiet)
    with console.status("loading the ICT-FaceKit face model..."):
        model = load_face_model(model_path)
    if identity_coefficients is not None and len(identity_coefficients) != len(model.identity_names):
        raise OptionError(f"--identity must be {len(model.identity_names)} comma-separated numbers, "
                          f"got {identity!r}")
    camera_rig = None if rig == "none" else RIG_PRESETS[rig]()
    rate = rate or (camera_rig.rate if camera_rig is not None and camera_rig.rate else 60.0)
    layout = dense_layout(model, mode="half" if half else "full", spacing_mm=spacing,
                          seed=seed if layout_seed is None else layout_seed, wide=wide_zone)
    motion = {"head_motion": head_motion, "rotation_deg": rotation, "translation_mm": translation}
    makers = {"session": lambda: ss.dense_session(
        model, layout, seed=seed, identity_coefficients=identity_coefficients, rate=rate,
        expressions_per_take=expressions, rest_seconds=rest, expression_seconds=hold,
        noise_mm=noise, gaps_per_minute=gaps, **motion)}
    if performance > 0:
        makers["performance"] = lambda: ss.performance_session(
            model, layout, seed=seed, seconds=performance, identity_coefficients=identity_coefficients,
            rate=rate, noise_mm=noise, gaps_per_minute=gaps, **motion)
    truths = {}
    for role, make in makers.items():  # one session in memory at a time
        synthetic = make()
        truth = truths[role] = synthetic.truth
        traj = synthetic.trajectories
        if camera_rig is not None:
            del synthetic, traj  # the direct observation is replaced by the capture: free it first
            with console.status(f"capturing the {role} through the {rig} rig "
                                f"({truth.n_frames} frames)..."), compile_notice(
                    lambda message: console.print(f"mocaptk: {message}", highlight=False,
                                                  soft_wrap=True)):
                traj = ss.camera_capture(model, truth, camera_rig, noise_mm=noise,
                                         dropout=dropout, ghost_rate=ghosts, seed=seed)
            if max_gap > 0:
                traj, report = fill_gaps(traj, max_gap=max_gap, method="cubic")
                typer.echo(f"{role}: short gaps filled: {report.summary()}")
        write_trajectories(traj, paths[role], fmt=fmt, force=force)
        ss.save_ground_truth(truth, paths[f"{role}_truth"], force=force)
        squared, seen = ss.truth_errors(traj, truth)
        rmse = (squared / seen) ** 0.5 if seen else float("nan")
        typer.echo(f"wrote {paths[role]} ({traj.n_markers} markers, {traj.n_frames} frames, "
                   f"{traj.rate:g} Hz, {len(traj.takes)} takes); "
                   f"{1 - seen / max(traj.n_frames * traj.n_markers, 1):.2%} missing, "
                   f"RMSE vs truth {rmse:.3f} mm")
        del traj
    truth = truths["session"]
    if images is not None:
        from mocaptk.acquisition.synth_images import write_image_set

        with console.status(f"rendering images into {images}..."):
            typer.echo(write_image_set(images, model, truth, camera_rig, rig_name=rig,
                                       frames=image_frames, seed=seed, force=force))
    ss.write_regions_file(truth, paths["regions"], force=force)
    ss.write_takes_file(truth.takes, paths["takes"], force=force)
    counts = ", ".join(f"{region} {len(labels)}" for region, labels in truth.regions_dict().items())
    typer.echo(f"wrote {paths['regions']} ({counts}), {paths['takes']}, {paths['session_truth']}")


def _unlabelled(source: Path, target: Path, *, seed: int, clouds: bool, force: bool) -> None:
    """``synth OUT --unlabelled LABELLED``: the raw capture and its truth mapping."""
    from mocaptk.acquisition.formats import output_format, read_trajectories, write_trajectories
    from mocaptk.acquisition.synth_unlabelled import save_truth, unlabelled_capture
    from mocaptk.atomic import check_writable

    output_format(target)
    truth_path = target.parent / f"{target.stem}_truth.npz"
    for path in (target, truth_path):
        check_writable(path, force=force)
    raw = unlabelled_capture(read_trajectories(source), seed=seed, clouds=clouds)
    write_trajectories(raw.trajectories, target, force=force)
    save_truth(raw, truth_path, force=force)
    ghosts = int((raw.truth == -1).sum())
    typer.echo(f"wrote {target} ({raw.trajectories.n_markers} unlabelled columns, "
               f"{'clouds' if clouds else 'fragments'}, {ghosts} ghost points) and {truth_path}")
