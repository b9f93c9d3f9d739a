"""batch's session side without a cluster: patterns, the command line split, sidecar options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mocaptk.batch.sessions import find_sessions, session_argv, split_batch_line
from mocaptk.errors import InputFileError, OptionError


def test_split_batch_line_keeps_patterns_and_checks_options(tmp_path):
    patterns, options = split_batch_line(
        "cluster", ["a/*.c3d", "--factor", "1.2", "--no-mirror", "b.c3d", "--regions=r.json"], base=tmp_path)
    assert patterns == ["a/*.c3d", "b.c3d"]
    assert options == ["--factor", "1.2", "--no-mirror", "--regions", str(tmp_path / "r.json")]
    with pytest.raises(OptionError, match="mocaptk evaluate has no option --factor"):
        split_batch_line("evaluate", ["x", "--factor", "1"], base=tmp_path)
    with pytest.raises(OptionError, match="--force is set by batch"):
        split_batch_line("cluster", ["x", "--force"], base=tmp_path)


def test_sidecars_folder_then_session_then_relative_paths(tmp_path):
    session = tmp_path / "anna" / "day2.c3d"
    session.parent.mkdir()
    session.write_bytes(b"")
    (session.parent / "mocaptk.json").write_text(json.dumps({"factor": 1.3, "mirror": False, "layout": "x.json"}))
    (session.parent / "day2.mocaptk.json").write_text(json.dumps(
        {"format": "mocaptk.session-options", "version": 1, "regions": "anna_regions.json",
         "rigid": ["H1", "H2", "H3"], "factor": 0.9}))
    argv = session_argv("cluster", session, tmp_path / "out" / "day2", ["--factor", "1.1", "--step", "2"])
    assert argv == ["cluster", str(session), "--factor", "1.1", "--step", "2",
                    "--factor", "1.3", "--no-mirror",  # folder-wide (layout is evaluate's: left out)
                    "--factor", "0.9", "--regions", str(session.parent / "anna_regions.json"),
                    "--rigid", "H1,H2,H3", "--quiet", "--out", str(tmp_path / "out" / "day2")]
    evaluate = session_argv("evaluate", session, tmp_path / "o", [])
    assert evaluate[evaluate.index("--layout") + 1] == str(session.parent / "x.json")
    assert session_argv("info", session, tmp_path / "o", []) == ["info", str(session), "--json"]


@pytest.mark.parametrize("doc, message", [
    ({"regoins": "r.json"}, "unknown option 'regoins' (no batch command has --regoins)"),
    ({"out": "elsewhere"}, "'out' is set by batch for every session"),
    ({"mirror": "yes"}, "'mirror' must be true or false"),
    ({"format": "other"}, "not a session options file"),
    ([1, 2], "expected a JSON object"),
])
def test_bad_sidecar_is_that_sessions_error(tmp_path, doc, message):
    session = tmp_path / "s.c3d"
    session.write_bytes(b"")
    (tmp_path / "s.mocaptk.json").write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        session_argv("cluster", session, tmp_path / "o", [])
    assert str(info.value).startswith(str(tmp_path / "s.mocaptk.json"))


def test_find_sessions_skips_sidecars_and_refuses_shared_stems(tmp_path):
    for name in ("a/x.c3d", "a/x.mocaptk.json", "a/mocaptk.json", "b/y.c3d", "c/x.trc"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text("")
    assert find_sessions([str(tmp_path / "a" / "*"), str(tmp_path / "b" / "*.c3d")]) == [
        tmp_path / "a" / "x.c3d", tmp_path / "b" / "y.c3d"]
    assert find_sessions([str(tmp_path / "**" / "y.c3d")]) == [tmp_path / "b" / "y.c3d"]
    with pytest.raises(OptionError, match="two sessions share the name 'x'"):
        find_sessions([str(tmp_path / "*" / "x.*")])
    with pytest.raises(OptionError, match="no session file matches"):
        find_sessions([str(tmp_path / "a" / "*.c3d"), str(tmp_path / "nope*")])
    assert Path(find_sessions([str(tmp_path / "a" / "x.c3d")])[0]).is_absolute()


def test_solve_takes_its_layout_from_the_batch_line_or_the_sidecar(tmp_path):
    capture = tmp_path / "shoot" / "take1.c3d"
    capture.parent.mkdir()
    capture.write_bytes(b"")
    patterns, options = split_batch_line("solve", ["shoot/*.c3d", "--layout", "L.json", "--formats", "none"],
                                         base=tmp_path)
    assert patterns == ["shoot/*.c3d"] and options == ["--layout", str(tmp_path / "L.json"), "--formats", "none"]
    argv = session_argv("solve", capture, tmp_path / "o", options)
    assert argv == ["solve", str(tmp_path / "L.json"), str(capture), "--formats", "none", "--quiet",
                    "--out", str(tmp_path / "o")]
    (capture.parent / "take1.mocaptk.json").write_text(json.dumps({"layout": "anna/layout.json"}))
    assert session_argv("solve", capture, tmp_path / "o", options)[1] == str(capture.parent / "anna" / "layout.json")
    with pytest.raises(InputFileError, match="no layout for it: give batch --layout L.json"):
        session_argv("solve", tmp_path / "take2.c3d", tmp_path / "o", [])
    with pytest.raises(OptionError, match="mocaptk cluster has no option --layout"):
        split_batch_line("cluster", ["x", "--layout", "L.json"], base=tmp_path)


def test_sidecar_timeout_is_batchs_own_key(tmp_path):
    from mocaptk.batch.sessions import session_timeout

    session = tmp_path / "s.c3d"
    session.write_bytes(b"")
    assert session_timeout(session, 30.0) == 30.0
    (tmp_path / "mocaptk.json").write_text(json.dumps({"timeout": 600}))
    (tmp_path / "s.mocaptk.json").write_text(json.dumps({"timeout": 0, "factor": 1.2}))
    assert session_timeout(session, 30.0) is None  # the session's own wins; 0 = no limit
    assert "--timeout" not in session_argv("cluster", session, tmp_path / "o", [])
    (tmp_path / "s.mocaptk.json").write_text(json.dumps({"timeout": "long"}))
    assert session_timeout(session, 30.0) == 600.0  # a bad value is the runner's error to report
    with pytest.raises(InputFileError, match="'timeout' must be a number of seconds >= 0"):
        session_argv("cluster", session, tmp_path / "o", [])


def test_largest_session_first(tmp_path):
    from mocaptk.batch.engine import tasks

    for name, size in (("a", 10), ("b", 300), ("c", 20), ("d", 300)):
        (tmp_path / f"{name}.c3d").write_bytes(b"x" * size)
    order = tasks(sorted(tmp_path.glob("*.c3d")), command="info", out=tmp_path / "o", options=[], force=False,
                  timeout=None, previous={}, run_id="r")
    assert [Path(t["session"]).stem for t in order] == ["b", "d", "c", "a"]


def _merge_one(out: str, k: int) -> None:
    from mocaptk.batch.summary import update_summary

    record = {"session": f"s{k:02d}", "command": "info", "status": "done", "finished": f"t{k:02d}",
              "warnings": [], "outputs": {}}
    update_summary(Path(out), [record], {"command": "info", "sessions": 1, "cluster": "test", "seconds": 0.0,
                                         "counts": {"done": 1, "skipped": 0, "failed": 0}})


def _merge_when_all_ready(start, out: str, k: int) -> None:
    start.wait()  # all at once
    _merge_one(out, k)


def test_concurrent_summary_updates_keep_every_record(tmp_path):
    """12 processes merge one record each into one batch.json at once: all 12 are kept."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    start = ctx.Barrier(12)
    procs = [ctx.Process(target=_merge_when_all_ready, args=(start, str(tmp_path), k)) for k in range(12)]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(60)
    assert [proc.exitcode for proc in procs] == [0] * 12
    doc = json.loads((tmp_path / "batch.json").read_text())
    assert [r["session"] for r in doc["sessions"]] == [f"s{k:02d}" for k in range(12)]
    assert not list(tmp_path.glob(".*"))  # the lock is gone


