"""The default layout method of ``mocaptk cluster`` against the paper's rule (issue 13).

The README's own commands, on a fresh copy of the bundled sample: the default layout must beat
random, farthest-point and k-means layouts of the same count on the README's held-out
evaluation; ``--method paper`` must still write the layout the paper's rule wrote before the
default changed (``tests/data/paper_layout_sample.json``, written by the code of 0c9bed4).
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SAMPLES

from mocaptk import Trajectories
from mocaptk.clustering.pipeline import ClusterOptions, cluster_session

PAPER_LAYOUT = Path(__file__).parent / "data" / "paper_layout_sample.json"


def mocaptk(*args: str | Path) -> str:
    """Run the CLI in-process; returns stdout (raises on a non-zero exit)."""
    from mocaptk.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            if exc.code:
                raise AssertionError(f"mocaptk {' '.join(map(str, args))}: exit {exc.code}\n{err.getvalue()}")
    return out.getvalue()


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    if not (SAMPLES / "dense_halfface.c3d").is_file():
        pytest.skip("bundled sample missing")
    folder = tmp_path_factory.mktemp("readme") / "sample_c3d"
    shutil.copytree(SAMPLES, folder, ignore=shutil.ignore_patterns("*_layout", "solved"))  # not a user's earlier outputs
    return folder


@pytest.fixture(scope="module")
def default_run(sample) -> tuple[str, dict, dict]:
    """The README's cluster command (rig files skipped: they do not change the layout) and its
    evaluate command: (summary, layout.json, evaluation.json)."""
    summary = mocaptk("cluster", sample / "dense_halfface.c3d", "--factor", "1.1", "--formats", "none")
    layout = sample / "dense_halfface_layout" / "layout.json"
    mocaptk("evaluate", sample / "dense_halfface.c3d", "--layout", layout,
            "--test", sample / "dense_halfface_performance.c3d")
    return (summary, json.loads(layout.read_text()),
            json.loads((layout.parent / "evaluation.json").read_text()))


def test_readme_layout_beats_random_farthest_point_and_kmeans_of_the_same_count(default_run):
    _, layout, evaluation = default_run
    assert layout["parameters"]["method"] == "hybrid"
    methods = evaluation["methods"]
    ours = methods["hybrid"]
    assert ours["count"] == methods["kmeans"]["count"] == 48  # the paper's rule at factor 1.1
    for baseline in ("random", "farthest-point", "kmeans"):
        assert ours["rmse_mm"] < methods[baseline]["rmse_mm"], baseline
    lost = ours["lost_marker"]  # the worst single lost marker, beside the normal error
    assert lost["lost_rmse_mm"] > lost["intact_rmse_mm"] and lost["marker"] in layout["layout"]


def test_summary_columns_add_up_and_say_what_chose_the_markers(default_run):
    summary, layout, _ = default_run
    assert "measured markers chosen by hybrid" in summary and "mean C" not in summary
    rows = {}
    for line in summary.splitlines():
        parts = line.split()
        if len(parts) == 5 and all(p.isdigit() for p in parts[1:]):
            rows[parts[0]] = [int(p) for p in parts[1:]]
    total = rows.pop("total")
    assert [sum(r[i] for r in rows.values()) for i in range(4)] == total
    assert all(dense and measured + mirrored == both for dense, measured, mirrored, both in rows.values())
    measured = sum(c["mirrored_from"] is None for c in layout["clusters"])
    assert total[1:] == [measured, len(layout["clusters"]) - measured, len(layout["clusters"])]


def test_method_paper_writes_the_layout_of_before_the_default_changed(sample, tmp_path):
    out = tmp_path / "paper"
    summary = mocaptk("cluster", sample / "dense_halfface.c3d", "--factor", "1.1", "--method", "paper",
                      "--formats", "none", "--out", out)
    written = json.loads((out / "layout.json").read_text())
    where = written["source"]  # where this run's session is
    assert Path(where.pop("absolute")) == (sample / "dense_halfface.c3d").resolve()
    assert (out / where.pop("relative")).resolve() == (sample / "dense_halfface.c3d").resolve()
    # keys added since (the face's orientation, how the session was read, the stabilization
    # markers' head-frame positions) hold no layout number: everything else is as before
    assert written.pop("orientation")["labels"] == "agree"
    assert where.pop("reading") == {"rate": None, "units": None, "first_frame": 0}
    reference = written["stabilization"].pop("reference")
    assert len(reference) == len(written["stabilization"]["rigid_labels"])
    assert written == json.loads(PAPER_LAYOUT.read_text())
    assert "mean C" in summary and "threshold" in summary


def test_markers_gives_exactly_that_many_with_any_method(sample, tmp_path):
    mocaptk("cluster", sample / "dense_halfface.c3d", "--markers", "12", "--formats", "none",
            "--out", tmp_path / "h12")
    hybrid = json.loads((tmp_path / "h12" / "layout.json").read_text())
    assert hybrid["parameters"]["markers"] == 12 and hybrid["parameters"]["method"] == "hybrid"
    assert sum(c["mirrored_from"] is None for c in hybrid["clusters"]) == 12
    mocaptk("cluster", sample / "dense_halfface.c3d", "--markers", "25", "--method", "paper",
            "--formats", "none", "--out", tmp_path / "p25")
    paper = json.loads((tmp_path / "p25" / "layout.json").read_text())
    assert sum(c["mirrored_from"] is None for c in paper["clusters"]) == 25
    members = [m for c in paper["clusters"] if c["mirrored_from"] is None for m in c["members"]]
    assert len(members) == len(set(members)) == 139  # still a partition of the dense markers


def test_a_threshold_no_correlation_reaches_is_named_with_the_factor_that_clusters_it():
    rng = np.random.default_rng(3)
    drivers = rng.normal(size=(300, 2))
    base = np.array([[0.0, 0, 0], [10, 0, 0], [20, 0, 0], [0, 10, 0], [10, 10, 0], [20, 10, 0]])
    mix = drivers[:, [0, 0, 0, 1, 1, 1]][:, :, None] * np.array([1.0, 0.5, 0.2])
    positions = base[None] + mix + rng.normal(scale=0.3, size=(300, 6, 3))
    labels = [f"MOUTH_{i:02d}_L" for i in range(6)]
    traj = Trajectories(positions, labels, 60.0)
    result = cluster_session(traj, options=ClusterOptions(method="paper", factor=2.5, stabilize=False,
                                                          mirror=False))
    notes = [n for n in result.notes if "own cluster" in n]
    assert len(notes) == 1 and "'mouth'" in notes[0]
    assert len(result.layout.clusters) == 6  # every marker its own cluster
    factor = float(notes[0].split("--factor ")[1].split()[0])
    fixed = cluster_session(traj, options=ClusterOptions(method="paper", factor=factor, stabilize=False,
                                                         mirror=False))
    assert len(fixed.layout.clusters) < 6 and not any("own cluster" in n for n in fixed.notes)
