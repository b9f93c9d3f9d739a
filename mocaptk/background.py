"""Run one output writer (or check) in a forked process while the caller goes on with its own work,
or share independent computations among this process and one forked child per further CPU.

The outputs of a run are independent files, so writing two of them side by side changes no byte;
it halves their wall time on two cores. Each shared computation runs alone with the same inputs
and one BLAS thread, so its numbers are the same bits wherever it ran. Where fork is not safe
(macOS frameworks, Windows) or this process has one CPU, everything runs in this process.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from typing import Any

from mocaptk.errors import MocaptkError
from mocaptk.threads import machine_workers


def can_fork() -> bool:
    """Linux with two or more CPUs for this process."""
    return sys.platform.startswith("linux") and machine_workers() > 1


def shared_map(function: Callable[[Any], Any], items: Sequence[Any], *, what: str) -> list[Any]:
    """``[function(item) for item in items]``, the items dealt round-robin to this process (the
    first item is always computed here, so its result is never pickled) and one forked child per
    further usable CPU. Results come back pickled: keep them small. Errors as :func:`beside`."""
    workers = max(1, min(machine_workers(), len(items))) if can_fork() else 1
    results: list[Any] = [None] * len(items)
    with ExitStack() as stack:
        shares = [stack.enter_context(beside(lambda k=k: [function(x) for x in items[k::workers]], what=what))
                  for k in range(1, workers)]
        results[0::workers] = [function(x) for x in items[0::workers]]
    for k, share in enumerate(shares, start=1):
        results[k::workers] = share.value
    return results


class Outcome:
    """What :func:`beside` gives the ``with`` body: the task's return value, set on leaving."""

    value: Any = None


@contextmanager
def beside(task: Callable[[], Any] | None, *, what: str) -> Iterator[Outcome]:
    """Run ``task()`` (nothing for None) while the ``with`` body runs; leave when both are done,
    with the task's return value (pickled back: keep it small) in the yielded :class:`Outcome`.

    An exception of the task is raised again after the body (its type and message; ``what``
    names the task when it died without one); an exception of the body kills the task first, so
    nothing writes on after the caller has given up.
    """
    outcome = Outcome()
    if task is None or not can_fork():
        outcome.value = None if task is None else task()
        yield outcome
        return
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: run the task, send its result or exception, never return into the caller
        code = 1
        try:
            os.close(read)
            try:
                payload = pickle.dumps((True, task()))
                code = 0
            except BaseException as error:  # noqa: BLE001 - every failure goes back to the parent
                payload = pickle.dumps((False, _picklable(error)))
            with os.fdopen(write, "wb") as pipe:
                pipe.write(payload)
        finally:
            os._exit(code)
    os.close(write)
    try:
        yield outcome
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(read)
        raise
    with os.fdopen(read, "rb") as pipe:
        payload = pipe.read()  # before waiting: a large result would block the child's write
    _, status = os.waitpid(pid, 0)
    if not payload:
        raise MocaptkError(f"{what} stopped without a result ({_status_text(status)})")
    ok, value = pickle.loads(payload)
    if not ok:
        raise value
    outcome.value = value


def _picklable(error: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:  # an unpicklable exception: its type and message
        return MocaptkError(f"{type(error).__name__}: {error}")


def _status_text(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by signal {os.WTERMSIG(status)}"
    return f"exit code {os.waitstatus_to_exitcode(status)}"
