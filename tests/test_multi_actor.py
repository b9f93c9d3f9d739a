"""One layout for several actors (clustering/multi_actor.py; issue 13 item 4): registration by
labels or by nearest neighbour after similarity alignment, the pooled layout, per-actor scores."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import shared_path

from mocaptk import Trajectories
from mocaptk.clustering.compare import _gap_free, compare_methods
from mocaptk.clustering.evaluation import error_summary, heldout_errors
from mocaptk.clustering.methods import select_layout
from mocaptk.clustering.multi_actor import (_part, _problem, compare_actors, load_actors, pooled_session,
                                            register_actor)
from mocaptk.clustering.neutral import neutral_pose


@pytest.fixture(scope="module")
def actors(tmp_path_factory):
    """Two synthetic actors: different faces (identity) and performances (seed), one dense layout."""
    from mocaptk.cli import main

    shared_path("face_mesh", "ict_facekit")  # the ICT-FaceKit model synth uses
    folder = tmp_path_factory.mktemp("actors")
    for k, identity in ((1, "1.5,-1,0.5"), (2, "-1,1.5,-0.5")):
        main(["synth", str(folder / f"actor{k}.c3d"), "--rig", "none", "--seed", str(k), "--layout-seed", "0",
              "--identity", identity, "--expressions", "2", "--performance", "6", "--spacing", "14", "-q"])
    return folder


def test_nearest_neighbour_registration_recovers_a_shuffled_relabelled_rotated_scaled_actor(actors):
    (a, b), _, regs, _ = load_actors([actors / "actor1.c3d", actors / "actor2.c3d"], None, stabilized=False)
    assert regs["actor2"].by == "labels" and 0.7 < regs["actor2"].transform.scale < 1.0  # another face
    perm = np.random.default_rng(0).permutation(b.n_markers)
    turn = 0.7  # rad about the vertical axis
    rot = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
    moved = Trajectories(1.1 * b.positions[:, perm] @ rot.T + [100.0, -20.0, 5.0],
                         [f"X{i}" for i in range(b.n_markers)], b.rate)
    reg = register_actor(a, moved)
    assert reg.by == "nearest"
    assert np.array_equal(reg.order, np.argsort(perm))  # every marker found
    assert reg.transform.scale == pytest.approx(regs["actor2"].transform.scale / 1.1, rel=0.02)


def test_an_ambiguous_correspondence_is_refused_in_one_line(actors, run_cli):
    from mocaptk.acquisition.formats import write_trajectories

    a, _, _, _ = load_actors([actors / "actor1.c3d"], None, stabilized=False)
    # every marker became two, 1 mm either side of it in a random direction: no alignment makes
    # one of them a clear match (a uniform offset would be absorbed by the translation)
    pos = a[0].positions
    offset = np.random.default_rng(0).normal(size=(a[0].n_markers, 3))
    offset /= np.linalg.norm(offset, axis=1, keepdims=True)
    twin = np.concatenate([pos - offset, pos + offset], axis=1)
    path = write_trajectories(Trajectories(twin, [f"T{i}" for i in range(twin.shape[1])], a[0].rate),
                              actors / "twins.c3d")
    result = run_cli("compare", actors / "actor1.c3d", path, "--no-stabilize", "--counts", "5",
                     "--methods", "qr", "--out", actors / "amb")
    assert result.exit_code == 2
    assert result.stderr.startswith(f"mocaptk: error: {path}: ambiguous marker correspondence")
    assert len(result.stderr.strip().splitlines()) == 1 and not (actors / "amb" / "compare.json").exists()


def test_compare_scores_the_pooled_layout_and_each_actors_own_on_its_test(actors, run_cli):
    sessions = [actors / "actor1.c3d", actors / "actor2.c3d"]
    tests = [actors / "actor1_performance.c3d", actors / "actor2_performance.c3d"]
    out = actors / "cmp"
    result = run_cli("compare", *sessions, "--test", tests[0], "--test", tests[1], "--counts", "6,10",
                     "--methods", "kmeans,qr", "--out", out, "--no-stabilize", "-q")
    assert result.exit_code == 0, result.stderr
    data = json.loads((out / "compare.json").read_text())
    assert data["format"] == "mocaptk-compare-actors" and set(data["actors"]) == {"actor1", "actor2"}
    assert len(data["rows"]) == 2 * 2 * 2
    # by hand, actor 2 with QR at 10 markers: shared layout from both sessions pooled, own from its own
    acts, held, _, _ = load_actors(sessions, tests, stabilized=False)
    pooled = _problem([_part(a) for a in acts], neutral_pose(acts[0].positions), acts[0].labels)
    own = _problem([_part(acts[1])], neutral_pose(acts[1].positions), acts[1].labels)
    row = next(r for r in data["rows"] if r["actor"] == "actor2" and r["method"] == "qr" and r["count"] == 10)
    for kind, problem in (("shared", pooled), ("own", own)):
        layout = select_layout(problem, 10, method="qr").layout
        assert row[f"{kind}_layout"] == [acts[0].labels[i] for i in layout]
        errors = heldout_errors(_gap_free(acts[1].positions), layout, [], test=held[1].positions)
        assert row[f"{kind}_rmse_mm"] == pytest.approx(error_summary(errors)["rmse_mm"], rel=1e-5)
    assert row["shared_layout"] != row["own_layout"]
    assert "shared / own" in (out / "compare.md").read_text()
    assert pooled_session(acts, ["actor1", "actor2"]).n_frames == acts[0].n_frames + acts[1].n_frames


def test_cluster_chooses_one_layout_on_both_actors(actors, run_cli):
    out = actors / "layout"
    result = run_cli("cluster", actors / "actor1.c3d", actors / "actor2.c3d", "--method", "qr",
                     "--markers", "12", "--formats", "none", "--out", out, "--no-stabilize")
    assert result.exit_code == 0, result.stderr
    layout = json.loads((out / "layout.json").read_text())
    assert [a["actor"] for a in layout["source"]["actors"]] == ["actor1", "actor2"]
    assert "actors (evidence pooled): actor1 by labels" in result.stdout
    acts, _, _, _ = load_actors([actors / "actor1.c3d", actors / "actor2.c3d"], None, stabilized=False)
    pooled = pooled_session(acts, ["actor1", "actor2"])
    expected = select_layout(_problem([_part(pooled)], neutral_pose(pooled.positions), pooled.labels), 12,
                             method="qr").layout
    measured = [c["representative"] for c in layout["clusters"] if c.get("mirrored_from") is None]
    assert sorted(measured) == sorted(pooled.labels[i] for i in expected)


def test_blenderface_subjects_share_a_layout_and_the_reference_keeps_its_own_score():
    paths = [shared_path("facial_mocap", "blenderface", f"Subject_0{k}.csv") for k in (1, 2)]
    acts, _, regs, _ = load_actors(paths, None, stabilized=False, rate=25.0, units="187")
    assert regs["Subject_02"].by == "labels" and regs["Subject_02"].residual_mm < 3.0
    rows = compare_actors(acts, list(regs), counts=[4], methods=["qr"])
    single = compare_methods(acts[0], counts=[4], methods=["qr"])[0]
    first = next(r for r in rows if r.actor == "Subject_01")
    assert first.own_rmse_mm == pytest.approx(single.rmse_mm)  # the reference is unchanged
    assert all(np.isfinite([r.shared_rmse_mm, r.own_rmse_mm]).all() for r in rows)
