"""``mocaptk plan``: how a camera rig sees a layout's markers, and what losing each one costs."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet, Rate, Units


def default_session(layout_path: Path, layout) -> Path:
    """The session a layout was computed from: the file its ``source`` names, beside the layout's
    folder (where ``mocaptk cluster`` writes ``<session>_layout/``)."""
    from mocaptk.errors import InputFileError

    name = layout.source.get("path")
    candidate = layout_path.resolve().parent.parent / str(name) if name else None
    if candidate is None or not candidate.is_file():
        raise InputFileError(layout_path, f"its session {name!r} is not beside the layout folder; "
                             "give it with --session")
    return candidate


@app.command()
def plan(
    layout: Path = typer.Argument(..., metavar="LAYOUT", help="layout.json written by mocaptk cluster."),
    rig: str = typer.Option(..., "--rig", help="Camera rig: cara (head-mounted, 4 cameras), room "
                            "(10-camera ring), or a rig file (mocaptk JSON or Qualisys .qca.txt, "
                            "calibrated in the session's coordinates)."),
    session: Path = typer.Option(None, "--session", help="Dense session whose motion the rig films "
                                 "(default: the layout's source, beside its folder)."),
    noise: float = typer.Option(0.3, "--noise", metavar="MM", help="Detection noise of one marker "
                                "(mm, turned into px per rig as in mocaptk synth)."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: <layout folder>_plan/ beside "
                             "the layout's folder)."),
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Overwrite plan.json / plan.png in an existing folder."),
    quiet: Quiet = False,
) -> None:
    """Per layout marker: cameras that see it, triangulation error, and the risk of losing it.

    For each layout marker: % of frames seen by >= 2 cameras, expected triangulation error, the
    face's held-out RMSE when that marker is lost, and the risk it brings (plan.json, plan.png)."""
    from rich.console import Console

    from mocaptk.atomic import claim_output
    from mocaptk.acquisition.cameras import RIG_PRESETS
    from mocaptk.clustering.camera_cost import read_rig_file
    from mocaptk.clustering.layout import read_layout
    from mocaptk.clustering.neutral import max_displacement, neutral_pose
    from mocaptk.clustering.regions import face_frame
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.clustering.camera_cost import captured_cloud
    from mocaptk.clustering.plan import layout_neutral, layout_plane, layout_plan, plan_picture, plan_table
    from mocaptk.errors import InputFileError, OptionError
    from mocaptk.jsonio import write_json
    from .cluster import OUT_HINT
    from mocaptk.clustering.layout import layout_rigid_set

    if not noise >= 0:
        raise OptionError(f"--noise must be >= 0 mm, got {noise}")
    if rig not in RIG_PRESETS:
        read_rig_file(rig)  # a bad rig fails before the slow part
    lay = read_layout(layout)
    session = session or default_session(layout, lay)
    if not session.is_file():
        raise InputFileError(session, "no such file")
    folder = out or layout.resolve().parent.with_name(layout.resolve().parent.name + "_plan")
    targets = [claim_output(folder / name, force=force, hint=OUT_HINT) for name in ("plan.json", "plan.png")]
    traj, _ = load_session(str(session), rate=rate, units=units)
    stabilized = traj
    if lay.parameters.get("stabilized"):  # lost-marker errors on the session the layout was made from
        stabilized, _ = stabilize(traj, rigid=layout_rigid_set(lay))
    with Console(stderr=True, quiet=quiet).status(f"filming {len(lay.clusters)} layout markers through {rig}"):
        result = layout_plan(traj, lay, rig, stabilized=stabilized.positions, takes=traj.takes,
                             noise_mm=noise, layout_path=str(layout), session_name=session.name)
        result["layout"] = layout.name
        result["session"] = session.name
        cloud = captured_cloud(traj.positions, traj.labels, layout_plane(lay))[0]
        rest = neutral_pose(cloud)
        plan_picture(result, dict(zip(traj.labels, rest)), layout_neutral(lay),
                     frame=face_frame(rest, max_displacement(cloud, rest)), path=targets[1])
    write_json(targets[0], result, digits=5, force=True)
    if not quiet:
        typer.echo(plan_table(result), nl=False)
        typer.echo(f"wrote {targets[0]}\nwrote {targets[1]}")

