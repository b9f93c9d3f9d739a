"""``mocaptk label`` and ``synth --unlabelled`` on the bundled sample (raw captures made from it) and
on blenderFace (real capture, labels stripped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_path

from mocaptk.acquisition.formats import read_trajectories, write_trajectories
from mocaptk.acquisition.labelling import capture as lc
from mocaptk.acquisition.labelling.template import build_template
from mocaptk.acquisition.synth_unlabelled import inject_swaps, load_truth, spread_subset, unlabelled_capture

SAMPLES = Path(__file__).resolve().parents[1] / "sample_c3d"
SESSION, PERFORMANCE = SAMPLES / "dense_halfface.c3d", SAMPLES / "dense_halfface_performance.c3d"


@pytest.fixture(scope="module")
def sample():
    session, performance = read_trajectories(SESSION), read_trajectories(PERFORMANCE)
    return session, performance, build_template(session)


def scores(result, raw, template) -> tuple[float, float, float]:
    """(correct, wrong) per visible marker-frame and labelled ghosts per ghost point."""
    idx = np.array([template.labels.index(label) for label in raw.labels])
    truth = np.where(raw.truth >= 0, idx[np.maximum(raw.truth, 0)], raw.truth)
    visible, ghost, found = truth >= 0, truth == -1, result.labels >= 0
    correct = visible & (result.labels == truth)
    wrong = visible & found & ~correct
    return correct.sum() / visible.sum(), wrong.sum() / visible.sum(), (ghost & found).sum() / max(ghost.sum(), 1)


def test_synth_unlabelled_matches_the_issue_settings(sample):
    _, performance, _ = sample
    raw = unlabelled_capture(performance, seed=5)
    truth = raw.truth
    visible = (truth >= 0).sum()
    assert abs((truth == -1).sum() / visible - 0.02) < 0.002  # 2 % ghosts
    occluded = 1 - visible / (~np.isnan(performance.positions).any(axis=2)).sum()
    assert 0.035 < occluded < 0.065  # ~5 % occluded marker-frames
    # every labelled point is its source marker moved rigidly: distances between two are kept
    f = 600
    cols = np.flatnonzero(truth[f] >= 0)[:2]
    a, b = raw.trajectories.positions[f, cols]
    sa, sb = performance.positions[f, truth[f, cols]]
    assert abs(np.linalg.norm(a - b) - np.linalg.norm(sa - sb)) < 1e-9
    # the head moved by up to ~15 degrees
    angles = np.degrees(np.arccos(np.clip((np.trace(raw.head_rotations, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert 8 < angles.max() < 30
    # fragments: ~2 s on average, so many more runs than markers
    runs = (np.diff(np.vstack([np.zeros((1, truth.shape[1])), truth >= 0]).astype(int), axis=0) == 1).sum()
    assert runs > 5 * performance.n_markers


@pytest.mark.slow
@pytest.mark.parametrize("clouds", [False, True], ids=["fragments", "clouds"])
@pytest.mark.parametrize("count", [139, 40])
def test_label_meets_the_targets_and_beats_the_baseline(sample, clouds, count):
    session, performance, template = sample
    if count != 139:
        keep = spread_subset(session, count)
        performance, template = performance.select(keep), build_template(session.select(keep))
    raw = unlabelled_capture(performance, seed=2, clouds=clouds)
    result = lc.label_capture(template, raw.trajectories)
    assert result.mode == ("clouds" if clouds else "fragments")
    correct, wrong, ghosts = scores(result, raw, template)
    assert correct >= 0.995 and wrong <= 0.001 and ghosts <= 0.001, (correct, wrong, ghosts)
    base = scores(lc.label_capture(template, raw.trajectories, tracked=False), raw, template)
    assert base[0] < correct and base[2] > ghosts  # the rigid-fit Hungarian baseline does worse


def test_chunks_give_the_same_labels_on_one_or_two_threads_and_a_wrong_start_is_redone(sample, monkeypatch):
    """The 1,200-frame capture is labelled as 2 chunks side by side; the labels do not depend on the
    threads. Seed 3 at 40 markers: the second chunk's pose search fails at its start (an extreme
    frame; alone it labels 60.8 %, 13.5 % wrongly), so it is labelled again from the first chunk."""
    from mocaptk.acquisition.labelling import fragments, tracker

    session, performance, _ = sample
    keep = spread_subset(session, 40)
    template = build_template(session.select(keep))
    raw = unlabelled_capture(performance.select(keep), seed=3)
    assert tracker.chunks(raw.trajectories.n_frames) == [(0, 600), (600, 1200)]
    runs = {}
    for threads in (1, 2):
        monkeypatch.setattr(tracker, "THREADS", threads)
        runs[threads] = lc.label_capture(template, raw.trajectories)
    assert np.array_equal(runs[1].labels, runs[2].labels)
    assert np.array_equal(runs[1].confidence, runs[2].confidence)
    correct, wrong, ghosts = scores(runs[2], raw, template)
    assert correct >= 0.995 and wrong <= 0.001 and ghosts <= 0.001, (correct, wrong, ghosts)
    # cloud linking in ranges: the same fragment ids whatever the threads
    clouds = unlabelled_capture(performance.select(keep), seed=3, clouds=True).trajectories.positions
    one = fragments.link_clouds(clouds, template.spacing, threads=1)
    assert np.array_equal(one, fragments.link_clouds(clouds, template.spacing, threads=3))
    assert one.max() < 0.2 * (one >= 0).sum()  # linked: far fewer fragments than points


@pytest.mark.slow
def test_a_lost_marker_is_found_again_after_an_expression_beyond_the_template(sample):
    """The sample's range-of-motion session at 6 Hz (every 10th frame) as untracked clouds, labelled
    with the performance as the template: its extreme expressions go beyond the template, where a
    marker's offset grows to 5-6 mm; once lost, the stale offset held its prediction off the marker
    (97.34 % correct, 0.116 % wrong before). It is now also looked for where the model alone puts it."""
    session, performance, _ = sample
    rom = session.replace(positions=session.positions[::10], rate=session.rate / 10, residuals=None, metadata={})
    raw = unlabelled_capture(rom, seed=1, rotation_deg=0, translation_mm=0, ghosts=0, occluded=0, clouds=True)
    template = build_template(performance)
    correct, wrong, _ = scores(lc.label_capture(template, raw.trajectories), raw, template)
    assert correct >= 0.985 and wrong <= 0.001, (correct, wrong)


def test_cloud_linking_does_not_let_a_ghost_beside_a_marker_carry_on_its_trajectory():
    """A ghost appears 1.0 mm from where a marker was, the marker has moved 1.5 mm: the ghost is the
    marker's nearest point but not clearly, so neither continues its fragment (before, the ghost
    did, and took the marker's label with it)."""
    from mocaptk.acquisition.labelling.fragments import link_clouds

    pos = np.full((2, 4, 3), np.nan)
    pos[0, :3] = [[0, 0, 0], [20, 0, 0], [0, 20, 0]]
    pos[1] = [[0, 20.3, 0], [-1.0, 0, 0], [20.2, 0, 0], [1.5, 0, 0]]  # shuffled; column 1 the ghost
    ids = link_clouds(pos, 9.0)
    assert ids[1, 2] == ids[0, 1] and ids[1, 0] == ids[0, 2]  # the clear ones continue
    assert ids[0, 0] not in (ids[1, 1], ids[1, 3])  # the marker's fragment ends; two new ones start


