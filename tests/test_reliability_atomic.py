"""Atomic outputs: a run killed with SIGKILL while writing leaves the old file (or none), never a
truncated one; its temporary file is hidden (``.NAME.*.part``) and never has the output's name.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

from mocaptk import Trajectories
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.atomic import atomic_open, atomic_path, write_text
from mocaptk.errors import OutputError


@pytest.fixture(scope="module")
def big_session(tmp_path_factory) -> Path:
    """An .npz session whose text export is ~8 MB (a second or more to write)."""
    rng = np.random.default_rng(0)
    traj = Trajectories(rng.normal(0, 100, (6000, 40, 3)), [f"M{i:02d}" for i in range(40)], 100.0)
    path = tmp_path_factory.mktemp("big") / "big.npz"
    np.savez(path, positions=traj.positions, labels=np.array(traj.labels), rate=traj.rate)
    return path


def kill_while_writing(argv: list[str], folder: Path, *, min_bytes: int = 1 << 18) -> None:
    """Start ``mocaptk ARGV`` and SIGKILL it once its temporary output holds ``min_bytes``."""
    proc = subprocess.Popen([sys.executable, "-m", "mocaptk", *argv], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    try:
        while time.monotonic() < deadline:
            parts = [p for p in folder.iterdir() if ".part" in p.name]
            if parts and parts[0].stat().st_size >= min_bytes:
                break
            if proc.poll() is not None:
                pytest.fail(f"finished before it could be killed: {proc.stderr.read().decode()[-300:]}")
            time.sleep(0.02)
        else:
            pytest.fail("no temporary output appeared")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.parametrize("suffix", [".csv", ".trc"])
def test_convert_killed_mid_write_keeps_the_old_file(big_session, tmp_path, suffix):
    target = tmp_path / f"out{suffix}"
    target.write_bytes(b"the previous, complete output\n")
    kill_while_writing(["convert", str(big_session), str(target), "--force"], tmp_path)
    assert target.read_bytes() == b"the previous, complete output\n"
    leftovers = [p.name for p in tmp_path.iterdir() if p != target]
    assert leftovers and all(n.startswith(f".{target.name}.") and n.endswith(".part") for n in leftovers)


def test_convert_killed_mid_write_without_old_file_leaves_no_output(big_session, tmp_path, run_cli):
    target = tmp_path / "fresh.trc"
    kill_while_writing(["convert", str(big_session), str(target)], tmp_path)
    assert not target.exists()
    # the next run is not confused by the hidden leftover and writes a complete file
    done = run_cli("convert", big_session, target)
    assert done.exit_code == 0, done.stderr
    assert read_trajectories(target).positions.shape == (6000, 40, 3)


def test_error_inside_a_write_leaves_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "data.txt"
    write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_open(target, "w") as handle:
        handle.write("new, half written")
        raise RuntimeError("disk full, say")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["data.txt"]
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "fig.png") as tmp:
        tmp.write_bytes(b"\x89PNG partial")
        raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["data.txt"]


def test_existing_output_needs_force_and_folders_are_refused(tmp_path):
    target = tmp_path / "a.json"
    write_text(target, "{}")
    with pytest.raises(OutputError, match="already exists"):
        write_text(target, "[]", force=False)
    assert target.read_text() == "{}"
    with pytest.raises(OutputError, match="is a folder"):
        write_text(tmp_path, "x")
    blocked = tmp_path / "file"
    blocked.write_text("x")
    with pytest.raises(OutputError, match="cannot write"):
        write_text(blocked / "sub" / "out.txt", "x")  # parent is a file


def test_atomic_output_permissions_follow_a_normal_file(tmp_path):
    target = write_text(tmp_path / "x.txt", "x")
    assert os.stat(target).st_mode & 0o777 == 0o644
