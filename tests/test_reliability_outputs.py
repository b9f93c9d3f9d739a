"""Where outputs go and how they land: read-only data folders, a full disk, the umask, ``--force``
swapping a whole folder in one rename (also under SIGKILL), and one writer per output at a time.

Tests run as root here, where ``chmod`` does not stop a write: read-only and full filesystems are
real ones (a tmpfs mounted read-only, or tiny), which stop root too; as a normal user a ``chmod
0o555`` folder does the same job. Tests that need a mount skip when neither is possible.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from clustering_synthetic import planted_session, save_session
from conftest import REPO, SAMPLES

from mocaptk.atomic import claim_output, release_claims, staged_folder
from mocaptk.errors import OutputError


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A small planted half-face session (.npz + takes), clustered in a second."""
    folder = tmp_path_factory.mktemp("planted")
    traj, _ = planted_session(seed=5, per_group=3, frames=240)
    path, _ = save_session(traj, folder / "planted.npz")
    return path


@contextlib.contextmanager
def tmpfs(path: Path, *, size: str = "4m") -> Path:
    """A fresh tmpfs at ``path`` (skips the test when mounting is not allowed)."""
    path.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True, text=True)
    if done.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


@contextlib.contextmanager
def read_only_copy(files: list[Path], folder: Path) -> Path:
    """``folder`` holding copies of ``files`` that nobody, root included, can write into."""
    if os.geteuid() != 0:
        folder.mkdir()
        for f in files:
            shutil.copy(f, folder)
        folder.chmod(0o555)
        try:
            yield folder
        finally:
            folder.chmod(0o755)
        return
    with tmpfs(folder) as mount:
        for f in files:
            shutil.copy(f, mount)
        subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
        yield mount


def one_error_line(result) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("mocaptk: error: "), result.stderr
    return lines[0]


def test_read_only_data_folder_fails_fast_in_one_line_naming_out(run_cli, session, tmp_path):
    with read_only_copy([session], tmp_path / "ro") as ro:
        data = ro / session.name
        with pytest.raises(OSError):  # the folder really refuses writes, for root too
            (ro / "probe").write_text("x")
        for args in (("cluster", data, "--formats", "none"), ("sweep", data, "--factors", "1.0"),
                     ("compare", data, "--counts", "5", "--methods", "random")):
            line = one_error_line(run_cli(*args, "--no-stabilize"))
            assert "cannot write" in line and "--out" in line and str(ro) in line, line
        assert sorted(p.name for p in ro.iterdir()) == ["planted.npz"]
        done = run_cli("cluster", data, "--no-stabilize", "--formats", "none", "--out", tmp_path / "mine", "-q")
        assert done.exit_code == 0, done.stderr
        assert (tmp_path / "mine" / "layout.json").is_file()


def test_help_says_where_outputs_go(run_cli):
    for command, needle in (("cluster", "next to the session"), ("sweep", "next to"),
                            ("evaluate", "beside the layout"), ("compare", "next to")):
        text = " ".join(run_cli(command, "--help").stdout.replace("│", " ").split())
        assert needle in text, command


def test_full_disk_is_one_line_and_leaves_nothing(run_cli, session, tmp_path):
    with tmpfs(tmp_path / "full", size="80k") as full:
        result = run_cli("cluster", session, "--no-stabilize", "--formats", "none", "--out", full / "out")
        line = one_error_line(result)
        assert "no space left on device" in line and str(full / "out") in line, line
        assert list(full.iterdir()) == []  # no half-written folder, no staging, no lock file


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077])
def test_output_folders_and_files_follow_the_umask(run_cli, session, tmp_path, mask):
    old = os.umask(mask)
    try:
        done = run_cli("cluster", session, "--no-stabilize", "--formats", "none", "--out", tmp_path / "c", "-q")
        swept = run_cli("sweep", session, "--no-stabilize", "--factors", "1.0", "--out", tmp_path / "s", "-q")
    finally:
        os.umask(old)
    assert done.exit_code == 0 and swept.exit_code == 0, done.stderr + swept.stderr
    for folder in (tmp_path / "c", tmp_path / "s"):
        assert folder.stat().st_mode & 0o777 == 0o777 & ~mask, folder
        for f in folder.iterdir():
            assert f.stat().st_mode & 0o777 == 0o666 & ~mask, f


