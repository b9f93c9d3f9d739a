"""Correlation, threshold clustering, reassignment, regions, takes and layout files on synthetic data."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from clustering_synthetic import planted_session
from conftest import SAMPLES

from mocaptk import InputFileError, OptionError, Take, Trajectories
from mocaptk.acquisition.c3d_read import read_c3d
from mocaptk.clustering.correlation import consolidated_correlation, mean_off_diagonal
from mocaptk.clustering.layout import read_layout, write_layout
from mocaptk.clustering.neutral import max_displacement, neutral_pose, seen_markers
from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
from mocaptk.clustering.regions import default_regions, read_regions, regions_from_prefixes
from mocaptk.clustering.takes import read_takes, region_segments, sample_frames
from mocaptk.clustering.threshold import cluster_region, region_statistics


def _corrcoef_sum(pos: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():  # numpy warns on zero variance; we compare against 0 there
        warnings.simplefilter("ignore", RuntimeWarning)
        return sum(np.nan_to_num(np.corrcoef(pos[:, :, a].T)) for a in range(3))


def test_consolidated_correlation_matches_numpy_and_flags_static_axes():
    rng = np.random.default_rng(1)
    pos = rng.normal(size=(60, 9, 3)).cumsum(axis=0)
    pos[:, 4, 1] = 7.0  # no motion on y
    pos[:, 6] = [1.0, 2.0, 3.0]  # static marker
    corr = consolidated_correlation(pos)
    off = ~np.eye(9, dtype=bool)
    assert np.allclose(corr.matrix[off], _corrcoef_sum(pos)[off], atol=1e-12)
    assert corr.static_axes[4].tolist() == [False, True, False]
    assert corr.static.tolist() == [i == 6 for i in range(9)]
    assert np.all(corr.matrix[6, off[6]] == 0)
    assert np.array_equal(corr.matrix, corr.matrix.T)


def test_gappy_correlation_is_pairwise_complete():
    rng = np.random.default_rng(2)
    pos = rng.normal(size=(80, 7, 3)).cumsum(axis=0)
    pos[rng.random((80, 7)) < 0.25] = np.nan
    pos[:, 3] = np.nan
    pos[:5, 3] = rng.normal(size=(5, 3))
    corr = consolidated_correlation(pos)
    for i, j in [(0, 1), (2, 5), (3, 6)]:
        both = np.isfinite(pos[:, i, 0]) & np.isfinite(pos[:, j, 0])
        expected = sum(np.corrcoef(pos[both, i, a], pos[both, j, a])[0, 1] for a in range(3))
        assert corr.matrix[i, j] == pytest.approx(expected, abs=1e-9)
    assert np.isfinite(corr.matrix).all()
    assert mean_off_diagonal(np.ones((1, 1))) != mean_off_diagonal(np.ones((1, 1)))  # NaN for one marker


def test_neutral_pose_and_seen_markers_match_numpy_bit_for_bit(monkeypatch):
    sample = read_c3d(SAMPLES / "dense_halfface.c3d").positions
    rng = np.random.default_rng(4)
    pos = sample[:1501, :130].copy()  # odd and (with gaps) even counts, blocks of 96 columns
    pos[rng.random(pos.shape[:2]) < 0.2] = np.nan
    pos[:, 5] = np.nan  # never seen: NaN
    pos[:700, 6] = np.nan
    pos[:3, 7, 1] = np.inf  # kept, as np.nanmedian keeps it
    pos[::2, 8, 2] = np.nan  # one axis missing more often
    seen = np.isfinite(pos).all(axis=2).any(axis=0)
    expected = np.full((130, 3), np.nan)
    expected[seen] = np.nanmedian(pos[:, seen], axis=0)
    assert np.array_equal(neutral_pose(pos), expected, equal_nan=True)
    assert np.isnan(neutral_pose(pos)[5]).all() and np.isfinite(neutral_pose(pos)[6]).all()
    rest = slice(10, 400, 3)
    assert np.array_equal(neutral_pose(pos, rest_frames=rest), neutral_pose(pos[rest].copy()),
                          equal_nan=True)
    assert np.isnan(neutral_pose(pos[:0])).all() and neutral_pose(pos[:, :0]).shape == (0, 3)
    from mocaptk.clustering import neutral

    for values in (1, 20 * 1501):  # blocks of one marker, of 6 (20 columns: whole markers only)
        monkeypatch.setattr(neutral, "MEDIAN_BLOCK_VALUES", values)
        assert np.array_equal(neutral_pose(pos), expected, equal_nan=True)
    monkeypatch.setattr(neutral, "BLOCK_FRAMES", 256)
    pos[5000 % 1501, 9, 0] = np.nan  # one frame with a missing axis among complete ones
    pos[:, 10, 0], pos[:, 10, 1] = np.nan, np.where(np.arange(1501) % 2, np.nan, 1.0)  # never all 3
    pos[1500, 11] = [1.0, 2.0, 3.0]  # seen in the last frame only (past a block)
    pos[:1500, 11] = np.nan
    pos[0, 12], pos[1:, 12] = [1.0, 2.0, 3.0], np.nan  # in the first frame only
    assert np.array_equal(seen_markers(pos), np.isfinite(pos).all(axis=2).any(axis=0))
    assert seen_markers(pos)[[5, 9, 10, 11, 12]].tolist() == [False, True, False, True, True]
    assert seen_markers(pos[:0]).tolist() == [False] * 130



@pytest.mark.parametrize("block_values", [None, 1, 5_000])
def test_max_displacement_is_the_largest_norm_over_valid_frames_in_any_blocks(monkeypatch, block_values):
    """Blocks of 1 frame, of a few frames and the default give np.linalg.norm's largest value
    bit for bit; a marker whose frames are all gaps or infinite gets 0."""
    from mocaptk.clustering import neutral

    if block_values is not None:
        monkeypatch.setattr(neutral, "DISPLACEMENT_BLOCK_VALUES", block_values)
    sample = read_c3d(SAMPLES / "dense_halfface.c3d").positions
    rng = np.random.default_rng(9)
    pos = sample[:777, :40].copy()
    pos[rng.random(pos.shape[:2]) < 0.1] = np.nan
    pos[:, 3] = np.nan  # never seen
    pos[:, 4, 0] = np.inf  # only infinite samples: no valid frame
    pos[776, 5] = sample[0, 5] + [9.0, 9.0, 9.0]  # largest in the last frame (past every block)
    rest = neutral_pose(sample[:777, :40])
    norms = np.linalg.norm(pos - rest[None], axis=2)
    norms[~np.isfinite(norms)] = np.nan
    expected = np.zeros(40)
    valid = np.isfinite(norms).any(axis=0)
    expected[valid] = np.nanmax(norms[:, valid], axis=0)
    got = max_displacement(pos, rest)
    assert np.array_equal(got, expected) and got[3] == got[4] == 0.0
    assert got[5] == pytest.approx(np.linalg.norm(pos[776, 5] - rest[5]))


@pytest.fixture(scope="module")
def smooth_field():
    """Markers on a 2-D grid moved by smooth random fields: correlation decays with distance."""
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(6)), axis=-1).reshape(-1, 2) * 10.0
    centres = rng.uniform(0, 70, size=(12, 2))
    influence = np.exp(-((grid[:, None] - centres[None]) ** 2).sum(-1) / (2 * 15.0 ** 2))  # (M, 12)
    signals = rng.normal(size=(400, 12, 3)).cumsum(axis=0)
    pos = np.einsum("mk,fka->fma", influence, signals) + rng.normal(scale=0.05, size=(400, len(grid), 3))
    return consolidated_correlation(pos).matrix, np.abs(pos - pos[0]).max(axis=(0, 2))


@pytest.mark.parametrize("factor", [0.8, 1.0, 1.1, 1.3])
def test_clusters_partition_and_reassignment_is_final(smooth_field, factor):
    matrix, disp = smooth_field
    result = cluster_region(matrix, disp, factor=factor)
    n = matrix.shape[0]
    assert sorted(np.bincount(result.assignment, minlength=len(result.representatives)) > 0) == [True] * len(
        result.representatives)
    assert result.assignment.shape == (n,) and result.assignment.min() >= 0  # every marker in exactly one
    for k, rep in enumerate(result.representatives):
        assert result.assignment[rep] == k  # representative in its own cluster
    # after reassignment no member correlates more with another representative
    corr_to_reps = matrix[result.representatives]  # (K, M)
    own = corr_to_reps[result.assignment, np.arange(n)]
    assert np.all(own >= corr_to_reps.max(axis=0) - 1e-12)
    assert np.allclose(result.member_correlation, own)
    # members joined by the threshold rule: first pass members reach the threshold
    first_own = matrix[result.representatives[result.first_assignment], np.arange(n)]
    non_rep = np.setdiff1d(np.arange(n), result.representatives)
    assert np.all(first_own[non_rep] >= result.threshold)
    assert result.threshold == pytest.approx(factor * mean_off_diagonal(matrix))


def test_larger_factor_never_gives_fewer_markers(smooth_field):
    matrix, disp = smooth_field
    counts = [len(cluster_region(matrix, disp, factor=f).representatives) for f in np.arange(0.5, 2.01, 0.05)]
    assert counts == sorted(counts)
    assert counts[-1] > counts[0]
    # a factor search passes the region's statistics once: the same clusters
    statistics = region_statistics(matrix)
    off = matrix[~np.eye(matrix.shape[0], dtype=bool)]
    assert statistics == (pytest.approx(off.mean(), rel=1e-12), off.max())
    for factor in (0.7, 1.3):
        given, own = (cluster_region(matrix, disp, factor=factor, statistics=s) for s in (statistics, None))
        assert np.array_equal(given.assignment, own.assignment) and given.max_correlation == own.max_correlation


def test_representatives_are_taken_by_largest_displacement(smooth_field):
    matrix, disp = smooth_field
    result = cluster_region(matrix, disp, factor=1.0)
    assert result.representatives[0] == int(np.argmax(disp))
    assert np.all(np.diff(disp[result.representatives]) <= 0)  # created in decreasing displacement


@pytest.mark.parametrize("factor", [0.9, 1.0, 1.1])
def test_planted_structure_is_recovered_exactly(factor):
    traj, group_of = planted_session(seed=4)
    result = cluster_session(traj, options=ClusterOptions(method="paper", factor=factor, stabilize=False, mirror=False))
    found = sorted(sorted(c.members) for c in result.layout.clusters)
    planted: dict[int, list[str]] = {}
    for label, group in group_of.items():
        planted.setdefault(group, []).append(label)
    assert found == sorted(sorted(m) for m in planted.values())
    assert result.notes == []


def test_planted_structure_with_gaps_and_without_takes():
    traj, group_of = planted_session(seed=5, gaps=0.1, takes=False)
    result = cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False, mirror=False))
    for cluster in result.layout.clusters:
        assert len({group_of[m] for m in cluster.members}) == 1
    assert len(result.layout.clusters) == len(set(group_of.values()))


def test_unreachable_threshold_and_negative_mean_are_reported():
    rng = np.random.default_rng(6)
    signal = rng.normal(size=(300, 1, 3)).cumsum(axis=0)
    pos = signal + rng.normal(scale=0.01, size=(300, 5, 3)) + rng.normal(size=(1, 5, 3)) * 20
    labels = [f"CHIN_{i:02d}" for i in range(1, 6)]
    traj = Trajectories(pos, labels, 60.0)
    result = cluster_session(traj, options=ClusterOptions(method="paper", factor=1.1, stabilize=False))
    assert len(result.layout.clusters) == 5  # every marker a representative, as the rule says
    assert any("own cluster" in note and "chin" in note for note in result.notes)  # τ ≥ max C
    anti = np.concatenate([signal, -signal], axis=1) + rng.normal(scale=0.01, size=(300, 2, 3))
    result = cluster_session(Trajectories(anti, ["NOSE_01", "NOSE_02"], 60.0),
                             options=ClusterOptions(method="paper", stabilize=False))
    assert any("<= 0" in note for note in result.notes)


def test_bad_markers_and_options_are_reported_not_crashing():
    traj, _ = planted_session(seed=7)
    pos = traj.positions.copy()
    pos[:, 0] = np.nan  # all-NaN marker
    pos[:, 1] = pos[0, 1]  # constant marker
    bad = traj.replace(positions=pos)
    result = cluster_session(bad, options=ClusterOptions(method="paper", stabilize=False, mirror=False))
    assert any("no data" in n and traj.labels[0] in n for n in result.notes)
    assert any("do not move" in n and traj.labels[1] in n for n in result.notes)
    assert traj.labels[0] not in {m for c in result.layout.clusters for m in c.members}
    assert result.layout.extra["static_markers"] == [traj.labels[1]]
    with pytest.raises(OptionError, match="factor"):
        cluster_session(traj, options=ClusterOptions(method="paper", factor=0, stabilize=False))
    with pytest.raises(OptionError, match="step"):
        cluster_session(traj, options=ClusterOptions(method="paper", step=traj.n_frames, stabilize=False))
    with pytest.raises(OptionError, match="smaller step"):  # a region's take too short for the step
        short = traj.replace(metadata={"takes": [Take("nose", 0, 8, "nose")]})
        cluster_session(short, options=ClusterOptions(method="paper", step=5, stabilize=False))
    one = cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False, regions={
        "nose": [traj.labels[0]], "rest": list(traj.labels[1:])}))
    assert any("only 1 marker" in n for n in one.notes)
    partial = cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False, mirror=False, regions={
        "nose": [m for m in traj.labels if m.startswith("NOSE")]}))
    loose = [m for m in traj.labels if not m.startswith("NOSE")]
    assert partial.layout.extra["unassigned_markers"] == loose
    assert any("in no region" in n for n in partial.notes)
    assert {m for c in partial.layout.clusters for m in c.members} == set(traj.labels) - set(loose)


def test_regions_files_and_defaults(tmp_path):
    labels = ["MOUTH_01_L", "MOUTH_02_C", "CHIN_01_L", "FOREHEAD_BROW_03_L"]
    assert regions_from_prefixes(labels) == {"mouth": ["MOUTH_01_L", "MOUTH_02_C"], "chin": ["CHIN_01_L"],
                                             "forehead_brow": ["FOREHEAD_BROW_03_L"]}
    assert regions_from_prefixes(["CL7", "A8"]) is None
    js = tmp_path / "r.json"
    js.write_text(json.dumps({"lips": ["MOUTH_01_L", "MOUTH_02_C"]}))
    assert read_regions(js, labels) == {"lips": ["MOUTH_01_L", "MOUTH_02_C"]}
    csv = tmp_path / "r.csv"
    csv.write_text("label,region\nMOUTH_01_L,lips\nCHIN_01_L,jaw\n")
    assert read_regions(csv, labels) == {"lips": ["MOUTH_01_L"], "jaw": ["CHIN_01_L"]}
    js.write_text(json.dumps({"lips": ["MOUTH_01_L", "NOPE_9"]}))
    with pytest.raises(InputFileError, match="NOPE_9"):
        read_regions(js, labels)
    js.write_text(json.dumps({"a": ["MOUTH_01_L"], "b": ["MOUTH_01_L"]}))
    with pytest.raises(InputFileError, match="two regions"):
        read_regions(js, labels)


def test_geometric_regions_on_a_face_shaped_cloud():
    # an ellipsoidal face cap (y up, z forward) with a nose bump; the jaw moves most
    rng = np.random.default_rng(8)
    xy = rng.uniform([-70, -100], [70, 90], size=(400, 2))
    xy = xy[(xy[:, 0] / 70) ** 2 + (xy[:, 1] / 100) ** 2 < 1]
    z = 60 * np.sqrt(np.clip(1 - (xy[:, 0] / 80) ** 2 - (xy[:, 1] / 110) ** 2, 0, None))
    z += 25 * np.exp(-((xy[:, 0] / 12) ** 2 + ((xy[:, 1] - 5) / 25) ** 2))
    neutral = np.column_stack([xy, z])
    disp = np.clip(-xy[:, 1], 0, None) + 1.0
    labels = [f"m{i}" for i in range(len(neutral))]
    regions, how = default_regions(labels, neutral, disp)
    assert how.startswith("geometric")
    assert set(regions) == {"forehead_brow", "eye", "nose", "cheek", "mouth", "chin"}
    where = {m: r for r, ms in regions.items() for m in ms}
    top, bottom = labels[int(np.argmax(xy[:, 1]))], labels[int(np.argmin(xy[:, 1]))]
    assert where[top] == "forehead_brow" and where[bottom] == "chin"
    assert where[labels[int(np.argmax(z))]] == "nose"


def test_takes_feed_their_regions(tmp_path):
    takes = [Take("mouth", 0, 100, "mouth"), Take("eye", 100, 180), Take("warmup", 180, 200)]
    seg = region_segments(takes, ["mouth", "eye", "chin"], 250)
    assert seg == {"mouth": [(0, 100), (180, 200)], "eye": [(100, 180), (180, 200)], "chin": [(180, 200)]}
    assert region_segments([], ["mouth"], 50) == {"mouth": [(0, 50)]}
    assert sample_frames([(0, 12), (12, 20)], 5).tolist() == [0, 5, 10, 12, 17]  # restarts at each cut
    path = tmp_path / "takes.json"
    path.write_text(json.dumps({"takes": [{"name": "mouth", "start": 0, "end": 90, "extra": 1}]}))
    assert read_takes(path, 100) == [Take("mouth", 0, 90, None)]
    path.write_text(json.dumps({"takes": [{"name": "mouth", "start": 0, "end": 190}]}))
    with pytest.raises(InputFileError, match="outside"):
        read_takes(path, 100)


#: damaged copies of the sample's layout (each found by fuzzing the CLI: a crash inside rig,
#: evaluate or plan before read_layout checked types) and the field the error must name
DAMAGED_LAYOUTS = [
    (lambda d: d["clusters"][2].update(mirrored_from=True), "clusters[2].mirrored_from"),
    (lambda d: d["clusters"][0].update(member_correlation=5), "clusters[0].member_correlation"),
    (lambda d: d["regions"][2].update(representatives=True), "regions[2].representatives"),
    (lambda d: d["clusters"][1].update(position=[1.0, "x", 2.0]), "clusters[1].position"),
    (lambda d: d["clusters"][1].update(position=[1.0, 2.0]), "clusters[1].position"),
    (lambda d: d["clusters"][3].update(members=[1, 2]), "clusters[3].members"),
    (lambda d: d["clusters"][3].pop("representative"), "clusters[3].representative is missing"),
    (lambda d: d["clusters"][0].update(side="left"), "clusters[0].side"),
    (lambda d: d["regions"][0].update(samples=1.5), "regions[0].samples"),
    (lambda d: d.update(source="x"), "source must be an object"),
    (lambda d: d.update(clusters=[]), "no clusters"),
    (lambda d: d["clusters"][1].update(representative=d["clusters"][0]["representative"]), "named twice"),
    (lambda d: d["sagittal_plane"].update(normal=["x", 0, 0]), "sagittal_plane.normal"),
    (lambda d: d["sagittal_plane"].update(point=[0, 0]), "sagittal_plane.point"),
    (lambda d: d["sagittal_plane"].update(normal=[0, 0, 0]), "sagittal_plane.normal must not be zero"),
    (lambda d: d.update(stabilization=[]), "stabilization must be an object"),
    (lambda d: d.update(stabilization={"rigid_labels": [1, 2]}), "stabilization.rigid_labels"),
]


@pytest.mark.parametrize("damage, field", DAMAGED_LAYOUTS, ids=[f for _, f in DAMAGED_LAYOUTS])
def test_a_damaged_layout_file_names_the_bad_field(tmp_path, damage, field):
    doc = json.loads((Path(__file__).parent / "data" / "paper_layout_sample.json").read_text())
    read_layout(Path(__file__).parent / "data" / "paper_layout_sample.json")  # the intact file reads
    damage(doc)
    path = tmp_path / "layout.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputFileError, match=re.escape(field)):
        read_layout(path)


def test_layout_file_round_trip_is_byte_identical(tmp_path):
    traj, _ = planted_session(seed=9)
    layout = cluster_session(traj, options=ClusterOptions(method="paper", stabilize=False),
                             source={"path": "x.c3d", "sha256": "0" * 64}).layout
    first = write_layout(layout, tmp_path / "a.json")
    again = read_layout(first)
    second = write_layout(again, tmp_path / "b.json")
    assert first.read_bytes() == second.read_bytes()
    data = json.loads(first.read_text())
    assert data["format"] == "mocaptk.layout" and data["version"] == 1 and data["units"] == "mm"
    assert {"path", "sha256", "frames", "rate"} <= set(data["source"])
    assert {"factor", "step", "stabilized"} <= set(data["parameters"])
    assert data["layout"] == [c["representative"] for c in data["clusters"]]
    for cluster in data["clusters"]:
        assert {"representative", "region", "members", "member_correlation", "position", "side",
                "mirrored_from"} <= set(cluster)
        assert cluster["members"][0] == cluster["representative"]
