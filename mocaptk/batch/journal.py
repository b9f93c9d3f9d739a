"""Each session's attempts in one batch, kept on the shared output storage.

``DIR/.mocaptk-batch/<run>/<stem>.<command>.jsonl`` gets one line when an attempt starts (host,
worker, pid, time) and one when it ends (how, and the session's record). The lines are appended
and flushed to disk before anything else happens, so they outlive a worker killed at any moment:

- a retry after a worker death finds the earlier attempt started and never ended (``worker lost``);
- a retry of a session whose attempt had already finished (its worker died before the client
  fetched the result) finds the finished record and returns it without running the command again:
  a session's outputs are written by one attempt at most.

The client creates the run's folder when the batch starts and removes it when nothing of the
batch runs any more; entries are never written without it (:func:`append` creates no folder), so
a worker thread that outlives its batch (its process dying) cannot start a session or leave a
journal behind.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

FOLDER = ".mocaptk-batch"
#: how an attempt that started and never wrote its end line ended: its process vanished with its worker
LOST = "worker lost"


def run_folder(out: Path, run_id: str) -> Path:
    """Where one batch run keeps its journals (inside ``--out``)."""
    return out / FOLDER / run_id


def journal_path(out: Path, run_id: str, session: str, command: str) -> Path:
    return run_folder(out, run_id) / f"{session}.{command}.jsonl"


def now() -> str:
    """UTC time to the millisecond, ISO 8601 (sorts as text)."""
    t = time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t * 1000) % 1000:03d}Z"


class BatchOver(Exception):
    """The batch's journal folder is gone: the batch has returned."""


def append(path: Path, entry: dict[str, Any]) -> None:
    """Add one line and make it durable (fsync) before returning; :class:`BatchOver` if the run's
    folder is gone."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    except FileNotFoundError:
        raise BatchOver(str(path.parent)) from None
    try:
        os.write(fd, (json.dumps(entry, sort_keys=True) + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)


def read(path: Path) -> list[dict[str, Any]]:
    """The journal's entries (a torn last line, from a kill mid-write, is ignored)."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError:
        return []
    entries = []
    for line in text.splitlines():
        try:
            entries.append(json.loads(line))
        except ValueError:
            continue
    return entries


def attempts(entries: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One dict per attempt, in start order: host, worker, pid, start, end, ended (how)."""
    table: dict[str, dict[str, Any]] = {}
    for entry in entries:
        item = table.setdefault(entry["attempt"], {"end": None, "ended": LOST})
        if "start" in entry:
            item |= {k: entry[k] for k in ("host", "worker", "pid", "start")}
        else:
            item |= {"end": entry["end"], "ended": entry["ended"]}
    return sorted((a for a in table.values() if "start" in a), key=lambda a: a["start"])


def finished_record(entries: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The record of an attempt that ran to its end (done, failed, timed out), if any."""
    ended = [e for e in entries if e.get("record") is not None and e["ended"] != "interrupted"]
    return ended[0]["record"] if ended else None


def remove_run(out: Path, run_id: str) -> None:
    """Delete the run's journals (and the journal folder when no other batch uses it)."""
    shutil.rmtree(run_folder(out, run_id), ignore_errors=True)
    try:
        (out / FOLDER).rmdir()
    except OSError:  # another batch into the same DIR is running
        pass
