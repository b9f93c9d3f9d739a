"""Shared plumbing of the text marker formats (Vicon CSV, TRC, column CSV): reading, units, cells."""

from __future__ import annotations

import os
from collections.abc import Sequence
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
    if b"\x00" in data:
        raise InputFileError(path, "binary content: not a text marker file")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (bad byte at offset {exc.start})") from None
    return text


def mm_per_unit(units: str, *, source: str | os.PathLike[str] | None = None) -> float:
    """Millimetres per ``units`` (mm, cm, dm, m, in, or a positive number = mm per unit).

    Unknown units raise :class:`InputFileError` naming ``source`` when the units came from a file,
    else :class:`OptionError` (a bad ``--units`` option).
    """
    key = units.strip().lower()
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


def cells_to_array(rows: Sequence[Sequence[str]], width: int, *, path: str | os.PathLike[str],
                   first_line: int, decimal_comma: bool = False) -> np.ndarray:
    """Parse text cells to a ``(rows, width)`` float64 array; missing cells become NaN.

    Rows shorter than ``width`` are padded with NaN, longer rows are cut. ``first_line`` is the
    1-based line number of ``rows[0]``, used to name a bad cell in the error.
    """
    padded = [row[:width] if len(row) >= width else list(row) + [""] * (width - len(row)) for row in rows]
    cells = np.array(padded, dtype=str).reshape(len(rows), width)
    if not decimal_comma:  # fast path: numbers and empty cells only (numpy parses them in C)
        try:
            return np.where(cells == "", "nan", cells).astype(np.float64)
        except ValueError:
            pass
    cells = np.char.strip(cells)
    if decimal_comma:
        cells = np.char.replace(cells, ",", ".")
    missing = np.isin(np.char.lower(cells), list(MISSING_CELLS))
    cells = np.where(missing, "nan", cells)  # not in place: a <U2 array would store "na"
    try:
        return cells.astype(np.float64)
    except ValueError:
        pass
    for r, row in enumerate(cells):  # slow path only to name the offending cell
        for c, cell in enumerate(row):
            try:
                float(cell)
            except ValueError:
                raise InputFileError(
                    path, f"line {first_line + r}, column {c + 1}: not a number: {cell[:30]!r}") from None
    raise AssertionError("unreachable: astype failed but every cell parsed")


def parse_lines(lines: Sequence[str], width: int, *, delimiter: str, path: str | os.PathLike[str],
                first_line: int) -> np.ndarray:
    """Parse delimited number lines to a ``(lines, width)`` float64 array (missing cells NaN).

    Fast path for plain numbers and empty cells (one split of the whole block, parsed in C);
    anything else (spaces, ``NA``...) goes through :func:`cells_to_array`, which also names a
    bad cell. Lines with fewer cells are padded, longer lines cut.
    """
    fixed = []
    for line in lines:
        count = line.count(delimiter) + 1
        if count < width:
            line += delimiter * (width - count)
        elif count > width:
            line = delimiter.join(line.split(delimiter, width)[:width])
        fixed.append(line)
    cells = delimiter.join(fixed).split(delimiter)
    try:
        return np.array([cell or "nan" for cell in cells], dtype=np.float64).reshape(len(lines), width)
    except ValueError:
        return cells_to_array([line.split(delimiter) for line in lines], width, path=path,
                              first_line=first_line)


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


def whole_point_gaps(positions: np.ndarray) -> np.ndarray:
    """``positions`` (frames, markers, 3) with a point missing entirely when any coordinate is."""
    positions[np.isnan(positions).any(axis=2)] = np.nan
    return positions


def format_rows(values: np.ndarray, *, delimiter: str) -> list[str]:
    """One text line per row of a (rows, columns) float array: 10 significant digits (sub-µm for
    mm), empty cells for NaN, no line ending."""
    if values.shape[1] == 0:
        return [""] * len(values)
    template = delimiter.join(["%.10g"] * values.shape[1])
    # one C-level format per row; "nan" never occurs in a formatted finite number
    return [(template % tuple(row)).replace("nan", "") for row in values.tolist()]
