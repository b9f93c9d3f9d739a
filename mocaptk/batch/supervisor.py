"""The Dask task of a batch: hand one session to this worker thread's runner process, wait for
its record, kill it (its whole process group) when it runs past its timeout or the batch stops.

One long-lived runner per worker thread keeps imports and numba caches warm between sessions; a
killed or crashed runner is replaced by a fresh one for the next session. A runner that dies by
itself (a crash in C code, the kernel's OOM killer) raises :class:`RunnerDied`, which Dask retries
once (``retries=1``); a timeout is a result, not retried: the same session would hang again.

Every attempt is written to the session's journal (:mod:`.journal`) before it starts and when it
ends. The batch stops its sessions through :func:`stop_run` (``client.run`` on every worker: the
worker's event loop answers even while its threads run sessions); a task whose key the scheduler
cancelled (its client went away) stops the same way.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from . import journal
from .runner import READY

_local = threading.local()
#: how long a new runner may take to import everything (a loaded farm node, a cold disk)
STARTUP_SECONDS = 300
#: how often a waiting task checks whether its batch still wants it
POLL_SECONDS = 0.25

_state = threading.Lock()
_active: dict[str, list[str]] = {}  # batch run id -> its sessions running in this worker process
_stopped: set[str] = set()  # batch runs stopped by their client (Ctrl-C, SIGTERM)
_runners: dict["_Runner", bool] = {}  # every runner of this worker process -> in use


class RunnerDied(RuntimeError):
    """The process running a session ended without answering (crash, signal)."""


class _Runner:
    """A ``python -m mocaptk.batch.runner`` child and the pipe it answers on."""

    def __init__(self) -> None:
        read_fd, write_fd = os.pipe()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "mocaptk.batch.runner", str(write_fd), str(os.getpid())],
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            pass_fds=(write_fd,), start_new_session=True)  # own group: a kill reaches its children
        os.close(write_fd)
        self.reply_fd = read_fd
        self.buffer = b""
        if self._line(STARTUP_SECONDS, lambda: False) != READY.strip():
            self.kill()
            raise RunnerDied(f"the session runner did not start within {STARTUP_SECONDS} s")

    def send(self, task: dict[str, Any]) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write((json.dumps(task) + "\n").encode())
        self.process.stdin.flush()

    def _line(self, timeout: float | None, stop: Callable[[], bool]) -> bytes | None:
        """The runner's next line; None after ``timeout`` s of silence or once ``stop()`` is true."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self.buffer:
            if stop():
                return None
            left = POLL_SECONDS if deadline is None else min(POLL_SECONDS, deadline - time.monotonic())
            if left <= 0:
                return None
            ready, _, _ = select.select([self.reply_fd], [], [], left)
            if not ready:
                continue
            chunk = os.read(self.reply_fd, 1 << 16)
            if not chunk:
                code = self.process.wait()
                how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
                raise RunnerDied(f"the process running it ended without a result ({how})")
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line

    def cpu_seconds(self) -> float:
        """User + system CPU of the runner process so far (0 where /proc is missing)."""
        try:
            fields = Path(f"/proc/{self.process.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            return 0.0

    def kill(self) -> None:
        """Kill the runner and everything it started; wait for it."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait()
        os.close(self.reply_fd)
        if self.process.stdin is not None:
            self.process.stdin.close()


@contextlib.contextmanager
def _runner() -> Iterator[_Runner]:
    """This thread's runner (a new one if it has none, or it died), marked in use for the block."""
    with _state:
        runner = getattr(_local, "runner", None)
        if runner is not None and runner in _runners and runner.process.poll() is None:
            _runners[runner] = True
        else:
            runner = None
    if runner is None:
        runner = _local.runner = _Runner()
        with _state:
            _runners[runner] = True
    try:
        yield runner
    finally:
        with _state:
            if runner in _runners:
                _runners[runner] = False


def release_runners() -> int:
    """Kill this worker's idle runners (the client calls it when a batch ends: no process of a
    finished batch stays on a farm's nodes); returns how many."""
    with _state:
        idle = [runner for runner, busy in _runners.items() if not busy]
        for runner in idle:
            del _runners[runner]
    for runner in idle:
        runner.kill()
    return len(idle)


def tidy_output(out_dir: Path) -> None:
    """Undo what a killed command left half-written in ``out_dir`` (temporary parts, an old folder
    moved aside, its lock file), as the next run of the command itself would."""
    from mocaptk.atomic import recover_output

    recover_output(out_dir)


def _discard(runner: _Runner, task: dict[str, Any]) -> None:
    """Kill a runner that timed out, was stopped or died; clear what its session left half-written."""
    with _state:
        _runners.pop(runner, None)
    runner.kill()
    _local.runner = None
    tidy_output(Path(task["out"]))


def stop_run(run_id: str) -> int:
    """Stop batch ``run_id`` in this worker process (its client calls this on every worker):
    its running sessions are killed within a poll; returns how many of them still run here."""
    with _state:
        _stopped.add(run_id)
        return len(_active.get(run_id, ()))


def running_sessions(run_id: str) -> list[str]:
    """The sessions of batch ``run_id`` running in this worker process (for its progress line)."""
    with _state:
        return list(_active.get(run_id, ()))


@contextlib.contextmanager
def _running(run_id: str, session: str) -> Iterator[None]:
    with _state:
        _active.setdefault(run_id, []).append(session)
    try:
        yield
    finally:
        with _state:
            _active[run_id].remove(session)
            if not _active[run_id]:
                del _active[run_id]


def _stop_check(run_id: str) -> Callable[[], bool]:
    """True once the batch stopped, or the scheduler cancelled this task (its client is gone)."""
    try:
        from distributed import get_worker

        worker = get_worker()
        key = worker.get_current_task()
    except (ImportError, ValueError):  # run outside a Dask worker (tests): only stop_run stops it
        worker = key = None

    def stop() -> bool:
        if run_id in _stopped:
            return True
        if worker is None:
            return False
        state = worker.state.tasks.get(key)
        return state is None or state.state in ("cancelled", "released", "forgotten")
    return stop


def _worker_address() -> str | None:
    with contextlib.suppress(ImportError, ValueError):
        from distributed import get_worker

        return get_worker().address
    return None


def run_session(task: dict[str, Any]) -> dict[str, Any]:
    """Dask task: one session's record (``task`` as built by :func:`mocaptk.batch.engine.tasks`),
    with ``attempts``: every attempt of this batch at it (host, worker, pid, start, end, ended)."""
    from .sessions import session_timeout

    path = Path(task["journal"])
    earlier = journal.read(path)
    finished = journal.finished_record(earlier)
    if finished is not None:  # an attempt ran to its end; its worker died before the client heard
        return finished | {"attempts": journal.attempts(earlier)}
    stop = _stop_check(task["run"])
    with _running(task["run"], Path(task["session"]).stem):
        if stop():
            return _base_record(task, {}) | {"status": "interrupted", "error": "not started: the batch stopped"}
        attempt = uuid.uuid4().hex[:12]
        try:
            journal.append(path, {"attempt": attempt, "start": journal.now(), "host": socket.gethostname(),
                                  "worker": _worker_address(), "pid": os.getpid()})
        except journal.BatchOver:  # a task of a batch that has returned: nothing may run for it
            return _base_record(task, {}) | {"status": "interrupted", "error": "not started: the batch stopped"}
        tidy_output(Path(task["out"]))  # an attempt lost with its worker may have left parts
        timeout = session_timeout(Path(task["session"]), task.get("timeout"))
        try:
            record, ended = _attempt(task, timeout, stop)
        except RunnerDied as exc:  # Dask retries it once; the journal keeps how this one ended
            with contextlib.suppress(journal.BatchOver):
                journal.append(path, {"attempt": attempt, "end": journal.now(), "ended": f"runner died: {exc}"})
            raise
        record["finished"] = journal.now()
        with contextlib.suppress(journal.BatchOver):
            journal.append(path, {"attempt": attempt, "end": record["finished"], "ended": ended, "record": record})
    return record | {"attempts": journal.attempts(journal.read(path))}


def _attempt(task: dict[str, Any], timeout: float | None, stop: Callable[[], bool]) -> tuple[dict[str, Any], str]:
    """(record, how the attempt ended) of one run of the session in this thread's runner."""
    with _runner() as runner:
        return _ask(runner, task, timeout, stop)


def _ask(runner: _Runner, task: dict[str, Any], timeout: float | None,
         stop: Callable[[], bool]) -> tuple[dict[str, Any], str]:
    start, cpu = time.perf_counter(), runner.cpu_seconds()  # the session's work, not the runner's start
    deadline = None if timeout is None else time.monotonic() + timeout
    started: dict[str, Any] = {}
    try:
        runner.send(task)
        while True:
            left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
            line = runner._line(left, stop)
            if line is None:
                break
            reply = json.loads(line)
            if "started" not in reply:
                return reply, reply["status"]
            started |= reply["started"]  # argv, inputs and key: kept for a record of a kill
    except RunnerDied:
        _discard(runner, task)
        raise
    used = runner.cpu_seconds() - cpu
    _discard(runner, task)
    record = _base_record(task, started) | {"seconds": time.perf_counter() - start, "cpu_seconds": used}
    if stop():
        return record | {"status": "interrupted", "error": "interrupted: the batch stopped; killed"}, "interrupted"
    return record | {"status": "failed", "error": f"timed out after {timeout:g} s (--timeout): killed"}, "timed out"


def _base_record(task: dict[str, Any], started: dict[str, Any]) -> dict[str, Any]:
    session = Path(task["session"])
    return {"session": session.stem, "path": str(session), "command": task["command"],
            "host": socket.gethostname(), "warnings": [], "outputs": {}, "seconds": None, **started}
