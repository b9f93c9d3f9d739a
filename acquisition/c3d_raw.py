"""Our own C3D reader in numpy, following the C3D specification (c3d.org, "The C3D File Format").

Two jobs:

* :func:`read_structure` parses and checks the header and parameter section (a few kB) of any
  C3D file — Intel, DEC (VAX floats) or MIPS (big-endian) processor, integer or float storage —
  and checks that the declared point data fit in the file, so a malformed file is refused in
  Python instead of reaching native code (ezc3d), and memory use is bounded by the file size.
* :func:`read_points` reads the 3-D point block with numpy, in blocks of frames; it is the
  reader :func:`.c3d_read.read_c3d` uses for every file (ezc3d only as a fallback).

Nothing here imports ezc3d.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError

BLOCK = 512
#: Processor type byte (parameter section byte 4) -> name.
PROCESSORS = {84: "intel", 85: "dec", 86: "mips"}
#: Refuse files whose point block would need more than this many (frame, marker) samples
#: (each becomes 4 float64 values in memory: ~32 bytes; 200 M samples ~ 6.4 GB).
MAX_POINT_SAMPLES = 200_000_000
#: The parameter section is parsed from at most this many bytes.
MAX_PARAMETER_BYTES = 4 * 2**20

#: Parameter value: list of strings (character parameters) or flat numeric array (file order).
ParamValue = list[str] | np.ndarray


@dataclass(frozen=True)
class C3DStructure:
    """What a C3D file declares, checked against its size.

    ``parameters`` maps upper-case ``GROUP -> PARAMETER -> value`` (character parameters as a
    list of right-stripped strings, numbers as a flat array in file order). ``scale`` is
    POINT:SCALE (negative: float storage); ``data_offset`` and ``frame_bytes`` locate frame ``i``
    at ``data_offset + i * frame_bytes``. ``notes`` lists repairs made while reading.
    """

    path: Path
    processor: str
    parameters: dict[str, dict[str, ParamValue]]
    n_points: int
    n_frames: int
    first_frame: int
    rate: float
    scale: float
    data_offset: int
    frame_bytes: int
    header_saturated: bool
    notes: tuple[str, ...] = ()

    @property
    def float_storage(self) -> bool:
        return self.scale < 0

    @property
    def analog_words(self) -> int:
        """Analog samples stored per frame (all channels)."""
        return self.frame_bytes // (4 if self.float_storage else 2) - 4 * self.n_points

    def param(self, group: str, name: str) -> ParamValue | None:
        """The value of ``GROUP:NAME`` or ``None``."""
        return self.parameters.get(group, {}).get(name)


def _dtypes(processor: str) -> tuple[str, str]:
    """(int16, float32) numpy dtype strings for ``processor`` (DEC floats need :func:`_dec`)."""
    return (">i2", ">f4") if processor == "mips" else ("<i2", "<f4")


def _dec(raw: np.ndarray) -> np.ndarray:
    """VAX F-floats (``uint32`` little-endian words as stored) -> float32."""
    swapped = ((raw >> 16) | (raw << 16)).astype(np.uint32)
    with np.errstate(invalid="ignore"):  # a signalling NaN (corrupt file) is just NaN
        return swapped.view("<f4") * np.float32(0.25)


def _floats(buf: bytes | np.ndarray, processor: str, count: int = -1, offset: int = 0) -> np.ndarray:
    if processor == "dec":
        return _dec(np.frombuffer(buf, "<u4", count, offset))
    return np.frombuffer(buf, _dtypes(processor)[1], count, offset).astype(np.float32)


def _signed_byte(byte: int) -> int:
    return byte - 256 if byte > 127 else byte


def _check(path: Path, condition: bool, problem: str) -> None:
    if not condition:
        raise InputFileError(path, problem)


def _parse_parameters(path: Path, data: bytes, processor: str,
                      data_blocks: int = 0) -> dict[str, dict[str, ParamValue]]:
    """Parse the group/parameter records of the parameter section ``data`` (from its 4-byte head).

    The section ends at its declared block count (one byte) or, if later, where the header
    puts the point data (``data_blocks`` blocks after the section's start): sections of more
    than 255 blocks (thousands of labels) declare a wrapped or saturated count. A record may
    run past the declared section (parameterOverflow.c3d); a record whose "next" pointer
    leaves the section ends the parse.
    """
    section_end = max(data[2], 1, data_blocks) * BLOCK
    i16 = np.dtype(_dtypes(processor)[0])
    groups: dict[int, str] = {}
    raw_params: list[tuple[int, str, ParamValue]] = []
    pos = 4
    end = len(data)
    while pos + 2 <= end:
        n_chars = abs(_signed_byte(data[pos]))
        group_id = _signed_byte(data[pos + 1])
        if n_chars == 0 or group_id == 0:
            break
        name_end = pos + 2 + n_chars
        _check(path, name_end + 2 <= end, "bad parameter section (record runs past the end of file)")
        name = data[pos + 2:name_end].decode("latin-1").strip().upper()
        shown = repr(name[:32])  # in messages: a corrupt name may be 127 NUL bytes
        offset = int(np.frombuffer(data, i16, 1, name_end)[0])
        next_pos = name_end + offset if offset > 0 else end
        _check(path, offset >= 0 and next_pos <= end,
               f"bad parameter section (record {shown} points to byte {name_end + offset})")
        body = name_end + 2
        if group_id > 0:
            _check(path, body + 2 <= next_pos, f"bad parameter section (parameter {shown} is cut)")
            size = _signed_byte(data[body])
            n_dims = data[body + 1]
            _check(path, size in (-1, 1, 2, 4) and n_dims <= 7,
                   f"bad parameter section (parameter {shown} has type {size}, {n_dims} dimensions)")
            dims = list(data[body + 2:body + 2 + n_dims])
            value_start = body + 2 + n_dims
            count = int(np.prod(dims)) if dims else 1
            value_end = value_start + abs(size) * count
            _check(path, value_end + 1 <= next_pos and len(dims) == n_dims,
                   f"bad parameter section (parameter {name!r} runs past its record)")
            desc_end = value_end + 1 + data[value_end]
            _check(path, desc_end <= next_pos,
                   f"bad parameter section (description of {name!r} runs past its record)")
            raw_params.append((group_id, name,
                               _decode_value(data[value_start:value_end], size, dims, processor)))
        else:
            _check(path, body + 1 <= next_pos and body + 1 + data[body] <= next_pos,
                   f"bad parameter section (group {name!r} runs past its record)")
            groups[-group_id] = name
        if offset == 0 or next_pos >= section_end:  # sgi_*.c3d: last record points far off
            break
        pos = next_pos
    params: dict[str, dict[str, ParamValue]] = {name: {} for name in groups.values()}
    for group_id, name, value in raw_params:
        group = groups.get(group_id)
        if group is not None:
            params[group].setdefault(name, value)
    return params


def _text(raw: bytes) -> str:
    """UTF-8 (what ezc3d writes) or, failing that, Latin-1; trailing blanks removed."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    return text.rstrip(" \0")


def _decode_value(raw: bytes, size: int, dims: list[int], processor: str) -> ParamValue:
    if size == -1:
        if not dims:
            return [_text(raw)]
        width = dims[0]
        n = len(raw) // width if width else 0
        return [_text(raw[k * width:(k + 1) * width]) for k in range(n)]
    if size == 1:
        return np.frombuffer(raw, np.int8).astype(np.int64)
    if size == 2:
        return np.frombuffer(raw, _dtypes(processor)[0]).astype(np.int64)
    with np.errstate(invalid="ignore"):  # a signalling NaN in a corrupt file is just NaN
        return _floats(raw, processor).astype(np.float64)


def _unsigned(value: ParamValue | None) -> int | None:
    """First element of an integer parameter read as unsigned 16-bit (a float is taken if it is
    a whole number in 0..65535, else ``None``)."""
    if not isinstance(value, np.ndarray) or value.size == 0 or not np.isfinite(value[0]):
        return None
    first = value[0]
    if value.dtype.kind == "f":
        return int(first) if 0 <= first <= 0xFFFF and first == int(first) else None
    return int(first) & 0xFFFF


def _field(value: ParamValue | None) -> int | None:
    """A TRIAL ``*_FIELD`` parameter (two unsigned 16-bit words, low first) as one integer."""
    if not isinstance(value, np.ndarray) or value.size < 2 or not np.isfinite(value[:2]).all():
        return None
    low, high = (int(v) & 0xFFFF for v in value[:2])
    return low + (high << 16)


def _scalar(value: ParamValue | None) -> float | None:
    if isinstance(value, np.ndarray) and value.size and np.isfinite(value[0]):
        return float(value[0])
    return None


def read_structure(path: str | os.PathLike[str]) -> C3DStructure:
    """Parse and check the header and parameter section of the C3D file ``path``.

    Raises :class:`InputFileError` for a file that is not a C3D, empty, truncated, has a bad
    parameter section, or declares more point data than the file holds.
    """
    path = Path(path)
    try:
        with open(path, "rb") as handle:
            file_size = os.fstat(handle.fileno()).st_size
            head = handle.read(BLOCK)
            _check(path, file_size > 0, "empty file (0 bytes)")
            _check(path, len(head) == BLOCK,
                   f"truncated C3D file ({file_size} bytes; the header alone is {BLOCK})")
            _check(path, head[1] == 0x50, "not a C3D file (no C3D key in the header)")
            param_start = (head[0] - 1) * BLOCK
            _check(path, head[0] >= 2 and param_start + 4 <= file_size,
                   f"bad parameter section (header points to block {head[0]})")
            handle.seek(param_start)
            param_head = handle.read(4)
            processor = PROCESSORS.get(param_head[3])
            _check(path, processor is not None,
                   f"unknown processor type {param_head[3]} (expected 84 Intel, 85 DEC, 86 MIPS)")
            assert processor is not None
            # the declared block count is not trusted (parameterOverflow.c3d): read on, bounded
            handle.seek(param_start)
            section = handle.read(min(file_size - param_start, MAX_PARAMETER_BYTES))
            data_block = int(np.frombuffer(head, _dtypes(processor)[0], 1, 16)[0]) & 0xFFFF
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror or exc})") from None
    params = _parse_parameters(path, section, processor, data_block - head[0])
    return _layout(path, head, params, processor, file_size, data_block)


