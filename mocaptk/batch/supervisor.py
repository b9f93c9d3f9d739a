"""The Dask task of a batch: hand one session to this worker thread's runner process, wait for
its record at most ``timeout`` seconds, kill it (its whole process group) if it does not answer.

One long-lived runner per worker thread keeps imports and numba caches warm between sessions; a
killed or crashed runner is replaced by a fresh one for the next session. A runner that dies by
itself (a crash in C code, the kernel's OOM killer) raises :class:`RunnerDied`, which Dask retries
once (``retries=1``); a timeout is a result, not retried: the same session would hang again.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .runner import READY

_local = threading.local()
#: how long a new runner may take to import everything (a loaded farm node, a cold disk)
STARTUP_SECONDS = 300


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
        if self._line(STARTUP_SECONDS) != READY.strip():
            self.kill()
            raise RunnerDied(f"the session runner did not start within {STARTUP_SECONDS} s")

    def ask(self, task: dict[str, Any], timeout: float | None) -> dict[str, Any] | None:
        """The runner's record for ``task``; None if it did not answer within ``timeout`` s."""
        assert self.process.stdin is not None
        self.process.stdin.write((json.dumps(task) + "\n").encode())
        self.process.stdin.flush()
        line = self._line(timeout)
        return None if line is None else json.loads(line)

    def _line(self, timeout: float | None) -> bytes | None:
        """The runner's next line; None after ``timeout`` s of silence."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self.buffer:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            ready, _, _ = select.select([self.reply_fd], [], [], left)
            if not ready:
                return None
            chunk = os.read(self.reply_fd, 1 << 16)
            if not chunk:
                code = self.process.wait()
                how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
                raise RunnerDied(f"the process running it ended without a result ({how})")
            self.buffer += chunk
        line, _, self.buffer = self.buffer.partition(b"\n")
        return line

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


def _runner() -> _Runner:
    runner = getattr(_local, "runner", None)
    if runner is None or runner.process.poll() is not None:
        runner = _local.runner = _Runner()
    return runner


def remove_partial_outputs(out_dir: Path) -> None:
    """Delete the temporary files a killed command left (atomic writers' ``.NAME.*.part``)."""
    candidates = [*out_dir.parent.glob(f".{out_dir.name}.*.part")]
    if out_dir.is_dir():
        candidates += [p for p in out_dir.rglob(".*.part*")]
    for path in candidates:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _discard(runner: _Runner, task: dict[str, Any]) -> None:
    """Kill a runner that timed out or died, and clear what its session left half-written."""
    runner.kill()
    _local.runner = None
    remove_partial_outputs(Path(task["out"]))


def run_session(task: dict[str, Any]) -> dict[str, Any]:
    """Dask task: one session's record (``task`` as built by :func:`mocaptk.batch.engine.tasks`)."""
    timeout = task.get("timeout")
    runner = _runner()
    start = time.perf_counter()  # the timeout counts the session's work, not the runner's start
    try:
        record = runner.ask(task, timeout)
    except RunnerDied:
        _discard(runner, task)
        raise
    if record is not None:
        return record
    _discard(runner, task)
    session = Path(task["session"])
    return {"session": session.stem, "path": str(session), "command": task["command"], "status": "failed",
            "error": f"timed out after {timeout:g} s (--timeout): killed", "warnings": [], "outputs": {},
            "seconds": time.perf_counter() - start}
