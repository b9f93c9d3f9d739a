"""``mocaptk convert IN OUT``: between C3D, Vicon CSV and TRC (output format from OUT's extension)."""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.errors import warn

from .app import app
from .options import Quiet, Rate, Units


@app.command()
def convert(
    source: Path = typer.Argument(..., metavar="SOURCE", help="Input marker file (C3D, Vicon CSV, TRC, column CSV, .npz)."),
    target: Path = typer.Argument(..., metavar="TARGET", help="Output file: .c3d, .csv (Nexus style) or .trc."),
    force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists."),
    units: Units = None,
    rate: Rate = None,
    strip_prefixes: bool = typer.Option(False, "--strip-prefixes",
                                        help="Drop 'Subject:' prefixes from marker labels."),
    quiet: Quiet = False,
) -> None:
    """Convert a marker file; the output is written atomically (never a partial file)."""
    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.atomic import claim_output
    from .info import read_marker_file

    fmt = output_format(target)
    claim_output(target, force=force)  # fail before the (possibly long) read
    traj = read_marker_file(source, units=units, rate=rate, strip_prefixes=strip_prefixes)
    write_trajectories(traj, target, fmt=fmt, force=force)
    if not quiet:
        typer.echo(f"wrote {target} ({fmt}: {traj.n_markers} markers, {traj.n_frames} frames, {traj.rate:g} Hz)")
    if traj.takes and fmt == "trc":
        warn(f"TRC has no place for takes; {len(traj.takes)} takes not written")
