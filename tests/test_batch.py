"""``mocaptk batch`` on real Dask clusters: a LocalCluster started by the command and a separately
started ``dask scheduler`` + 2 ``dask worker`` processes, over 20 short sessions cut from the
bundled sample (2 corrupt, 1 that hangs), against the serial command's outputs.

Cost: only the first batch (the command's own LocalCluster) clusters all 17 sessions. The farm is
started once for the module; its batch of the same line skips them (and kills, retries, times
out), then recomputes two with --force; the later small batches (changed input, evaluate, solve)
go through it too, so no further cluster starts and the runners stay warm."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import pytest
from batch_faults import (dask_farm, free_port, problems, run_trial, runners_alive, tree_hashes,
                          wait_for_workers, worker_pids)
from conftest import REPO

SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"
GOOD = 17
FRAMES = 150
TIMEOUT = "30"  # a short session takes ~1-6 s here (loaded 2-core machine); the hang is killed
MOCAPTK = [sys.executable, "-m", "mocaptk"]
ENV = {**os.environ, "PYTHONWARNINGS": "ignore"}


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> Path:
    """17 short mouth-region sessions (15 markers, 150 frames each, different windows of the
    sample's mouth take), a truncated C3D, a file that is not C3D, and a FIFO: reading it blocks
    forever in open(2), as a stale network mount does."""
    from mocaptk.acquisition.formats import read_trajectories, write_trajectories

    folder = tmp_path_factory.mktemp("sessions")
    traj = read_trajectories(SAMPLE)
    regions = json.loads((REPO / "sample_c3d" / "dense_halfface_regions.json").read_text())
    mouth = traj.take("mouth").select(regions["mouth"])
    for k in range(GOOD):
        write_trajectories(mouth.frames(40 * k, 40 * k + FRAMES), folder / f"actor{k % 3}_s{k:02d}.c3d")
    (folder / "corrupt_cut.c3d").write_bytes((folder / "actor0_s00.c3d").read_bytes()[:3000])
    (folder / "corrupt_text.c3d").write_text("this is not a capture\n")
    os.mkfifo(folder / "a_hangs.c3d")  # first in order: it hangs while the others run
    # one session with its own options (a sidecar beside it overrides the batch line)
    (folder / "actor0_s03.mocaptk.json").write_text(json.dumps({"factor": 1.4, "step": 2}))
    return folder


def _batch(*args, timeout=600, cwd=REPO) -> subprocess.CompletedProcess:
    return subprocess.run([*MOCAPTK, "batch", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=ENV, cwd=cwd)


def _records(out: Path) -> dict[str, dict]:
    return {r["session"]: r for r in json.loads((out / "batch.json").read_text())["sessions"]}


def _files(folder: Path) -> dict[str, bytes]:
    """The command's outputs in a session folder (batch's own log.txt beside them left out)."""
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name != "log.txt"}


@pytest.fixture(scope="module")
def local_run(sessions, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    start = time.perf_counter()
    first = _batch(sessions / "*.c3d", "--do", "cluster", "--formats", "none", "--out", out,
                   "--workers", 2, "--timeout", TIMEOUT)
    seconds = time.perf_counter() - start
    return out, first, _records(out), seconds


def test_local_cluster_isolates_failures(local_run, sessions):
    out, first, records, seconds = local_run
    assert first.returncode == 1, first.stderr[-2000:]  # some sessions failed; the batch finished
    assert "Traceback" not in first.stderr
    done = sorted(s for s, r in records.items() if r["status"] == "done")
    assert done == sorted(f"actor{k % 3}_s{k:02d}" for k in range(GOOD))
    failed = {s: r["error"] for s, r in records.items() if r["status"] == "failed"}
    assert set(failed) == {"corrupt_cut", "corrupt_text", "a_hangs"}
    assert "truncated C3D file" in failed["corrupt_cut"] and failed["corrupt_cut"].startswith(str(sessions))
    assert "corrupt_text.c3d: " in failed["corrupt_text"]
    assert failed["a_hangs"] == f"timed out after {TIMEOUT} s (--timeout): killed"
    md = (out / "batch.md").read_text()
    for session, reason in failed.items():
        assert f"| {session} | cluster | failed |" in md and reason in md
    assert "17 done, 0 skipped (unchanged), 3 failed" in md and "on 2 local workers" in md
    assert all(r["metrics"]["markers"] == 15 and r["metrics"]["layout_markers"] >= 1
               for r in records.values() if r["status"] == "done")
    assert not list(out.glob(".*")), "a killed or failed session left temporary files"
    assert first.stdout.count("| cluster |") == 20 and "done 17" in first.stderr  # table + progress bar
    assert "mocaptk: note: dashboard http://127.0.0.1:" in first.stderr and "ETA" in first.stderr
    print(f"first batch: {seconds:.1f} s")


def test_outputs_identical_to_the_serial_command(local_run, sessions, tmp_path, run_cli):
    out = local_run[0]
    for k, own in ((0, []), (3, ["--factor", "1.4", "--step", "2"])):  # serial, as the CLI runs
        name = f"actor{k % 3}_s{k:02d}"
        serial = tmp_path / "out" / name  # as deep as the batch's: layout.json records its session relatively
        result = run_cli("cluster", sessions / f"{name}.c3d", "--formats", "none", *own, "--out", serial)
        assert result.exit_code == 0, result.stderr
        assert _files(out / name) == _files(serial), name
    assert sorted(p.name for p in (out / "actor0_s00").iterdir()) == ["layout.json", "log.txt", "report.html",
                                                                      "summary.txt"]
    log = (out / "corrupt_cut" / "log.txt").read_text()  # a failed session's own stderr, kept
    assert log.startswith(f"$ mocaptk cluster {sessions / 'corrupt_cut.c3d'}") and "exit code 2" in log
    assert "mocaptk: error: " in log and "truncated C3D file" in log


def test_second_run_skips_unchanged_sessions(local_run, sessions):
    out, _, first, _ = local_run
    again = _batch(sessions / "*.c3d", "--do", "cluster", "--formats", "none", "--out", out,
                   "--workers", 2, "--timeout", 5)
    assert again.returncode == 1, again.stderr[-2000:]
    records = _records(out)
    skipped = sorted(s for s, r in records.items() if r["status"] == "skipped")
    assert len(skipped) == GOOD and all(records[s]["key"] == first[s]["key"] for s in skipped)
    assert {s for s, r in records.items() if r["status"] == "failed"} == {"corrupt_cut", "corrupt_text", "a_hangs"}
    assert "0 done, 17 skipped (unchanged), 3 failed" in (out / "batch.md").read_text()


@pytest.fixture(scope="module")
def farm_folder(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("farm")


@pytest.fixture(scope="module")
def farm(farm_folder):
    """``dask scheduler`` + 2 ``dask worker`` processes on 127.0.0.1 (free ports), configured as
    docs/batch.md says; the workers kill themselves on a ``kill-me`` session (test preload)."""
    with dask_farm(farm_folder, preload=REPO / "tests" / "batch_worker_killer.py") as address:
        yield address


def test_separate_scheduler_and_workers(farm, local_run, sessions, tmp_path):
    """The first batch's line through --scheduler, into its DIR: the farm's workers hash and skip
    the 17, kill the hang, report the corrupt, retry a session that kills its worker once; then
    --force recomputes two sessions on the farm, byte-identical to the LocalCluster batch's (which
    is itself checked against the serial command)."""
    out = local_run[0]
    extra = tmp_path / "extra"
    extra.mkdir()
    (extra / "kill-me.c3d").write_bytes((sessions / "actor0_s00.c3d").read_bytes())
    os.mkfifo(extra / "b_hangs.c3d")  # its sidecar's own timeout wins over the batch line's
    (extra / "b_hangs.mocaptk.json").write_text(json.dumps({"timeout": 2}))
    run = _batch(sessions / "*.c3d", extra / "kill-me.c3d", extra / "b_hangs.c3d", "--do", "cluster",
                 "--formats", "none", "--out", out, "--scheduler", farm, "--timeout", 5)
    assert run.returncode == 1, run.stderr[-2000:]
    records = _records(out)
    assert sorted(s for s, r in records.items() if r["status"] == "skipped") == sorted(
        f"actor{k % 3}_s{k:02d}" for k in range(GOOD))
    failed = {s: r["error"] for s, r in records.items() if r["status"] == "failed"}
    assert set(failed) == {"corrupt_cut", "corrupt_text", "a_hangs", "b_hangs", "kill-me"}
    assert failed["kill-me"] == "the worker processing it died 2 times (retried 1x on another worker)"
    assert [a["ended"] for a in records["kill-me"]["attempts"]] == ["worker lost", "worker lost"]
    assert len({a["worker"] for a in records["kill-me"]["attempts"]}) == 2  # the retry went elsewhere
    assert failed["a_hangs"] == "timed out after 5 s (--timeout): killed"
    assert failed["b_hangs"] == "timed out after 2 s (--timeout): killed"
    hung = records["a_hangs"]  # a killed session's record still tells where and what ran
    assert hung["host"] and hung["cpu_seconds"] is not None and hung["argv"][:2] == ["cluster", str(sessions / "a_hangs.c3d")]
    assert "key" not in hung  # it hung reading its input: no hash to key it by
    assert [a["ended"] for a in hung["attempts"]] == ["timed out"]
    assert all([a["ended"] for a in records[f"actor{k % 3}_s{k:02d}"]["attempts"]] == ["skipped"]
               for k in range(GOOD))
    assert "(2 workers)" in (out / "batch.md").read_text()
    names = ["actor0_s00", "actor2_s05"]
    before = {name: _files(out / name) for name in names}
    forced = _batch(*(sessions / f"{name}.c3d" for name in names), "--do", "cluster", "--formats", "none",
                    "--out", out, "--scheduler", farm, "--force")
    assert forced.returncode == 0, forced.stderr[-2000:]
    records = _records(out)
    for name in names:
        assert records[name]["status"] == "done" and _files(out / name) == before[name], name


def test_worker_killed_and_batch_interrupted_at_random_moments(farm, local_run, sessions, tmp_path):
    """A worker SIGKILLed, then Ctrl-C, then SIGTERM, each at a random moment while sessions run
    (the campaign, 3 kills + 3 Ctrl-C: benchmarks/bench_batch.py --faults). After each batch returned: no file in its DIR
    changes for 10 s, every record tells its attempts, at most one attempt of a session ran to its
    end, its outputs are a clean run's (the LocalCluster batch's), no runner process is left."""
    names = sorted(f"actor{k % 3}_s{k:02d}" for k in range(8))
    reference = {name: {k: v for k, v in tree_hashes(local_run[0] / name).items() if k != "log.txt"}
                 for name in names}
    rng = random.Random(31)
    trials = []
    for kind in ("kill", "interrupt", "terminate"):
        wait_for_workers(farm, 2)  # the killed worker's nanny starts a new one
        trials.append(run_trial(kind, sessions=[str(sessions / f"{n}.c3d") for n in names],
                                out=tmp_path / kind, scheduler=farm, rng=rng, window=(0.0, 3.0)))
    kill, interrupt, terminate = trials
    assert sorted(kill.records) == names and all(r["status"] == "done" for r in kill.records.values())
    assert interrupt.exit_code == 130 or len(interrupt.records) == len(names)  # or it had finished
    assert terminate.exit_code == 143 or len(terminate.records) == len(names)
    problems_found = [p for trial in trials for p in problems(trial, reference)]
    assert problems_found == [], problems_found
    print(f"kill after {kill.delay:.1f} s: attempts "
          f"{ {n: [a['ended'] for a in r['attempts']] for n, r in kill.records.items()} }; "
          f"interrupt after {interrupt.delay:.1f} s: returned {interrupt.stop_seconds:.1f} s later")


def test_two_batches_into_one_out_keep_every_record(farm, farm_folder, sessions, tmp_path):
    """Two batches started together into one DIR (one through the scheduler's file): batch.json
    keeps both's records; a re-run of both sets skips them all."""
    out = tmp_path / "shared"
    line = ("--do", "info", "--out", out, "--scheduler", farm, "--quiet")
    first = subprocess.Popen([*MOCAPTK, "batch", str(sessions / "actor0_*.c3d"), "--do", "info", "--out", str(out),
                              "--scheduler-file", str(farm_folder / "scheduler.json"), "--quiet"],
                             stderr=subprocess.PIPE, text=True, env=ENV)
    second = _batch(sessions / "actor1_*.c3d", *line)
    assert first.wait(timeout=600) == 0 and second.returncode == 0, (first.stderr.read(), second.stderr)
    names = sorted(p.stem for p in sessions.glob("actor[01]_*.c3d"))
    assert sorted(_records(out)) == names and len(names) == 12
    again = _batch(sessions / "actor[01]_*.c3d", *line)
    assert again.returncode == 0, again.stderr[-2000:]
    assert {r["status"] for r in _records(out).values()} == {"skipped"}
    assert not list(out.glob(".*")), "a lock or a journal was left in DIR"


def test_changed_input_is_redone_and_only_it(farm, local_run, sessions):
    """Into the first batch's DIR (after the farm test: that compared its untouched outputs)."""
    out = local_run[0]
    changed = sessions / "actor1_s01.c3d"
    changed.write_bytes((sessions / "actor1_s04.c3d").read_bytes())
    third = _batch(sessions / "actor1_*.c3d", "--do", "cluster", "--formats", "none", "--out", out,
                   "--scheduler", farm)
    assert third.returncode == 0, third.stderr[-2000:]
    records = _records(out)
    assert records["actor1_s01"]["status"] == "done"
    assert [records[f"actor1_s{k:02d}"]["status"] for k in (4, 7, 10, 13, 16)] == ["skipped"] * 5
    source = [json.loads((out / name / "layout.json").read_text())["source"] for name in ("actor1_s01", "actor1_s04")]
    assert source[0]["sha256"] == source[1]["sha256"] and source[0]["path"] == "actor1_s01.c3d"  # redone on the new bytes


def test_scheduler_that_does_not_answer(tmp_path):
    start = time.perf_counter()  # baseline, same run: an address Dask refuses at once (same imports)
    refused = _batch(SAMPLE, "--do", "info", "--out", tmp_path / "o", "--scheduler", "nonsense://x")
    baseline = time.perf_counter() - start
    assert refused.returncode == 2 and refused.stderr.startswith("mocaptk: error: --scheduler nonsense://x")
    start = time.perf_counter()
    run = _batch(SAMPLE, "--do", "info", "--out", tmp_path / "o", "--scheduler",
                 f"tcp://127.0.0.1:{free_port()}", "--connect-timeout", 2)
    seconds = time.perf_counter() - start
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mocaptk: error: --scheduler tcp://127.0.0.1:"), run.stderr
    assert "no Dask scheduler answered within 2 s" in lines[0]
    assert seconds < baseline + 2 + 10, (seconds, baseline)  # the connect timeout + load jitter


def test_pattern_matching_nothing(tmp_path):
    run = _batch(tmp_path / "nothing*.c3d", "--do", "cluster", "--out", tmp_path / "o")
    assert run.returncode == 2
    assert run.stderr.strip() == f"mocaptk: error: no session file matches '{tmp_path}/nothing*.c3d'"
    assert not (tmp_path / "o").exists()


def test_import_and_help_never_import_dask():
    code = ("import sys, mocaptk, mocaptk.cli\n"
            "try:\n    mocaptk.cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
            "try:\n    mocaptk.cli.main(['batch', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert run.stdout.strip().splitlines()[-1] == "[]", run.stdout[-500:] + run.stderr[-500:]


def test_evaluate_batch_reads_the_cluster_batch_layouts(farm, local_run, sessions, tmp_path, run_cli):
    """--do evaluate into the same DIR: DIR/<stem>/layout.json in, evaluation.json beside it (as the
    serial command writes it), and one batch.json listing both commands."""
    out, name = local_run[0], "actor2_s02"
    run = _batch(sessions / f"{name}.c3d", sessions / "corrupt_text.c3d", "--do", "evaluate", "--seeds", 2,
                 "--out", out, "--scheduler", farm)
    assert run.returncode == 1, run.stderr[-2000:]
    serial = run_cli("evaluate", sessions / f"{name}.c3d", "--layout", out / name / "layout.json",
                     "--seeds", "2", "--out", tmp_path / "evaluation.json")
    assert serial.exit_code == 0, serial.stderr
    assert (out / name / "evaluation.json").read_bytes() == (tmp_path / "evaluation.json").read_bytes()
    records = {(r["session"], r["command"]): r for r in json.loads((out / "batch.json").read_text())["sessions"]}
    assert records[(name, "evaluate")]["status"] == "done" and records[(name, "cluster")]["status"] != "failed"
    assert records[(name, "evaluate")]["metrics"]["rmse_mm"] > 0
    assert "no layout for this session" in records[("corrupt_text", "evaluate")]["error"]


def test_solve_batch_with_a_layout_for_all_and_one_from_a_sidecar(farm, local_run, sessions, tmp_path, run_cli):
    """--do solve: the matched files are captures (the layout's markers only), solved with the
    batch line's --layout/--session, or those of a capture's sidecar; outputs as the serial solve."""
    from mocaptk.acquisition.formats import read_trajectories, write_trajectories

    out, layouts = local_run[0], {name: local_run[0] / name / "layout.json" for name in ("actor0_s00", "actor2_s05")}
    captures = tmp_path / "captures"
    captures.mkdir()
    source = read_trajectories(sessions / "actor1_s07.c3d")
    for name, layout in (("take_a", "actor0_s00"), ("take_b", "actor0_s00"), ("take_c", "actor2_s05")):
        doc = json.loads(layouts[layout].read_text())  # its markers and its head's rigid set
        labels = [m for m in dict.fromkeys(doc["layout"] + doc["stabilization"].get("rigid_labels", []))
                  if m in source.labels]
        start = {"take_a": 0, "take_b": 50, "take_c": 20}[name]
        write_trajectories(source.select(labels).frames(start, start + 100), captures / f"{name}.c3d")
    write_trajectories(source.select(source.labels[:1]).frames(0, 50), captures / "take_bad.c3d")
    (captures / "take_c.mocaptk.json").write_text(json.dumps(
        {"layout": str(layouts["actor2_s05"]), "session": str(sessions / "actor2_s05.c3d")}))
    solved = tmp_path / "solved"
    run = _batch(captures / "*.c3d", "--do", "solve", "--layout", layouts["actor0_s00"], "--session",
                 sessions / "actor0_s00.c3d", "--formats", "none", "--out", solved, "--scheduler", farm)
    assert run.returncode == 1, run.stderr[-2000:]
    records = _records(solved)
    assert {s: r["status"] for s, r in records.items()} == {
        "take_a": "done", "take_b": "done", "take_c": "done", "take_bad": "failed"}
    assert "take_bad.c3d: lacks" in records["take_bad"]["error"]
    assert records["take_c"]["argv"][1] == str(layouts["actor2_s05"])  # the sidecar's layout won
    for name, layout in (("take_a", "actor0_s00"), ("take_c", "actor2_s05")):
        serial = run_cli("solve", layouts[layout], captures / f"{name}.c3d", "--session",
                         sessions / f"{layout}.c3d", "--formats", "none", "--out", tmp_path / name)
        assert serial.exit_code == 0, serial.stderr
        assert _files(solved / name) == _files(tmp_path / name), name
    assert "report.html" in _files(solved / "take_a")
    assert records["take_a"]["metrics"]["markers"] == 15
    cluster_record = _records(out)["actor0_s00"]  # one layout, one count, whichever command ran
    assert records["take_a"]["metrics"]["layout_markers"] == cluster_record["metrics"]["layout_markers"]
    assert 0 < records["take_a"]["metrics"]["solve_markers"] <= records["take_a"]["metrics"]["layout_markers"]
    # as docs/batch.md shows it: the layout alone (no --session); layout.json records where its
    # session is (relative to itself, and absolute), checked by sha256
    chained = _batch("captures/take_*[ab].c3d", "--do", "solve", "--layout", layouts["actor0_s00"],
                     "--formats", "none", "--out", "chained", "--scheduler", farm, cwd=tmp_path)
    assert chained.returncode == 0, chained.stderr[-2000:]
    assert {s: r["status"] for s, r in _records(tmp_path / "chained").items()} == {"take_a": "done", "take_b": "done"}
    assert _files(tmp_path / "chained" / "take_a") == _files(solved / "take_a")
    # no layout anywhere: that capture's one line, not a batch error
    (captures / "take_c.mocaptk.json").unlink()
    bare = _batch(captures / "take_c.c3d", "--do", "solve", "--out", tmp_path / "bare", "--scheduler", farm)
    assert bare.returncode == 1, bare.stderr[-2000:]
    assert "no layout for it: give batch --layout L.json" in _records(tmp_path / "bare")["take_c"]["error"]


def test_no_runner_process_outlives_a_batch(local_run, farm):
    """After the batches above (the farm's workers still running), no session runner is left
    (of this farm's workers, or orphaned: another test's batch may be running beside this one)."""
    assert runners_alive(parents=set(worker_pids(farm).values())) == []
