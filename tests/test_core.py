"""The shared core: Trajectories, takes, gap statistics, atomic outputs, deterministic JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mocaptk import MocaptkError, Take, Trajectories, concatenate_takes
from mocaptk.atomic import atomic_open, write_text
from mocaptk.errors import OutputError
from mocaptk.jsonio import dumps


def _session(frames=10, markers=3, rate=60.0):
    pos = np.arange(frames * markers * 3, dtype=float).reshape(frames, markers, 3)
    return Trajectories(pos, [f"M{i}" for i in range(markers)], rate)


def test_rejects_bad_shapes_labels_and_rate():
    with pytest.raises(MocaptkError, match="shape"):
        Trajectories(np.zeros((4, 2)), ["a", "b"], 60)
    with pytest.raises(MocaptkError, match="duplicate"):
        Trajectories(np.zeros((4, 2, 3)), ["a", "a"], 60)
    with pytest.raises(MocaptkError, match="rate"):
        Trajectories(np.zeros((4, 2, 3)), ["a", "b"], 0)
    with pytest.raises(MocaptkError, match="take"):
        Trajectories(np.zeros((4, 2, 3)), ["a", "b"], 60, metadata={"takes": [Take("t", 2, 9)]})


def test_select_and_frames_keep_takes_consistent():
    s = _session().replace(metadata={"takes": [Take("a", 0, 4), Take("b", 4, 10, "mouth")]})
    sub = s.select(["M2", "M0"])
    assert sub.labels == ("M2", "M0")
    np.testing.assert_array_equal(sub.positions[:, 0], s.positions[:, 2])
    cut = s.frames(3, 7)
    assert cut.n_frames == 4 and cut.first_frame == 3
    assert cut.takes == [Take("a", 0, 1), Take("b", 1, 4, "mouth")]
    np.testing.assert_array_equal(s.take("b").positions, s.positions[4:10])
    with pytest.raises(MocaptkError, match="unknown marker"):
        s.select(["nope"])


def test_concatenate_records_take_boundaries():
    a, b = _session(frames=5), _session(frames=7)
    joined = concatenate_takes([a, b], names=["brow", "mouth"], regions=["forehead_brow", None])
    assert joined.n_frames == 12
    assert joined.takes == [Take("brow", 0, 5, "forehead_brow"), Take("mouth", 5, 12)]
    with pytest.raises(MocaptkError, match="labels"):
        concatenate_takes([a, a.select(["M0"])])


def test_gap_stats_counts_runs_and_longest_gap():
    s = _session(frames=10, markers=2)
    pos = s.positions.copy()
    pos[0:3, 0] = np.nan      # leading gap of 3
    pos[5, 0, 1] = np.nan     # one missing coordinate counts as a missing frame
    pos[9, 1] = np.nan        # trailing gap of 1
    stats = s.replace(positions=pos).gap_stats()
    np.testing.assert_array_equal(stats.longest_gap, [3, 1])
    np.testing.assert_array_equal(stats.gap_count, [2, 1])
    np.testing.assert_allclose(stats.missing_fraction, [0.4, 0.1])


def test_strip_prefixes():
    s = Trajectories(np.zeros((1, 2, 3)), ["Anna:NOSE_01", "Anna:CHIN_02"], 60)
    assert s.strip_prefixes().labels == ("NOSE_01", "CHIN_02")


def test_atomic_write_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_open(target, "w") as handle:
            handle.write("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with pytest.raises(OutputError, match="already exists"):
        write_text(target, "new", force=False)


def test_json_is_deterministic_and_nan_free():
    text = dumps({"b": np.float32(0.1), "a": [np.nan, np.int64(3)], "c": -0.0000001})
    assert text == dumps(json.loads(text))
    assert json.loads(text) == {"a": [None, 3], "b": 0.1, "c": 0.0}


def test_json_rows_one_per_line_also_when_a_string_looks_like_a_row_break():
    """Rows of numbers (one C-encoder call for all) and rows holding text give the same layout:
    one row a line, floats rounded, no "-0.0"."""
    text = dumps({"rows": [[1, 0.1234567891], [], [True, None, -1e-9]],
                  "names": [["a], [b", 1], [2]], "mesh": np.array([[0.5, 1.0], [2.0, np.nan]])})
    assert text == ('{\n  "mesh": [\n    [0.5, 1.0],\n    [2.0, null]\n  ],\n'
                    '  "names": [\n    ["a], [b", 1],\n    [2]\n  ],\n'
                    '  "rows": [\n    [1, 0.123457],\n    [],\n    [true, null, 0.0]\n  ]\n}\n')


def test_vector_lengths_are_numpy_norms_on_either_axis():
    """The values of np.linalg.norm bit for bit (components from 1e-3 to 1e4, NaN, inf), the
    coordinate axis last or in the middle; the input is squared in place."""
    from mocaptk.geometry import vector_lengths

    rng = np.random.default_rng(3)
    vectors = rng.normal(size=(12000, 3)) * 10.0 ** rng.uniform(-3, 4, size=(12000, 1))
    vectors[::97, 1] = np.nan
    vectors[5::89, 2] = -np.inf
    expected = np.linalg.norm(vectors, axis=-1)
    middle = vectors.reshape(3, 4000, 3).transpose(0, 2, 1).copy()  # (3, xyz, 4000)
    np.testing.assert_array_equal(vector_lengths(middle, axis=1), expected.reshape(3, 4000))
    squared = vectors.copy()
    np.testing.assert_array_equal(vector_lengths(squared), expected)
    np.testing.assert_array_equal(squared, vectors ** 2)


def test_bounds_are_numpys_per_axis_min_and_max():
    """The mesh writers' extents: what ``min/max(axis=0)`` of the ``(N, 3)`` rows gives, dtype
    kept, NaN propagated, for a frame or a chunk of frames."""
    from mocaptk.geometry import bounds

    rng = np.random.default_rng(4)
    chunk = (rng.normal(size=(5, 1000, 3)) * 40).astype(np.float32)
    for points in (chunk[2], chunk, chunk[:, ::2]):
        low, high = bounds(points)
        rows = points.reshape(-1, 3)
        assert low.dtype == high.dtype == np.float32
        assert low.tobytes() == rows.min(axis=0).tobytes() and high.tobytes() == rows.max(axis=0).tobytes()
    chunk[3, 7, 1] = np.nan
    low, high = bounds(chunk)
    assert np.isnan(low[1]) and np.isnan(high[1]) and np.isfinite(low[[0, 2]]).all()


def test_json_records_one_key_a_line_also_when_a_string_looks_like_a_record_break():
    """Records of scalars (one C-encoder call for all) keep one key a line and a record per
    block, also when a string holds braces, commas and line breaks, or a record is empty."""
    records = [{"note": "},\n    {", "b": 1.0}, {"a": None, "é": "x}"}]
    expected = ('{\n  "gaps": [\n    {\n      "b": 1.0,\n      "note": "},\\n    {"\n    },\n'
                '    {\n      "a": null,\n      "é": "x}"\n    }\n  ]\n}\n')
    assert dumps({"gaps": records}) == expected
    assert json.loads(expected) == {"gaps": records}
    assert dumps({"gaps": [{}, {"a": 1}]}) == '{\n  "gaps": [\n    {},\n    {\n      "a": 1\n    }\n  ]\n}\n'