def test_newest_record_wins_the_merge():
    from mocaptk.batch.summary import merged

    old = {"session": "a", "command": "info", "status": "done", "finished": "2026-12-06T01:00:00.000Z"}
    new = old | {"status": "failed", "finished": "2026-12-06T02:00:00.000Z"}
    assert merged({("a", "info"): new}, [old]) == [new]
    assert merged({("a", "info"): old}, [new]) == [new]


def test_stale_lock_of_a_dead_process_is_broken(tmp_path):
    import subprocess
    import sys

    from mocaptk.batch.lock import locked
    from mocaptk.errors import OutputError

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock = tmp_path / ".batch.json.lock"
    import socket

    lock.write_text(json.dumps({"host": socket.gethostname(), "pid": int(dead.stdout), "token": "x"}))
    with locked(lock, wait=1):
        assert json.loads(lock.read_text())["token"] != "x"
    assert not lock.exists()
    alive = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        lock.write_text(json.dumps({"host": socket.gethostname(), "pid": alive.pid, "token": "y"}))
        with pytest.raises(OutputError, match="another batch has held this lock"):
            with locked(lock, wait=0.3):
                pass
        assert json.loads(lock.read_text())["token"] == "y"  # a live owner's lock is left alone
    finally:
        alive.kill()
        alive.wait()


def test_solve_finds_the_session_a_layout_records(tmp_path):
    """layout.json records its session relative to itself and absolute; solve finds it after the
    tree moved, and of two same-named files takes the one with the recorded sha256."""
    import hashlib
    import shutil

    from mocaptk.cli.options import session_path

    tree = tmp_path / "project"
    (tree / "captures").mkdir(parents=True)
    (tree / "runs" / "anna").mkdir(parents=True)
    (tree / "captures" / "anna.c3d").write_bytes(b"session bytes")
    source = {"path": "anna.c3d", "sha256": hashlib.sha256(b"session bytes").hexdigest(),
              "absolute": str(tree / "captures" / "anna.c3d"), "relative": "../../captures/anna.c3d"}
    layout = tree / "runs" / "anna" / "layout.json"
    assert session_path(layout, source, None) == tree / "runs" / "anna" / "../../captures/anna.c3d"
    moved = tmp_path / "moved"
    shutil.move(tree, moved)
    (moved / "runs" / "anna" / "anna.c3d").write_bytes(b"another take, same name")
    found = session_path(moved / "runs" / "anna" / "layout.json", source, None)
    assert found.read_bytes() == b"session bytes"
    with pytest.raises(InputFileError, match="its session anna.c3d is not where it records it"):
        session_path(tmp_path / "elsewhere" / "layout.json", source, None)
