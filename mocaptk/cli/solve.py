"""``mocaptk solve``: a production capture with the layout's markers only -> the whole face."""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.errors import InputFileError, OptionError

from .app import app
from .options import Quiet, Rate, Units, recorded_reading, session_path


def bake_solved_rig(layout, session, staging: Path, name: str, *, rigid, progress) -> None:
    """``mocaptk rig --animate``'s rig files in ``staging/rig/``, keyed with the solved dense
    markers (``staging/dense.c3d``; head-relative copy when head motion was removed)."""
    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.pipeline import rigid_reference, stabilize
    from mocaptk.retarget.build import Capture, write_rig_outputs
    from .rig import rig_options

    solved = read_c3d(staging / "dense.c3d")
    # into the session's head frame, the rig's
    relative = stabilize(solved, rigid=rigid, reference=rigid_reference(session, rigid))[0] \
        if rigid else solved
    write_rig_outputs(layout, session, staging / "rig", options=rig_options(4, None, False, 1),
                      formats=("json", "fbx", "glb"), title=f"solve {name}", force=True,
                      captures=[Capture(name, relative, solved if rigid else None)], progress=progress)


def parse_frame_range(text: str | None, option: str) -> range | None:
    """``FIRST:LAST`` (0-based, LAST excluded) as a range; None for None."""
    if text is None:
        return None
    try:
        first, last = (int(part) for part in text.split(":"))
    except ValueError:
        raise OptionError(f"{option} must be FIRST:LAST frame numbers, got {text!r}") from None
    if not 0 <= first < last:
        raise OptionError(f"{option} must name at least one frame (0 <= FIRST < LAST), got {text!r}")
    return range(first, last)


def summary_text(summary: dict) -> str:
    """What solve prints, and its report's side panel shows (from solve.json's ``summary``)."""
    frames, model = summary["frames"], summary["model"]
    mean = lambda key: summary[key]["mean"] if summary[key]["mean"] is not None else float("nan")  # noqa: E731
    lines = [f"solved {frames['solved']} of {summary['capture']['frames']} frames with {model['kind']} "
             f"({len(model['layout_markers'])} layout -> {model['dense_markers']} dense markers, mesh "
             f"{summary['mesh']['vertices']} vertices); {frames['with_lost_markers']} frames with "
             f"lost markers, {frames['with_flagged_markers']} with markers flagged as ghosts; error "
             f"mean {mean('estimated_error_mm'):.2f} mm estimated (model expected {mean('expected_error_mm'):.2f} mm, "
             f"layout-marker consistency {mean('consistency_mm'):.2f} mm vs "
             f"{model['training_consistency_mm']:.2f} mm in training"
             + (f", measured {mean('measured_error_mm'):.2f} mm at the stabilization markers "
                f"{', '.join(summary['measured_error_mm']['markers'])}"
                if summary.get("measured_error_mm", {}).get("mean") is not None else "") + ")"]
    if frames["unsolved"]:
        lines.append(f"warning: {frames['unsolved']} frames without any layout marker (or head pose) "
                     "are not solved (see solve_frames.csv)")
    return "\n".join(lines + [note if note.startswith("warning:") else f"note: {note}"
                             for note in summary["notes"]]) + "\n"


