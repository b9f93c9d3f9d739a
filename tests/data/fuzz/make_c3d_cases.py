"""Regenerate the C3D fuzz reproducers in this folder (issue 14, items 11/14): each is a small file
written by mocaptk's own C3D writer (2 markers x 3 frames), then mutated the way the campaign's
mutators did; and ``face_in_metres_read_as_mm.trc`` (item 6): 24 markers x 40 frames of the
bundled synthetic sample in metres, so no rigid marker set can be detected.

    python tests/data/fuzz/make_c3d_cases.py
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mocaptk import Trajectories
from mocaptk.acquisition import c3d_write, read_trajectories, write_trajectories

HERE = Path(__file__).parent
SAMPLE = HERE.parents[2] / "sample_c3d" / "dense_halfface.c3d"


def base(path: Path) -> bytearray:
    pos = np.arange(18, dtype=float).reshape(3, 2, 3) * 10.0
    c3d_write.write_c3d(Trajectories(pos, ["A", "B"], 100.0), path)
    return bytearray(path.read_bytes())


def record(data: bytearray, name: bytes) -> int:
    """Offset of the type byte of parameter ``name`` (our writer: no descriptions)."""
    at = data.index(bytes([len(name)]) + b"\x01" + name, 512)  # POINT is group 1
    return at + 2 + len(name) + 2


def vax(values: np.ndarray) -> np.ndarray:
    """float32 -> DEC (VAX F) words as stored (inverse of ``c3d_raw._dec``)."""
    bits = (np.asarray(values, "<f4") * np.float32(4)).view("<u4")
    return ((bits >> 16) | (bits << 16)).astype("<u4")


def to_dec(data: bytearray) -> bytearray:
    """Re-encode every float of one of our files (header, float parameters, point block) as DEC."""
    for at in (12, 20):
        data[at:at + 4] = vax(np.frombuffer(data, "<f4", 1, at)).tobytes()
    pos = 516
    while True:
        n, group = data[pos], struct.unpack_from("b", data, pos + 1)[0]
        offset = struct.unpack_from("<h", data, pos + 2 + n)[0]
        body = pos + 4 + n
        if group > 0 and struct.unpack_from("b", data, body)[0] == 4:
            dims = data[body + 2:body + 2 + data[body + 1]]
            count = int(np.prod(list(dims))) if dims else 1
            at = body + 2 + len(dims)
            data[at:at + 4 * count] = vax(np.frombuffer(data, "<f4", count, at)).tobytes()
        if offset == 0:
            break
        pos += 2 + n + offset
    data[512 + 3] = 85  # processor: DEC
    start = (struct.unpack_from("<H", data, 16)[0] - 1) * 512
    words = len(data) - start
    data[start:] = vax(np.frombuffer(data, "<f4", words // 4, start)).tobytes()
    return data


def main() -> None:
    tmp = HERE / ".base.c3d"
    data = base(tmp)
    tmp.unlink()
    units = record(data, b"UNITS")  # type -1 (char), 1 dim [2], "mm"
    one = bytearray(data)
    one[units], one[units + 2] = 2, 1  # int16 x 1: the two bytes "mm" read as one number
    (HERE / "c3d_units_numeric.c3d").write_bytes(one)
    two = bytearray(data)
    two[units] = 1  # int8 x 2: two numbers
    (HERE / "c3d_units_two_numbers.c3d").write_bytes(two)

    groups = c3d_write._groups(Trajectories(np.zeros((3, 2, 3)), ["A", "B"], 100.0))
    point = dict((name, (kind, value)) for name, kind, value in groups[0][1])
    point["USED"] = (4, np.array([-1.0]))  # float -1.0 instead of int16 2
    groups[0] = ("POINT", [(name, kind, value) for name, (kind, value) in point.items()])
    section = c3d_write._parameter_section(groups, data_start=3, path="x")
    assert len(section) == 512
    used = bytearray(data[:512]) + bytearray(section) + data[1024:]
    (HERE / "c3d_used_float_minus_one.c3d").write_bytes(used)

    dec = to_dec(bytearray(data))
    dec[12:16] = struct.pack("<I", 0x00007FA0)  # DEC words swapped: a signalling NaN scale
    (HERE / "c3d_dec_header_scale_snan.c3d").write_bytes(dec)

    face = read_trajectories(SAMPLE)
    face = face.select(list(face.labels[::6])).frames(0, 40)
    face = face.replace(positions=np.round(face.positions * 0.001, 6), metadata={})
    write_trajectories(face, HERE / "face_in_metres_read_as_mm.trc")


if __name__ == "__main__":
    main()
