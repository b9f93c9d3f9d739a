"""Fault trials of ``mocaptk batch`` on a running Dask scheduler: SIGKILL one worker, or Ctrl-C
(SIGINT) the batch, at a random moment while sessions run; then check what a farm user relies on.

Used by tests/test_batch.py (one trial of each kind) and benchmarks/bench_batch.py --faults (the
campaign: 3 of each). Nothing in mocaptk knows this module.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

MOCAPTK = [sys.executable, "-m", "mocaptk"]
#: how long after the batch returned its outputs must still be unchanged
SETTLE_SECONDS = 10.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def dask_farm(folder: Path, *, workers: int = 2, preload: Path | None = None,
              env: dict[str, str] | None = None) -> Iterator[str]:
    """``dask scheduler`` + ``workers`` ``dask worker`` processes on 127.0.0.1 (free ports),
    configured as docs/batch.md says; yields the scheduler's address. The scheduler writes its
    file to folder/scheduler.json (for --scheduler-file); logs go to folder/farm.log."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONWARNINGS": "ignore", "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "1",
           "DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION": "1.0", **(env or {})}
    dask = str(Path(sys.executable).with_name("dask"))
    log = open(folder / "farm.log", "w")
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(folder / "scheduler.json")],
                              env=env, stdout=log, stderr=log, start_new_session=True)]
    try:
        for _ in range(workers):
            procs.append(subprocess.Popen(
                [dask, "worker", address, "--nworkers", "1", "--nthreads", "1", "--host", "127.0.0.1",
                 "--dashboard-address", "127.0.0.1:0", "--memory-limit", "0",
                 *(["--preload", str(preload)] if preload else [])],
                env=env, stdout=log, stderr=log, start_new_session=True, cwd=folder))
        wait_for_workers(address, workers)
        yield address
    finally:
        stop_processes(procs)
        log.close()


def stop_processes(procs: list[subprocess.Popen]) -> None:
    """SIGTERM the process groups started (last first), SIGKILL any still there 30 s later."""
    for proc in reversed(procs):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def wait_for_workers(address: str, count: int) -> None:
    """Until ``count`` workers are connected (a killed one is restarted by its nanny)."""
    from distributed import Client

    with Client(address, timeout=60) as client:
        client.wait_for_workers(count, timeout=120)


