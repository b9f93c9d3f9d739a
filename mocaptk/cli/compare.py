"""``mocaptk compare``: every layout method at several marker counts, on one held-out metric."""

from __future__ import annotations

from pathlib import Path

import typer

from ..errors import OptionError
from .app import app
from .options import Quiet, Rate, Rigid, Units, rigid_labels
from .report import write_compare_report


def parse_counts(text: str) -> list[int]:
    """``"20,30,40"`` → [20, 30, 40] (OptionError on anything else)."""
    try:
        counts = [int(c) for c in text.split(",") if c.strip()]
    except ValueError:
        raise OptionError(f"--counts must be comma-separated whole numbers, got {text!r}") from None
    if not counts or min(counts) < 1:
        raise OptionError(f"--counts must be positive whole numbers, got {text!r}")
    return counts


@app.command()
def compare(
    session: Path = typer.Argument(..., help="Dense session file (C3D, Vicon CSV, TRC, generic CSV, npz)."),
    test: Path = typer.Option(None, "--test", help="Held-out performance (same markers): every method "
                              "runs on the whole session and is scored on it. Default: leave one take "
                              "of the session out at a time."),
    counts: str = typer.Option("20,30,40,60", "--counts", help="Marker counts to compare (comma-separated; "
                               "counts not below the session's marker count are skipped)."),
    methods: str = typer.Option(None, "--methods", help="Comma-separated methods (default: paper, random, "
                                "farthest-point, kmeans, qr, greedy, thin-shell, hybrid; also set-cover)."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: <session>_compare/ next to it)."),
    rig: str = typer.Option(None, "--rig", help="Camera rig the layouts are for: cara, room or a rig file; "
                            "the methods then avoid markers it sees badly or triangulates noisily (the "
                            "paper's rule ignores it; the score stays the held-out one)."),
    restarts: int = typer.Option(3, "--restarts", help="Random restarts of the thin-shell optimizer."),
    seed: int = typer.Option(0, "--seed", help="Seed of random layouts, k-means and restarts."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Skip removing rigid head motion "
                                      "(for already head-relative data)."),
    rigid: Rigid = None,
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Overwrite files in an existing output folder."),
    quiet: Quiet = False,
) -> None:
    """Held-out RMSE and p95 (mm), run time and layout statistics of every layout method at every count.

    Layout statistics (Zell & McDonnell, ε = 0.3 and 0.7): % of layout markers where no extreme
    frame of the session moves ≥ ε, and how many extreme frames no layout marker sees move ≥ ε.
    Writes compare.md, compare.json, rmse_vs_markers.png, layouts.png and report.html.
    """
    from rich.console import Console

    from ..atomic import claim_output, write_text
    from ..clustering.compare import (DEFAULT_METHODS, compare_methods, compare_plot, layout_gallery,
                                      rows_as_json, rows_as_markdown)
    from ..clustering.methods import method_names
    from ..clustering.neutral import max_displacement, neutral_pose
    from ..clustering.pipeline import load_session_and_test
    from ..jsonio import write_json

    count_list = parse_counts(counts)
    method_list = [m.strip() for m in methods.split(",") if m.strip()] if methods else list(DEFAULT_METHODS)
    unknown = [m for m in method_list if m not in method_names()]
    if unknown:
        raise OptionError(f"unknown method(s) {', '.join(unknown)} (choose from {', '.join(method_names())})")
    if restarts < 1:
        raise OptionError(f"--restarts must be >= 1, got {restarts}")
    if rig is not None:
        from ..clustering.pipeline import check_rig
        check_rig(rig, methods=())
    folder = out or session.with_name(session.stem + "_compare")
    targets = [folder / name for name in ("compare.md", "compare.json", "rmse_vs_markers.png", "layouts.png",
                                            "report.html")]
    from .cluster import OUT_HINT

    for target in targets:
        claim_output(target, force=force, hint=OUT_HINT)
    console = Console(stderr=True, quiet=quiet)
    traj, perf, source = load_session_and_test(session, test, stabilized=not no_stabilize,
                                               rate=rate, units=units, rigid=rigid_labels(rigid))
    with console.status("comparing") as status:
        rows = compare_methods(traj, test=perf, counts=count_list, methods=method_list, seed=seed,
                               options={"thin-shell": {"restarts": restarts}},
                               progress=lambda text: status.update(f"comparing: {text}"), rig=rig)
    protocol = (f"methods run on {session.name}, scored on {test.name}" if test is not None
                else f"leave one take out of {session.name}" if len(traj.takes) >= 2
                else f"5 contiguous blocks of {session.name}, one held out at a time")
    table = rows_as_markdown(rows)
    source["test"] = test.name if test is not None else None
    if rig is not None:
        protocol += f"; layouts chosen for the {rig} rig"
    write_text(targets[0], f"# Layout methods on {session.name}\n\nProtocol: {protocol}; held-out ridge "
               "reconstruction of every dense marker (mm); time = seconds per layout.\n\n" + table)
    write_json(targets[1], rows_as_json(rows, traj.labels, source=source, protocol=protocol))
    compare_plot(rows, targets[2], title=f"{session.name}: held-out RMSE")
    neutral = neutral_pose(traj.positions)
    layout_gallery(rows, neutral, max_displacement(traj.positions, neutral), targets[3])
    report = write_compare_report(targets[4], traj, rows, test=perf, protocol=protocol,
                                  summary=rows_as_markdown(rows, times=False))
    for row in rows:
        if row.error is not None:
            typer.echo(f"mocaptk: warning: {row.method} at {row.count} markers: {row.error}", err=True)
    if not quiet:
        typer.echo(table, nl=False)
        typer.echo(f"wrote {folder}/ ({report})")
