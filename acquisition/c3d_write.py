"""Write :class:`mocaptk.Trajectories` to a C3D file with numpy, streamed by frame blocks (atomic).

The file follows the C3D specification (c3d.org, "The C3D File Format") as ezc3d 1.7 writes
it: Intel processor, float storage, POINT:SCALE −1 (residuals in whole mm), units ``mm``. The
point block is encoded and written a few MB at a time, so the extra memory is bounded by
:data:`BLOCK_BYTES`, not by the session size; the header and parameter section are a few kB
(plus the labels).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_open
from mocaptk.errors import OutputError
from mocaptk.trajectories import Trajectories

from .c3d_raw import BLOCK
from .c3d_read import TAKES_GROUP

#: Encoded point data per write (float32 words); bounds the writer's extra memory.
BLOCK_BYTES = 8 * 2**20
#: A parameter record's "next" offset is a signed 16-bit word.
MAX_RECORD_BYTES = 32_767
#: C3D stores a count (dimension) in one byte.
MAX_DIM = 255
INTEL = 84
SCALE = -1.0  # float storage; residual words count in units of |SCALE| mm

#: A parameter: (name, C3D type: -1 char, 2 int16, 4 float32, value) with value a list of str
#: or an int / float array.
Param = tuple[str, int, "list[str] | np.ndarray"]


def write_c3d(traj: Trajectories, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``traj`` to the C3D file ``path`` (Intel, float storage, units ``mm``).

    Gaps (NaN) are written as invalid points (residual −1, coordinates 0), never as valid
    zeros. Labels go to POINT:LABELS, LABELS2, LABELS3... (255 per parameter, fewer for labels
    over 128 bytes), up to 65,535 markers; more than 65,535 frames are written whole (the
    header field saturates, TRIAL:ACTUAL_START_FIELD/ACTUAL_END_FIELD hold the 32-bit frame
    range); ``first_frame`` is stored in the header and TRIAL fields; takes go to the
    ``MOCAPTK`` parameter group (TAKE_NAMES, TAKE_STARTS, TAKE_ENDS, TAKE_REGIONS; 0-based
    frames, end exclusive) so :func:`.c3d_read.read_c3d` restores them. Residuals are stored
    as the C3D standard allows: whole multiples of the scale (1 mm), 0-255.

    The file is written to a temporary sibling and renamed into place; an existing ``path``
    is refused unless ``force``.
    """
    n_frames, n_markers = traj.n_frames, traj.n_markers
    if n_frames == 0 or n_markers == 0:
        raise OutputError(f"{path}: nothing to write ({n_frames} frames, {n_markers} markers)")
    if n_markers > 0xFFFF:
        raise OutputError(f"{path}: C3D holds at most 65,535 markers, the session has {n_markers}")
    if len(traj.takes) > MAX_DIM:
        raise OutputError(f"{path}: C3D stores at most {MAX_DIM} takes, the session has "
                          f"{len(traj.takes)}")
    groups = _groups(traj)
    section = _parameter_section(groups, data_start=0, path=path)
    data_start = 2 + len(section) // BLOCK
    section = _parameter_section(groups, data_start=data_start, path=path)
    with atomic_open(path, "wb", force=force) as handle:
        try:
            handle.write(_header(traj, data_start))
            handle.write(section)
            written = _write_points(handle, traj)
            handle.write(bytes(-written % BLOCK))  # C3D files end on a block boundary
        except OSError as exc:
            raise OutputError(f"{path}: cannot write C3D ({exc.strerror or exc})") from None
    return Path(path)


def _header(traj: Trajectories, data_start: int) -> bytes:
    """The 512-byte header block (little-endian words)."""
    first = min(max(traj.first_frame, 1), 0xFFFF)
    last = min(first + traj.n_frames - 1, 0xFFFF)  # saturates past 65,535 (TRIAL holds it)
    head = bytearray(BLOCK)
    head[0:2] = bytes([2, 0x50])  # parameters in block 2; C3D key
    struct.pack_into("<HHHHH", head, 2, traj.n_markers, 0, first, last, 10)
    struct.pack_into("<fHHf", head, 12, SCALE, data_start, 0, traj.rate)
    struct.pack_into("<H", head, 298, 12345)  # "4-character event labels" key, as ezc3d writes
    return bytes(head)


def _groups(traj: Trajectories) -> list[tuple[str, list[Param]]]:
    """The parameter groups to write; POINT:DATA_START is filled in by the caller."""
    first, last = traj.first_frame, traj.first_frame + traj.n_frames - 1
    point: list[Param] = [
        ("USED", 2, np.array([traj.n_markers])),
        ("SCALE", 4, np.array([SCALE])),
        ("RATE", 4, np.array([traj.rate])),
        ("DATA_START", 2, np.array([0])),
        ("FRAMES", 2, np.array([min(traj.n_frames, 0xFFFF)])),
        ("UNITS", -1, ["mm"]),
    ]
    point += _split_strings("LABELS", list(traj.labels))
    descriptions = traj.metadata.get("descriptions") or {}
    if descriptions:
        point += _split_strings("DESCRIPTIONS",
                                [str(descriptions.get(label, "")) for label in traj.labels])
    groups = [("POINT", point),
              ("ANALOG", [("USED", 2, np.array([0])), ("RATE", 4, np.array([0.0]))]),
              ("TRIAL", [("ACTUAL_START_FIELD", 2, _words(first)),
                         ("ACTUAL_END_FIELD", 2, _words(max(last, first)))])]
    takes = traj.takes
    if takes:
        groups.append((TAKES_GROUP, [
            ("TAKE_NAMES", -1, [t.name for t in takes]),
            ("TAKE_STARTS", 4, np.array([float(t.start) for t in takes])),
            ("TAKE_ENDS", 4, np.array([float(t.end) for t in takes])),
            ("TAKE_REGIONS", -1, [t.region or "" for t in takes])]))
    return groups


