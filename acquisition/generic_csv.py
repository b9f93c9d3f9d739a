"""Column CSV marker files: one column per coordinate (``LABEL_x``, ``LABEL_y``, ``LABEL_z``).

Accepted coordinate headers: ``NOSE_x``, ``NOSE X``, ``NOSE.x``, ``NOSE:X``, ``NOSE-x``, ``NOSE (x)``,
optionally followed by a unit such as ``NOSE_x (mm)`` / ``NOSE_x [m]``. The delimiter (``,``,
``;``, tab, ``|``) is sniffed; ``NA``, ``NaN`` and empty cells are gaps; a decimal comma is
accepted with ``;``-separated files. Optional columns:

- a frame column (``Frame``, ``Frame#``, ``Sample``...): rows are placed at their frame number,
  skipped numbers become gap frames;
- a time column (``Time``, ``Time (s)``, ``t``... in seconds): gives the frame rate;
- a text column (e.g. ``Stimulustype``): each run of equal values becomes a take.

Files without a header row are read by column count: ``3M`` columns are coordinates, ``3M+1``
starts with a frame column, ``3M+2`` with frame and sub-frame columns (as in headerless Nexus
exports). Markers are then named ``M01``, ``M02``...
"""

from __future__ import annotations

import os
import re

import numpy as np

from mocaptk.errors import InputFileError
from mocaptk.trajectories import Take, Trajectories

from .text_io import (MAX_LABEL_CHARS, MISSING_CELLS, cells_to_array, check_labels, check_table_size,
                      csv_rows, mm_per_unit, numbered_labels, positions_mm, rate_from_times, read_text,
                      rows_by_frame)

_COORD = re.compile(
    r"^(?P<label>.*?\S)(?:[\s_.:\-]+(?P<a1>[xyz])|\s*\((?P<a2>[xyz])\))"
    r"(?:\s*[(\[](?P<unit>[a-z]+)[)\]])?$", re.IGNORECASE)
_FRAME = re.compile(r"^(frame|frame#|frames|frame[ _]?(no|nr|number|index)|sample|index)$", re.IGNORECASE)
_TIME = re.compile(r"^(time|t|time[ _]?s|time ?[(\[]s[)\]]|timestamp|seconds)$", re.IGNORECASE)
_DELIMITERS = (",", ";", "\t", "|")


def sniff_delimiter(lines: list[str]) -> str:
    """The delimiter splitting the first lines into the same, largest number of cells (else space)."""
    sample = lines[:10]
    best, best_count = " ", 0
    for delim in _DELIMITERS:
        counts = {line.count(delim) for line in sample}
        count = min(counts)
        if count > best_count and (len(counts) == 1 or count >= 2):
            best, best_count = delim, count
    return best


def is_number(cell: str) -> bool:
    text = cell.strip()
    if text.lower() in MISSING_CELLS:
        return True
    try:
        float(text.replace(",", "."))
    except ValueError:
        return False
    return True


def _all_numbers(cells: list[str]) -> bool:
    try:  # numbers and empty cells: parsed by numpy in C (a headerless line can hold 10^6 cells)
        np.array([cell or "nan" for cell in cells], dtype=np.float64)
        return True
    except ValueError:
        return all(map(is_number, cells))


