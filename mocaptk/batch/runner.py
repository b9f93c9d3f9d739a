"""One session's command, run exactly as ``mocaptk COMMAND ...`` runs it, in a child process.

:func:`process_session` is the whole job for one session: build its argv, hash its inputs, skip it
when an earlier run with the same inputs left complete outputs, else call
:func:`mocaptk.cli.main` with that argv and describe what happened (a *record*, plain data).

Run as ``python -m mocaptk.batch.runner REPLY_FD PARENT_PID`` it serves one task per line of
stdin (JSON) and answers each on ``REPLY_FD``. The supervisor kills it on a timeout: a process is
the one thing that can be stopped while it is stuck in numba or C code.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import socket
import sys
import time
import traceback
from pathlib import Path
from collections.abc import Callable
from typing import Any

from mocaptk.errors import MocaptkError

ERROR_PREFIX = "mocaptk: error: "
#: the runner's first line on its reply pipe: imports done, ready for sessions
READY = b"ready\n"


def run_cli(argv: list[str]) -> tuple[int, str, str, str | None]:
    """``mocaptk ARGV`` in this process: (exit code, stdout, stderr, traceback of a crash or None)."""
    from mocaptk.cli import main

    out, err = io.StringIO(), io.StringIO()
    crash = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(argv)
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except Exception as exc:  # a bug in the command: keep its traceback for the summary
            code, crash = 1, traceback.format_exc()
            print(f"{ERROR_PREFIX}internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
    return code, out.getvalue(), err.getvalue(), crash


def error_line(stderr: str, code: int, stdout: str = "") -> str:
    """The command's one-line error (without the ``mocaptk: error:`` prefix); ``info --json``
    reports a file's error inside its JSON document instead."""
    lines = [line for line in stderr.splitlines() if line.startswith(ERROR_PREFIX)]
    if lines:
        return lines[-1][len(ERROR_PREFIX):]
    with contextlib.suppress(ValueError, TypeError, KeyError, IndexError, AttributeError):
        return str(next(f["error"] for f in json.loads(stdout)["files"] if "error" in f))
    tail = [line for line in stderr.splitlines() if line.strip()]
    return tail[-1] if tail else f"exit code {code}"


def _snapshot(folder: Path) -> dict[str, tuple[int, int, int]]:
    if not folder.is_dir():
        return {}
    return {str(p.relative_to(folder)): (s.st_ino, s.st_mtime_ns, s.st_size)
            for p in sorted(folder.rglob("*")) if p.is_file() and (s := p.stat())}


def outputs_intact(outputs: dict[str, str], folder: Path) -> bool:
    """Whether every recorded output file is still there with the recorded content."""
    from .sessions import file_digest

    try:
        return bool(outputs) and all(file_digest(folder / name) == digest for name, digest in outputs.items())
    except OSError:
        return False


#: the session's own stdout and stderr, beside its outputs (not one of them: not hashed, not compared)
LOG_FILE = "log.txt"


