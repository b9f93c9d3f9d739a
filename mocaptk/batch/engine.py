"""The Dask side of a batch: connect (a ``LocalCluster``, a running scheduler, a scheduler file
or a SLURM / PBS / SGE cluster through dask-jobqueue), submit one task per session, collect the
records as they finish, and stop every running session on Ctrl-C or SIGTERM.

Tasks carry paths and options only (a few hundred bytes); each worker reads its sessions itself
and sends back a small record, so no marker array ever goes through the scheduler or the client.
A finished task is released at once: the scheduler then forgets it, so a worker dying later has
nothing of it to recompute.
"""

from __future__ import annotations

import contextlib
import logging
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mocaptk.errors import OptionError
from mocaptk.threads import machine_workers

from . import journal

#: a task whose worker dies is retried this many times, then reported failed
WORKER_DEATH_RETRIES = 1
#: scheduler settings batch relies on (a farm's scheduler: see docs/batch.md). Saturation 1.0: a
#: worker holds only the tasks it runs, so a dying worker takes no queued session down with it.
SCHEDULER_CONFIG = {"distributed.scheduler.allowed-failures": WORKER_DEATH_RETRIES,
                    "distributed.scheduler.worker-saturation": 1.0}
#: farm schedulers batch starts workers on through dask-jobqueue (its configuration file:
#: ~/.config/dask/jobqueue.yaml, see docs/batch.md)
JOBQUEUE = {"slurm": "SLURMCluster", "pbs": "PBSCluster", "sge": "SGECluster"}
#: how long a stopped batch waits for its running sessions to be killed
STOP_SECONDS = 60.0
#: how often the progress line asks the workers which sessions they run
RUNNING_SECONDS = 2.0


def new_run_id() -> str:
    return uuid.uuid4().hex[:12]


def tasks(sessions: list[Path], *, command: str, out: Path, options: list[str], force: bool,
          timeout: float | None, previous: dict[tuple[str, str], dict[str, Any]],
          run_id: str) -> list[dict[str, Any]]:
    """One task per session, largest file first (the longest sessions start first instead of
    running last, alone): what :func:`mocaptk.batch.supervisor.run_session` needs (plain data)."""
    def size(path: Path) -> int:
        try:
            return path.stat().st_size
        except OSError:
            return 0

    return [{"command": command, "session": str(s), "out": str(out / s.stem), "options": options,
             "force": force, "timeout": timeout, "previous": previous.get((s.stem, command)), "run": run_id,
             "journal": str(journal.journal_path(out, run_id, s.stem, command))}
            for s in sorted(sessions, key=lambda s: (-size(s), str(s)))]


