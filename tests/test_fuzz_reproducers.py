"""The fault campaign's reproducers (tests/data/fuzz/, see its README.md), re-run on every test run.

Every marker file there is read in an isolated, memory-capped worker (``benchmarks/fuzz_readers.py``)
and must load or stop with one line naming the file: no traceback, no RuntimeWarning, no hang, no
MemoryError. Cases with a known outcome are checked against it. Plus: memory stays linear in the
text, an out-of-memory read names the file, and infinite cells are gaps.
"""

from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, fuzz_readers

FUZZ = REPO / "tests" / "data" / "fuzz"
MARKER_SUFFIXES = (".c3d", ".csv", ".trc")

#: reproducer -> "loaded" or a fragment of its one-line error (files of other cases are only
#: required to load or fail cleanly)
EXPECT = {
    "column_csv_long_cell.csv": "loaded",  # csv.Error: field larger than field limit (131072)
    "vicon_long_event.csv": "loaded",  # same, in an Events description
    "vicon_long_label.csv": "a marker label of 140,002 characters, more than 255",
    "semicolons_1mb.csv": "no coordinate columns",  # took quadratic time (killed at 60 s)
    "trc_long_cell.trc": "line 27, column 8: not a number: 'xxx",  # allocated 3.1 GiB (<U100000)
    "csv_million_cells.csv": "loaded",  # a <U702 array of 10^6 cells: 2.8 GB
    "trc_wide_row.trc": "a table of 3,000 rows x 1,000,007 columns, but the file holds only",
    "trc_inf_cells.trc": "loaded",  # inf / -1e309 cells were values, not gaps
    "utf16_column.csv": "not UTF-8 text (UTF-16",  # was "binary content that is not C3D"
    "cluster_no_data.trc": "loaded", "cluster_one_frame.trc": "loaded", "cluster_short_take.csv": "loaded",
}


def marker_reproducers() -> list[Path]:
    return sorted(p for p in FUZZ.iterdir() if p.name.removesuffix(".gz").endswith(MARKER_SUFFIXES))


def unpacked(path: Path, folder: Path) -> Path:
    """``path`` itself, or its decompressed copy in ``folder`` for a ``.gz`` reproducer."""
    if path.suffix != ".gz":
        return path
    target = folder / path.name.removesuffix(".gz")
    target.write_bytes(gzip.decompress(path.read_bytes()))
    return target


@pytest.fixture(scope="module")
def worker():
    module = fuzz_readers()
    w = module.Worker(memory_limit=2 << 30)
    w.start()
    yield w
    w.close()


def test_every_reproducer_loads_or_fails_in_one_line(worker, tmp_path):
    files = marker_reproducers()
    assert set(EXPECT) <= {p.name.removesuffix(".gz") for p in files}, "a reproducer went missing"
    for original in files:
        path = unpacked(original, tmp_path)
        rate = 100.0 if path.name.startswith(("column_csv", "csv_")) else None
        out = worker.read(str(path), 60.0, rate)  # 60 s: only a hang guard (each takes < 15 s loaded)
        assert out["outcome"] in ("loaded", "error"), (path.name, out)
        if out["outcome"] == "error":
            assert out["one_line"] and out["names_file"], (path.name, out)
        expected = EXPECT.get(path.name)
        if expected == "loaded":
            assert out["outcome"] == "loaded", (path.name, out)
        elif expected is not None:
            assert out["outcome"] == "error" and expected in out["message"], (path.name, out)


def test_infinite_cells_are_gaps():
    """``inf``, ``-1e309`` and ``1e400`` cells are gaps (as C3D treats them), without RuntimeWarning."""
    from mocaptk.acquisition.formats import read_trajectories

    traj = read_trajectories(FUZZ / "trc_inf_cells.trc")
    gaps = np.isnan(traj.positions).all(axis=2)
    assert np.isfinite(traj.positions[~gaps]).all()
    assert gaps.tolist() == [[False, False], [True, False], [False, True], [True, False], [False, False]]


def test_values_beyond_float_range_once_scaled_are_gaps(tmp_path):
    """1e308 m is beyond float range in mm: a gap, not inf (and no overflow RuntimeWarning)."""
    from mocaptk.acquisition.formats import read_trajectories

    path = tmp_path / "m.csv"
    path.write_text("Time,A_x (m),A_y (m),A_z (m)\n0,1e308,0,0\n0.01,0.1,0.2,0.3\n")
    traj = read_trajectories(path)
    assert np.isnan(traj.positions[0]).all() and np.allclose(traj.positions[1], [[100, 200, 300]])


MEMORY_PROBE = r"""
import json, resource, sys, tracemalloc
resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
from mocaptk.acquisition.formats import detect_format, read_trajectories
from mocaptk.errors import MocaptkError
out = {}
for path in sys.argv[1:]:
    rate = 100.0 if detect_format(path) == "generic_csv" else None
    tracemalloc.start()
    try:
        read_trajectories(path, rate=rate)
    except MocaptkError:
        pass
    out[path] = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
print(json.dumps(out))
"""


def _peaks(paths: list[Path]) -> dict[str, int]:
    run = subprocess.run([sys.executable, "-c", MEMORY_PROBE, *map(str, paths)], capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout)


