"""A lock file that works across the hosts of a farm: ``DIR/.batch.json.lock``.

Created with ``O_CREAT | O_EXCL`` (atomic on local disks and NFS), it holds its owner (host, pid,
time). A lock whose owner is a dead process on this host, or that is older than
:data:`STALE_SECONDS` (its owner on another host died or lost the storage), is stale: it is
removed and taken. Held only for a read-merge-write of batch.json (milliseconds), never while
sessions run.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

from mocaptk.errors import OutputError

#: a lock older than this belongs to a process that can no longer finish a summary write
STALE_SECONDS = 120.0


def _owner_alive(owner: dict) -> bool:
    if owner.get("host") != socket.gethostname():
        return True  # another host's process: only its age tells
    try:
        os.kill(int(owner["pid"]), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, KeyError, TypeError, ValueError):
        return True
    return True


def is_stale(path: Path) -> bool:
    """Whether the lock at ``path`` is left by a dead owner (dead pid here, or too old)."""
    try:
        text, age = path.read_text(), time.time() - path.stat().st_mtime
    except OSError:
        return False  # gone already: nothing to break
    try:
        owner = json.loads(text)
    except ValueError:  # its owner died between creating and filling it
        return age > 5.0
    return age > STALE_SECONDS or not _owner_alive(owner)


@contextlib.contextmanager
def locked(path: Path, *, wait: float = 60.0) -> Iterator[None]:
    """Hold the lock file ``path`` for the block; wait up to ``wait`` s for a live owner."""
    token = uuid.uuid4().hex
    deadline = time.monotonic() + wait
    while True:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            if is_stale(path):
                _break(path)
                continue
            if time.monotonic() > deadline:
                raise OutputError(f"{path}: another batch has held this lock for over {wait:g} s "
                                  "(remove the file if no batch is running)") from None
            time.sleep(0.05)
        except OSError as exc:
            raise OutputError(f"{path}: cannot create the lock: {exc.strerror}") from None
    try:
        os.write(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "token": token}).encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            if json.loads(path.read_text()).get("token") == token:  # ours still (not broken as stale)
                path.unlink()


def _break(path: Path) -> None:
    """Remove a stale lock. Renamed aside first and checked again there: if another breaker was
    quicker and a live batch has taken the lock since, that fresh lock is put back."""
    aside = path.with_name(f"{path.name}.{uuid.uuid4().hex[:8]}.stale")
    try:
        os.rename(path, aside)
    except OSError:
        return
    with contextlib.suppress(OSError):
        if not is_stale(aside):
            os.link(aside, path)  # fails if yet another lock is there: then that one holds
    with contextlib.suppress(OSError):
        aside.unlink()
