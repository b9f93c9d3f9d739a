"""``mocaptk retarget``: a capture of the layout's markers -> a blendshape character's weights."""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.errors import InputFileError, OptionError

from .app import app
from .options import Quiet, Rate, Units, recorded_reading


def summary_text(summary: dict) -> str:
    """What retarget prints (from retarget.json)."""
    frames, shapes = summary["frames"], summary["shapes"]
    moving = sum(1 for s in shapes if s["max_weight"] > 0.1)
    blind = sum(1 for s in shapes if not s.get("observed", True))
    lines = [f"retargeted {summary['capture']['frames']} frames onto {summary['character']['source']} "
             f"({len(shapes)} shapes, {moving} above 0.1"
             + (f", {blind} unobserved by the layout, held at 0" if blind else "")
             + f") from {len(summary['layout_markers'])} layout markers; "
             f"{frames['with_lost_markers']} frames with lost markers"]
    if frames["without_markers"]:
        lines.append(f"warning: {frames['without_markers']} frames without any layout marker hold "
                     "the previous weights")
    return "\n".join(lines + [f"note: {note}" for note in summary["notes"]]) + "\n"


@app.command()
def retarget(
    layout: Path = typer.Argument(..., metavar="LAYOUT", help="layout.json written by mocaptk cluster."),
    capture: Path = typer.Argument(..., metavar="CAPTURE", help="Production capture holding the layout's markers "
                                   "(C3D, CSV, TRC); other markers are ignored."),
    character: str = typer.Option(..., "--character", help="arkit (the bundled generic ARKit-52 "
                                  "face), or a .glb/.gltf with morph targets, a binary .fbx "
                                  "with blend shapes, or a .usd with UsdSkel blend shapes."),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    session: Path = typer.Option(None, "--session", help="Dense range-of-motion session (default: "
                                 "the one recorded in layout.json, looked up beside it)."),
    calibration: Path = typer.Option(None, "--calibration", help="calibration.npz of an earlier "
                                     "retarget onto the same character (skips the fit)."),
    l1: float = typer.Option(None, "--l1", help="Sparsity weight (unitless, default 0.001)."),
    smooth: float = typer.Option(None, "--smooth", help="Temporal smoothness weight (unitless, "
                                 "default 0.05)."),
    prior: float = typer.Option(None, "--prior", help="Pull of the actor's calibrated shapes "
                                "towards the character's (default 1)."),
    rom_reach: float = typer.Option(None, "--rom-reach", metavar="Q", help="The ROM performs every shape "
                                    "to Q of its range (Ribera's full protocol: 1): each shape it performs "
                                    "is scaled so its extreme is Q. Off by default (the character's amplitude, "
                                    "stretched only where the ROM goes past 1): right only for a ROM that "
                                    "takes each shape to Q; ours do not, and it loses (docs/retarget.md)."),
    formats: str = typer.Option("glb,usd,fbx", "--formats", help="Character files: glb, usd, fbx "
                                "(or none)."),
    renders: bool = typer.Option(True, "--renders/--no-renders", help="Write retarget_frames.png "
                                 "(actor beside character at rest, widest jaw, smile, blink) and "
                                 "correspondence.png."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Do not remove head motion even "
                                      "if the layout was made on stabilized data."),
    label: bool = typer.Option(False, "--label", help="CAPTURE is unlabelled: label it first (as solve --label)."),
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty folder."),
    quiet: Quiet = False,
) -> None:
    """Blendshape weights of a character (ARKit 52 or its own shapes) from a capture.

    Calibrated on the actor's range of motion; Live Link Face CSV, glTF, USD and FBX out."""
    from rich.console import Console

    from mocaptk.atomic import staged_folder
    from mocaptk.clustering.layout import read_layout
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.retarget.character_files import load_character
    from mocaptk.retarget.retarget_outputs import (CHARACTER_FORMATS, fit_retargeter, load_calibration,
                                                   retarget_capture, write_renders, write_report_page,
                                                   write_retarget_outputs)
    from mocaptk.retarget.rom_calibration import DEFAULT_PRIOR
    from mocaptk.retarget.solve import train_solver
    from mocaptk.retarget.weight_solve import DEFAULT_L1, DEFAULT_SMOOTH
    from mocaptk.clustering.layout import layout_rigid_set
    from .report import report_line
    from .rig import parse_formats
    from .options import session_path

    options = {"l1": DEFAULT_L1 if l1 is None else l1, "smooth": DEFAULT_SMOOTH if smooth is None else smooth,
               "prior": DEFAULT_PRIOR if prior is None else prior}
    for name, value in options.items():
        if not value >= 0 or value == float("inf"):
            raise OptionError(f"--{name} must be a finite number >= 0, got {value}")
    chosen = tuple(f for f in parse_formats(formats) if f != "none")
    unknown = [f for f in chosen if f not in CHARACTER_FORMATS]
    if unknown:
        raise OptionError(f"unknown --formats {', '.join(unknown)} (choose from {', '.join(CHARACTER_FORMATS)})")
    if rom_reach is not None and not 0 < rom_reach <= 1:
        raise OptionError(f"--rom-reach must be in (0, 1], got {rom_reach}")
    options["rom_reach"] = rom_reach  # None: the character's amplitude
    if calibration is not None and (prior is not None or rom_reach is not None):
        raise OptionError("--prior and --rom-reach are calibration options; a --calibration file is "
                          "already calibrated")
    lay = read_layout(layout)
    rigid = None if no_stabilize else layout_rigid_set(lay)
    console = Console(stderr=True, quiet=quiet)
    with console.status("reading") as status:
        say = lambda text: status.update(text)  # noqa: E731
        char = load_character(character)
        traj, capture_source = load_session(str(capture), rate=rate, units=units)
        path = session_path(layout, lay.source, session)
        say(f"reading the session {path.name}")
        session_rate, session_units = recorded_reading(lay, path, rate=None, units=None)
        dense, source = load_session(str(path), rate=session_rate, units=session_units)  # as cluster read it
        if lay.source.get("sha256") and source["sha256"] != lay.source["sha256"]:
            raise InputFileError(path, f"is not the session {layout.name} was made from (sha256 differs)")
        if rigid and lay.parameters.get("stabilized"):  # else the session is its own head frame
            dense, _ = stabilize(dense, rigid=rigid)
        solver = train_solver(lay, dense, source, kind="ridge", rigid_labels=rigid or ())
        if label:
            from .label import label_for_layout

            traj, line = label_for_layout(lay, layout, traj, session=dense)
            console.print(f"note: {line}", markup=False, highlight=False)
        if calibration is not None:
            retargeter = load_calibration(calibration, char, dense.labels)
        else:
            say("placing the character on the actor and calibrating on the session")
            retargeter = fit_retargeter(char, dense, prior=options["prior"], l1=options["l1"], reach=rom_reach)
        say("solving the weights")
        result = retarget_capture(retargeter, solver, traj, str(capture), l1=options["l1"],
                                  smooth=options["smooth"], stabilize=not no_stabilize)
        identity = {"path": source.get("path"), "sha256": source.get("sha256")}
        with staged_folder(out, force=force) as staging:
            pictures = []
            if renders:
                say("rendering the actor beside the character")
                pictures = write_renders(staging, retargeter, solver, traj, result, stabilize=not no_stabilize)
            summary = write_retarget_outputs(retargeter, result, traj, capture_source, identity, staging,
                                             options=options, formats=chosen,
                                             extra_outputs=[*pictures, "report.html"], progress=say)
            say("writing report.html")
            _, size, clips = write_report_page(
                staging / "report.html", retargeter, solver, lay, traj, result, summary=summary_text(summary),
                title=f"mocaptk retarget: {capture.name} onto {char.source}", stabilize=not no_stabilize)
    if not quiet:
        typer.echo(summary_text(summary) + report_line(out / "report.html", size, clips) + "\n"
                   + f"wrote {out}/ ({', '.join(summary['outputs'])})")