def test_cloud_linking_of_points_at_exactly_one_place_keeps_the_column_order():
    """Two points at exactly the previous point's place: the first column continues it, as in a
    full scan (the linker compares only points within a band of x, sorted stably)."""
    from mocaptk.acquisition.labelling.fragments import link_clouds

    pos = np.full((2, 3, 3), np.nan)
    pos[0, :2] = [[0, 0, 0], [30, 0, 0]]
    pos[1] = [[30.5, 0, 0], [0, 0, 0], [0, 0, 0]]
    ids = link_clouds(pos, 9.0)
    assert ids[1, 1] == ids[0, 0] and ids[1, 0] == ids[0, 1]
    assert ids[1, 2] not in ids[0]


def test_a_ghost_whose_label_jumps_off_the_markers_track_is_dropped(sample, monkeypatch):
    """Seed 8 of the bench's raw captures: ghosts sit 2-5 mm from where occluded markers
    (NOSE_11_C, CHEEK_11_L) should be, inside the gate; the labels' residuals jump where they take
    over and jump back where the markers return, so their runs are left out of the labels' chains:
    ghosts labelled 0.881 % before, fewer now, with the visible markers as well labelled."""
    session, performance, template = sample
    raw = unlabelled_capture(performance, seed=8)
    now = scores(lc.label_capture(template, raw.trajectories), raw, template)
    monkeypatch.setattr(lc, "drop_jumps", lambda labels, *_, **__: (labels, 0))
    before = scores(lc.label_capture(template, raw.trajectories), raw, template)
    assert before[2] > 0.008 and now[2] < 0.5 * before[2], (before, now)
    assert now[0] >= 0.995 and now[1] == 0.0, now


