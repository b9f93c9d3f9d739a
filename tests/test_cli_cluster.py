"""``mocaptk cluster`` / ``sweep`` / ``evaluate`` end to end: synthetic files, the sample, real data."""

from __future__ import annotations

import json

import numpy as np
import pytest
from clustering_synthetic import planted_session, save_session
from conftest import SAMPLES, shared_path


@pytest.fixture(scope="module")
def session_files(tmp_path_factory):
    """A planted half-face session as .npz plus its takes file."""
    folder = tmp_path_factory.mktemp("planted")
    traj, group_of = planted_session(seed=21)
    path, takes = save_session(traj, folder / "planted.npz")
    return path, takes, group_of


def test_cluster_writes_all_outputs_deterministically(run_cli, session_files, tmp_path):
    path, takes, group_of = session_files
    first = run_cli("cluster", path, "--takes", takes, "--no-stabilize", "--out", tmp_path / "a",
                    "--formats", "none")  # rig + guide outputs are tested with the rig commands
    assert first.exit_code == 0, first.stderr
    assert "total" in first.stdout
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == ["layout.json", "report.html", "summary.txt"]  # --formats none: no pictures either
    second = run_cli("cluster", path, "--takes", takes, "--no-stabilize", "--out", tmp_path / "b", "--quiet",
                     "--formats", "none")
    assert second.exit_code == 0 and second.stdout == ""
    assert (tmp_path / "a" / "layout.json").read_bytes() == (tmp_path / "b" / "layout.json").read_bytes()
    data = json.loads((tmp_path / "a" / "layout.json").read_text())
    measured = [c for c in data["clusters"] if c["mirrored_from"] is None]
    assert len(measured) == len(set(group_of.values()))
    assert data["parameters"]["stabilized"] is False and data["parameters"]["mirror"] is True
    assert data["source"]["sha256"] and data["source"]["path"] == "planted.npz"
    assert "forehead_brow" in (tmp_path / "a" / "summary.txt").read_text()


