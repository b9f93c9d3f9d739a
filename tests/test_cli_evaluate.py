"""``mocaptk evaluate`` on a mirrored half-face layout: option errors come before any note."""

from __future__ import annotations

import json

import pytest
from clustering_synthetic import planted_session, save_session


@pytest.fixture(scope="module")
def mirrored(tmp_path_factory):
    """A planted half-face session (.npz), its takes and the mirrored layout clustering makes of it."""
    from mocaptk.clustering.layout import write_layout
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session, load_session

    folder = tmp_path_factory.mktemp("evaluate")
    traj, _ = planted_session(seed=5, per_group=3, frames=240)
    path, takes = save_session(traj, folder / "session.npz")
    session, source = load_session(str(path))
    result = cluster_session(session, options=ClusterOptions(method="paper", stabilize=False, takes=traj.takes), source=source)
    layout = folder / "layout.json"
    write_layout(result.layout, layout)
    assert any(c.mirrored_from is not None for c in result.layout.clusters)  # the note's condition
    return path, takes, layout


@pytest.mark.parametrize("args, message", [
    (["--seeds", "0"], "--seeds must be >= 1, got 0"),
    (["--folds", "1"], "need at least 2 folds, got 1"),
    (["--split", "coin"], "unknown split 'coin'"),
    (["--ridge", "-1"], "ridge must be >= 0"),
    (["--split", "takes", "--takes", "{empty_takes}"], "--split takes needs a session with at least 2 takes"),
])
def test_option_errors_are_the_only_output(run_cli, mirrored, tmp_path, args, message):
    session, _, layout = mirrored
    empty = tmp_path / "one_take.json"
    empty.write_text(json.dumps({"takes": [{"name": "all", "start": 0, "end": 10}]}))
    args = [str(empty) if a == "{empty_takes}" else a for a in args]
    result = run_cli("evaluate", session, "--layout", layout, "--out", tmp_path / "e.json", *args)
    assert result.exit_code == 2
    assert result.stderr.strip().splitlines() == [result.stderr.strip()]  # one line: no note before it
    assert result.stderr.startswith("mocaptk: error: ") and message in result.stderr
    assert result.stdout == "" and not (tmp_path / "e.json").exists()


def test_mirrored_note_follows_a_successful_evaluation(run_cli, mirrored, tmp_path):
    session, takes, layout = mirrored
    result = run_cli("evaluate", session, "--layout", layout, "--takes", takes, "--seeds", "2", "--folds", "3",
                     "--out", tmp_path / "e.json", "--quiet")
    assert result.exit_code == 0, result.stderr
    clusters = json.loads(layout.read_text())["clusters"]
    mirrored_count = sum(c["mirrored_from"] is not None for c in clusters)
    assert result.stderr.strip().splitlines() == [
        f"mocaptk: note: {mirrored_count} mirrored layout markers are not in the session; evaluated the "
        f"{len(clusters) - mirrored_count} measured ones"]
    assert json.loads((tmp_path / "e.json").read_text())["count"] == len(clusters) - mirrored_count


def test_out_is_a_folder_as_for_every_other_command(run_cli, mirrored, tmp_path):
    """``--out DIR`` wrote a file named DIR; now DIR/evaluation.json and .html, both paths printed."""
    session, takes, layout = mirrored
    out = tmp_path / "results"
    result = run_cli("evaluate", session, "--layout", layout, "--takes", takes, "--seeds", "1", "--folds", "2",
                     "--out", out)
    assert result.exit_code == 0, result.stderr
    assert sorted(p.name for p in out.iterdir()) == ["evaluation.html", "evaluation.json"]
    assert f"wrote {out / 'evaluation.json'}" in result.stdout and f"wrote {out / 'evaluation.html'}" in result.stdout


def test_the_layouts_shared_among_processes_give_the_bytes_of_one_process(run_cli, mirrored, tmp_path, monkeypatch):
    """``evaluate`` shares its layouts' held-out fits and lost-marker errors among a forked process
    per CPU (``background.shared_map``): the JSON and the report are the bytes of the run in one."""
    from mocaptk import background

    session, takes, layout = mirrored
    runs = {}
    for fork in (True, False):
        monkeypatch.setattr(background, "can_fork", lambda fork=fork: fork and background.machine_workers() > 1)
        runs[fork] = tmp_path / str(fork)
        result = run_cli("evaluate", session, "--layout", layout, "--takes", takes, "--seeds", "3", "--folds", "3",
                         "--out", runs[fork], "--quiet")
        assert result.exit_code == 0, result.stderr
    for name in ("evaluation.json", "evaluation.html"):
        assert (runs[True] / name).read_bytes() == (runs[False] / name).read_bytes()