def process_session(task: dict[str, Any], *,
                    announce: Callable[[dict[str, Any]], None] = lambda started: None) -> dict[str, Any]:
    """Run (or skip) one session; returns its record (see :mod:`mocaptk.batch.summary`).

    ``announce`` gets argv, then inputs and key, before the command starts (a record of a kill keeps them).
    """
    from mocaptk import __version__
    from mocaptk.errors import InputFileError, unreadable
    from .sessions import COMMANDS, input_files, file_digest, session_argv
    from .summary import session_metrics

    start, cpu = time.perf_counter(), time.process_time()
    command, session, out_dir = task["command"], Path(task["session"]), Path(task["out"])
    record: dict[str, Any] = {"session": session.stem, "path": str(session), "command": command,
                              "host": socket.gethostname(), "warnings": [], "outputs": {}}
    try:
        argv = session_argv(command, session, out_dir, task["options"])
        layout = (Path(argv[1]) if COMMANDS[command].layout_argument  # solve LAYOUT CAPTURE
                  else Path(argv[argv.index("--layout") + 1]) if "--layout" in argv else None)
        if layout is not None and not layout.exists() and not COMMANDS[command].layout_argument:
            raise InputFileError(layout, "no layout for this session: run the batch with --do cluster "
                                         "into the same --out first, or name one as \"layout\" in a sidecar")
        announce({"argv": argv})  # before hashing: reading the inputs may hang too (a dead mount)
        files = input_files(command, argv, session)
        inputs = {}
        for path in files:
            try:
                inputs[str(path)] = file_digest(path)
            except OSError as exc:
                raise unreadable(path, exc) from None
    except MocaptkError as exc:
        return record | {"status": "failed", "error": str(exc), "seconds": time.perf_counter() - start}
    key = hashlib.sha256(json.dumps({"argv": argv, "inputs": inputs, "mocaptk": __version__},
                                    sort_keys=True).encode()).hexdigest()
    record |= {"argv": argv, "inputs": inputs, "key": key}
    announce({"inputs": inputs, "key": key})
    previous = task.get("previous") or {}
    if (not task["force"] and previous.get("status") in ("done", "skipped") and previous.get("key") == key
            and outputs_intact(previous.get("outputs", {}), out_dir)):
        return previous | {"status": "skipped", "error": None}
    before = _snapshot(out_dir)
    run = list(argv)
    if before and any(p.name == "force" for p in _params(command)):
        run.append("--force")  # inputs changed or --force: replace this session's earlier outputs
    code, stdout, stderr, crash = run_cli(run)
    _write_log(out_dir, run, code, stdout, stderr, crash)
    record["warnings"] = [line for line in stderr.splitlines()
                          if line.startswith(("mocaptk: warning:", "mocaptk: note:"))]
    record["exit_code"] = code
    if code == 0 and COMMANDS[command].stdout_file:
        from mocaptk.atomic import write_text

        write_text(out_dir / COMMANDS[command].stdout_file, stdout)
    if code != 0:
        record |= {"status": "failed", "error": error_line(stderr, code, stdout)}
        if crash:
            record["traceback"] = crash
    else:
        after = _snapshot(out_dir)
        record |= {"status": "done", "error": None,
                   "outputs": {name: file_digest(out_dir / name) for name, stat in after.items()
                               if before.get(name) != stat and name != LOG_FILE},
                   "metrics": session_metrics(out_dir, layout_file=layout)}
    record["seconds"] = time.perf_counter() - start
    record["cpu_seconds"] = time.process_time() - cpu  # this runner's CPU (the session's own work)
    return record


def _write_log(out_dir: Path, argv: list[str], code: int, stdout: str, stderr: str, crash: str | None) -> None:
    """DIR/<stem>/log.txt: the command line, its exit code, its stdout and stderr (and a crash's traceback)."""
    from mocaptk.atomic import write_text

    text = (f"$ mocaptk {' '.join(argv)}\nexit code {code}\n--- stdout\n{stdout}--- stderr\n{stderr}"
            + (f"--- traceback\n{crash}" if crash else ""))
    with contextlib.suppress(OSError, MocaptkError):
        write_text(out_dir / LOG_FILE, text)


def _params(command: str):
    from .sessions import click_command

    return click_command(command).params


def _die_with_parent(parent: int) -> None:
    """Ask Linux to kill this process when its parent (the Dask worker) dies, even mid-task."""
    if sys.platform.startswith("linux"):
        import ctypes
        import signal

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def _serve(reply_fd: int) -> None:
    # import once per runner, before the first session's clock starts: the CLI and what its
    # layout commands import lazily (matplotlib figures, the clustering pipeline)
    import mocaptk.cli  # noqa: F401
    import mocaptk.clustering.figures  # noqa: F401
    import mocaptk.clustering.pipeline  # noqa: F401

    os.write(reply_fd, READY)
    def reply(message: dict[str, Any]) -> None:
        data = (json.dumps(message) + "\n").encode()
        while data:
            data = data[os.write(reply_fd, data):]

    for line in sys.stdin:
        reply(process_session(json.loads(line), announce=lambda started: reply({"started": started})))


if __name__ == "__main__":
    _die_with_parent(int(sys.argv[2]))
    _serve(int(sys.argv[1]))