def test_force_replaces_the_whole_folder(run_cli, session, tmp_path):
    out = tmp_path / "out"
    assert run_cli("cluster", session, "--no-stabilize", "--formats", "none", "--out", out, "-q").exit_code == 0
    (out / "stale_from_an_old_run.png").write_bytes(b"old")
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    again = run_cli("cluster", session, "--no-stabilize", "--formats", "none", "--out", out, "--force", "-q")
    assert again.exit_code == 0, again.stderr
    now = {p.name: p.read_bytes() for p in out.iterdir()}
    assert "stale_from_an_old_run.png" not in now and now == {k: v for k, v in first.items() if k in now}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing aside, no lock left


def old_folder(out: Path) -> Path:
    """``out`` holding 17 files reading "old" (a killed swap's new folder holds 17 "new" ones)."""
    out.mkdir()
    for i in range(17):
        (out / f"file{i:02d}.txt").write_text("old")
    return out


SWAP_KILLER = """
import os, signal, sys
from pathlib import Path
import mocaptk.atomic
from mocaptk.atomic import staged_folder
out, kill_at = Path(sys.argv[1]), int(sys.argv[2])
mocaptk.atomic._exchange = lambda a, b: False  # the fallback of systems without RENAME_EXCHANGE
real_replace, calls = os.replace, [0]
def replace(a, b):  # the fault: SIGKILL just before the kill_at-th rename of the swap
    calls[0] += 1
    if calls[0] == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
    real_replace(a, b)
os.replace = replace
with staged_folder(out, force=True) as folder:
    for i in range(17):
        (folder / f"file{i:02d}.txt").write_text("new")
os.kill(os.getpid(), signal.SIGKILL)  # kill_at past the swap: die before anything else runs
"""


