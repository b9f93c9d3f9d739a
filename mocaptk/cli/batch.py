"""``mocaptk batch PATTERN... --do COMMAND [its options] --out DIR``: one command on many sessions,
as Dask tasks on a local cluster or a studio farm, one summary across them."""

from __future__ import annotations

import contextlib
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import typer

from mocaptk.errors import OptionError

from .app import app
from .options import Quiet

COMMAND_NAMES = "cluster, evaluate, compare, info, solve, label"
#: exit codes of a batch stopped by Ctrl-C / SIGTERM (128 + the signal, as a shell reports it)
STOPPED_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}


@app.command(context_settings={"ignore_unknown_options": True, "allow_extra_args": True})
def batch(
    tokens: list[str] = typer.Argument(None, metavar="PATTERN... [COMMAND OPTIONS]",
                                       help="Session files or glob patterns (quote them; ** recurses), "
                                            "then any options of the --do command (e.g. --factor 1.2)."),
    do: str = typer.Option(..., "--do", help=f"Command to run on every session: {COMMAND_NAMES}."),
    out: Path = typer.Option(..., "--out", help="Output folder: DIR/<session stem>/ holds what the single "
                             "command writes (and its log.txt); DIR/batch.json and batch.md summarize "
                             "every session."),
    scheduler: str = typer.Option(None, "--scheduler", metavar="ADDRESS",
                                  help="A running Dask scheduler (tcp://host:8786), e.g. a studio farm; "
                                       "default: a local cluster of one worker process per core."),
    scheduler_file: Path = typer.Option(None, "--scheduler-file", metavar="PATH",
                                        help="A running Dask scheduler's file (dask scheduler "
                                             "--scheduler-file, dask-mpi)."),
    cluster: str = typer.Option(None, "--cluster", metavar="slurm|pbs|sge",
                                help="Start the workers as jobs of this farm scheduler (dask-jobqueue; "
                                     "its ~/.config/dask/jobqueue.yaml sets queue, memory, walltime)."),
    workers: int = typer.Option(None, "--workers", help="Worker processes of the local cluster "
                                "(default: one per core), or worker jobs of --cluster (default 1)."),
    timeout: float = typer.Option(3600.0, "--timeout", metavar="S",
                                  help="Kill a session still running after S seconds and report it failed "
                                       "(0: no limit; a sidecar's \"timeout\" sets one session's)."),
    connect_timeout: float = typer.Option(10.0, "--connect-timeout", metavar="S",
                                          help="Give up on --scheduler if it does not answer within S s."),
    force: bool = typer.Option(False, "--force", help="Redo sessions whose inputs did not change and "
                               "whose outputs are complete (default: skip them)."),
    quiet: Quiet = False,
) -> None:
    """Run cluster / evaluate / compare / info / solve / label on every matching session (Dask).

    Failures are isolated. With --do solve the matched files are captures, solved with the layout
    of --layout L.json (or of "layout" in a capture's sidecar); with --do label they are raw
    captures labelled against --template T (or "template" in a sidecar). A session's own options
    may sit beside it in <stem>.mocaptk.json (or mocaptk.json for its whole folder), e.g.
    {"regions": "anna_regions.json", "rigid": ["HEAD_1", "HEAD_2", "HEAD_3"]}; they override the
    batch line's. Exit code 0 when every session is done or skipped, 1 when some failed (see
    batch.md), 2 for a mistake in the batch itself, 130 / 143 when Ctrl-C / SIGTERM stopped it
    (its running sessions killed first). See docs/batch.md.
    """
    from rich.console import Console

    from mocaptk.batch import engine, journal, sessions, summary

    if do not in sessions.COMMANDS:
        raise OptionError(f"--do must be one of {COMMAND_NAMES}, got {do!r}")
    if cluster is not None and cluster not in engine.JOBQUEUE:
        raise OptionError(f"--cluster must be one of {', '.join(engine.JOBQUEUE)}, got {cluster!r}")
    if sum(x is not None for x in (scheduler, scheduler_file, cluster)) > 1:
        raise OptionError("give one of --scheduler, --scheduler-file and --cluster")
    if workers is not None and (workers < 1 or scheduler is not None or scheduler_file is not None):
        raise OptionError("--workers must be >= 1, and only sizes the local cluster or --cluster's jobs")
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
    run_id = engine.new_run_id()
    task_list = engine.tasks(files, command=do, out=out, options=options, force=force,
                             timeout=timeout or None, previous=previous, run_id=run_id)
    start = time.perf_counter()
    with _stop_signals() as stopped_by:
        records, interrupted, where = _run(task_list, out, run_id, console=console, scheduler=scheduler,
                                           scheduler_file=scheduler_file, cluster=cluster, workers=workers,
                                           connect_timeout=connect_timeout, signals=stopped_by)
        run = {"command": do, "sessions": len(files), "cluster": where, "options": options,
               "seconds": time.perf_counter() - start, "counts": summary.counts(records),
               "interrupted": interrupted}
        all_records = summary.update_summary(out, records, run)
        ours = {(r["session"], r["command"]) for r in records}
        if not quiet:  # still under the handlers: a late Ctrl-C cannot cut the summary short
            this_run = [r for r in all_records if (r["session"], r["command"]) in ours]
            typer.echo(summary.summary_markdown(this_run, run), nl=False)
            typer.echo(f"wrote {out / 'batch.json'} and {out / 'batch.md'}")
    if interrupted:
        console.print(f"mocaptk: note: stopped by {stopped_by[0].name}; {run['counts']['interrupted']} running "
                      "sessions were killed, nothing of the batch runs any more", highlight=False, soft_wrap=True)
        raise typer.Exit(STOPPED_EXIT[stopped_by[0]])
    if run["counts"]["failed"]:
        raise typer.Exit(1)