@app.command()
def solve(
    layout: Path = typer.Argument(..., metavar="LAYOUT", help="layout.json written by mocaptk cluster."),
    capture: Path = typer.Argument(..., metavar="CAPTURE", help="Production capture holding the layout's markers "
                                   "(C3D, CSV, TRC); other markers are ignored."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    session: Path = typer.Option(None, "--session", help="Dense session to train on (default: the "
                                 "one recorded in layout.json, looked up beside it)."),
    model: Path = typer.Option(None, "--model", help="A model.npz saved by an earlier solve "
                               "(must come from the layout's session)."),
    model_kind: str = typer.Option(None, "--model-kind", help="ridge-cv (default: its strength "
                                   "chosen on the session, docs/testbed.md), ridge, local-ridge, "
                                   "tapered-ridge, thin-shell, pdm-linear, pdm-biquadratic."),
    formats: str = typer.Option("npz,usd,glb", "--formats", help="Mesh outputs: npz (mesh_frames.npy), "
                                "usd, glb (a morph basis keyed per frame: any length); dense.c3d is "
                                "always written."),
    surface: str = typer.Option("face", "--surface", help="The mesh without --mesh: face (the "
                                "ICT-FaceKit face fitted to the actor: closed lips, blinking lids, "
                                "the whole face) or markers (the marker surface)."),
    no_face_parts: bool = typer.Option(False, "--no-face-parts", help="The default face's skin "
                                       "alone, without its eyeballs, teeth and mouth socket."),
    subdivisions: int = typer.Option(1, "--subdivisions", help="Subdivide the marker surface mesh "
                                     "this many times (0-4; 3 gives ~7,700 vertices)."),
    mesh: Path = typer.Option(None, "--mesh", help="Animate this face mesh (OBJ, PLY, glTF/GLB, STL, "
                              "OFF; any unit, Y up, facing +Z) instead of the marker surface: "
                              "aligned to the dense neutral as 'mocaptk rig --mesh' does."),
    landmarks: Path = typer.Option(None, "--landmarks", help="With --mesh: JSON as 'mocaptk rig "
                                   "--landmarks' (marker/vertex pairs for the alignment, the "
                                   "mesh's mouth and eye corners for its openings)."),
    ridge: float = typer.Option(1e-3, "--ridge", help="Ridge strength of the ridge models, relative "
                                "to the mean input variance (ridge-cv chooses its own)."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Do not remove head motion (the "
                                      "capture is already in the session's head frame)."),
    adapt_neutral: bool = typer.Option(False, "--adapt-neutral", help="Another actor (or another "
                                       "day): solve relative to the capture's own neutral, estimated "
                                       "from the whole capture (or from --neutral frames)."),
    neutral: str = typer.Option(None, "--neutral", metavar="FIRST:LAST", help="Capture frames at "
                                "rest (0-based, LAST excluded) giving the capture's neutral; implies "
                                "--adapt-neutral."),
    label: bool = typer.Option(False, "--label", help="CAPTURE is unlabelled (or its labels are not "
                               "trusted): label it first against the layout's markers in its session "
                               "(as mocaptk label --template layout.json)."),
    rig: bool = typer.Option(False, "--bake-rig", help="Also build the layout's face rig and bake the "
                             "solved capture onto its joints (DIR/rig/: rig.json/.fbx/.glb as "
                             "'mocaptk rig --animate' writes them; needs the session)."),
    rig_alias: bool = typer.Option(False, "--rig", hidden=True),  # the old spelling; --rig is a camera rig elsewhere
    rate: Rate = None,  # the capture's (default: the layout's session's, for a file of its kind)
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty folder."),
    quiet: Quiet = False,
) -> None:
    """Solve every dense marker and an animated face mesh from a capture of the layout's markers."""
    from rich.console import Console

    from mocaptk.atomic import claim_output
    from mocaptk.clustering.layout import check_members, read_layout
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.clustering.reconstruction_models import DEFAULT_KIND, MODEL_KINDS
    from mocaptk.jsonio import write_json
    from mocaptk.retarget.build import check_surface
    from mocaptk.retarget.solve import load_solver, train_solver
    from mocaptk.retarget.solve_outputs import SOLVE_FORMATS, write_solve_outputs
    from .cluster import staged_folder
    from mocaptk.clustering.layout import layout_rigid_set
    from .report import write_solve_report
    from .rig import parse_formats, read_landmarks

    rig = rig or rig_alias

    if model_kind is not None and model_kind not in MODEL_KINDS:
        raise OptionError(f"unknown --model-kind {model_kind!r} (choose from {', '.join(MODEL_KINDS)})")
    if model is not None and model_kind is not None:
        raise OptionError("--model-kind chooses a model to train; a --model file already has its kind")
    chosen = tuple(f for f in parse_formats(formats) if f != "none")
    rest = parse_frame_range(neutral, "--neutral")
    check_surface(surface)
    if landmarks is not None and mesh is None:
        raise OptionError("--landmarks needs --mesh (they name the mesh's vertices)")
    pairs = read_landmarks(landmarks) if landmarks is not None else None
    claim_output(out, force=force, folder=True)  # refused (read-only, exists) and locked before any work
    lay = read_layout(layout)
    rigid = None if no_stabilize else layout_rigid_set(lay)
    console = Console(stderr=True, quiet=quiet)
    with console.status("reading") as status:
        say = lambda text: status.update(text)  # noqa: E731
        capture_rate, capture_units = recorded_reading(lay, capture, rate=rate, units=units)
        traj, capture_source = load_session(str(capture), rate=capture_rate, units=capture_units)
        if model is not None:
            identity = {"sha256": lay.source.get("sha256")} if lay.source.get("sha256") else {}
            solver = load_solver(model, session=identity)
            unknown = [label for label in solver.layout_labels if label not in set(lay.labels)]
            if unknown:
                raise InputFileError(model, f"its layout markers are not the layout's: {', '.join(unknown[:5])}")
        else:
            path = session_path(layout, lay.source, session)
            say(f"reading the session {path.name}")
            # read as cluster read it (layout.json's source.reading): no --rate/--units again
            session_rate, session_units = recorded_reading(lay, path, rate=None, units=None)
            dense, source = load_session(str(path), rate=session_rate, units=session_units)
            if lay.source.get("sha256") and source["sha256"] != lay.source["sha256"]:
                raise InputFileError(path, f"is not the session {layout.name} was made from (sha256 differs)")
            check_members(lay, dense.labels, layout_path=layout, session_name=path.name)
            if rigid and lay.parameters.get("stabilized"):  # else the session is its own head frame
                dense, _ = stabilize(dense, rigid=rigid)
            say(f"training the {model_kind or DEFAULT_KIND} model")
            solver = train_solver(lay, dense, source, kind=model_kind or DEFAULT_KIND, ridge=ridge,
                                  rigid_labels=rigid or ())
        check_members(lay, solver.labels, layout_path=layout, session_name="the model's session"
                      if model is not None else path.name)
        if pairs:  # before the solve, and blamed on the landmarks file, not on --model
            from mocaptk.retarget.mesh_openings import CORNERS

            known = set(solver.labels)
            strange = [k for k in pairs if k not in CORNERS and k not in known]
            if strange:
                raise InputFileError(landmarks, f"not dense markers of the model: {', '.join(strange[:6])}")
        notes = []
        if label:
            from .label import label_for_layout

            say("labelling the capture")
            traj, line = label_for_layout(lay, layout, traj, session=dense if model is None else None,
                                          given=session)
            notes.append(line)
        uncaptured = [label for label in lay.labels if label not in set(solver.layout_labels)]
        notes += [f"{len(uncaptured)} layout markers the session never captured (mirrored twins of a "
                 f"half-face layout) take no part: {', '.join(uncaptured[:5])}"
                 + (" ..." if len(uncaptured) > 5 else "")] if uncaptured else []
        if rig and model is not None:
            raise OptionError("--bake-rig needs the session (it builds the rig on it): leave out --model")
        if rest is not None and rest.stop > traj.n_frames:
            raise OptionError(f"--neutral {neutral}: the capture has {traj.n_frames} frames")
        unknown = [f for f in chosen if f not in SOLVE_FORMATS]
        if unknown:
            raise OptionError(f"unknown --formats {', '.join(unknown)} (choose from {', '.join(SOLVE_FORMATS)})")
        with staged_folder(out, force=force) as staging:
            try:
                summary = write_solve_outputs(solver, traj, capture_source, staging, formats=chosen,
                                              subdivisions=subdivisions, mesh_path=mesh,
                                              landmarks=pairs,
                                              layout=lay, surface=surface,
                                              face_parts=not no_face_parts,
                                              stabilize=not no_stabilize,
                                              adapt=adapt_neutral or rest is not None,
                                              rest_frames=None if rest is None else list(rest),
                                              save_trained=model is None, notes=notes, progress=say)
            except OptionError as exc:  # the options were checked: with --model, the model's markers
                if model is None:
                    raise
                raise InputFileError(model, str(exc)) from None
            if rig:
                say("building the rig and baking the solve onto it")
                bake_solved_rig(lay, dense, staging, capture.stem, rigid=rigid, progress=say)
                summary["outputs"].append("rig/")
            say("writing report.html")
            try:
                report = write_solve_report(staging / "report.html", lay, solver, solved=staging / "dense.c3d",
                                            rigid=rigid, training=dense if model is None else None,
                                            summary=summary, text=summary_text(summary))
            except OptionError as exc:  # e.g. a model that solves no frame of some markers
                if model is None:
                    raise
                raise InputFileError(model, str(exc)) from None
            summary["outputs"] = sorted([*summary["outputs"], "report.html"])
            write_json(staging / "solve.json", summary)  # again: it lists rig/ and report.html now
    if not quiet:
        typer.echo(summary_text(summary) + report)
        typer.echo(f"wrote {out}/ ({', '.join(summary['outputs'])})")
