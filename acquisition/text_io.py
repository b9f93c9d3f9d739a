"""Shared plumbing of the text marker formats (Vicon CSV, TRC, column CSV): reading, units, cells."""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError, OptionError, unreadable

#: Millimetres per unit for the length units the text formats declare.
MM_PER_UNIT: dict[str, float] = {"mm": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0, "in": 25.4}

#: Largest text marker file read: parsing needs ~18 bytes of memory per byte of text (~9 GB here).
MAX_TEXT_BYTES = 512 * 2**20

#: Frame numbering may skip frames (they become gap frames), but the span may not exceed
#: ``MAX_GAP_FACTOR`` times the rows in the file plus ``MAX_GAP_FRAMES``: a corrupt frame number
#: (10^9) must not allocate billions of empty frames.
MAX_GAP_FACTOR, MAX_GAP_FRAMES = 10, 100_000

#: Short rows are padded with gaps up to the widest row: the padded table may hold at most
#: ``MAX_PADDING`` times the cells of the file plus ``MIN_PADDED_CELLS`` (128 MB of float64).
MAX_PADDING, MIN_PADDED_CELLS = 4, 2**24

#: Cells parsed at once (a block of rows): bounds the memory of their Python strings.
CHUNK_CELLS = 2**16

#: Longest marker label accepted (a C3D label holds at most 255 bytes too).
MAX_LABEL_CHARS = 255

#: Cell texts that mean "no value" (besides the empty cell).
MISSING_CELLS = frozenset({"", "na", "nan", "n/a", "null", "none", "-"})


def read_text(path: str | os.PathLike[str]) -> str:
    """The whole file as text; one-line :class:`InputFileError` if unreadable, empty or not UTF-8."""
    target = Path(path)
    try:
        size = target.stat().st_size
        if size > MAX_TEXT_BYTES:
            raise InputFileError(path, f"text file of {size / 2**20:,.0f} MB, more than the "
                                       f"{MAX_TEXT_BYTES // 2**20} MB mocaptk reads as text (export C3D instead)")
        data = target.read_bytes()
    except OSError as exc:
        raise unreadable(path, exc) from None
    if not data.strip():
        raise InputFileError(path, "file is empty")
    if looks_utf16(data[:8192]):
        raise InputFileError(path, UTF16_PROBLEM)
    if b"\x00" in data:
        raise InputFileError(path, "binary content: not a text marker file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (bad byte at offset {exc.start})") from None
    return text


#: The problem reported for UTF-16 text (Windows "Unicode" exports).
UTF16_PROBLEM = "not UTF-8 text (UTF-16: re-save or export it as UTF-8)"


def looks_utf16(head: bytes) -> bool:
    """True when ``head`` (a file's first bytes) is UTF-16 text: a byte-order mark, or ASCII with a
    NUL byte beside every character."""
    if head.startswith((b"\xff\xfe", b"\xfe\xff")):
        return True
    pairs = len(head) // 2
    if pairs < 2:
        return False
    for zeros, chars in ((head[1::2], head[0::2]), (head[0::2], head[1::2])):  # little / big endian
        if zeros[:pairs].count(0) >= 0.9 * pairs and chars[:pairs].count(0) <= 0.1 * pairs:
            return True
    return False


def mm_per_unit(units: str | float, *, source: str | os.PathLike[str] | None = None) -> float:
    """Millimetres per ``units`` (mm, cm, dm, m, in, or a positive number = mm per unit, given as
    text or, from Python, as a number: ``read_trajectories(p, units=187.6)``).

    Unknown units raise :class:`InputFileError` naming ``source`` when the units came from a file,
    else :class:`OptionError` (a bad ``--units`` option).
    """
    key = str(units).strip().lower() if isinstance(units, (str, int, float)) and not isinstance(units, bool) else ""
    if key in MM_PER_UNIT:
        return MM_PER_UNIT[key]
    try:  # a bare number: millimetres per file unit (e.g. Blender units scaled by a known distance)
        value = float(key)
    except ValueError:
        value = float("nan")
    if np.isfinite(value) and value > 0:
        return value
    known = ", ".join(MM_PER_UNIT) + " or a number of mm per unit"
    if source is not None:
        raise InputFileError(source, f"unknown length units {units!r} (known: {known})")
    raise OptionError(f"unknown length units {units!r} (known: {known})")


def check_table_size(rows: int, width: int, cells: int, *, path: str | os.PathLike[str]) -> None:
    """Refuse padding ``rows`` rows to ``width`` columns when the file holds only ``cells`` cells.

    Short rows are padded with gaps; a single overlong row or header line (10^6 cells) must not make
    every row that wide (memory growing faster than the file).
    """
    if rows * width > MAX_PADDING * cells + MIN_PADDED_CELLS:
        raise InputFileError(path, f"a table of {rows:,} rows x {width:,} columns, but the file holds only "
                                   f"{cells:,} cells: one overlong row or header line? (padding the rows "
                                   f"would need {rows * width * 8 / 2**30:,.1f} GB)")