@pytest.mark.parametrize("kill_at", [1, 2, 3])
def test_sigkill_mid_swap_leaves_old_or_new_never_a_mix(tmp_path, kill_at):
    """Without an atomic exchange (two renames): killed before the swap, between its two renames,
    or after it (before the old folder is removed): the next claim recovers a complete folder,
    old or new, and cleans up."""
    out = old_folder(tmp_path / "out")
    proc = subprocess.run([sys.executable, "-c", SWAP_KILLER, str(out), str(kill_at)], cwd=REPO)
    assert proc.returncode == -signal.SIGKILL
    claim_output(out, force=True, folder=True)
    release_claims()
    contents = {p.read_text() for p in out.iterdir()}
    assert len(list(out.iterdir())) == 17 and contents in ({"old"}, {"new"}), contents
    assert contents == ({"old"} if kill_at <= 2 else {"new"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


EXCHANGE_KILLER = """
import os, shutil, signal, sys
from pathlib import Path
import mocaptk.atomic
from mocaptk.atomic import staged_folder
out, kill_at = Path(sys.argv[1]), int(sys.argv[2])
real_exchange, real_unlink, steps = mocaptk.atomic._exchange, os.unlink, [0]
def step():  # the fault: SIGKILL at the kill_at-th step of the swap
    steps[0] += 1
    if steps[0] == kill_at:
        os.kill(os.getpid(), signal.SIGKILL)
def exchange(a, b):
    step()
    assert real_exchange(a, b), "no RENAME_EXCHANGE here"
    step()
    return True
def unlink(path, *args, **kwargs):  # rmtree of the old folder, file by file
    step()
    real_unlink(path, *args, **kwargs)
mocaptk.atomic._exchange = exchange
with staged_folder(out, force=True) as folder:
    for i in range(17):
        (folder / f"file{i:02d}.txt").write_text("new")
    os.unlink = unlink
os.kill(os.getpid(), signal.SIGKILL)
"""


def exchange_supported(tmp_path: Path) -> bool:
    from mocaptk.atomic import _exchange

    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    try:
        return _exchange(tmp_path / "a", tmp_path / "b")
    finally:
        for name in ("a", "b"):
            (tmp_path / name).rmdir()


@pytest.mark.parametrize("kill_at", [1, 2, 3, 9, 18])
def test_sigkill_during_the_exchange_swap_leaves_a_complete_out_at_every_moment(tmp_path, kill_at):
    """With renameat2(RENAME_EXCHANGE): killed before the exchange, just after it, or while the old
    folder is removed: out/ is complete (17 files, all old or all new) before any recovery, and the
    next claim only removes the leftover."""
    if not exchange_supported(tmp_path):
        pytest.skip("no renameat2(RENAME_EXCHANGE) on this system or filesystem")
    out = old_folder(tmp_path / "out")
    proc = subprocess.run([sys.executable, "-c", EXCHANGE_KILLER, str(out), str(kill_at)], cwd=REPO)
    assert proc.returncode == -signal.SIGKILL
    contents = {p.read_text() for p in out.iterdir()}  # as a reader sees it, before any recovery
    assert len(list(out.iterdir())) == 17 and contents == ({"old"} if kill_at == 1 else {"new"}), contents
    claim_output(out, force=True, folder=True)
    release_claims()
    assert {p.read_text() for p in out.iterdir()} == contents
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def holding_the_lock(argv: list[str], out: Path, *, cwd: Path | None = None) -> subprocess.Popen:
    """``mocaptk ARGV`` started in a process, returned once it holds the lock of ``out``."""
    first = subprocess.Popen([sys.executable, "-m", "mocaptk", *argv], cwd=cwd,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out.parent / f".{out.name}.lock").exists():
        assert first.poll() is None and time.monotonic() < deadline, first.stderr.read()
        time.sleep(0.05)
    return first


def test_second_writer_of_the_same_output_fails_in_one_line(run_cli, tmp_path):
    """Two concurrent ``cluster`` runs into one folder: the second stops at once, the first wins."""
    out = tmp_path / "out"
    session_file = SAMPLES / "dense_halfface.c3d"
    first = holding_the_lock(["cluster", str(session_file), "--factor", "1.1", "--formats", "none",
                              "--out", str(out), "-q"], out, cwd=tmp_path)
    try:
        second = run_cli("cluster", session_file, "--factor", "1.3", "--formats", "none", "--out", out)
        line = one_error_line(second)
        assert line == f"mocaptk: error: {out}: is being written by another mocaptk process"
    finally:
        _, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    layout = (out / "layout.json").read_text()
    assert '"factor": 1.1' in layout


def test_library_staged_folder_refuses_a_folder_locked_by_another_process(tmp_path):
    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from mocaptk.atomic import claim_output; "
                               f"claim_output({str(out)!r}, force=False, folder=True); print('held', flush=True); "
                               "time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputError, match="being written by another mocaptk process"):
            with staged_folder(out, force=False):
                pass
    finally:
        holder.kill()
        holder.wait()
    with staged_folder(out, force=False) as folder:  # the lock died with its process
        (folder / "a.txt").write_text("a")
    assert (out / "a.txt").read_text() == "a"


@pytest.fixture(scope="module")
def solved(tmp_path_factory, session):
    """(layout.json, model.npz) of the planted session, made by cluster and solve."""
    from mocaptk.cli import main

    folder = tmp_path_factory.mktemp("solved")
    for argv in (["cluster", str(session), "--no-stabilize", "--formats", "none", "--out", str(folder / "lay"), "-q"],
                 ["solve", str(folder / "lay" / "layout.json"), str(session), "--session", str(session),
                  "--out", str(folder / "s"), "--formats", "npz", "--no-stabilize", "-q"]):
        main(argv)  # exit 0: returns
    return folder / "lay" / "layout.json", folder / "s" / "model.npz"


def fill(folder: Path, leave: int) -> None:
    """Fill the filesystem of ``folder`` up to ``leave`` free bytes with a hidden file."""
    stat = os.statvfs(folder)
    free = stat.f_bavail * stat.f_frsize
    with open(folder / ".filler", "wb") as handle:
        handle.write(b"\0" * max(0, free - leave))


@pytest.mark.slow
@pytest.mark.parametrize("leave", [0, 50_000, 1 << 20, 3 << 20])
def test_solve_on_a_full_disk_is_one_line_and_leaves_nothing(run_cli, session, solved, tmp_path, leave):
    """The campaign's SIGBUS (mesh_frames.npy mapped on a full tmpfs) and USD's own exception: now
    one line, exit 2, and nothing of the run left on the disk."""
    layout, model = solved
    with tmpfs(tmp_path / "full", size="6m") as full:
        fill(full, leave)
        result = run_cli("solve", layout, session, "--model", model, "--out", full / "out",
                         "--formats", "npz,usd,glb", "--no-stabilize")
        line = one_error_line(result)
        assert "no space left on device" in line, line
        assert [p.name for p in full.iterdir()] == [".filler"]


@pytest.mark.slow
def test_every_command_on_a_full_disk_is_one_line(run_cli, session, solved, tmp_path):
    layout, model = solved
    with tmpfs(tmp_path / "full", size="1m") as full:
        fill(full, 20_000)
        for argv in (("cluster", session, "--no-stabilize", "--formats", "none", "--out", full / "c"),
                     ("sweep", session, "--no-stabilize", "--factors", "1.0", "--out", full / "w"),
                     ("evaluate", session, "--layout", layout, "--seeds", "1", "--out", full / "e" / "ev.json"),
                     ("rig", layout, "--session", session, "--formats", "json", "--no-stabilize", "--out", full / "r"),
                     ("solve", layout, session, "--model", model, "--no-stabilize", "--out", full / "s"),
                     ("convert", session, full / "x.c3d"),
                     ("clean", session, full / "clean.c3d")):
            line = one_error_line(run_cli(*argv))
            assert "no space left on device" in line or "cannot write" in line, (argv[0], line)
            assert [p.name for p in full.iterdir()] == [".filler"], argv[0]


def test_solve_and_rig_refuse_a_read_only_output_before_reading_anything(run_cli, session, tmp_path):
    """The output is checked first: the layout named here does not even exist."""
    with read_only_copy([session], tmp_path / "ro") as ro:
        for argv in (("solve", tmp_path / "missing.json", session, "--out", ro / "out"),
                     ("rig", tmp_path / "missing.json", "--session", session, "--out", ro / "rig")):
            line = one_error_line(run_cli(*argv))
            assert "cannot write" in line and str(ro) in line, line


def test_a_failed_run_leaves_no_empty_output_folder(run_cli, session, tmp_path):
    for argv in (("evaluate", session, "--layout", tmp_path / "missing.json", "--out", tmp_path / "e" / "x.json"),
                 ("plan", tmp_path / "missing.json", "--session", session, "--rig", "cara",
                  "--out", tmp_path / "p" / "deeper")):
        one_error_line(run_cli(*argv))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_second_solve_one_second_later_into_the_same_folder_is_refused(run_cli, tmp_path):
    """The lock is taken before the training, not only for the final swap: two solves started 1 s
    apart into one folder (with --force) both ran to exit 0 before. The sample's 6,841 frames make
    the first one train for seconds."""
    from mocaptk.cli import main

    session, lay, out = SAMPLES / "dense_halfface.c3d", tmp_path / "lay", tmp_path / "out"
    main(["cluster", str(session), "--method", "paper", "--formats", "none", "--out", str(lay), "-q"])
    argv = ["solve", str(lay / "layout.json"), str(session), "--session", str(session), "--out", str(out),
            "--formats", "npz", "--force", "-q"]
    first = holding_the_lock(argv, out)
    try:
        time.sleep(1)
        assert first.poll() is None, "the first solve ended within a second: nothing to race"
        second = run_cli(*argv)
        assert one_error_line(second) == f"mocaptk: error: {out}: is being written by another mocaptk process"
    finally:
        _, err = first.communicate(timeout=900)
    assert first.returncode == 0, err


def test_the_recorded_sha256_is_that_of_the_bytes_read(session, tmp_path, monkeypatch):
    """A file cut while it is read is refused; else the digest is that of the bytes parsed."""
    import hashlib

    import mocaptk.acquisition.formats as formats
    from mocaptk.clustering.pipeline import load_session
    from mocaptk.errors import InputFileError

    path = tmp_path / session.name
    shutil.copy(session, path)
    _, source = load_session(str(path))
    assert source["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    real = formats.read_trajectories

    def read_then_cut(file, **kwargs):  # another program truncates the file during the read
        traj = real(file, **kwargs)
        with open(file, "r+b") as handle:
            handle.truncate(100)
        return traj

    monkeypatch.setattr(formats, "read_trajectories", read_then_cut)
    with pytest.raises(InputFileError, match="changed while it was read"):
        load_session(str(path))