def _run(task_list: list[dict], out: Path, run_id: str, *, console, scheduler, scheduler_file, cluster, workers,
         connect_timeout: float, signals: list) -> tuple[list[dict], bool, str]:
    """Connect, run the tasks, release the cluster: (records, stopped by a signal, the cluster's name)."""
    from mocaptk.batch import engine, journal

    with engine.dask_client(scheduler=scheduler, scheduler_file=scheduler_file, cluster=cluster,
                            workers=workers, connect_timeout=connect_timeout) as (client, where):
        link = engine.dashboard_link(client)
        if link:
            console.print(f"mocaptk: note: dashboard {link}", highlight=False, soft_wrap=True)
        retries = engine.scheduler_retries(client)
        if retries is not None and retries != engine.WORKER_DEATH_RETRIES:
            console.print(f"mocaptk: note: this scheduler retries a task whose worker died {retries} times "
                          f"(start it with DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=1 for one retry)",
                          highlight=False, soft_wrap=True)
        try:
            records, interrupted = _run_with_progress(client, task_list, console=console)
        finally:
            journal.remove_run(out, run_id)
            signals.append(None)  # from here on a signal stops nothing: the sessions have ended
    return records, interrupted, where


@contextlib.contextmanager
def _stop_signals() -> Iterator[list]:
    """SIGTERM (a farm's job killer, ``kill``) stops the batch as Ctrl-C does; yields the signals
    seen (the caller appends None once its sessions ended: later signals let the summary be written)."""
    seen: list = []

    def handler(number, frame):
        seen.append(signal.Signals(number))
        if seen[0] is not None and len(seen) == 1:  # a second one does not cut the stop short (bounded)
            raise KeyboardInterrupt

    previous = {sig: signal.signal(sig, handler) for sig in STOPPED_EXIT}
    try:
        yield seen
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def _run_with_progress(client, task_list: list[dict], *, console) -> tuple[list[dict], bool]:
    """Run the tasks with a progress line (done / skipped / failed, the running sessions, an ETA)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from mocaptk.batch import engine, summary

    columns = (TextColumn("batch"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[tally]}"),
               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        bar = progress.add_task("batch", total=len(task_list), tally="starting")

        def update(finished: list[dict], running: list[str]) -> None:
            tally = summary.counts(finished)
            names = ", ".join(running[:3]) + (f" +{len(running) - 3}" if len(running) > 3 else "")
            progress.update(bar, completed=len(finished),
                            tally=f"done {tally['done']}  skipped {tally['skipped']}  failed {tally['failed']}  "
                                  f"running {len(running)}{': ' + names if names else ''}")

        return engine.run_tasks(client, task_list, on_update=update)
