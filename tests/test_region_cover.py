"""Region cover (issue 28): a region that moves on its own (the lids) keeps a layout marker."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SAMPLES, shared_path
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.clustering.methods.problem import layout_problem
from mocaptk.clustering.methods.region_cover import OWN_MOTION_MM, cover_regions, own_motion
from mocaptk.clustering.regions import regions_from_prefixes

#: the sample's default hybrid layout at ``--markers 20`` (measured markers), as cluster chose it
SAMPLE_20 = ("CHEEK_06_L", "CHEEK_16_L", "CHEEK_20_L", "CHEEK_27_L", "CHEEK_28_L", "CHEEK_34_L", "CHIN_03_L",
             "CHIN_10_L", "CHIN_16_L", "CHIN_18_L", "EYE_01_L", "EYE_04_L", "EYE_08_L", "FOREHEAD_BROW_26_L",
             "MOUTH_04_L", "MOUTH_05_C", "MOUTH_08_L", "MOUTH_11_L", "MOUTH_15_C", "NOSE_15_L")


def _sample():
    session = read_c3d(SAMPLES / "dense_halfface.c3d")
    index = {label: i for i, label in enumerate(session.labels)}
    regions = {k: np.array([index[m] for m in v]) for k, v in regions_from_prefixes(session.labels).items()}
    return layout_problem(session, regions=regions), index, regions


def test_lid_marker_comes_back_where_the_eye_has_none():
    """The sample's 20-marker layout with its 3 eye markers moved to the nearest other markers:
    the lids blink with nothing around them moving, so an eye marker comes back (size kept)."""
    problem, index, regions = _sample()
    layout = np.array([index[m] for m in SAMPLE_20])
    eye = regions["eye"]
    others = np.setdiff1d(np.setdiff1d(np.arange(problem.n_points), eye), layout)
    stripped = []
    for p in np.sort(layout):
        if p in eye:
            p = others[np.argmin(np.linalg.norm(problem.neutral[others] - problem.neutral[p], axis=1))]
            others = others[others != p]
        stripped.append(int(p))
    stripped = np.sort(stripped)
    assert not np.isin(stripped, eye).any()
    moving = own_motion(problem, stripped, eye)
    assert moving.max() > 3 * OWN_MOTION_MM  # a lid's blink, unseen by the brow and cheek markers
    covered, swaps = cover_regions(problem, stripped, {"eye": eye, "mouth": regions["mouth"]})
    assert covered.size == stripped.size and np.isin(covered, eye).sum() == 1
    assert int(np.intersect1d(covered, eye)[0]) == int(eye[np.argmax(moving)])
    assert len(swaps) == 1 and swaps[0].region == "eye" and swaps[0].added == int(eye[np.argmax(moving)])
    assert swaps[0].note(problem.labels).startswith("region cover: eye had no layout marker")
    again, more = cover_regions(problem, covered, {"eye": eye})  # covered now: nothing to do
    assert np.array_equal(again, covered) and more == []


def test_a_region_following_its_neighbours_keeps_no_marker():
    """blenderFace S01: its 2 under-eye markers follow the cheek markers beside them (> 95 % of
    their motion from the 2 nearest layout markers), so the default layout stays without one."""
    from mocaptk.acquisition.formats import read_trajectories

    session = read_trajectories(shared_path("facial_mocap", "blenderface", "Subject_01.csv"), rate=25,
                                units="187.6")
    index = {label: i for i, label in enumerate(session.labels)}
    problem = layout_problem(session)
    layout = np.sort([index[m] for m in ("CL7", "BL7", "CR7", "A8", "A7", "BL5", "BR5", "DL2", "BL2", "DR2")])
    eye = np.array([index["BL4"], index["BR4"]])
    assert np.all(own_motion(problem, layout, eye) == 0.0)
    covered, notes = cover_regions(problem, layout, {"eye (L)": eye[:1], "eye (R)": eye[1:]})
    assert np.array_equal(covered, layout) and notes == []


@pytest.mark.slow
def test_cluster_gives_each_lid_a_marker_on_a_full_face(run_cli, tmp_path, identity_actor):
    """The identity actor of bench_retarget at --markers 20: the default layout had no eye marker
    (retarget's eyeBlink r 0.00); now one per side, each an upper-lid marker."""
    done = run_cli("cluster", identity_actor, "--markers", "20", "--formats", "none", "--quiet", "--out", tmp_path / "lay")
    assert done.exit_code == 0, done.stderr
    layout = json.loads((tmp_path / "lay" / "layout.json").read_text())
    eyes = sorted(c["representative"] for c in layout["clusters"] if c["region"] == "eye")
    assert len(layout["layout"]) == 20
    assert [e[-1] for e in eyes] == ["L", "R"]
    assert sum(note.startswith("region cover: eye (") for note in layout["notes"]) == 2


def test_compare_and_several_actors_score_cluster_s_layout(run_cli, tmp_path):
    """The cover is the hybrid's own last step: on the sample at 12 markers it swaps a lid marker
    in (the winner has no eye marker), and ``compare``'s hybrid layout, the several-actor
    comparison's own layout and ``layout.json`` (its ``parameters.region_cover``) are all that
    same layout — the cover ran only in cluster's relayout before, so compare scored another."""
    from mocaptk.clustering.multi_actor import compare_actors
    from mocaptk.clustering.pipeline import load_session_and_test

    session, performance = SAMPLES / "dense_halfface.c3d", SAMPLES / "dense_halfface_performance.c3d"
    done = run_cli("cluster", session, "--markers", "12", "--formats", "none", "--quiet", "--out", tmp_path / "lay")
    assert done.exit_code == 0, done.stderr
    layout = json.loads((tmp_path / "lay" / "layout.json").read_text())
    measured = sorted(c["representative"] for c in layout["clusters"] if c.get("mirrored_from") is None)
    [swap] = layout["parameters"]["region_cover"]
    assert swap["region"] == "eye (L)" and swap["added"].startswith("EYE_") and swap["added"] in measured
    assert swap["replaced"] not in measured
    done = run_cli("compare", session, "--test", performance, "--counts", "12", "--methods", "hybrid",
                   "--quiet", "--out", tmp_path / "cmp")
    assert done.exit_code == 0, done.stderr
    [row] = json.loads((tmp_path / "cmp" / "compare.json").read_text())["rows"]
    assert sorted(row["layout"]) == measured
    traj, perf, _ = load_session_and_test(session, performance, stabilized=True)
    [own] = [r for r in compare_actors([traj, traj], ["a", "b"], tests=[perf, perf], counts=[12])
             if r.actor == "a"]
    assert sorted(traj.labels[i] for i in own.own_layout) == measured
