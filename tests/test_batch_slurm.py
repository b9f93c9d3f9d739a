"""``mocaptk batch --cluster slurm`` on a real single-node SLURM (Debian's slurm-wlm + munge,
installed by scripts/install-readers.sh), started here on this host: munged, slurmctld and slurmd
in a private folder with free ports, as root. The same batch through SLURM and through the local
cluster gives the same records and byte-identical outputs. Skips where SLURM cannot start."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from batch_faults import free_port, stop_processes
from conftest import REPO

SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"
DAEMONS = ("munged", "slurmctld", "slurmd")
#: what a record says about where and when it ran, not what it computed
RUN_FIELDS = {"host", "seconds", "cpu_seconds", "attempts", "finished", "argv", "key"}  # argv, key: --out


def _daemon(name: str) -> str | None:
    return shutil.which(name) or next((p for p in (f"/usr/sbin/{name}",) if os.access(p, os.X_OK)), None)


def _slurm_conf(folder: Path, host: str) -> str:
    return "\n".join([
        "ClusterName=mocaptk", f"SlurmctldHost={host}(127.0.0.1)", "SlurmUser=root", "SlurmdUser=root",
        "AuthType=auth/munge", f"AuthInfo=socket={folder}/munge.socket", "CredType=cred/munge",
        f"SlurmctldPort={free_port()}", f"SlurmdPort={free_port()}",
        f"StateSaveLocation={folder}/state", f"SlurmdSpoolDir={folder}/spool",
        f"SlurmctldPidFile={folder}/slurmctld.pid", f"SlurmdPidFile={folder}/slurmd.pid",
        f"SlurmctldLogFile={folder}/slurmctld.log", f"SlurmdLogFile={folder}/slurmd.log",
        # no cgroups in a container: plain process tracking, no task binding, no accounting
        "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none",
        "AccountingStorageType=accounting_storage/none", "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_Core", "SchedulerType=sched/backfill", "MpiDefault=none", "ReturnToService=2",
        f"NodeName={host} NodeAddr=127.0.0.1 CPUs={os.cpu_count()} RealMemory=2000 State=UNKNOWN",
        "PartitionName=batch Nodes=ALL Default=YES MaxTime=INFINITE State=UP", ""])


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    """A running single-node SLURM; yields the environment that reaches it (SLURM_CONF)."""
    missing = [name for name in (*DAEMONS, "sbatch", "sinfo") if _daemon(name) is None]
    if missing:
        pytest.skip(f"SLURM not installed ({', '.join(missing)} missing; scripts/install-readers.sh installs it)")
    if os.geteuid() != 0:
        pytest.skip("starting slurmd needs root")
    folder = tmp_path_factory.mktemp("slurm")
    (folder / "state").mkdir()
    (folder / "spool").mkdir()
    key = folder / "munge.key"
    key.write_bytes(os.urandom(1024))
    key.chmod(0o600)
    host = socket.gethostname()
    (folder / "slurm.conf").write_text(_slurm_conf(folder, host))
    env = {**os.environ, "SLURM_CONF": str(folder / "slurm.conf")}
    log = open(folder / "daemons.log", "w")
    procs = []
    try:
        procs.append(subprocess.Popen(
            [_daemon("munged"), "-F", "--force", f"--key-file={key}", f"--socket={folder}/munge.socket",
             f"--pid-file={folder}/munged.pid", f"--log-file={folder}/munged.log", f"--seed-file={folder}/munge.seed"],
            stdout=log, stderr=log, start_new_session=True))
        procs.append(subprocess.Popen([_daemon("slurmctld"), "-D", "-i"], env=env, stdout=log, stderr=log,
                                      start_new_session=True))
        procs.append(subprocess.Popen([_daemon("slurmd"), "-D"], env=env, stdout=log, stderr=log,
                                      start_new_session=True))
        deadline = time.monotonic() + 60
        state = ""
        while time.monotonic() < deadline and "idle" not in state:
            time.sleep(0.5)
            if any(p.poll() is not None for p in procs):
                break
            state = subprocess.run(["sinfo", "-h", "-o", "%T"], env=env, capture_output=True, text=True).stdout
        if "idle" not in state:
            log.flush()
            pytest.skip(f"SLURM did not start here (node state {state.strip() or 'unknown'}): "
                        f"{(folder / 'daemons.log').read_text()[-300:]}")
        yield env
    finally:
        subprocess.run(["scancel", "--user", "root"], env=env, capture_output=True)
        stop_processes(procs)
        log.close()


def _sessions(folder: Path) -> Path:
    from mocaptk.acquisition.formats import read_trajectories, write_trajectories

    traj = read_trajectories(SAMPLE)
    regions = json.loads((REPO / "sample_c3d" / "dense_halfface_regions.json").read_text())
    mouth = traj.take("mouth").select(regions["mouth"])
    folder.mkdir()
    for k in range(3):
        write_trajectories(mouth.frames(60 * k, 60 * k + 150), folder / f"take{k}.c3d")
    (folder / "broken.c3d").write_text("not a capture\n")
    return folder


def _outputs(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in ("log.txt", "batch.json", "batch.md")}


def _records(out: Path) -> dict[str, dict]:
    return {r["session"]: {k: v for k, v in r.items() if k not in RUN_FIELDS}
            for r in json.loads((out / "batch.json").read_text())["sessions"]}


def test_slurm_batch_matches_the_local_cluster(slurm, tmp_path):
    sessions = _sessions(tmp_path / "sessions")
    config = tmp_path / "dask"
    config.mkdir()
    (config / "jobqueue.yaml").write_text(  # the standard dask-jobqueue file, as docs/batch.md shows
        "jobqueue:\n  slurm:\n    queue: batch\n    cores: 1\n    processes: 1\n    memory: 1GB\n"
        "    walltime: '00:20:00'\n    interface: lo\n"
        f"    log-directory: {tmp_path / 'jobs'}\n    local-directory: {tmp_path / 'scratch'}\n"
        "    scheduler-options: {dashboard_address: '127.0.0.1:0'}\n")
    env = {**slurm, "DASK_CONFIG": str(config), "PYTHONWARNINGS": "ignore"}
    line = [sys.executable, "-m", "mocaptk", "batch", str(sessions / "*.c3d"), "--do", "cluster",
            "--formats", "none", "--workers", "2", "--timeout", "300"]
    local = subprocess.run([*line, "--out", str(tmp_path / "local")], capture_output=True, text=True,
                           env=env, timeout=900)
    farm = subprocess.run([*line, "--out", str(tmp_path / "slurm"), "--cluster", "slurm"],
                          capture_output=True, text=True, env=env, timeout=900)
    assert local.returncode == 1 and farm.returncode == 1, (local.stderr[-2000:], farm.stderr[-2000:])
    assert "on slurm (2 worker jobs)" in (tmp_path / "slurm" / "batch.md").read_text()
    assert _records(tmp_path / "slurm") == _records(tmp_path / "local")
    assert {r["status"] for r in _records(tmp_path / "slurm").values()} == {"done", "failed"}
    assert _outputs(tmp_path / "slurm") == _outputs(tmp_path / "local")
    jobs = list((tmp_path / "jobs").glob("*.err"))
    assert jobs, "no SLURM job ran a worker"  # dask-jobqueue's job logs: the workers were SLURM jobs


def test_unconfigured_farm_is_one_line(tmp_path):
    """No jobqueue.yaml (no memory per job): one line naming the file to write, nothing started."""
    env = {**os.environ, "DASK_CONFIG": str(tmp_path), "PYTHONWARNINGS": "ignore"}
    for extra, message in ((["--cluster", "slurm"], "--cluster slurm: You must specify how much cores and memory"),
                           (["--cluster", "k8s"], "--cluster must be one of slurm, pbs, sge, got 'k8s'"),
                           (["--scheduler-file", str(tmp_path / "none.json")], "no such file")):
        run = subprocess.run([sys.executable, "-m", "mocaptk", "batch", str(SAMPLE), "--do", "info",
                              "--out", str(tmp_path / "o"), *extra], capture_output=True, text=True, env=env)
        assert run.returncode == 2 and run.stderr.count("\n") == 1 and message in run.stderr, run.stderr
    assert not (tmp_path / "o").exists()