def test_cli_synth_then_label_writes_capture_report_and_summary(run_cli, tmp_path):
    raw_path = tmp_path / "raw.c3d"
    made = run_cli("synth", raw_path, "--unlabelled", PERFORMANCE, "--seed", "4")
    assert made.exit_code == 0, made.stderr
    truth, source = load_truth(tmp_path / "raw_truth.npz")
    described = run_cli("info", raw_path)
    assert f"0 labelled, {(truth >= 0).sum() + (truth == -1).sum():,} unlabelled" in described.stdout
    out = tmp_path / "labelled.c3d"
    result = run_cli("label", raw_path, "--template", SESSION, "--out", out)
    assert result.exit_code == 0, result.stderr
    assert "uncertain" in result.stdout and "labelled" in result.stdout
    labelled, raw = read_trajectories(out), read_trajectories(raw_path)
    assert labelled.labels[:139] == read_trajectories(SESSION).labels
    assert labelled.rate == raw.rate and labelled.n_frames == raw.n_frames
    # every labelled point is the raw point its truth says
    f = 700
    for col in np.flatnonzero(truth[f] >= 0)[:20]:
        name = source[truth[f, col]]
        assert np.allclose(labelled.positions[f, labelled.labels.index(name)], raw.positions[f, col], atol=1e-3)
    import json
    report = json.loads((tmp_path / "label_report.json").read_text())
    assert report["format"] == "mocaptk.label-report" and report["labelled_points"] > 0.97 * report["points"]
    again = run_cli("label", raw_path, "--template", SESSION, "--out", tmp_path / "again.c3d",
                    "--report", tmp_path / "again.json", "--drop-unlabelled")
    assert again.exit_code == 0 and read_trajectories(tmp_path / "again.c3d").n_markers == 139
    assert (tmp_path / "again.json").read_bytes() == (tmp_path / "label_report.json").read_bytes()


def test_check_finds_injected_swaps_fix_repairs_them_and_clean_capture_has_none(sample):
    _, performance, template = sample
    assert lc.check_labels(template, performance)[0] == []
    swapped, swaps = inject_swaps(performance, 20, seed=0)
    runs, _ = lc.check_labels(template, swapped)
    found = sum(any({r.label, r.found} == {a, b} and r.start < end and r.end > start for r in runs)
                for a, b, start, end in swaps)
    assert found >= 19
    fixed = lc.fix_labels(template, swapped, runs)
    same = np.isclose(fixed.positions, performance.positions, equal_nan=True).all(axis=2)
    assert same.all()


def test_cli_check_and_fix(run_cli, tmp_path, sample):
    _, performance, _ = sample
    swapped, _ = inject_swaps(performance, 3, seed=1)
    write_trajectories(swapped, tmp_path / "swapped.c3d")
    listed = run_cli("label", tmp_path / "swapped.c3d", "--template", SESSION, "--check")
    assert listed.exit_code == 0 and "6 mislabelled runs (6 in swaps)" in listed.stdout, listed.stdout
    fixed = run_cli("label", tmp_path / "swapped.c3d", "--template", SESSION, "--check", "--fix",
                    "--out", tmp_path / "fixed.c3d")
    assert fixed.exit_code == 0
    assert run_cli("label", tmp_path / "fixed.c3d", "--template", SESSION, "--check").stdout.startswith("0 mislabelled")


@pytest.mark.parametrize("subject, other", [(1, 2), (2, 1)])
def test_blenderface_labels_stripped_cut_into_fragments(subject, other):
    """Real capture (blenderFace, 16 markers, 25 Hz): another subject's session as the template, and
    each take labelled with the subject's other takes as the template; the issue's 99 % target in
    every case (measured: 100 % in all 10; S02 "happy" was 98.38 % before a marker whose fragment
    broke was looked for where it was last seen)."""
    from mocaptk.trajectories import concatenate_takes

    def read(k):
        return read_trajectories(shared_path("facial_mocap", "blenderface", f"Subject_0{k}.csv"),
                                 rate=25, units="187.6")
    own, template_session = read(subject), read(other)
    cases = [(own.select(list(template_session.labels)), template_session)]
    for take in own.takes:
        rest = [own.frames(t.start, t.end) for t in own.takes if t.name != take.name]
        cases.append((own.take(take.name), concatenate_takes(rest)))
    totals = np.zeros(3)
    for k, (capture, session) in enumerate(cases):
        template = build_template(session)
        raw = unlabelled_capture(capture, seed=k, rotation_deg=0, translation_mm=0, ghosts=0, occluded=0)
        correct, wrong, _ = scores(lc.label_capture(template, raw.trajectories), raw, template)
        visible = (raw.truth >= 0).sum()
        totals += (correct * visible, wrong * visible, visible)
        assert correct >= 0.99 and wrong <= 0.01, (k, correct, wrong)
    assert totals[0] / totals[2] >= 0.99 and totals[1] / totals[2] <= 0.01, totals