@contextlib.contextmanager
def dask_client(*, scheduler: str | None, scheduler_file: Path | None, cluster: str | None,
                workers: int | None, connect_timeout: float) -> Iterator[tuple[Any, str]]:
    """A connected ``distributed.Client`` and a description of the cluster ("2 local workers").

    Without ``scheduler``, ``scheduler_file`` or ``cluster``: a LocalCluster of ``workers``
    single-threaded worker processes (numba and BLAS hold the GIL, so threads would not run
    sessions in parallel); every port it opens (its HTTP status pages too) is on 127.0.0.1 and
    chosen free. ``cluster`` ("slurm", "pbs", "sge"): ``workers`` workers as jobs of that
    scheduler, configured by dask-jobqueue's configuration file.
    """
    import dask
    from distributed import Client, LocalCluster

    if cluster is not None:
        with dask.config.set(SCHEDULER_CONFIG), _jobqueue(cluster, workers or 1) as farm, \
                Client(farm, timeout=connect_timeout) as client:
            yield client, f"{cluster} ({workers or 1} worker job{'s' * ((workers or 1) != 1)})"
        return
    if scheduler is None and scheduler_file is None:
        count = workers or machine_workers()
        with dask.config.set(SCHEDULER_CONFIG):
            with _sigint_ignored():  # while its worker processes start
                local = LocalCluster(n_workers=count, threads_per_worker=1, processes=True, host="127.0.0.1",
                                     dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                                     memory_limit=0, silence_logs=logging.CRITICAL)
            with local, Client(local, timeout=connect_timeout) as client:
                yield client, f"{count} local worker{'s' * (count != 1)}"
        return
    logging.getLogger("distributed").setLevel(logging.CRITICAL)  # a failed connect is our one line
    name = f"--scheduler {scheduler}" if scheduler else f"--scheduler-file {scheduler_file}"
    if scheduler_file is not None and not scheduler_file.is_file():
        raise OptionError(f"{name}: no such file (the scheduler writes it when it starts)")
    try:
        client = (Client(scheduler, timeout=connect_timeout) if scheduler
                  else Client(scheduler_file=str(scheduler_file), timeout=connect_timeout))
    except (OSError, TimeoutError, ValueError, KeyError) as exc:
        reason = "no Dask scheduler answered" if isinstance(exc, (OSError, TimeoutError)) else str(exc)
        raise OptionError(f"{name}: {reason} within {connect_timeout:g} s "
                          "(is `dask scheduler` running there, and the port open?)") from None
    with client:
        n = len(client.scheduler_info(n_workers=-1)["workers"])
        yield client, f"{scheduler or client.scheduler.address} ({n} worker{'s' * (n != 1)})"


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Start processes that ignore SIGINT (an ignored signal stays ignored in a child, and Python
    keeps it so): a terminal's Ctrl-C, sent to the whole process group, then reaches only the
    client, which stops the sessions itself instead of the local workers dying mid-session."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def _jobqueue(kind: str, workers: int) -> Iterator[Any]:
    """A dask-jobqueue cluster of ``workers`` single-threaded workers (one per job)."""
    try:
        import dask_jobqueue
    except ImportError:
        raise OptionError(f"--cluster {kind} needs dask-jobqueue (pip install dask-jobqueue)") from None
    try:  # one single-threaded worker per job: a session is one process, as on a LocalCluster
        farm = getattr(dask_jobqueue, JOBQUEUE[kind])(processes=1, cores=1)
    except (ValueError, TypeError, KeyError) as exc:
        raise OptionError(f"--cluster {kind}: {exc} (configure it in ~/.config/dask/jobqueue.yaml, "
                          "see docs/batch.md)") from None
    with farm:
        farm.scale(workers)
        yield farm


def dashboard_link(client) -> str | None:
    """The scheduler's status pages (Bokeh dashboard), if it serves them."""
    with contextlib.suppress(Exception):
        return client.dashboard_link
    return None


def scheduler_retries(client) -> int | None:
    """How often the scheduler reschedules a task whose worker died (its ``allowed-failures``)."""
    try:
        return int(client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.allowed_failures))
    except Exception:  # an old or locked-down scheduler: unknown, not fatal
        return None