def _normalised(cell: str, *, decimal_comma: bool) -> str:
    """A cell ready for float parsing: stripped, ``MISSING_CELLS`` as ``"nan"``, decimal comma as point."""
    text = cell.strip()
    if text.lower() in MISSING_CELLS:
        return "nan"
    return text.replace(",", ".") if decimal_comma else text


def cells_to_array(rows: Sequence[Sequence[str]], width: int, *, path: str | os.PathLike[str],
                   first_line: int, decimal_comma: bool = False) -> np.ndarray:
    """Parse text cells to a ``(rows, width)`` float64 array; missing cells become NaN.

    Rows shorter than ``width`` are padded with NaN, longer rows are cut. ``first_line`` is the
    1-based line number of ``rows[0]``, used to name a bad cell in the error. Memory is linear in
    the text: blocks of rows are parsed by numpy from their Python strings, never gathered in a
    fixed-width string array (as wide as the longest cell, for every cell).
    """
    check_table_size(len(rows), width, sum(min(len(row), width) for row in rows), path=path)
    out = np.empty((len(rows), width), dtype=np.float64)
    step = max(1, CHUNK_CELLS // max(width, 1))
    for start in range(0, len(rows), step):
        block = [row[:width] for row in rows[start:start + step]]
        _fill(out[start:start + len(block)], [len(row) for row in block],
              [cell for row in block for cell in row], decimal_comma=decimal_comma, path=path,
              first_line=first_line + start)
    return out


def parse_lines(lines: Sequence[str], width: int, *, delimiter: str, path: str | os.PathLike[str],
                first_line: int) -> np.ndarray:
    """Parse delimited number lines to a ``(lines, width)`` float64 array (missing cells NaN).

    Lines with fewer cells are padded, longer lines cut; blocks of lines are split and parsed by
    numpy in C, anything else than numbers and empty cells (spaces, ``NA``...) goes through the
    cell-by-cell path, which also names a bad cell.
    """
    counts = [min(line.count(delimiter) + 1, width) for line in lines]
    check_table_size(len(lines), width, sum(counts), path=path)
    out = np.empty((len(lines), width), dtype=np.float64)
    step = max(1, CHUNK_CELLS // max(width, 1))
    for start in range(0, len(lines), step):
        block = [line if count < width else delimiter.join(line.split(delimiter, width)[:width])
                 for line, count in zip(lines[start:start + step], counts[start:start + step])]
        _fill(out[start:start + len(block)], counts[start:start + step], delimiter.join(block).split(delimiter),
              decimal_comma=False, path=path, first_line=first_line + start)
    return out


def _fill(out: np.ndarray, lengths: Sequence[int], flat: list[str], *, decimal_comma: bool,
          path: str | os.PathLike[str], first_line: int) -> None:
    """Fill ``out`` (rows, width) with the ``flat`` cells of rows of ``lengths`` cells; NaN past each
    row's end (padding costs no parsing)."""
    ends = np.cumsum(lengths)

    def where(i: int) -> str:  # line and column of flat cell i, for an error
        row = int(np.searchsorted(ends, i, side="right"))
        return f"line {first_line + row}, column {i - int(ends[row] - lengths[row]) + 1}"

    values = _parse_cells(flat, decimal_comma=decimal_comma, path=path, where=where)
    if len(values) == out.size:
        out.flat[:] = values
        return
    out[:] = np.nan
    out[np.arange(out.shape[1])[None, :] < np.asarray(lengths)[:, None]] = values


def _parse_cells(flat: list[str], *, decimal_comma: bool, path: str | os.PathLike[str],
                 where) -> np.ndarray:
    """``flat`` cells as float64, parsed in slices of :data:`CHUNK_CELLS` (a row may hold 10^6
    cells); ``where(i)`` names the place of cell ``i`` in an error."""
    out = np.empty(len(flat), dtype=np.float64)
    for start in range(0, len(flat), CHUNK_CELLS):
        part = flat[start:start + CHUNK_CELLS]
        if not decimal_comma:  # fast path: numbers and empty cells only (numpy parses them in C)
            try:
                out[start:start + len(part)] = np.array([cell or "nan" for cell in part], dtype=np.float64)
                continue
            except ValueError:
                pass
        cells = [_normalised(cell, decimal_comma=decimal_comma) for cell in part]
        try:
            out[start:start + len(part)] = np.array(cells, dtype=np.float64)
            continue
        except ValueError:
            pass
        for i, cell in enumerate(cells, start=start):  # slow path only to name the offending cell
            try:
                out[i] = float(cell)
            except ValueError:
                raise InputFileError(path, f"{where(i)}: not a number: {cell[:30]!r}") from None
    return out


def csv_rows(lines: Iterable[str], *, path: str | os.PathLike[str], delimiter: str = ",") -> list[list[str]]:
    """``csv.reader`` rows of ``lines``, with no limit on the length of a cell (the csv module's
    default, 131,072 characters, would end in a ``csv.Error``); a csv error names the file."""
    previous = csv.field_size_limit()
    csv.field_size_limit(2**31 - 1)  # the C long limit on every platform
    reader = csv.reader(lines, delimiter=delimiter)
    try:
        return list(reader)
    except csv.Error as exc:
        raise InputFileError(path, f"line {reader.line_num}: {exc}") from None
    finally:
        csv.field_size_limit(previous)


def numbered_labels(count: int, *, start: int = 1, total: int | None = None,
                    prefix: str = "M") -> list[str]:
    """Names for unlabelled markers ``start ... start+count-1``: ``M01``, ``M02``...

    Zero-padded to the width of ``total`` (default: the last number), at least two digits.
    """
    width = max(2, len(str(total if total is not None else start + count - 1)))
    return [f"{prefix}{i:0{width}d}" for i in range(start, start + count)]


def check_labels(labels: Sequence[str], *, path: str | os.PathLike[str]) -> None:
    """Refuse zero markers, empty and duplicate labels with a one-line error naming the file."""
    if not labels:
        raise InputFileError(path, "no markers in file")
    if any(not label for label in labels):
        raise InputFileError(path, "a marker column has an empty label")
    longest = max(labels, key=len)
    if len(longest) > MAX_LABEL_CHARS:
        raise InputFileError(path, f"a marker label of {len(longest):,} characters, more than "
                                   f"{MAX_LABEL_CHARS} (starts {longest[:20]!r}): damaged label row?")
    seen: set[str] = set()
    duplicates = sorted({label for label in labels if label in seen or seen.add(label)})
    if duplicates:
        raise InputFileError(path, f"duplicate marker labels: {', '.join(duplicates[:5])}")


def rate_from_times(times: np.ndarray, *, path: str | os.PathLike[str]) -> float:
    """Frame rate (Hz) from a time column in seconds; the spacing must be uniform (±1 %)."""
    valid = times[np.isfinite(times)]
    steps = np.diff(valid)
    if steps.size == 0:
        raise InputFileError(path, "cannot derive the frame rate from a single time value")
    step = float(valid[-1] - valid[0]) / steps.size  # overall span: robust to rounded time stamps
    if step <= 0 or np.any(np.abs(steps - step) > 0.01 * step):
        raise InputFileError(path, "time column is not uniformly increasing: cannot derive the frame rate")
    return 1.0 / step


def rows_by_frame(frame_numbers: np.ndarray, values: np.ndarray, *,
                  path: str | os.PathLike[str]) -> tuple[int, np.ndarray]:
    """Place data rows at their frame numbers: ``(first_frame_number, (frames, ...) array)``.

    Frames missing from the file (numbering jumps) become NaN rows, so positions stay on a
    uniform time base. Numbers must be integers and strictly increasing.
    """
    if (not np.all(np.isfinite(frame_numbers)) or np.any(frame_numbers != np.round(frame_numbers))
            or np.any(np.abs(frame_numbers) > 2**53)):
        raise InputFileError(path, "frame column holds non-integer or out-of-range values")
    frames = frame_numbers.astype(np.int64)
    if np.any(np.diff(frames) <= 0):
        raise InputFileError(path, "frame numbers are not strictly increasing")
    first = int(frames[0])
    if frames[-1] - first + 1 == len(frames):
        return first, values
    if frames[-1] - first + 1 > MAX_GAP_FACTOR * len(frames) + MAX_GAP_FRAMES:  # corrupt numbering
        raise InputFileError(path, f"frame numbers run from {first} to {frames[-1]} but the file holds "
                                   f"only {len(frames)} rows: corrupt frame column?")
    out = np.full((int(frames[-1]) - first + 1,) + values.shape[1:], np.nan)
    out[frames - first] = values
    return first, out


def positions_mm(positions: np.ndarray, scale: float | np.ndarray) -> np.ndarray:
    """``positions`` (frames, markers, 3) in file units times ``scale`` (in place) (mm per unit: a number, or
    one per marker ``(markers,)``), in mm. A point is a gap (all NaN) when any coordinate is NaN or
    infinite (``inf``, ``-1e309``, or beyond float range once scaled), as in C3D."""
    with np.errstate(over="ignore", invalid="ignore"):  # in place: the table is the reader's own
        positions *= np.asarray(scale, dtype=np.float64)[None, :, None] if np.ndim(scale) else float(scale)
    positions[~np.isfinite(positions).all(axis=2)] = np.nan
    return positions


def format_rows(values: np.ndarray, *, delimiter: str) -> list[str]:
    """One text line per row of a (rows, columns) float array: 10 significant digits (sub-µm for
    mm), empty cells for NaN, no line ending."""
    if values.shape[1] == 0:
        return [""] * len(values)
    template = delimiter.join(["%.10g"] * values.shape[1])
    # one C-level format per row; "nan" never occurs in a formatted finite number
    return [(template % tuple(row)).replace("nan", "") for row in values.tolist()]
