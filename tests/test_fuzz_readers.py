"""A short deterministic subset of ``benchmarks/fuzz_readers.py`` (the 10,000-case campaign is a
benchmark run, see docs/reliability.md): mutated C3D / Vicon CSV / TRC / column CSV files read in an
isolated, memory-limited worker must load or fail with a one-line MocaptkError naming the file;
no crash, no hang, no other exception. Plus the campaign's past findings as regression cases.
"""

from __future__ import annotations


import pytest
from conftest import fuzz_readers, shared_path

CASES_PER_FORMAT = 24


@pytest.fixture(scope="module")
def fuzz():
    return fuzz_readers()


@pytest.fixture(scope="module")
def worker(fuzz):
    w = fuzz.Worker(memory_limit=3 << 30)
    w.start()
    yield w
    w.close()


def check(outcome: dict, case) -> None:
    assert outcome["outcome"] in ("loaded", "error"), (case, outcome)
    if outcome["outcome"] == "error":
        assert outcome["one_line"] and outcome["names_file"], (case, outcome)


@pytest.fixture(scope="module")
def pools(fuzz, tmp_path_factory):
    shared_path()
    return fuzz.seed_files(tmp_path_factory.mktemp("writer_seeds"))


@pytest.mark.parametrize("fmt", ["c3d", "vicon_csv", "trc", "generic_csv"])
def test_mutated_files_load_or_fail_cleanly(fuzz, worker, pools, fmt, tmp_path):
    blobs = [(p, fuzz.load_seed(p)) for p in pools[fmt]]
    assert blobs, f"no {fmt} seeds"
    rate = 100.0 if fmt == "generic_csv" else None
    kinds = set()
    for i in range(CASES_PER_FORMAT):
        source, name, data = fuzz.make_case(fmt, blobs, 11, i)
        kinds.add(name)
        case = tmp_path / f"case{i}{source.suffix}"
        case.write_bytes(data)
        check(worker.read(str(case), 20.0, rate), (fmt, fuzz.seed_name(source), name, i))
    assert len(kinds) >= 4  # the subset exercises several mutation kinds


def test_cases_are_reproducible_one_by_one(fuzz, tmp_path):
    blobs = [(tmp_path / "a.trc", b"PathFileType\t4\n" + bytes(range(256)) * 8)]
    assert fuzz.make_case("trc", blobs, 3, 17) == fuzz.make_case("trc", blobs, 3, 17)
    assert fuzz.make_case("trc", blobs, 3, 17) != fuzz.make_case("trc", blobs, 3, 18)


def test_past_findings_stay_fixed(fuzz, worker, tmp_path):
    """Campaign findings: a TRC declaring 10^9 markers hung (>20 s); NA cells of the blenderFace
    CSVs were rejected; an inf NumMarkers raised OverflowError; frame numbers of 10^9 / 1e308;
    C3D with 65,535 markers hung; overlong C3D parameter names in messages."""
    trc = shared_path("csv_trc", "btkdata", "10002-20130731010438-Unnamed.trc")
    lines = fuzz.load_seed(trc).split(b"\n")
    values = lines[2].split(b"\t")
    cases = {}
    for count in (b"999999999", b"inf", b"1e400"):
        bad = list(values)
        bad[3] = count  # NumMarkers
        cases[f"markers_{count.decode()}.trc"] = b"\n".join(lines[:2] + [b"\t".join(bad)] + lines[3:])
    data_at = next(i for i, line in enumerate(lines) if line[:1] == b"1")
    for number in (b"1000000000", b"1e308"):
        row = lines[data_at + 3].split(b"\t")
        row[0] = number
        cases[f"frame_{number.decode()}.trc"] = b"\n".join(lines[:data_at + 3] + [b"\t".join(row)]
                                                         + lines[data_at + 4:])
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        out = worker.read(str(tmp_path / name), 20.0)
        check(out, name)
        if name.startswith("frame_"):
            assert out["outcome"] == "error" and "frame" in out["message"], out
    # campaign 2: 65,535 header markers made Trajectories' duplicate check quadratic (115 s);
    # a corrupt 127-byte parameter name made a 520-character message
    phase = bytearray(shared_path("c3d", "btkdata", "c3d.org", "sample20", "phasespace_sample.c3d").read_bytes())
    for at in (2, 8, 18):
        phase[at:at + 2] = b"\xff\xff"
    opto = bytearray(shared_path("c3d", "ezc3d-testFiles", "Optotrak.c3d").read_bytes())
    for at, value in ((1159, 255), (1192, 41), (1346, 53), (2017, 232), (3060, 110), (3537, 227)):
        opto[at] = value
    for name, data in (("phase.c3d", phase), ("opto.c3d", opto)):
        (tmp_path / name).write_bytes(bytes(data))
        check(worker.read(str(tmp_path / name), 20.0), name)
    face = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    small = tmp_path / "face.csv"
    small.write_bytes(fuzz.load_seed(face))
    out = worker.read(str(small), 20.0, 100.0)
    assert out["outcome"] == "loaded", out
