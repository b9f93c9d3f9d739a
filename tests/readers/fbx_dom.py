"""A minimal binary FBX 7.x record parser for structural assertions on the files we write."""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

_SCALARS = {b"Y": "<h", b"C": "<?", b"I": "<i", b"F": "<f", b"D": "<d", b"L": "<q"}
_ARRAYS = {b"f": "<f4", b"d": "<f8", b"i": "<i4", b"l": "<i8", b"b": "bool"}


@dataclass
class Record:
    name: str
    props: list
    children: list["Record"] = field(default_factory=list)

    def find(self, name: str) -> list["Record"]:
        return [c for c in self.children if c.name == name]

    def first(self, name: str) -> "Record":
        found = self.find(name)
        assert found, f"{self.name} has no child {name}"
        return found[0]


def parse_fbx(data: bytes) -> tuple[int, Record]:
    """(version, root record whose children are the top-level records)."""
    assert data[:23] == b"Kaydara FBX Binary  \x00\x1a\x00"
    version = struct.unpack_from("<I", data, 23)[0]
    root = Record("", [])
    offset = 27
    while True:
        record, offset = _parse(data, offset)
        if record is None:
            return version, root
        root.children.append(record)


def _parse(data: bytes, offset: int) -> tuple[Record | None, int]:
    end, count, _length, name_len = struct.unpack_from("<3IB", data, offset)
    if end == 0:
        return None, offset + 13
    offset += 13
    name = data[offset:offset + name_len].decode("ascii")
    offset += name_len
    props = []
    for _ in range(count):
        code = data[offset:offset + 1]
        offset += 1
        if code in _SCALARS:
            fmt = _SCALARS[code]
            props.append(struct.unpack_from(fmt, data, offset)[0])
            offset += struct.calcsize(fmt)
        elif code in (b"S", b"R"):
            size = struct.unpack_from("<I", data, offset)[0]
            raw = data[offset + 4:offset + 4 + size]
            props.append(raw.decode("utf-8") if code == b"S" else raw)
            offset += 4 + size
        else:
            n, encoding, size = struct.unpack_from("<3I", data, offset)
            raw = data[offset + 12:offset + 12 + size]
            props.append(np.frombuffer(zlib.decompress(raw) if encoding else raw,
                                       dtype=_ARRAYS[code], count=n))
            offset += 12 + size
    record = Record(name, props)
    while offset < end:
        child, offset = _parse(data, offset)
        if child is None:
            break
        record.children.append(child)
    assert offset == end, f"{name}: end offset {end} but parsed to {offset}"
    return record, offset