def _layout(path: Path, head: bytes, params: dict[str, dict[str, ParamValue]], processor: str,
            file_size: int, header_data_block: int) -> C3DStructure:
    """Resolve counts, storage and data location from header + parameters; check against size."""
    i16 = _dtypes(processor)[0]
    words = np.frombuffer(head, i16, 12).astype(np.int64) & 0xFFFF
    header_points, analog_per_frame = int(words[1]), int(words[2])
    first, last = int(words[3]), int(words[4])
    header_scale = float(_floats(head, processor, 1, 12)[0])
    header_rate = float(_floats(head, processor, 1, 20)[0])
    point = params.get("POINT", {})

    notes = []
    n_points = _unsigned(point.get("USED"))
    if n_points is None:
        used = point.get("USED")
        if isinstance(used, np.ndarray) and used.size:  # e.g. a float -1.0 (fuzzed file)
            notes.append(f"POINT:USED {used[0]:g} is not a point count; used the header's "
                         f"{header_points}")
        n_points = header_points
    scale = _scalar(point.get("SCALE"))
    scale = header_scale if scale is None or scale == 0 else scale
    if np.isfinite(header_scale) and not np.isclose(abs(header_scale), abs(scale), rtol=1e-4):
        notes.append(f"header scale {header_scale:.6g} differs from POINT:SCALE {scale:.6g}; "
                     "used POINT:SCALE")  # MACsample.c3d
    _check(path, np.isfinite(scale) and scale != 0, f"invalid POINT:SCALE {scale}")
    rate = _scalar(point.get("RATE"))
    rate = header_rate if rate is None or rate <= 0 else rate
    data_block = _unsigned(point.get("DATA_START"))
    if not data_block:  # Dance.c3d / golfswing.c3d store 0
        data_block = header_data_block
    _check(path, data_block >= 2, f"invalid data start block {data_block}")
    data_offset = (data_block - 1) * BLOCK
    word_bytes = 4 if scale < 0 else 2
    header_frames = last - first + 1 if last >= first else 0
    data_bytes = max(file_size - data_offset, 0)
    analog_per_frame = _analog_words(params, analog_per_frame, int(words[9]), rate,
                                     lambda words: (4 * n_points + words) * word_bytes,
                                     header_frames, data_bytes)
    frame_bytes = (4 * n_points + analog_per_frame) * word_bytes
    available = data_bytes // frame_bytes if frame_bytes else 0

    saturated = last == 0xFFFF
    n_frames = header_frames
    trial = params.get("TRIAL", {})
    start_field, end_field = _field(trial.get("ACTUAL_START_FIELD")), _field(trial.get("ACTUAL_END_FIELD"))
    if start_field is not None and end_field is not None and end_field >= start_field:
        if saturated or header_frames == 0:
            n_frames = end_field - start_field + 1
        first = start_field  # 32-bit; equals the header's where both exist in the corpus
    if saturated and n_frames <= header_frames:
        declared = _unsigned(point.get("FRAMES"))
        if declared and declared > header_frames:
            n_frames = declared
        else:
            n_frames = available - _padding_frames(path, file_size, data_offset, frame_bytes,
                                                   available)
            notes.append(f"header frame count saturated; {n_frames} frames from the file size")
    if n_points == 0:
        n_frames = header_frames if frame_bytes == 0 else min(header_frames, available)
    _check(path, n_points * max(n_frames, 1) <= MAX_POINT_SAMPLES,
           f"declares {n_frames} frames of {n_points} markers, more than the "
           f"{MAX_POINT_SAMPLES:,} marker samples mocaptk reads at once")
    if frame_bytes and n_frames > available:
        # Optotrak.c3d declares 1149 frames but holds 29 whole ones (data end on a frame
        # boundary): read those. Data ending mid-frame is a cut file.
        _check(path, available > 0 and (file_size - data_offset) % frame_bytes == 0,
               f"truncated C3D file (declares {n_frames} frames of {frame_bytes} bytes from byte "
               f"{data_offset}, but holds only {available} whole frames)")
        notes.append(f"header declares {n_frames} frames, file holds {available}; read {available}")
        n_frames = available
    return C3DStructure(path=path, processor=processor, parameters=params, n_points=n_points,
                        n_frames=n_frames, first_frame=first, rate=rate, scale=scale,
                        data_offset=data_offset, frame_bytes=frame_bytes,
                        header_saturated=saturated, notes=tuple(notes))


