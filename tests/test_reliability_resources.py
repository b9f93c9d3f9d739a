"""Resource bounds: 1 GB files and files declaring 10^9 frames/markers are refused (or read within
the documented limits) by a reader process capped at 2 GB of address space, in bounded time --
never a MemoryError, a crash or a hang. Limits: docs/reliability.md "Resource limits".
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import fuzz_readers

from mocaptk import Trajectories
from mocaptk.acquisition import c3d_raw, text_io
from mocaptk.acquisition.c3d_write import write_c3d
from mocaptk.acquisition.formats import write_trajectories

GB = 1 << 30


@pytest.fixture(scope="module")
def worker():
    module = fuzz_readers()
    w = module.Worker(memory_limit=2 * GB)  # RLIMIT_AS: reading may not need more
    w.start()
    yield w
    w.close()


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, object]:
    folder = tmp_path_factory.mktemp("big")
    rng = np.random.default_rng(3)
    traj = Trajectories(rng.normal(0, 100, (40, 3, 3)), ["A", "B", "C"], 100.0)
    small = write_c3d(traj, folder / "small.c3d").read_bytes()
    out = {}

    def sparse(name: str, head: bytes, size: int = GB) -> str:
        path = folder / name
        path.write_bytes(head)
        os.truncate(path, size)  # sparse: no disk used
        return str(path)

    out["c3d_1gb_tail"] = sparse("tail.c3d", small)  # 40 frames declared, 1 GB of zeros after
    saturated = bytearray(small)
    saturated[8:10] = b"\xff\xff"  # header last frame saturated: frames from the 1 GB size
    out["c3d_1gb_frames_from_size"] = sparse("size.c3d", bytes(saturated))
    at = small.index(b"ACTUAL_END_FIELD", 512) + len(b"ACTUAL_END_FIELD") + 5
    huge = bytearray(small[:at] + b"\xff\xff\x00\x40" + small[at + 4:])  # 2^30 frames
    huge[8:10] = b"\xff\xff"
    out["c3d_1e9_frames"] = sparse("declared.c3d", bytes(huge), len(huge))
    out["c3d_1e9_frames_1gb"] = sparse("declared_1gb.c3d", bytes(huge))
    trc = write_trajectories(traj, folder / "small.trc").read_bytes()
    lines = trc.split(b"\n")
    values = lines[2].split(b"\t")
    values[2] = values[3] = b"1000000000"  # NumFrames, NumMarkers
    out["trc_1e9_declared"] = str(folder / "declared.trc")
    (folder / "declared.trc").write_bytes(b"\n".join(lines[:2] + [b"\t".join(values)] + lines[3:]))
    rows = lines[6:-1]
    rows[-1] = b"1000000000" + rows[-1][rows[-1].index(b"\t"):]  # last frame number 10^9
    out["trc_frame_1e9"] = str(folder / "frame.trc")
    (folder / "frame.trc").write_bytes(b"\n".join(lines[:6] + rows) + b"\n")
    text_head = (trc * (8192 // len(trc) + 2))[: 16384]  # > the 8 KB the format sniffer reads
    out["trc_1gb"] = sparse("big.trc", text_head)
    csv_lines = [b"Frame,A_x,A_y,A_z"] + [b"%d,1,2,3" % f for f in (1, 2, 3, 1_000_000_000)]
    out["csv_frame_1e9"] = str(folder / "frame.csv")
    (folder / "frame.csv").write_bytes(b"\n".join(csv_lines) + b"\n")
    return out


EXPECT = {  # case -> "loaded" or a fragment of the one-line error
    "c3d_1gb_tail": "loaded",
    "c3d_1gb_frames_from_size": "",  # read within the sample limit, or refused for lack of memory
    "c3d_1e9_frames": f"more than the {c3d_raw.MAX_POINT_SAMPLES:,} marker samples",
    "c3d_1e9_frames_1gb": f"more than the {c3d_raw.MAX_POINT_SAMPLES:,} marker samples",
    "trc_1e9_declared": "loaded",  # counts are only noted: the data rows decide
    "trc_frame_1e9": "frame numbers run from",
    "trc_1gb": f"more than the {text_io.MAX_TEXT_BYTES // 2**20} MB",
    "csv_frame_1e9": "frame numbers run from",
}


@pytest.mark.parametrize("case", sorted(EXPECT))
def test_huge_files_are_refused_or_read_within_bounds(worker, files, case):
    rate = 100.0 if case.startswith("csv") else None
    out = worker.read(files[case], 60.0, rate)
    assert out["outcome"] in ("loaded", "error"), (case, out)  # not memory / crash / hang
    if EXPECT[case] == "loaded":
        assert out["outcome"] == "loaded", out
    else:
        assert out["outcome"] == "error" or not EXPECT[case], out
        if out["outcome"] == "error":
            assert out["one_line"] and out["names_file"], out
            assert EXPECT[case] in out["message"] or not EXPECT[case], out
    if case == "c3d_1gb_frames_from_size" and out["outcome"] == "error":
        assert "not enough memory" in out["message"], out
    if case == "trc_1e9_declared":
        assert out["shape"] == [40, 3, 3]


def test_huge_inputs_through_the_cli(run_cli, files):
    for case in ("c3d_1e9_frames", "trc_1gb", "csv_frame_1e9"):
        extra = ("--rate", "100") if case.startswith("csv") else ()
        result = run_cli("info", files[case], *extra)
        assert result.exit_code == 2, (case, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"mocaptk: error: {files[case]}: "), lines