def _split_strings(name: str, values: list[str]) -> list[Param]:
    """``NAME``, ``NAME2``, ``NAME3``... of at most 255 strings each (fewer if long)."""
    width = max([len(v.encode("utf-8")) for v in values] + [1])
    per_param = min(MAX_DIM, (MAX_RECORD_BYTES - 64) // width)
    return [(name if k == 0 else f"{name}{k + 1}", -1, values[start:start + per_param])
            for k, start in enumerate(range(0, len(values), per_param))]


def _words(value: int) -> np.ndarray:
    """A 32-bit unsigned frame number as the two 16-bit words of a TRIAL ``*_FIELD``."""
    value = max(int(value), 0)
    return np.array([value & 0xFFFF, value >> 16])


def _parameter_section(groups: list[tuple[str, list[Param]]], *, data_start: int,
                       path: str | os.PathLike[str]) -> bytes:
    """The parameter section (4-byte head + group and parameter records), padded to blocks."""
    records = []
    for group_id, (group, params) in enumerate(groups, start=1):
        records.append(_record(group, -group_id, b""))
        for name, kind, value in params:
            if name == "DATA_START" and group == "POINT":
                value = np.array([data_start])
            records.append(_record(name, group_id, _value(name, kind, value, path)))
    last = records[-1]
    records[-1] = last[:2 + last[0]] + b"\0\0" + last[4 + last[0]:]  # offset 0 ends the section
    body = b"".join(records)
    n_blocks = -(-(4 + len(body)) // BLOCK)
    # the block count is one byte; readers that trust it read up to 255 blocks (ours and ezc3d
    # read on to the data start)
    head = bytes([1, 0x50, min(n_blocks, MAX_DIM), INTEL])
    return (head + body).ljust(n_blocks * BLOCK, b"\0")


def _record(name: str, group_id: int, value: bytes) -> bytes:
    """A group (``group_id`` < 0, empty ``value``) or parameter record, no description."""
    raw = name.encode("ascii")
    offset = 2 + len(value) + 1  # from this word to the next record
    return bytes([len(raw), group_id & 0xFF]) + raw + struct.pack("<h", offset) + value + b"\0"


def _value(name: str, kind: int, value: list[str] | np.ndarray,
           path: str | os.PathLike[str]) -> bytes:
    """Type byte, dimensions and data of one parameter."""
    if kind == -1:
        encoded = [str(v).encode("utf-8") for v in value]
        width = max([len(v) for v in encoded] + [1])
        if width > MAX_DIM:
            raise OutputError(f"{path}: a {name} entry is {width} bytes long; C3D stores at "
                              f"most {MAX_DIM}")
        dims = [width] if name == "UNITS" else [width, len(encoded)]
        data = b"".join(v.ljust(width, b" ") for v in encoded)
    else:
        array = np.asarray(value)
        dims = [] if array.size == 1 else [array.size]
        data = (array.astype(np.int64) & 0xFFFF).astype("<u2").tobytes() if kind == 2 \
            else array.astype("<f4").tobytes()
    return struct.pack("<bB", kind, len(dims)) + bytes(dims) + data


def _write_points(handle, traj: Trajectories) -> int:
    """Write the point block frame block by frame block; returns the bytes written."""
    n_markers = traj.n_markers
    frames_per_block = max(1, BLOCK_BYTES // (16 * n_markers))
    written = 0
    for start in range(0, traj.n_frames, frames_per_block):
        stop = min(start + frames_per_block, traj.n_frames)
        handle.write(_encode(traj, start, stop).tobytes())
        written += (stop - start) * n_markers * 16
    return written


def _encode(traj: Trajectories, start: int, stop: int) -> np.ndarray:
    """Frames ``start:stop`` as C3D float words (frames, markers, 4): x, y, z, residual word."""
    pos = traj.positions[start:stop]
    missing = ~np.isfinite(pos).all(axis=2)
    words = np.empty(pos.shape[:2] + (4,), "<f4")
    with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, read back as gaps
        words[..., :3] = pos
    words[missing, :3] = 0.0
    if traj.residuals is None:
        residual = np.zeros(pos.shape[:2])
    else:  # a valid point without a residual (e.g. gap-filled) gets 0, "interpolated"
        residual = np.nan_to_num(traj.residuals[start:stop], nan=0.0, posinf=0.0, neginf=0.0)
    words[..., 3] = np.rint(np.clip(residual / abs(SCALE), 0, 255))
    words[missing, 3] = -1.0
    return words