def test_bad_inputs_are_one_line_and_exit_2(run_cli, tmp_path, sample):
    session, performance, _ = sample
    raw = unlabelled_capture(performance.frames(0, 120), seed=0).trajectories
    write_trajectories(raw, tmp_path / "raw.c3d")
    out = tmp_path / "out.c3d"
    cases = {
        "no labels": ("label", tmp_path / "raw.c3d", "--template", tmp_path / "raw.c3d", "--out", out),
    }
    metres = raw.replace(positions=raw.positions / 1000.0)  # written in mm: a face 1000 x too small
    write_trajectories(metres, tmp_path / "metres.c3d")
    cases["units"] = ("label", tmp_path / "metres.c3d", "--template", SESSION, "--out", out)
    body = raw.replace(positions=raw.positions * 12.0)  # points spaced like a body's markers
    write_trajectories(body, tmp_path / "body.c3d")
    cases["body"] = ("label", tmp_path / "body.c3d", "--template", SESSION, "--out", out)
    sparse = raw.replace(positions=np.where(np.arange(raw.n_markers)[None, :, None] < 2, raw.positions, np.nan))
    write_trajectories(sparse, tmp_path / "two.c3d")
    cases["two points"] = ("label", tmp_path / "two.c3d", "--template", SESSION, "--out", out)
    cases["ignored --units"] = ("label", tmp_path / "raw.c3d", "--template", SESSION, "--out", out, "--units", "10")
    face = shared_path("facial_mocap", "blenderface", "Subject_01.csv")  # another face and layout
    cases["other face"] = ("label", face, "--template", SESSION, "--out", out, "--units", "187.6", "--rate", "25")
    for name, args in cases.items():
        result = run_cli(*args)
        assert result.exit_code == 2, (name, result.stdout)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mocaptk: error: "), (name, result.stderr)
        assert not out.exists()


def truly_labelled(raw) -> "Trajectories":
    """The raw capture under its true labels (what a perfect labeller would write; ghosts dropped)."""
    from mocaptk.trajectories import Trajectories

    pos = np.full((raw.trajectories.n_frames, len(raw.labels), 3), np.nan)
    f, c = np.nonzero(raw.truth >= 0)
    pos[f, raw.truth[f, c]] = raw.trajectories.positions[f, c]
    return Trajectories(pos, raw.labels, raw.trajectories.rate, metadata={"takes": []})


