"""Run ezc3d (C++) on a checked C3D file in a forked child: crashes, hangs and memory blow-ups stay
there.

ezc3d can abort, run long or allocate far more than a file's size on odd input (it takes 12 GB
and half a minute to reject the 583 kB ``sample22/BKINtechnologies.c3d``). The child runs
under an address-space limit and a time limit and writes the points straight into an anonymous
shared memory mapping, so the parent gets its arrays without a copy; any failure comes back as
a short reason and the caller falls back to mocaptk's own reader. Where ``os.fork`` does not
exist, ezc3d runs in-process without these guards.
"""

from __future__ import annotations

import mmap
import os
import select
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Address space ezc3d may add, per byte of C3D file (measured: ~13x the file size).
MEMORY_PER_FILE_BYTE = 25
#: ... plus this much, in bytes.
MEMORY_BASE = 512 * 2**20
#: Never let ezc3d use more than this fraction of the memory available when the read starts.
MEMORY_AVAILABLE_FRACTION = 0.5
#: Time limit: this many seconds plus one per MB of file (ezc3d reads ~5 MB/s).
TIME_BASE = 30.0


@dataclass(frozen=True)
class Ezc3dPoints:
    """Points as ezc3d read them: ``xyz`` (frames, points, 3), ``residual`` (frames, points), both
    in file units; ``analog_words`` = analog samples per frame in ezc3d's reading."""

    xyz: np.ndarray
    residual: np.ndarray
    analog_words: int


def read_points(path: Path, n_frames: int, n_points: int) -> Ezc3dPoints | str:
    """ezc3d's points for the C3D file ``path`` (expected ``n_frames`` x ``n_points``).

    Returns the points, or a one-line reason why ezc3d could not supply them.
    """
    import ezc3d  # imported before forking: the child must not take the import lock

    size = path.stat().st_size
    budget = MEMORY_PER_FILE_BYTE * size + MEMORY_BASE
    available = available_memory()
    if available is not None and budget > MEMORY_AVAILABLE_FRACTION * available:
        return (f"ezc3d would need ~{budget / 2**30:.1f} GB, more than half of the "
                f"{available / 2**30:.1f} GB available")
    if not hasattr(os, "fork"):
        return _in_process(ezc3d, path, n_frames, n_points)
    shared = mmap.mmap(-1, max(n_frames * n_points * 4 * 8, 1))
    buffer = np.frombuffer(shared, np.float64, n_frames * n_points * 4)
    xyz = buffer[:n_frames * n_points * 3].reshape(n_frames, n_points, 3)
    residual = buffer[n_frames * n_points * 3:].reshape(n_frames, n_points)
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: never returns
        os.close(read_end)
        _child(ezc3d, path, xyz, residual, write_end, budget)
    os.close(write_end)
    try:
        message = _wait(pid, read_end, TIME_BASE + size / 2**20)
    finally:
        os.close(read_end)
    if not message.startswith("ok "):
        return message
    return Ezc3dPoints(xyz, residual, int(message.split()[1]))


def _child(ezc3d, path: Path, xyz: np.ndarray, residual: np.ndarray, pipe: int,
           budget: int) -> None:
    status = 1
    try:
        import faulthandler
        import resource

        faulthandler.disable()  # a crash here is reported by the parent, once

        used = _address_space()
        if used:  # Linux: bound what ezc3d may add
            hard = resource.getrlimit(resource.RLIMIT_AS)[1]
            limit = used + budget if hard == resource.RLIM_INFINITY else min(used + budget, hard)
            resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
        c3d = ezc3d.c3d(str(path))
        points = c3d["data"]["points"]  # (4, points, frames)
        analogs = c3d["data"]["analogs"]  # (1, channels, samples)
        if points.shape[1:] != xyz.shape[1::-1]:
            message = f"ezc3d read {points.shape[2]} frames of {points.shape[1]} points"
        else:
            xyz[...] = points[:3].transpose(2, 1, 0)
            residual[...] = c3d["data"]["meta_points"]["residuals"][0].T
            message = f"ok {analogs.shape[1] * analogs.shape[2] // max(xyz.shape[0], 1)}"
            status = 0
    except MemoryError:
        message = f"ezc3d needed more than {budget / 2**30:.1f} GB"
    except BaseException as exc:  # noqa: BLE001 - everything must reach the parent as text
        message = f"ezc3d: {(str(exc).splitlines() or [type(exc).__name__])[0][:100]}"
    try:
        os.write(pipe, message.encode("utf-8", "replace"))
        os.close(pipe)  # the parent goes on while this process tears down
    finally:
        os._exit(status)


def _wait(pid: int, pipe: int, timeout: float) -> str:
    """The child's message; kills it after ``timeout`` s; reports a crash by its signal."""
    deadline = time.monotonic() + timeout
    chunks = []
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return f"ezc3d did not finish within {timeout:.0f} s"
        ready, _, _ = select.select([pipe], [], [], remaining)
        if ready:
            chunk = os.read(pipe, 4096)
            if not chunk:
                break
            chunks.append(chunk)
    message = b"".join(chunks).decode("utf-8", "replace")
    if message.startswith("ok "):  # data complete; reap the exiting child in the background
        threading.Thread(target=os.waitpid, args=(pid, 0), daemon=True).start()
        return message
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status):
        return f"ezc3d crashed ({signal.Signals(os.WTERMSIG(status)).name})"
    return message or "ezc3d exited without a result"


def _in_process(ezc3d, path: Path, n_frames: int, n_points: int) -> Ezc3dPoints | str:
    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as exc:  # noqa: BLE001 - ezc3d raises many types
        return f"ezc3d: {(str(exc).splitlines() or [type(exc).__name__])[0][:100]}"
    points, analogs = c3d["data"]["points"], c3d["data"]["analogs"]
    if points.shape[1:] != (n_points, n_frames):
        return f"ezc3d read {points.shape[2]} frames of {points.shape[1]} points"
    return Ezc3dPoints(np.ascontiguousarray(points[:3].transpose(2, 1, 0)),
                       np.ascontiguousarray(c3d["data"]["meta_points"]["residuals"][0].T),
                       analogs.shape[1] * analogs.shape[2] // max(n_frames, 1))


def _address_space() -> int:
    """Current virtual memory size of this process in bytes (Linux), else 0."""
    try:
        with open("/proc/self/statm", encoding="ascii") as handle:
            return int(handle.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


def available_memory() -> int | None:
    """MemAvailable in bytes (Linux), else None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None