def run_tasks(client, task_list: list[dict[str, Any]], *,
              on_update: Callable[[list[dict[str, Any]], list[str]], None]) -> tuple[list[dict[str, Any]], bool]:
    """Submit every task; return (the records, whether the batch was stopped) once nothing of it
    runs any more. ``on_update(records so far, running sessions)`` is called about twice a second.

    A task whose worker died twice, or whose runner crashed twice, becomes a failed record; nothing
    here raises for one session's trouble. Ctrl-C (KeyboardInterrupt; the CLI turns SIGTERM into
    one) stops the batch: queued sessions never start, running ones are killed and recorded
    ``interrupted``.
    """
    from distributed import wait

    from .supervisor import run_session

    count = len(task_list)
    if not count:
        return [], False
    Path(task_list[0]["journal"]).parent.mkdir(parents=True, exist_ok=True)  # the batch is on
    pending: dict[Any, int] = {}  # the only references to unfinished futures
    for rank, task in enumerate(task_list):  # higher priority runs first: largest first
        future = client.submit(run_session, task, key=_key(task), pure=False, retries=1, priority=count - rank)
        pending[future] = rank
    run_id = task_list[0]["run"]
    records: list[dict[str, Any] | None] = [None] * count
    running: list[str] = []
    asked = 0.0
    try:
        while pending:
            try:
                done, _ = wait(list(pending), timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:  # nothing finished in this half second
                done = set()
            for future in done:
                rank = pending.pop(future)
                records[rank] = _record(future, task_list[rank])
                future.release()  # forgotten by the scheduler: a later worker death recomputes nothing
            del done
            if time.monotonic() - asked > RUNNING_SECONDS:  # one question to every worker: not too often
                running, asked = _running(client, run_id), time.monotonic()
            on_update([r for r in records if r is not None], running)
    except KeyboardInterrupt:
        stop(client, run_id, list(pending))
        for rank in pending.values():
            records[rank] = stopped_record(task_list[rank])
        pending.clear()
        return [r for r in records if r is not None], True
    finally:
        _release_runners(client)
    return [r for r in records if r is not None], False


def _key(task: dict[str, Any]) -> str:
    return f"mocaptk-batch-{task['command']}-{Path(task['session']).stem}-{task['run']}"


def stop(client, run_id: str, futures: list) -> None:
    """Cancel the batch's unfinished tasks and return once none of them runs on any worker (its
    runners killed, their partial outputs removed), or after :data:`STOP_SECONDS`."""
    from .supervisor import stop_run

    deadline = time.monotonic() + STOP_SECONDS
    while True:
        try:
            running = client.run(stop_run, run_id, on_error="ignore")  # also: nothing new starts
            if futures:
                client.cancel(futures, force=True)
                futures = []
        except Exception:  # the scheduler is gone: its workers die with it, and their runners too
            return
        if sum(running.values()) == 0 or time.monotonic() > deadline:
            return
        time.sleep(0.2)


def stopped_record(task: dict[str, Any]) -> dict[str, Any] | None:
    """The record of a session the batch stopped, from its journal: the finished record if it got
    that far, else ``interrupted`` (None if it never started: its earlier record stays)."""
    from .supervisor import tidy_output

    entries = journal.read(Path(task["journal"]))
    if not entries:
        return None
    attempts = journal.attempts(entries)
    ended = [e["record"] for e in entries if e.get("record") is not None]
    record = journal.finished_record(entries) or (ended[-1] if ended else None)
    if record is None:  # its attempts were lost with their workers
        tidy_output(Path(task["out"]))
        record = _failed(task, "interrupted: its worker was lost while the batch stopped") | {"status": "interrupted"}
    return record | {"attempts": attempts, "finished": record.get("finished") or journal.now()}


def _record(future, task: dict[str, Any]) -> dict[str, Any]:
    from distributed import KilledWorker

    from .supervisor import RunnerDied, tidy_output

    try:
        return future.result()
    except KilledWorker:
        tidy_output(Path(task["out"]))  # the last attempt's runner died with its worker mid-write
        error = (f"the worker processing it died {WORKER_DEATH_RETRIES + 1} times "
                 f"(retried {WORKER_DEATH_RETRIES}x on another worker)")
    except RunnerDied as exc:
        error = f"crashed twice: {exc}"
    except Exception as exc:  # a bug in batch itself: still only this session fails
        error = f"internal error: {type(exc).__name__}: {exc}"
    return _failed(task, error)


def _failed(task: dict[str, Any], error: str) -> dict[str, Any]:
    session = Path(task["session"])
    started = [e["record"] for e in journal.read(Path(task["journal"])) if e.get("record")]
    known = {k: started[-1][k] for k in ("argv", "inputs", "key") if started and k in started[-1]}
    return {"session": session.stem, "path": str(session), "command": task["command"], "status": "failed",
            "error": error, "warnings": [], "outputs": {}, "seconds": None, **known,
            "attempts": journal.attempts(journal.read(Path(task["journal"]))), "finished": journal.now()}


def _running(client, run_id: str) -> list[str]:
    """Sessions of this batch running on a worker now (queued ones are not), by name."""
    from .supervisor import running_sessions

    try:
        return sorted(name for names in client.run(running_sessions, run_id, on_error="ignore").values()
                      for name in names)
    except Exception:  # the scheduler is busy or gone: no names this time
        return []


def _release_runners(client) -> None:
    """No idle runner of this batch stays on the workers (a farm's workers outlive the batch)."""
    from .supervisor import release_runners

    with contextlib.suppress(Exception):
        client.run(release_runners, on_error="ignore")
