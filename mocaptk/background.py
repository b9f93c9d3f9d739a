"""Run one output writer in a forked process while the caller goes on with its own work.

The outputs of a run are independent files, so writing two of them side by side changes no byte;
it halves their wall time on two cores. Where fork is not safe (macOS frameworks, Windows) or this
process has one CPU, the task simply runs first, in this process.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from mocaptk.errors import MocaptkError


def can_fork() -> bool:
    """Linux with two or more CPUs for this process."""
    return sys.platform.startswith("linux") and len(os.sched_getaffinity(0)) > 1


@contextmanager
def beside(task: Callable[[], object] | None, *, what: str) -> Iterator[None]:
    """Run ``task()`` (nothing for None) while the ``with`` body runs; leave when both are done.

    An exception of the task is raised again after the body (its type and message; ``what``
    names the task when it died without one); an exception of the body kills the task first, so
    nothing writes on after the caller has given up.
    """
    if task is None or not can_fork():
        if task is not None:
            task()
        yield
        return
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: run the task, report its exception, never return into the caller
        code = 1
        try:
            os.close(read)
            payload = b""
            try:
                task()
                code = 0
            except BaseException as error:  # noqa: BLE001 - every failure goes back to the parent
                payload = _pickled(error)
            with os.fdopen(write, "wb") as pipe:
                pipe.write(payload)
        finally:
            os._exit(code)
    os.close(write)
    try:
        yield
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(read)
        raise
    with os.fdopen(read, "rb") as pipe:
        payload = pipe.read()  # before waiting: a large exception would block the child's write
    _, status = os.waitpid(pid, 0)
    if payload:
        raise pickle.loads(payload)
    if status:
        raise MocaptkError(f"{what} stopped without a result ({_status_text(status)})")


def _pickled(error: BaseException) -> bytes:
    try:
        return pickle.dumps(error)
    except Exception:  # an unpicklable exception: its type and message
        return pickle.dumps(MocaptkError(f"{type(error).__name__}: {error}"))


def _status_text(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by signal {os.WTERMSIG(status)}"
    return f"exit code {os.waitstatus_to_exitcode(status)}"