@pytest.fixture(scope="module")
def production(tmp_path_factory):
    """A layout of the sample (``mocaptk cluster``) and the performance's layout + stabilization
    markers made raw (±15° / 30 mm, ghosts, occlusions, fragments; ``raw.c3d``), and the same raw
    capture under its true labels (``truth_labelled.c3d``)."""
    import json
    import shutil
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("production")
    shutil.copy(SESSION, root)
    done = subprocess.run([sys.executable, "-m", "mocaptk", "cluster", root / "dense_halfface.c3d", "--out",
                           root / "layout", "--formats", "none", "--quiet"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    layout = json.loads((root / "layout" / "layout.json").read_text())
    wanted = set(layout["layout"]) | set(layout["stabilization"]["rigid_labels"])
    performance = read_trajectories(PERFORMANCE)
    raw = unlabelled_capture(performance.select([m for m in performance.labels if m in wanted]), seed=1)
    write_trajectories(raw.trajectories, root / "raw.c3d")
    write_trajectories(truly_labelled(raw), root / "truth_labelled.c3d")
    return root, wanted, raw


@pytest.mark.slow
def test_solve_label_is_within_5_percent_of_solving_the_truly_labelled_capture(run_cli, production):
    """Issue 29 end to end: ``solve --label`` of the raw production capture against ``solve`` of
    the same capture truly labelled: dense RMSE against the ground truth (moved by the same head
    motion) within 5 % (measured: 0.5210 vs 0.5214 mm)."""
    from mocaptk.acquisition.synth_session import load_ground_truth

    root, wanted, raw = production
    ground = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    moved = (np.einsum("fij,fmj->fmi", raw.head_rotations, ground.positions - raw.pivot) + raw.pivot
             + raw.head_translations[:, None])
    other = [m for m in ground.labels if m not in wanted]  # the markers the solve predicts
    truth = moved[:, [ground.labels.index(m) for m in other]]
    errors = {}
    for name, capture, extra in (("truth", "truth_labelled.c3d", ()), ("label", "raw.c3d", ("--label",))):
        done = run_cli("solve", root / "layout" / "layout.json", root / capture, "--out", root / name,
                       "--formats", "none", "--surface", "markers", *extra)
        assert done.exit_code == 0, done.stderr
        dense = read_trajectories(root / name / "dense.c3d")
        solved = dense.positions[:, [dense.labels.index(m) for m in other]]
        errors[name] = float(np.sqrt(np.nanmean(np.sum((solved - truth) ** 2, axis=2))))
    assert "note: labelled" in done.stdout  # the labelling's summary is a note of the solve
    print(f"dense RMSE: solve --label {errors['label']:.4f} mm, truly labelled {errors['truth']:.4f} mm")
    assert errors["label"] <= 1.05 * errors["truth"], errors
    # mocaptk label with the layout as template: the layout's and stabilization markers, named
    named = run_cli("label", root / "raw.c3d", "--template", root / "layout" / "layout.json", "--out",
                    root / "labelled.c3d", "--drop-unlabelled")
    assert named.exit_code == 0, named.stderr
    assert set(read_trajectories(root / "labelled.c3d").labels) == set(raw.labels)  # (no mirrored twins)
    # without --label the raw capture's *N columns are not the layout's markers: refused
    plain = run_cli("solve", root / "layout" / "layout.json", root / "raw.c3d", "--out", root / "plain",
                    "--formats", "none")
    assert plain.exit_code == 2 and "--label" in plain.stderr, plain.stderr


@pytest.mark.slow
def test_retarget_label_matches_retargeting_the_truly_labelled_capture(run_cli, production):
    root, _, _ = production
    weights = {}
    calibrated = ("--calibration", root / "rt_truth" / "calibration.npz")  # the same fit: skip it
    for name, capture, extra in (("truth", "truth_labelled.c3d", ()), ("label", "raw.c3d", ("--label", *calibrated))):
        done = run_cli("retarget", root / "layout" / "layout.json", root / capture, "--character", "arkit",
                       "--out", root / f"rt_{name}", "--formats", "none", "--no-renders", *extra)
        assert done.exit_code == 0, done.stderr
        with np.load(root / f"rt_{name}" / "weights.npz") as data:
            weights[name] = data["weights"]
    assert "note: labelled" in done.stderr
    gap = np.abs(weights["label"] - weights["truth"]).mean()
    print(f"retarget --label: mean |weight difference| {gap:.5f}")
    assert gap < 0.005, gap


@pytest.mark.slow
def test_batch_do_label_matches_the_single_command(run_cli, tmp_path, sample):
    """``batch --do label``: the template from a capture's sidecar; a capture with no template
    anywhere fails with one line; the outputs are the single command's bytes."""
    import json
    import subprocess
    import sys

    _, performance, _ = sample
    folder = tmp_path / "raw"
    folder.mkdir()
    for k in range(2):
        write_trajectories(unlabelled_capture(performance.frames(0, 240), seed=k).trajectories, folder / f"take{k}.c3d")
    (folder / "take0.mocaptk.json").write_text(json.dumps({"template": str(SESSION)}))
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-m", "mocaptk", "batch", str(folder / "*.c3d"), "--do", "label",
                           "--out", str(out), "--workers", "1", "--quiet"], capture_output=True, text=True)
    assert done.returncode == 1, done.stderr  # take1 has no template
    records = {r["session"]: r for r in json.loads((out / "batch.json").read_text())["sessions"]}
    by_stem = {Path(name).stem: r for name, r in records.items()}
    assert by_stem["take0"]["status"] == "done" and by_stem["take1"]["status"] == "failed"
    metrics = by_stem["take0"]["metrics"]
    assert metrics["markers"] == 139 and metrics["labelled_points"] > 0.97 * metrics["points"], metrics
    assert "--template" in by_stem["take1"]["error"]
    single = run_cli("label", folder / "take0.c3d", "--template", SESSION, "--out", tmp_path / "one" / "labelled.c3d")
    assert single.exit_code == 0, single.stderr
    for name in ("labelled.c3d", "label_report.json"):
        assert (out / "take0" / name).read_bytes() == (tmp_path / "one" / name).read_bytes(), name