def tree_hashes(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` (hidden ones too), by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def runners_alive(*, parents: set[int] | None = None) -> list[int]:
    """PIDs of session runners of this venv (python or python3: ``dask worker``'s shebang): none
    may outlive a batch. ``parents``: only runners started by these worker PIDs (their argv names
    it) or orphaned (that worker gone), not those of another test's batch running beside this one."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
            state = (proc / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        venv = Path(cmd[0].decode()).parent == Path(sys.executable).parent
        if state != "Z" and len(cmd) > 4 and venv and cmd[2] == b"mocaptk.batch.runner" and (
                parents is None or int(cmd[4]) in parents or not Path(f"/proc/{int(cmd[4])}").exists()):
            pids.append(int(proc.name))
    return pids


@dataclass
class Trial:
    """One fault trial: what was done when, and what was found."""

    kind: str  # "kill" (SIGKILL a worker), "interrupt" (SIGINT the batch) or "terminate" (SIGTERM it)
    out: Path
    delay: float = 0.0  # seconds after the first session started
    exit_code: int | None = None
    stop_seconds: float = 0.0  # from the fault to the batch's return
    records: dict[str, dict] = field(default_factory=dict)
    hashes: dict[str, str] = field(default_factory=dict)  # right after the return
    returned: float = 0.0  # time.monotonic() of the return
    runners_left: list[int] = field(default_factory=list)
    stderr: str = ""


def worker_pids(scheduler: str) -> dict[str, int]:
    """The PID of each worker of the dask ``scheduler``, by worker address."""
    from distributed import Client

    with Client(scheduler, timeout=30) as client:
        return client.run(os.getpid)


def _first_session_started(out: Path, process: subprocess.Popen, limit: float = 300.0) -> bool:
    """Wait until a session's attempt is in the journal (sessions are running)."""
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline and process.poll() is None:
        if any(p.stat().st_size for p in (out / ".mocaptk-batch").rglob("*.jsonl")) if (out / ".mocaptk-batch").is_dir() else False:
            return True
        time.sleep(0.05)
    return False


def run_trial(kind: str, *, sessions: list[str], out: Path, scheduler: str, rng: random.Random,
              window: tuple[float, float], extra: tuple[str, ...] = ()) -> Trial:
    """Start a batch of ``sessions`` into ``out`` on ``scheduler``; once a session runs, wait a
    random time in ``window`` (seconds), then SIGKILL one worker (``kill``), SIGINT the batch (``interrupt``,
    as Ctrl-C) or SIGTERM it (``terminate``)."""
    trial = Trial(kind, out, delay=rng.uniform(*window))
    workers = worker_pids(scheduler)
    process = subprocess.Popen([*MOCAPTK, "batch", *sessions, "--do", "cluster", "--formats", "none",
                                "--out", str(out), "--scheduler", scheduler, *extra],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "PYTHONWARNINGS": "ignore"})
    if _first_session_started(out, process):
        time.sleep(trial.delay)
    fault = time.monotonic()
    if process.poll() is None:
        if kind == "kill":
            os.kill(rng.choice(sorted(workers.values())), signal.SIGKILL)
        else:
            process.send_signal(signal.SIGINT if kind == "interrupt" else signal.SIGTERM)
    trial.stderr = process.communicate(timeout=600)[1]
    trial.returned = time.monotonic()
    trial.stop_seconds = trial.returned - fault
    trial.exit_code = process.returncode
    trial.hashes = tree_hashes(out)
    trial.runners_left = runners_alive(parents=set(workers.values()))
    batch_json = out / "batch.json"
    if batch_json.exists():
        trial.records = {r["session"]: r for r in json.loads(batch_json.read_text())["sessions"]}
    return trial


def problems(trial: Trial, reference: dict[str, dict[str, str]]) -> list[str]:
    """What went wrong in a trial, settled (call at least SETTLE_SECONDS after its return).

    ``reference``: a clean run's output files (name -> sha256, log.txt left out) per session."""
    found = []
    wait = trial.returned + SETTLE_SECONDS - time.monotonic()
    if wait > 0:
        time.sleep(wait)
    if tree_hashes(trial.out) != trial.hashes:
        found.append(f"{trial.kind}: files changed after the batch returned")
    if trial.runners_left:
        found.append(f"{trial.kind}: runner processes left: {trial.runners_left}")
    leftovers = [name for name in trial.hashes if "/." in f"/{name}"]  # parts, locks, journals
    if leftovers:
        found.append(f"{trial.kind}: temporary files left: {leftovers}")
    expected = {"kill": 0, "interrupt": 130, "terminate": 143}[trial.kind]
    if trial.exit_code not in (expected, 0):  # 0: the batch had finished before the signal
        found.append(f"{trial.kind}: exit code {trial.exit_code}: {trial.stderr[-400:]}")
    for name, record in trial.records.items():
        attempts = record.get("attempts") or []
        if not attempts or not all({"host", "start", "end", "ended"} <= set(a) for a in attempts):
            found.append(f"{trial.kind}: {name}: attempts not recorded: {attempts}")
        if sum(a["ended"] in ("done", "failed", "timed out") for a in attempts) > 1:
            found.append(f"{trial.kind}: {name}: more than one attempt ran to its end: {attempts}")
        if record["status"] == "done":
            on_disk = {k: v for k, v in tree_hashes(trial.out / name).items() if k != "log.txt"}
            if on_disk != reference.get(name) or on_disk != record["outputs"]:
                found.append(f"{trial.kind}: {name}: outputs differ from a clean run's or from its record")
        elif record["status"] != "interrupted" or trial.kind == "kill":
            found.append(f"{trial.kind}: {name}: {record['status']}: {record.get('error')}")
    return found