def read_generic_csv(path: str | os.PathLike[str], *, units: str | None = None,
                     rate: float | None = None) -> Trajectories:
    """Read a column CSV marker file.

    Parameters
    ----------
    path : file path
    units : str, optional
        Units of the coordinates (mm, cm, m, in, or mm per unit as a number); default: the unit in
        the column headers, else mm (recorded as assumed in ``metadata["units_assumed"]``).
    rate : float, optional
        Frame rate in Hz; required when the file has no time column.
    """
    text = read_text(path)
    lines = [line for line in text.splitlines() if line.strip()]
    delimiter = sniff_delimiter(lines)
    if delimiter == " ":
        rows = [line.split() for line in lines]
    else:
        rows = csv_rows(lines, delimiter=delimiter, path=path)
    has_header = not _all_numbers(rows[0])
    header = [cell.strip() for cell in rows[0]] if has_header else None
    body = rows[1:] if has_header else rows
    if not body:
        raise InputFileError(path, "no data rows")
    first_line = 2 if has_header else 1
    check_table_size(len(body), max(len(rows[0]), max(map(len, body))), sum(map(len, rows)), path=path)
    decimal_comma = delimiter != "," and any("," in c for c in body[0])  # 1,5;2,25
    if header is None:
        columns, labels, frame_col, time_col, text_col, unit = _headerless_layout(body, path=path)
    else:
        columns, labels, frame_col, time_col, text_col, unit = _header_layout(header, body, path=path)
    check_labels(labels, path=path)
    cells = ([r[columns.start:columns.stop] for r in body] if isinstance(columns, range)  # headerless
             else [[r[c] if c < len(r) else "" for c in columns] for r in body])
    table = cells_to_array(cells, len(columns), path=path, first_line=first_line, decimal_comma=decimal_comma)
    del cells
    positions = table.reshape(len(body), len(labels), 3)
    first_number = 1
    row_frames = np.arange(len(body))
    if frame_col is not None:
        numbers = cells_to_array([[r[frame_col] if frame_col < len(r) else ""] for r in body], 1,
                                 path=path, first_line=first_line)[:, 0]
        first_number, positions = rows_by_frame(numbers, positions, path=path)
        row_frames = numbers.astype(np.int64) - first_number
    if rate is None:
        if time_col is None:
            raise InputFileError(path, "no time column to derive the frame rate from: give the rate (--rate HZ)")
        times = cells_to_array([[r[time_col] if time_col < len(r) else ""] for r in body], 1,
                               path=path, first_line=first_line, decimal_comma=decimal_comma)[:, 0]
        rate = rate_from_times(times if frame_col is None else times[np.diff(row_frames, prepend=-1) == 1],
                               path=path)
    meta: dict = {"source": os.fspath(path), "format": "generic_csv"}
    if units is not None:
        scale, meta["original_units"] = mm_per_unit(units), units
    elif unit is not None:
        scale, meta["original_units"] = mm_per_unit(unit, source=path), unit
    else:
        scale, meta["original_units"], meta["units_assumed"] = 1.0, "mm", True
    if text_col is not None:
        meta["takes"] = _takes_from_column([r[text_col] if text_col < len(r) else "" for r in body],
                                           row_frames)
        meta["take_column"] = header[text_col] if header else text_col
    return Trajectories(positions_mm(positions, scale), labels, rate,
                        first_frame=first_number, metadata=meta)


def _filled_width(row: list[str]) -> int:
    """Cells of ``row`` up to its last non-empty one (trailing delimiters add no column)."""
    return next((i + 1 for i in range(len(row) - 1, -1, -1) if row[i].strip()), 0)


def _headerless_layout(body: list[list[str]], *, path: str | os.PathLike[str]):
    n = max(map(_filled_width, body))  # one pass: linear in the cells, however many delimiters
    lead = n % 3  # 0: coordinates only, 1: frame column, 2: frame + sub-frame columns
    if (n - lead) < 3:
        raise InputFileError(path, "no coordinate columns (need 3 per marker)")
    count = (n - lead) // 3
    return range(lead, n), numbered_labels(count), (0 if lead else None), None, None, None


def _header_layout(header: list[str], body: list[list[str]], *, path: str | os.PathLike[str]):
    axes: dict[str, dict[str, int]] = {}
    units: set[str] = set()
    frame_col = time_col = text_col = None
    for col, name in enumerate(header):
        # longer cells are no coordinate header (and the lazy pattern would take quadratic time)
        match = _COORD.match(name) if len(name) <= MAX_LABEL_CHARS + 16 else None
        if match:
            label = match["label"].strip()
            axis = (match["a1"] or match["a2"]).lower()
            if axis in axes.setdefault(label, {}):
                raise InputFileError(path, f"duplicate column {name!r}")
            axes[label][axis] = col
            if match["unit"]:
                units.add(match["unit"].lower())
        elif frame_col is None and _FRAME.match(name):
            frame_col = col
        elif time_col is None and _TIME.match(name):
            time_col = col
        elif text_col is None and name and any(
                col < len(r) and not is_number(r[col]) for r in body):
            text_col = col
    incomplete = [label for label, found in axes.items() if set(found) != {"x", "y", "z"}]
    if incomplete:
        raise InputFileError(path, f"marker {incomplete[0]!r} lacks one of its x/y/z columns")
    if not axes:
        raise InputFileError(path, "no coordinate columns found (expected headers like NOSE_x, NOSE_y, NOSE_z): "
                                   "not a marker file")
    if len(units) > 1:
        raise InputFileError(path, f"coordinate columns mix units: {', '.join(sorted(units))}")
    columns = [axes[label][a] for label in axes for a in "xyz"]
    return columns, list(axes), frame_col, time_col, text_col, (units.pop() if units else None)


def _takes_from_column(values: list[str], row_frames: np.ndarray) -> list[Take]:
    """One take per run of equal non-empty values (frame ranges; repeated names get ``_2``...)."""
    takes: list[Take] = []
    seen: dict[str, int] = {}
    i = 0
    while i < len(values):
        name = values[i].strip()
        j = i + 1
        while j < len(values) and values[j].strip() == name:
            j += 1
        if name:
            seen[name] = seen.get(name, 0) + 1
            unique = name if seen[name] == 1 else f"{name}_{seen[name]}"
            takes.append(Take(unique, int(row_frames[i]), int(row_frames[j - 1]) + 1))
        i = j
    return takes
