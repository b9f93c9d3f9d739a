"""The Dask side of a batch: connect (or start a ``LocalCluster``), submit one task per session,
collect the records as they finish.

Tasks carry paths and options only (a few hundred bytes); each worker reads its sessions itself
and sends back a small record, so no marker array ever goes through the scheduler or the client.
"""

from __future__ import annotations

import contextlib
import logging
import os
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mocaptk.errors import OptionError

#: a task whose worker dies is retried this many times, then reported failed
WORKER_DEATH_RETRIES = 1
#: scheduler settings batch relies on (a farm's scheduler: see docs/batch.md). Saturation 1.0: a
#: worker holds only the tasks it runs, so a dying worker takes no queued session down with it.
SCHEDULER_CONFIG = {"distributed.scheduler.allowed-failures": WORKER_DEATH_RETRIES,
                    "distributed.scheduler.worker-saturation": 1.0}


def tasks(sessions: list[Path], *, command: str, out: Path, options: list[str], force: bool,
          timeout: float | None, previous: dict[tuple[str, str], dict[str, Any]]) -> list[dict[str, Any]]:
    """One task per session: what :func:`mocaptk.batch.supervisor.run_session` needs (plain data)."""
    return [{"command": command, "session": str(s), "out": str(out / s.stem), "options": options,
             "force": force, "timeout": timeout, "previous": previous.get((s.stem, command))}
            for s in sessions]


def machine_workers() -> int:
    """Worker processes for a LocalCluster on this machine: one per usable core."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@contextlib.contextmanager
def dask_client(*, scheduler: str | None, workers: int | None,
                connect_timeout: float) -> Iterator[tuple[Any, str]]:
    """A connected ``distributed.Client`` and a description of the cluster ("2 local workers").

    Without ``scheduler``: a LocalCluster of ``workers`` single-threaded worker processes (numba and
    BLAS hold the GIL, so threads would not run sessions in parallel); every port it opens (its
    HTTP status pages too) is on 127.0.0.1 and chosen free.
    """
    import dask
    from distributed import Client, LocalCluster

    if scheduler is None:
        count = workers or machine_workers()
        with dask.config.set(SCHEDULER_CONFIG), \
                LocalCluster(n_workers=count, threads_per_worker=1, processes=True, host="127.0.0.1",
                             dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0",
                             memory_limit=0, silence_logs=logging.CRITICAL) as cluster, \
                Client(cluster, timeout=connect_timeout) as client:
            yield client, f"{count} local worker{'s' * (count != 1)}"
        return
    logging.getLogger("distributed").setLevel(logging.CRITICAL)  # a failed connect is our one line
    try:
        client = Client(scheduler, timeout=connect_timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        reason = "no Dask scheduler answered" if isinstance(exc, (OSError, TimeoutError)) else str(exc)
        raise OptionError(f"--scheduler {scheduler}: {reason} within {connect_timeout:g} s "
                          "(is `dask scheduler` running there, and the port open?)") from None
    with client:
        n = len(client.scheduler_info(n_workers=-1)["workers"])
        yield client, f"{scheduler} ({n} worker{'s' * (n != 1)})"


def scheduler_retries(client) -> int | None:
    """How often the scheduler reschedules a task whose worker died (its ``allowed-failures``)."""
    try:
        return int(client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.allowed_failures))
    except Exception:  # an old or locked-down scheduler: unknown, not fatal
        return None


def run_tasks(client, task_list: list[dict[str, Any]], *,
              on_update: Callable[[list[dict[str, Any]], int], None]) -> list[dict[str, Any]]:
    """Submit every task, return the records in task order; ``on_update(records so far, running)``
    is called about twice a second. A task whose worker died twice, or whose runner crashed twice,
    becomes a failed record; nothing here raises for one session's trouble."""
    from distributed import wait

    from .supervisor import run_session

    run_id = uuid.uuid4().hex[:8]
    futures = [client.submit(run_session, task, key=f"mocaptk-batch-{task['command']}-"
                             f"{Path(task['session']).stem}-{run_id}", pure=False, retries=1)
               for task in task_list]
    index = {future.key: i for i, future in enumerate(futures)}
    records: list[dict[str, Any] | None] = [None] * len(futures)
    pending = set(futures)
    try:
        while pending:
            try:
                done, pending = wait(pending, timeout=0.5, return_when="FIRST_COMPLETED")
            except TimeoutError:  # nothing finished in this half second
                done = set()
            for future in done:
                i = index[future.key]
                records[i] = _record(future, task_list[i])
            on_update([r for r in records if r is not None], _running(client, index, pending))
    finally:
        client.cancel(list(pending))
    return [r for r in records if r is not None]


def _record(future, task: dict[str, Any]) -> dict[str, Any]:
    from distributed import KilledWorker

    from .supervisor import RunnerDied

    try:
        return future.result()
    except KilledWorker:
        error = (f"the worker processing it died {WORKER_DEATH_RETRIES + 1} times "
                 f"(retried {WORKER_DEATH_RETRIES}x on another worker)")
    except RunnerDied as exc:
        error = f"crashed twice: {exc}"
    except Exception as exc:  # a bug in batch itself: still only this session fails
        error = f"internal error: {type(exc).__name__}: {exc}"
    session = Path(task["session"])
    return {"session": session.stem, "path": str(session), "command": task["command"], "status": "failed",
            "error": error, "warnings": [], "outputs": {}, "seconds": None}


def _running(client, index: dict[str, int], pending: set) -> int:
    """Tasks of this batch currently on a worker (queued ones are not running)."""
    if not pending:
        return 0
    try:
        processing, threads = client.processing(), client.nthreads()
    except Exception:
        return 0
    return sum(min(sum(key in index for key in keys), threads.get(worker, 1))
               for worker, keys in processing.items())