def test_text_memory_stays_linear(tmp_path):
    """docs/reliability.md: ~18 bytes of memory per byte of text for ordinary files (TRC, Vicon CSV,
    column CSV of a 100-marker session); the adversarial reproducers (a 100,000-character cell, a
    10^6-cell line) stay within a small multiple, never a fixed-width array of the longest cell."""
    from mocaptk import Trajectories
    from mocaptk.acquisition.formats import write_trajectories

    rng = np.random.default_rng(5)
    positions = rng.normal(0, 50, (1500, 100, 3))  # 4-5 MB files: per-block constants amortised
    positions[rng.random((1500, 100)) < 0.05] = np.nan
    traj = Trajectories(positions, [f"M{i:03d}" for i in range(100)], 100.0)
    ordinary = [write_trajectories(traj, tmp_path / f"s.{ext}") for ext in ("trc", "csv")]
    column = tmp_path / "column.csv"
    header = "Time," + ",".join(f"M{i:03d}_{a}" for i in range(100) for a in "xyz")
    column.write_text(header + "\n" + "\n".join(
        f"{f / 100:.2f}," + ",".join("NA" if np.isnan(v) else f"{v:.4f}" for v in row)
        for f, row in enumerate(positions.reshape(len(positions), -1))) + "\n")
    ordinary.append(column)
    adversarial = [unpacked(FUZZ / f"{name}.gz", tmp_path) for name in
                   ("trc_long_cell.trc", "csv_million_cells.csv", "semicolons_1mb.csv")]
    peaks = _peaks(ordinary + adversarial)
    ratios = {}
    for path in ordinary:
        ratio = peaks[str(path)] / path.stat().st_size
        assert ratio < 18, (path.name, ratio)
        ratios[path.name] = round(ratio, 1)
    for path in adversarial:
        assert peaks[str(path)] < 50 * path.stat().st_size + (8 << 20), (path.name, peaks[str(path)])
        ratios[path.name] = round(peaks[str(path)] / path.stat().st_size, 1)
    print("peak bytes per byte of text:", ratios)


def test_out_of_memory_names_the_file(tmp_path):
    """A text file too big for the memory left ends as one line naming the file, exit 2."""
    from mocaptk import Trajectories
    from mocaptk.acquisition.formats import write_trajectories

    traj = Trajectories(np.random.default_rng(1).normal(0, 50, (6000, 100, 3)),
                        [f"M{i:03d}" for i in range(100)], 100.0)
    big = write_trajectories(traj, tmp_path / "big.trc")  # ~ 20 MB of text: needs ~ 60 MB to parse
    small = write_trajectories(traj.select(["M000"]), tmp_path / "small.trc")
    probe = ("import resource, sys\n"
             "from mocaptk.cli import main\n"
             "try:\n    main(['info', sys.argv[2]])\n"  # imports all info needs before the limit
             "except SystemExit:\n    pass\n"
             "vm = next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmSize'))\n"
             "limit = vm * 1024 + (16 << 20)\n"  # 16 MB beyond what the interpreter holds now
             "resource.setrlimit(resource.RLIMIT_AS, (limit, limit))\n"
             "main(['info', sys.argv[1]])\n")
    run = subprocess.run([sys.executable, "-c", probe, str(big), str(small)], capture_output=True, text=True, timeout=300)
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1, run.stderr[-2000:]
    assert lines[0].startswith(f"mocaptk: error: {big}: out of memory while reading it"), lines


#: cluster option files (tests/data/fuzz/cluster_options/) -> (option, fragment of the one-line error)
OPTION_CASES = {
    "takes_end_1e400.json": ("--takes", "take 1 ('smile'): end inf is not a whole frame number"),  # OverflowError
    "takes_start_minus_infinity.json": ("--takes", "start -inf is not a whole frame number"),  # OverflowError
    "takes_fraction.json": ("--takes", "start 0.9 is not a whole frame number"),  # was truncated to 0
    "regions_latin1.csv": ("--regions", "not UTF-8 text (bad byte at offset 34)"),  # UnicodeDecodeError
    "regions_empty_list.json": ("--regions", "region 'eye' lists no markers"),  # a 0-marker layout, exit 0
}


@pytest.mark.parametrize("name", sorted(OPTION_CASES))
def test_cluster_option_reproducers_fail_in_one_line(run_cli, tmp_path, name):
    option, fragment = OPTION_CASES[name]
    path = FUZZ / "cluster_options" / name
    result = run_cli("cluster", REPO / "sample_c3d" / "dense_halfface.c3d", option, path,
                     "--out", tmp_path / "out", "--formats", "none")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and "Traceback" not in result.stderr, result.stderr[-800:]
    assert lines[-1] == lines[-1].strip() and lines[-1].startswith(f"mocaptk: error: {path}: "), lines
    assert fragment in lines[-1], lines[-1]
    assert not (tmp_path / "out").exists()


def test_cluster_option_reproducers_are_all_checked():
    assert sorted(p.name for p in (FUZZ / "cluster_options").iterdir()) == sorted(OPTION_CASES)


#: sessions whose cluster errors did not name the file -> fragment of the one-line error
SESSION_CASES = {
    "cluster_no_data.trc": "need at least 2 markers with data, the session has 0",
    "cluster_one_frame.trc": "--step 5 is not smaller than the session's 1 frames",
    "cluster_short_take.csv": "region 'forehead_brow': only 1 frames sampled with --step 5; use a smaller step",
}


@pytest.mark.parametrize("name", sorted(SESSION_CASES))
def test_cluster_errors_about_the_session_name_it(run_cli, tmp_path, name):
    session = FUZZ / name
    result = run_cli("cluster", session, "--no-stabilize", "--out", tmp_path / "o", "--formats", "none")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and "Traceback" not in result.stderr, result.stderr[-800:]
    assert lines[-1] == f"mocaptk: error: {session}: {SESSION_CASES[name]}", lines