def _padding_frames(path: Path, file_size: int, data_offset: int, frame_bytes: int,
                    available: int) -> int:
    """Whole frames at the end that are only the zero padding of the last 512-byte block."""
    if not frame_bytes or not available:
        return 0
    end = data_offset + available * frame_bytes
    first = max(data_offset, file_size - BLOCK)  # ezc3d adds a whole block when data end on one
    first_frame = -(-(first - data_offset) // frame_bytes)  # frames starting in the padding
    if first_frame >= available:
        return 0
    try:
        with open(path, "rb") as handle:
            handle.seek(data_offset + first_frame * frame_bytes)
            tail = handle.read(end - data_offset - first_frame * frame_bytes)
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror or exc})") from None
    frames = np.frombuffer(tail, np.uint8).reshape(-1, frame_bytes)
    nonzero = np.flatnonzero(frames.any(axis=1))
    return len(frames) - (nonzero[-1] + 1 if nonzero.size else 0)


def _analog_words(params: dict[str, dict[str, ParamValue]], header_words: int,
                  header_ratio: int, rate: float, frame_size: Callable[[int], int], n_frames: int,
                  data_bytes: int) -> int:
    """Analog samples per frame: the header's count unless another reading of header and
    parameters is the one that fills the data section (MotionMonitorC3D.c3d stores the channel
    count in the header, 7 samples per frame in word 10)."""
    analog = params.get("ANALOG", {})
    used, analog_rate = _unsigned(analog.get("USED")), _scalar(analog.get("RATE"))
    candidates = [header_words, header_words * max(header_ratio, 1)]
    if used is not None and analog_rate and rate > 0:
        candidates.append(used * round(analog_rate / rate))
    for words in candidates:
        size = frame_size(words) * n_frames
        if size and size <= data_bytes < size + max(BLOCK, frame_size(words)):
            return words
    return header_words


