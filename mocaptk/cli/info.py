"""``mocaptk info FILE...``: what is in marker files (format, markers, frames, rate, gaps, takes)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from .app import app
from .options import Quiet, Rate, Units


def read_marker_file(path: Path, *, units: str | None, rate: float | None, strip_prefixes: bool = False):
    """Read ``path`` as every command does: ``--units`` for text files only and ``--rate`` for column
    CSV only; given for a file that declares its own (a C3D's POINT:UNITS, a TRC's rate), they are
    refused (OptionError), never silently ignored."""
    from mocaptk.acquisition.formats import read_trajectories

    return read_trajectories(path, units=units, rate=rate, strip_prefixes=strip_prefixes)


def summary(traj, path: Path) -> dict[str, Any]:
    """Plain-data description of a session (sizes, units, missing data, takes)."""
    stats = traj.gap_stats()
    worst = int(stats.longest_gap.argmax()) if traj.n_markers else 0
    longest = int(stats.longest_gap[worst]) if traj.n_markers else 0
    units = str(traj.metadata.get("original_units", "mm"))
    if traj.metadata.get("units_assumed"):
        units += " (assumed)"
    return {
        "path": str(path), "format": traj.metadata.get("format", "?"),
        "reader": traj.metadata.get("reader", "mocaptk"),  # C3D: "mocaptk" or "ezc3d" (fallback)
        "markers": traj.n_markers, "frames": traj.n_frames, "first_frame": traj.first_frame,
        "rate_hz": traj.rate, "duration_s": traj.duration, "units": units,
        "missing_percent": 100.0 * stats.total_missing_fraction,
        "longest_gap_frames": longest, "longest_gap_s": longest / traj.rate,
        "longest_gap_marker": traj.labels[worst] if longest else None,
        "takes": [t.as_dict() for t in traj.takes],
        **_point_counts(traj),
        "notes": list(traj.metadata.get("notes", [])),
    }


def _point_counts(traj) -> dict[str, int]:
    """Points in labelled columns and in unlabelled ones (``*N``; see ``mocaptk label``)."""
    import numpy as np

    from mocaptk.acquisition.labelling import is_unnamed

    seen = (~np.isnan(traj.positions).any(axis=2)).sum(axis=0)
    unnamed = np.array([is_unnamed(label) for label in traj.labels], dtype=bool)
    return {"labelled_points": int(seen[~unnamed].sum()), "unlabelled_points": int(seen[unnamed].sum())}


def _human(info: dict[str, Any]) -> str:
    takes = ", ".join(f"{t['name']} [{t['start']}-{t['end']})" for t in info["takes"]) or "none"
    gap = f"{info['longest_gap_frames']} frames ({info['longest_gap_s']:.3f} s)"
    if info["longest_gap_marker"]:
        gap += f", marker {info['longest_gap_marker']}"
    lines = [
        info["path"],
        f"  format       {info['format']}",
        f"  markers      {info['markers']}",
        f"  frames       {info['frames']} (first frame {info['first_frame']})",
        f"  rate         {info['rate_hz']:g} Hz",
        f"  duration     {info['duration_s']:.3f} s",
        f"  units        {info['units']} (read as mm)",
        f"  missing      {info['missing_percent']:.2f} %",
        f"  points       {info['labelled_points']:,} labelled, {info['unlabelled_points']:,} unlabelled",
        f"  longest gap  {gap}",
        f"  takes        {takes}",
    ]
    lines += [f"  note         {note}" for note in info["notes"]]
    return "\n".join(lines)


@app.command()
def info(
    files: list[Path] = typer.Argument(..., metavar="FILE", help="Marker files: C3D, Vicon CSV, TRC, column CSV, .npz."),
    as_json: bool = typer.Option(False, "--json", help="Print one deterministic JSON document instead of text."),
    units: Units = None,
    rate: Rate = None,
    quiet: Quiet = False,
) -> None:
    """Describe marker files: format, markers, frames, rate, duration, units, missing data, takes.

    A file that cannot be read is reported (one line on stderr, or an "error" entry with --json)
    and the others are still described; the exit code is then 2. With --quiet only the errors
    are printed (a check that files read: exit code 0 or 2).
    """
    from mocaptk.errors import MocaptkError
    from mocaptk.jsonio import dumps

    results: list[dict[str, Any]] = []
    failed = False
    for path in files:
        try:
            results.append(summary(read_marker_file(path, units=units, rate=rate), path))
        except MocaptkError as exc:
            failed = True
            results.append({"path": str(path), "error": str(exc)})
            if not as_json:
                typer.echo(f"mocaptk: error: {exc}", err=True)
    if as_json and not quiet:
        typer.echo(dumps({"format": "mocaptk-info", "version": 1, "files": results}), nl=False)
    elif not quiet and any("error" not in r for r in results):
        typer.echo("\n\n".join(_human(r) for r in results if "error" not in r))
    if failed:
        raise typer.Exit(2)
