"""report.html without a browser: self-contained, byte-identical for the same input, written
atomically, its replay subsampled within budget and its data matching the layout."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
from clustering_synthetic import planted_session, save_session

from mocaptk.retarget.report import replay_clips, replay_step, report_html, write_report


@pytest.fixture(scope="module")
def planted_reports(tmp_path_factory):
    """``mocaptk cluster`` twice on one planted session (rig.json + guide included)."""
    from mocaptk.cli import main

    folder = tmp_path_factory.mktemp("planted_report")
    path, takes = save_session(planted_session(seed=21)[0], folder / "planted.npz")
    outs = []
    for name in ("a", "b"):
        try:
            main(["cluster", str(path), "--takes", str(takes), "--no-stabilize", "--quiet",
                  "--out", str(folder / name), "--formats", "json"])
        except SystemExit as exc:
            assert not exc.code, exc
        outs.append(folder / name)
    return outs


def page_data(path) -> dict:
    text = path.read_text(encoding="utf-8")
    block = re.search(r'<script id="report-data" type="application/json">(.*?)</script>', text, re.S)
    return json.loads(block.group(1))


def test_report_is_byte_identical_and_self_contained(planted_reports):
    a, b = (folder / "report.html" for folder in planted_reports)
    assert a.read_bytes() == b.read_bytes()
    text = a.read_text(encoding="utf-8")
    # nothing is fetched: no external script, stylesheet, image or frame
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)=", text)
    assert not [p.name for p in planted_reports[0].parent.rglob("*.part")]  # staging cleaned up
    summary = (planted_reports[0] / "summary.txt").read_text()
    size = re.search(r"report\.html: ([\d.]+) MB", summary)
    assert size and abs(float(size.group(1)) - a.stat().st_size / 1e6) <= 0.051


def test_report_data_matches_the_layout(planted_reports):
    folder = planted_reports[0]
    data = page_data(folder / "report.html")
    layout = json.loads((folder / "layout.json").read_text())
    assert data["format"] == "mocaptk.report" and data["version"] == 1 and data["kind"] == "cluster"
    assert [c["label"] for c in data["clusters"]] == layout["layout"]
    assert [c["number"] for c in data["clusters"]] == list(range(1, len(layout["layout"]) + 1))
    assert all(c["name"].rstrip("LR").isdigit() for c in data["clusters"])  # as in guide.pdf
    labels = data["markers"]["labels"]
    for cluster, source in zip(data["clusters"], layout["clusters"]):
        assert [labels[m] for m in cluster["members"]] == source["members"]
    # mirrored markers are drawn from their source marker; the rig moves the face
    captured = data["markers"]["captured"]
    assert all(m >= 0 for m in data["markers"]["mirror_of"][captured:])
    assert any(c["mirrored_from"] for c in data["clusters"])
    assert len(data["mesh"]["vertices"]) > captured and len(data["mesh"]["skin_marker"]) == len(data["mesh"]["vertices"])
    clip = data["clips"][0]
    track = np.frombuffer(base64.b64decode(clip["positions"]), "<i2")
    assert track.size == clip["frames"] * captured * 3
    assert clip["frames"] == -(-clip["source_frames"] // clip["step"])


def test_page_text_that_looks_like_a_placeholder_stays_as_given(tmp_path):
    # the template is filled once: a title or summary naming a placeholder is not filled in again
    data = {"title": "take @@CSS@@", "summary": "markers @@APP@@ @@PLOTLY@@ @@DATA@@ × 2"}
    path, size = write_report(tmp_path / "report.html", data)
    raw = path.read_bytes()
    assert size == len(raw) and raw.decode("utf-8") == report_html(data)
    assert "<title>take @@CSS@@</title>" in raw.decode("utf-8")
    shown = page_data(path)
    assert shown["summary"] == data["summary"] and shown["title"] == data["title"]
    assert abs(float(shown["size"].removesuffix(" MB")) - len(raw) / 1e6) <= 0.051


def test_replay_subsampling_keeps_rate_and_budget():
    assert replay_step(60.0, 6841, 139, budget_bytes=4_000_000) == 2  # 30 Hz fits
    assert replay_step(60.0, 6841, 139, budget_bytes=1_000_000) == 6  # budget forces 10 Hz
    assert replay_step(25.0, 100, 10, budget_bytes=4_000_000) == 1
    positions = np.zeros((10, 2, 3))
    positions[4, 1] = np.nan
    positions[:, 0, 0] = np.arange(10) * 0.1
    (clip,) = replay_clips([("s", positions)], 100.0, np.zeros((2, 3)))
    assert clip["step"] == 4 and clip["frames"] == 3 and clip["rate_hz"] == 25.0
    track = np.frombuffer(base64.b64decode(clip["positions"]), "<i2").reshape(3, 2, 3)
    np.testing.assert_array_equal(track[:, 0, 0], [0, 8, 16])  # 0.05 mm steps: 0, 0.4, 0.8 mm
    assert (track[1, 1] == -32768).all() and (track[[0, 2], 1] == 0).all()  # the gap stays a gap


def test_evaluate_and_compare_write_error_reports(planted_reports, run_cli, tmp_path):
    folder = planted_reports[0]
    session, takes = folder.parent / "planted.npz", folder.parent / "takes.json"
    result = run_cli("evaluate", session, "--layout", folder / "layout.json", "--takes", takes,
                     "--seeds", "2", "--folds", "3", "--out", tmp_path / "e.json", "--quiet")
    assert result.exit_code == 0, result.stderr
    evaluation = json.loads((tmp_path / "e.json").read_text())
    data = page_data(tmp_path / "e.html")
    assert data["kind"] == "evaluate" and len(data["clusters"]) == len(json.loads(
        (folder / "layout.json").read_text())["clusters"])
    (errors,) = data["errors"]
    values = np.array([np.nan if v is None else v for v in errors["values"]])
    captured = data["markers"]["captured"]
    assert np.isfinite(values[:captured]).all() and np.isnan(values[captured:]).all()
    # the map's RMSE over all markers is the table's (same protocol, same frames)
    (table,) = data["tables"]
    assert sorted(row[0] for row in table["rows"]) == sorted(evaluation["methods"])
    name = table["rows"][table["picks"].index(0)][0]
    assert name == json.loads((folder / "layout.json").read_text())["parameters"]["method"]
    # per-marker RMSEs pool back to the table's RMSE (same protocol; markers tested equally often)
    assert np.sqrt(np.mean(values[:captured] ** 2)) == pytest.approx(evaluation["methods"][name]["rmse_mm"], rel=0.02)

    result = run_cli("compare", session, "--counts", "4,6", "--methods", "kmeans,farthest-point",
                     "--out", tmp_path / "cmp", "--no-stabilize", "--quiet")
    assert result.exit_code == 0, result.stderr
    data = page_data(tmp_path / "cmp" / "report.html")
    assert data["kind"] == "compare" and not data["clusters"]
    assert [(m["name"], len(m["layout"])) for m in data["errors"]] == [
        ("kmeans × 4", 4), ("kmeans × 6", 6), ("farthest-point × 4", 4), ("farthest-point × 6", 6)]
    assert data["tables"][0]["picks"] == [0, 1, 2, 3]
    # the page shows no measured run time, so the same input gives the same bytes
    again = run_cli("compare", session, "--counts", "4,6", "--methods", "kmeans,farthest-point",
                    "--out", tmp_path / "cmp2", "--no-stabilize", "--quiet")
    assert again.exit_code == 0, again.stderr
    assert (tmp_path / "cmp" / "report.html").read_bytes() == (tmp_path / "cmp2" / "report.html").read_bytes()
    assert data["tables"][0]["columns"] == ["method", "markers", "RMSE", "p95", "1 lost"]
    assert "(s)" in (tmp_path / "cmp" / "compare.md").read_text() and "(s)" not in data["summary"]


def test_solve_writes_a_deterministic_report(planted_reports, run_cli, tmp_path):
    """solve on the planted session itself (its layout markers are in it): the page holds the
    layout, the per-marker expected error whose RMS is the model's, the solved replay, the
    printed summary and its own size; twice the same bytes."""
    folder = planted_reports[0]
    session = folder.parent / "planted.npz"
    runs = [run_cli("solve", folder / "layout.json", session, "--formats", "none", "--out", tmp_path / name)
            for name in ("a", "b")]
    assert all(r.exit_code == 0 for r in runs), runs[0].stderr
    page = tmp_path / "a" / "report.html"
    assert page.read_bytes() == (tmp_path / "b" / "report.html").read_bytes()
    summary = json.loads((tmp_path / "a" / "solve.json").read_text())
    assert "report.html" in summary["outputs"] and sorted(summary["outputs"]) == sorted(
        p.name for p in (tmp_path / "a").iterdir())
    size = re.search(r"report\.html: ([\d.]+) MB", runs[0].stdout)
    assert size and abs(float(size.group(1)) - page.stat().st_size / 1e6) <= 0.051
    data = page_data(page)
    layout = json.loads((folder / "layout.json").read_text())
    assert data["kind"] == "solve" and [c["label"] for c in data["clusters"]] == layout["layout"]
    (errors,) = data["errors"]
    values = np.array([np.nan if v is None else v for v in errors["values"]])
    captured = data["markers"]["captured"]
    assert np.isfinite(values[:captured]).all()
    # per-marker errors pool back to the model's expected error (all layout markers present)
    expected = summary["model"]["expected_error_all_present_mm"]
    assert np.sqrt(np.mean(values[:captured] ** 2)) == pytest.approx(expected, rel=0.01)
    assert runs[0].stdout.splitlines()[0] in data["summary"]  # the printed summary, in the side panel
    (clip,) = data["clips"]
    assert clip["name"] == "solved performance" and clip["source_frames"] == summary["capture"]["frames"]
