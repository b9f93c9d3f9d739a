"""``mocaptk compare``: every layout method at several marker counts, on one held-out metric."""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.errors import OptionError, warn

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
    sessions: list[Path] = typer.Argument(..., metavar="SESSION", help="Dense session file (C3D, "
                                          "Vicon CSV, TRC, generic CSV, npz); several: one actor each, "
                                          "one shared layout (registered to the first)."),
    tests: list[Path] = typer.Option(None, "--test", help="Held-out performance (same markers): every "
                                     "method runs on the whole session and is scored on it; one per "
                                     "session. Default: leave one take of the session out at a time."),
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
    """Held-out RMSE and p95 (mm), run time and layout statistics of every method at every count.

    Layout statistics (Zell & McDonnell, ε = 0.3 and 0.7): % of layout markers where no extreme
    frame of the session moves ≥ ε, and how many extreme frames no layout marker sees move ≥ ε.
    Writes compare.md, compare.json, rmse_vs_markers.png, layouts.png and report.html. With several
    sessions (actors): per actor the held-out error of one layout chosen on all actors' evidence
    beside the actor's own layout (compare.md, compare.json).
    """
    from rich.console import Console

    from mocaptk.atomic import claim_output, write_text
    from mocaptk.clustering.compare import (DEFAULT_METHODS, compare_methods, compare_plot, layout_gallery,
                                      rows_as_json, rows_as_markdown)
    from mocaptk.clustering.methods import method_names
    from mocaptk.clustering.neutral import max_displacement, neutral_pose
    from mocaptk.clustering.pipeline import load_session_and_test
    from mocaptk.jsonio import write_json

    count_list = parse_counts(counts)
    method_list = [m.strip() for m in methods.split(",") if m.strip()] if methods else list(DEFAULT_METHODS)
    unknown = [m for m in method_list if m not in method_names()]
    if unknown:
        raise OptionError(f"unknown method(s) {', '.join(unknown)} (choose from {', '.join(method_names())})")
    if restarts < 1:
        raise OptionError(f"--restarts must be >= 1, got {restarts}")
    if rig is not None:
        from mocaptk.clustering.pipeline import check_rig
        check_rig(rig, methods=())
    session, test = sessions[0], tests[0] if tests else None
    folder = out or session.with_name(session.stem + "_compare")
    if len(sessions) > 1:
        if rig is not None:
            raise OptionError("--rig takes one session; several sessions (actors) with a rig are not supported")
        return compare_actors_command(sessions, tests or None, folder, counts=count_list,
                                      methods=method_list, seed=seed, restarts=restarts,
                                      stabilized=not no_stabilize, rigid=rigid_labels(rigid), rate=rate,
                                      units=units, force=force, quiet=quiet)
    if tests and len(tests) > 1:
        raise OptionError(f"give one --test per session (1 session, {len(tests)} --test)")
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
    finish(rows, table, f"wrote {folder}/ ({report})", quiet=quiet)


def compare_actors_command(sessions: list[Path], tests: list[Path] | None, folder: Path, *, counts: list[int],
                           methods: list[str], seed: int, restarts: int, stabilized: bool, rigid, rate, units,
                           force: bool, quiet: bool) -> None:
    """``compare`` of several actors: the shared layout against each actor's own (compare.md/.json)."""
    from rich.console import Console

    from mocaptk.atomic import claim_output, write_text
    from mocaptk.clustering.multi_actor import actor_rows_as_json, actor_rows_as_markdown, compare_actors, load_actors
    from mocaptk.jsonio import write_json
    from .cluster import OUT_HINT

    targets = [folder / "compare.md", folder / "compare.json"]
    for target in targets:
        claim_output(target, force=force, hint=OUT_HINT)
    actors, held, registrations, sources = load_actors(sessions, tests, stabilized=stabilized, rate=rate,
                                                       units=units, rigid=rigid)
    console = Console(stderr=True, quiet=quiet)
    with console.status("comparing") as status:
        rows = compare_actors(actors, list(registrations), tests=held, counts=counts, methods=methods,
                              seed=seed, options={"thin-shell": {"restarts": restarts}},
                              progress=lambda text: status.update(f"comparing: {text}"))
    protocol = ("layouts chosen on the sessions, scored on each actor's --test" if tests
                else "leave one take of an actor out (the shared layout sees every other take of every actor)")
    registered = "; ".join(f"{name} by {r.by} (scale {r.transform.scale:.3f}, residual {r.residual_mm:.2f} mm)"
                           for name, r in registrations.items())
    table = actor_rows_as_markdown(rows)
    write_text(targets[0], f"# One layout for {len(actors)} actors\n\nProtocol: {protocol}; per actor, the "
               "held-out ridge reconstruction of every dense marker (mm), fitted on that actor's training "
               "frames: the shared layout (chosen on every actor's training data pooled) / the actor's own "
               f"layout (the same method on that actor alone).\n\nRegistered to {sessions[0].name}: "
               f"{registered}.\n\n" + table)
    data = actor_rows_as_json(rows, actors[0].labels, registrations=registrations, protocol=protocol)
    data["source"] = sources
    write_json(targets[1], data)
    finish(rows, table, f"wrote {folder}/", quiet=quiet)


def finish(rows, table: str, wrote: str, *, quiet: bool) -> None:
    """A warning per row a method could not produce, then the table and what was written."""
    for row in rows:
        if row.error is not None:
            warn(f"{row.method} at {row.count} markers: {row.error}")
    if not quiet:
        typer.echo(table, nl=False)
        typer.echo(wrote)
