"""``mocaptk batch PATTERN... --do COMMAND [its options] --out DIR``: one command on many sessions,
as Dask tasks on a local cluster or a studio farm, one summary across them."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from mocaptk.errors import OptionError

from .app import app
from .options import Quiet

COMMAND_NAMES = "cluster, evaluate, compare, info, solve"


@app.command(context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
def batch(
    tokens: list[str] = typer.Argument(None, metavar="PATTERN... [COMMAND OPTIONS]",
                                       help="Session files or glob patterns (quote them; ** recurses), "
                                            "then any options of the --do command (e.g. --factor 1.2)."),
    do: str = typer.Option(..., "--do", help=f"Command to run on every session: {COMMAND_NAMES}."),
    out: Path = typer.Option(..., "--out", help="Output folder: DIR/<session stem>/ holds what the single "
                             "command writes; DIR/batch.json and batch.md summarize every session."),
    scheduler: str = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                  help="A running Dask scheduler (tcp://host:8786), e.g. a studio farm; "
                                       "default: a local cluster of one worker process per core."),
    workers: int = typer.Option(None, "--workers", help="Worker processes of the local cluster "
                                "(default: one per core)."),
    timeout: float = typer.Option(3600.0, "--timeout", metavar="S",
                                  help="Kill a session still running after S seconds and report it failed "
                                       "(0: no limit)."),
    connect_timeout: float = typer.Option(10.0, "--connect-timeout", metavar="S",
                                          help="Give up on --scheduler if it does not answer within S s."),
    force: bool = typer.Option(False, "--force", help="Redo sessions whose inputs did not change and "
                               "whose outputs are complete (default: skip them)."),
    quiet: Quiet = False,
) -> None:
    """Run cluster / evaluate / compare / info / solve on every matching session (Dask; failures isolated).

    With --do solve the matched files are captures, solved with the layout of --layout L.json (or
    of "layout" in a capture's sidecar). A session's own options may sit beside it in <stem>.mocaptk.json (or mocaptk.json for its whole
    folder), e.g. {"regions": "anna_regions.json", "rigid": ["HEAD_1", "HEAD_2", "HEAD_3"]}; they
    override the batch line's. Exit code 0 when every session is done or skipped, 1 when some
    failed (see batch.md), 2 for a mistake in the batch itself. See docs/batch.md.
    """
    from rich.console import Console

    from mocaptk.batch import engine, sessions, summary

    if do not in sessions.COMMANDS:
        raise OptionError(f"--do must be one of {COMMAND_NAMES}, got {do!r}")
    if workers is not None and (workers < 1 or scheduler is not None):
        raise OptionError("--workers must be >= 1, and only sizes the local cluster (not --scheduler)")
    if timeout < 0 or connect_timeout <= 0:
        raise OptionError("--timeout must be >= 0 and --connect-timeout > 0 seconds")
    patterns, options = sessions.split_batch_line(do, list(tokens or []), base=Path.cwd())
    sessions.check_command_line(do, options)
    files = sessions.find_sessions(patterns)
    out = out.absolute()
    previous, note = summary.previous_records(out)
    console = Console(stderr=True, quiet=quiet)
    if note:
        console.print(f"mocaptk: note: {note}", highlight=False, soft_wrap=True)
    task_list = engine.tasks(files, command=do, out=out, options=options, force=force,
                             timeout=timeout or None, previous=previous)
    start = time.perf_counter()
    records: list[dict] = []
    with engine.dask_client(scheduler=scheduler, workers=workers,
                            connect_timeout=connect_timeout) as (client, where):
        retries = engine.scheduler_retries(client)
        if retries is not None and retries != engine.WORKER_DEATH_RETRIES:
            console.print(f"mocaptk: note: this scheduler retries a task whose worker died {retries} times "
                          f"(start it with DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=1 for one retry)",
                          highlight=False, soft_wrap=True)
        try:
            _run_with_progress(client, task_list, console=console, records=records)
        finally:  # even after Ctrl-C the finished sessions are recorded (a re-run skips them)
            done = {(r["session"], r["command"]) for r in records}
            run = {"command": do, "sessions": len(files), "cluster": where, "options": options,
                   "seconds": time.perf_counter() - start, "counts": summary.counts(records),
                   "interrupted": len(done) < len(files)}
            all_records = summary.merged(previous, records)
            json_path, md_path = summary.write_summary(out, all_records, run)
    if not quiet:
        this_run = [r for r in all_records if (r["session"], r["command"]) in done]
        typer.echo(summary.summary_markdown(this_run, run), nl=False)
        typer.echo(f"wrote {json_path} and {md_path}")
    if run["counts"]["failed"]:
        raise typer.Exit(1)


def _run_with_progress(client, task_list: list[dict], *, console, records: list[dict]) -> None:
    """Run the tasks with a progress bar (done / skipped / failed / running); ``records`` fills up
    as sessions finish."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from mocaptk.batch import engine, summary

    columns = (TextColumn("batch"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[tally]}"),
               TimeElapsedColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        bar = progress.add_task("batch", total=len(task_list), tally="starting")

        def update(finished: list[dict], running: int) -> None:
            records[:] = finished
            tally = summary.counts(finished)
            progress.update(bar, completed=len(finished),
                            tally=f"done {tally['done']}  skipped {tally['skipped']}  "
                                  f"failed {tally['failed']}  running {running}")

        engine.run_tasks(client, task_list, on_update=update)