#: Bytes of frames decoded per step of :func:`read_points`: a block and its decoded values stay
#: in a core's L2 cache across the decode's passes (4 MB blocks: 5-10 % slower).
READ_BLOCK_BYTES = 2**19


def read_points(structure: C3DStructure, *, unit_scale: float = 1.0,
                gaps_as_nan: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Read the 3-D point block of a checked C3D file, a few MB of frames at a time.

    Parameters
    ----------
    unit_scale : multiply positions and residuals by this (e.g. mm per POINT:UNITS unit).
    gaps_as_nan : set positions and residuals to NaN where the file marks a point invalid
        (residual < 0) or a coordinate is not finite.

    Returns
    -------
    positions : (frames, points, 3) float64
        File units times ``unit_scale``, SCALE applied.
    residuals : (frames, points) float64
        Same units; negative where the file marks the point invalid (unless ``gaps_as_nan``).

    Memory: the two outputs plus one block of :data:`READ_BLOCK_BYTES`.
    """
    s = structure
    int_type, float_type = _dtypes(s.processor)
    if s.float_storage:
        word = "<u4" if s.processor == "dec" else float_type
    else:
        word = int_type
    frame = np.dtype([("points", word, (s.n_points, 4)),
                      ("rest", "V", s.frame_bytes - s.n_points * 4 * np.dtype(word).itemsize)])
    xyz = np.empty((s.n_frames, s.n_points, 3))
    residuals = np.empty((s.n_frames, s.n_points))
    step = max(1, READ_BLOCK_BYTES // max(frame.itemsize, 1))
    try:
        with open(s.path, "rb") as handle:
            handle.seek(s.data_offset)
            for start in range(0, s.n_frames, step):
                count = min(step, s.n_frames - start)
                block = np.fromfile(handle, frame, count)["points"]
                _check(s.path, len(block) == count, "truncated C3D file (point data cut short)")
                with np.errstate(over="ignore", invalid="ignore"):  # garbage: inf / NaN
                    _decode_points(block, s, unit_scale, gaps_as_nan,
                                   xyz[start:start + count], residuals[start:start + count])
    except OSError as exc:
        raise InputFileError(s.path, f"cannot read ({exc.strerror or exc})") from None
    return xyz, residuals


def _decode_points(block: np.ndarray, s: C3DStructure, unit_scale: float, gaps_as_nan: bool,
                   xyz: np.ndarray, residuals: np.ndarray) -> None:
    """Decode raw point words ``block`` (frames, points, 4) into ``xyz`` and ``residuals``."""
    if s.processor == "dec" and s.float_storage:
        block = _dec(block)
    # one strided (frames, points, 3) pass each: per axis is ~1.4x slower on numpy 2
    if s.float_storage:
        xyz[...] = block[..., :3]
        if unit_scale != 1.0:  # in float64, as the values are stored
            xyz *= unit_scale
    else:
        np.multiply(block[..., :3], abs(s.scale) * unit_scale, out=xyz)
    fourth = block[..., 3]  # kept in the file's word type: no float64 / int64 copies
    invalid = ~(fourth >= 0)  # NaN / -1: invalid
    if fourth.dtype.kind == "f":  # a float word holds the 16-bit integer
        fourth = np.minimum(fourth, 0xFFFF).astype(np.uint16)
    code = fourth & 0xFF  # low byte: residual in units of |SCALE|; high byte: camera mask
    np.multiply(code, abs(s.scale) * unit_scale, out=residuals)
    np.copyto(residuals, -1.0, where=invalid)
    if gaps_as_nan:
        mark_gaps(xyz, residuals)


def mark_gaps(xyz: np.ndarray, residuals: np.ndarray) -> None:
    """In place: NaN in ``xyz`` (F, N, 3) and ``residuals`` (F, N) where the residual is
    negative (invalid point) or a coordinate is not finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        total = xyz[..., 0] + xyz[..., 1]
        total += xyz[..., 2]
        missing = ~np.isfinite(total)
    missing |= residuals < 0
    # assigned at the (few) gaps: a masked copy over every sample is ~2x slower
    xyz[missing] = np.nan
    residuals[missing] = np.nan


def header_only_labels(n_points: int) -> list[str]:
    """Labels for files without POINT:LABELS: ``M001``, ``M002``... (width grows with count)."""
    width = max(3, len(str(n_points)))
    return [f"M{k + 1:0{width}d}" for k in range(n_points)]