def test_cluster_refuses_existing_folder_and_bad_options(run_cli, session_files, tmp_path):
    path, takes, _ = session_files
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    for args, needle in [
        ((), "--force"),
        (("--force", "--factor", "0"), "factor"),
        (("--force", "--step", "100000"), "step"),
        (("--force", "--regions", path.with_name("missing.json")), "missing.json"),
    ]:
        result = run_cli("cluster", path, "--no-stabilize", "--out", out, "--formats", "none", *args)
        assert result.exit_code == 2, (args, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert lines[-1].startswith("mocaptk: error:") and needle in lines[-1]
    regions = tmp_path / "regions.json"
    regions.write_text(json.dumps({"mouth": ["MOUTH_01_L", "NOT_A_MARKER"]}))
    result = run_cli("cluster", path, "--no-stabilize", "--out", out, "--force", "--regions", regions,
                     "--formats", "none")
    assert result.exit_code == 2 and "NOT_A_MARKER" in result.stderr
    result = run_cli("cluster", path.with_name("nope.c3d"), "--no-stabilize", "--formats", "none")
    assert result.exit_code == 2 and "nope.c3d" in result.stderr
    ok = run_cli("cluster", path, "--no-stabilize", "--out", out, "--force", "--quiet", "--takes", takes,
                 "--formats", "none")
    # --force replaces the whole folder in one rename: nothing of the old run is left in it
    assert ok.exit_code == 0 and not (out / "keep.txt").exists() and (out / "layout.json").exists()


def test_evaluate_and_sweep(run_cli, session_files, tmp_path):
    path, takes, group_of = session_files
    assert run_cli("cluster", path, "--takes", takes, "--no-stabilize", "--out", tmp_path / "L",
                   "--method", "paper", "--quiet", "--formats", "none").exit_code == 0  # the planted groups
    result = run_cli("evaluate", path, "--layout", tmp_path / "L" / "layout.json", "--takes", takes,
                     "--seeds", "2", "--folds", "3")
    assert result.exit_code == 0, result.stderr
    assert "random" in result.stdout and "kmeans" in result.stdout
    report = json.loads((tmp_path / "L" / "evaluation.json").read_text())
    counts = {m["count"] for m in report["methods"].values()}
    layout = json.loads((tmp_path / "L" / "layout.json").read_text())
    assert counts == {sum(c["mirrored_from"] is None for c in layout["clusters"])}
    assert report["methods"]["paper"]["rmse_mm"] < report["methods"]["random"]["rmse_mm"]
    sweep = run_cli("sweep", path, "--takes", takes, "--no-stabilize", "--factors", "0.5,1.5,2.5", "--folds", "3",
                    "--out", tmp_path / "S", "--quiet")
    assert sweep.exit_code == 0, sweep.stderr
    rows = json.loads((tmp_path / "S" / "sweep.json").read_text())["rows"]
    assert [r["factor"] for r in rows] == [0.5, 1.5, 2.5]
    markers = [r["markers"] for r in rows]
    assert markers == sorted(markers) and all(np.isfinite(r["rmse_mm"]) for r in rows)
    assert (tmp_path / "S" / "sweep.png").stat().st_size > 1000
    bad = run_cli("sweep", path, "--factors", "1.3:0.8:0.1", "--no-stabilize")
    assert bad.exit_code == 2 and "factors" in bad.stderr
    for typo in ("0.1:1e6:1e-7", "0.1:inf:0.1", "1,nan"):  # 10^13 factors, endless, NaN
        bad = run_cli("sweep", path, "--factors", typo, "--no-stabilize")
        assert bad.exit_code == 2 and "--factors" in bad.stderr and "\n" not in bad.stderr.strip()


def test_cluster_on_real_blenderface_data(run_cli, tmp_path):
    csv = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    result = run_cli("cluster", csv, "--rate", "50", "--no-stabilize", "--out", tmp_path / "bf", "--formats", "none")
    assert result.exit_code == 0, result.stderr
    data = json.loads((tmp_path / "bf" / "layout.json").read_text())
    assert data["parameters"]["regions_from"].startswith("geometric")
    members = sorted(m for c in data["clusters"] for m in c["members"])
    assert len(members) == 16 and len(set(members)) == 16  # a partition of the 16 markers
    assert 2 <= len(data["layout"]) < 16


def test_cluster_on_bundled_sample(run_cli, tmp_path):
    sessions = sorted(SAMPLES.glob("*.c3d")) if SAMPLES.is_dir() else []
    dense = [p for p in sessions if "perf" not in p.name.lower()]
    if not dense:
        pytest.skip("sample_c3d/ has no session yet")
    result = run_cli("cluster", dense[0], "--no-stabilize", "--out", tmp_path / "s", "--factor", "1.1",
                     "--formats", "none")
    assert result.exit_code == 0, result.stderr
    data = json.loads((tmp_path / "s" / "layout.json").read_text())
    assert data["parameters"]["regions_from"] == "label prefixes"
    assert len(data["layout"]) > 10


@pytest.mark.slow
def test_blenderface_region_bookkeeping_agrees(run_cli, tmp_path):
    """Issue 33: the table said eye 2 dense / 0 measured beside a warning that every eye marker is
    its own cluster, and the per-region RMSE lines counted the eye's markers under cheek (8)."""
    import re

    csv = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    done = run_cli("cluster", csv, "--rate", "25", "--units", "187.6", "--no-stabilize", "--formats", "json",
                   "--out", tmp_path / "bf")
    assert done.exit_code == 0, done.stderr
    table = dict(re.findall(r"^(\w+)\s+(\d+)\s+\d+\s+\d+\s+\d+$", done.stdout, re.M))
    table.pop("total")
    checked = dict(re.findall(r"^  (\w+)\s+RMSE [\d.]+ mm, max [\d.]+ mm \((\d+) markers?\)$", done.stdout, re.M))
    assert checked == table  # the same regions, the same dense marker counts
    assert "(1 markers)" not in done.stdout
    assert "eye: no layout marker of its own; its 2 markers follow" in done.stdout
    assert "each of its 2 markers its own cluster" in done.stderr and "see the table" in done.stderr
