"""Vicon Nexus CSV export: the "Trajectories" section (reader and writer).

Layout of a section::

    Trajectories
    100                                   <- rate (Hz)
    ,,Subject:LABEL,,,Subject:OTHER,,,    <- one label per X/Y/Z column triple
    Frame,Sub Frame,X,Y,Z,X,Y,Z
    ,,mm,mm,mm,mm,mm,mm                   <- units row (absent in old exports)
    1,0,44.16,-276.86,675.69,,,           <- empty cells are gaps
                                          <- a blank line ends the section

Other sections (``Devices``, ``Model Outputs``, ``Events``...) may come before or after. Takes
are stored as ``Take Start`` / ``Take End`` rows of an ``Events`` section (time in seconds from the
first exported frame; description = take name, extra ``Region`` column), which other CSV readers
ignore.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_open
from mocaptk.errors import InputFileError
from mocaptk.trajectories import Take, Trajectories

from .text_io import (check_labels, csv_rows, format_rows, mm_per_unit, parse_lines, positions_mm,
                      read_text, rows_by_frame)

#: First cell of a section header line in a Nexus CSV export.
SECTION_NAMES = ("Trajectories", "Devices", "Model Outputs", "Segments", "Joints", "Events")

_EVENTS_HEADER = ["Subject", "Context", "Name", "Time (s)", "Description", "Region"]


def _section_name(line: str) -> str | None:
    """The section a header line such as ``Trajectories,,,,`` opens, else None."""
    name = line.split(",", 1)[0].strip().strip('"')
    if name in SECTION_NAMES and line.replace(",", "").replace('"', "").strip() == name:
        return name
    return None


def _sections(lines: list[str]) -> dict[str, int]:
    """Line index of each section header (first occurrence)."""
    found: dict[str, int] = {}
    for i, line in enumerate(lines):
        name = _section_name(line)
        if name is not None:
            found.setdefault(name, i)
    return found


def _blank(line: str) -> bool:
    return not line.replace(",", "").strip()


def read_vicon_csv(path: str | os.PathLike[str], *, units: str | None = None) -> Trajectories:
    """Read the Trajectories section of a Vicon Nexus CSV export.

    Parameters
    ----------
    path : file path
    units : str, optional
        Units of the numbers in the file (mm, cm, m...), overriding the file's units row
        (default: the units row, else mm).

    Returns
    -------
    Trajectories
        Positions in mm, labels as written (``Subject:Marker``), ``first_frame`` = first
        exported frame number, takes from ``Take Start``/``Take End`` events.
    """
    lines = read_text(path).splitlines()
    sections = _sections(lines)
    if "Trajectories" not in sections:
        found = ", ".join(sections) or "none"
        raise InputFileError(path, f"Vicon CSV has no Trajectories section (sections: {found})")
    start = sections["Trajectories"]
    rows = csv_rows(lines[start:start + 6], path=path)  # section header rows (labels may be quoted)
    coord_at = next((i for i in range(3, len(rows)) if rows[i] and rows[i][0].strip().lower().startswith("frame")),
                    None)
    if coord_at is None:
        raise InputFileError(path, "Trajectories section is truncated (no label row and Frame/X/Y/Z row)")
    try:
        rate = float(rows[1][0])
    except (ValueError, IndexError):
        raise InputFileError(path, f"line {start + 2}: expected the frame rate, got {rows[1][:1]}") from None
    data_at = coord_at + 1
    has_units = data_at < len(rows) and (not rows[data_at] or not rows[data_at][0].strip())
    label_row, coord_row = rows[coord_at - 1], rows[coord_at]
    unit_row = rows[data_at] if has_units else []
    first_data = start + data_at + has_units
    end = first_data
    while end < len(lines) and not _blank(lines[end]) and _section_name(lines[end]) is None:
        end += 1
    data_lines = lines[first_data:end]
    columns: list[int] = []
    labels: list[str] = []
    for col, label in enumerate(label_row):
        if not label.strip():
            continue
        axes = [c.strip().upper() for c in coord_row[col:col + 3]]
        if axes != ["X", "Y", "Z"]:
            raise InputFileError(path, f"marker {label.strip()!r}: expected X,Y,Z columns, got {axes}")
        columns.append(col)
        labels.append(label.strip())
    check_labels(labels, path=path)
    if not data_lines:
        raise InputFileError(path, "Trajectories section has no data rows (truncated?)")
    width = max(columns) + 3
    values = parse_lines(data_lines, width, delimiter=",", path=path, first_line=first_data + 1)
    first_number, values = rows_by_frame(values[:, 0], values, path=path)
    col_index = np.array(columns)[:, None] + np.arange(3)[None, :]
    positions = values[:, col_index]  # (frames, markers, 3)
    if units is not None:
        scale = np.full(len(labels), mm_per_unit(units))
        original = units
    else:
        file_units = [(unit_row[c].strip() if c < len(unit_row) else "") or "mm" for c in columns]
        scale = np.array([mm_per_unit(u, source=path) for u in file_units])
        original = file_units[0] if len(set(file_units)) == 1 else "mixed"
    positions = positions_mm(positions, scale)
    takes = _read_takes(lines, sections, rate=rate, n_frames=len(positions), path=path)
    meta = {"source": os.fspath(path), "format": "vicon_csv", "original_units": original,
            "subjects": sorted({lab.split(":", 1)[0] for lab in labels if ":" in lab}),
            "takes": takes}
    return Trajectories(positions, labels, rate, first_frame=first_number, metadata=meta)


def _read_takes(lines: list[str], sections: dict[str, int], *, rate: float, n_frames: int,
                path: str | os.PathLike[str]) -> list[Take]:
    """Takes written by :func:`write_vicon_csv` as Take Start / Take End events."""
    if "Events" not in sections:
        return []
    end = start = sections["Events"] + 2
    while end < len(lines) and not _blank(lines[end]) and _section_name(lines[end]) is None:
        end += 1
    starts: dict[str, tuple[int, str | None]] = {}
    takes: list[Take] = []
    for cells in csv_rows(lines[start:end], path=path):
        cells = cells + [""] * (6 - len(cells))
        kind, name, region = cells[2].strip(), cells[4].strip(), cells[5].strip() or None
        if kind not in ("Take Start", "Take End"):
            continue  # ordinary Nexus events (Foot Strike...)
        try:
            frame = int(round(float(cells[3]) * rate))
        except (ValueError, OverflowError):
            raise InputFileError(path, f"event {kind!r} of take {name!r} has a bad time {cells[3]!r}") from None
        if kind == "Take Start":
            starts[name] = (frame, region)
        elif name in starts:
            begin, region = starts.pop(name)
            if not 0 <= begin < frame <= n_frames:
                raise InputFileError(path, f"take {name!r} [{begin}, {frame}) lies outside the data")
            takes.append(Take(name, begin, frame, region))
    return sorted(takes, key=lambda t: (t.start, t.end, t.name))


def write_vicon_csv(traj: Trajectories, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``traj`` as a Nexus-style CSV (Events section for takes, then Trajectories, in mm).

    Frame numbers are ``first_frame ...``; gaps are empty cells. Atomic: an error leaves
    no partial file.
    """
    with atomic_open(path, "w", force=force) as handle:
        writer = csv.writer(handle, lineterminator="\n")
        if traj.takes:
            writer.writerow(["Events"])
            writer.writerow(_EVENTS_HEADER)
            for take in traj.takes:
                for kind, frame in (("Take Start", take.start), ("Take End", take.end)):
                    writer.writerow(["", "General", kind, f"{frame / traj.rate:.9f}", take.name,
                                     take.region or ""])
            writer.writerow([])
        writer.writerow(["Trajectories"])
        writer.writerow([f"{traj.rate:g}"])
        writer.writerow(["", ""] + [cell for label in traj.labels for cell in (label, "", "")])
        writer.writerow(["Frame", "Sub Frame"] + ["X", "Y", "Z"] * traj.n_markers)
        writer.writerow(["", ""] + ["mm"] * (3 * traj.n_markers))
        lines = format_rows(traj.positions.reshape(traj.n_frames, -1), delimiter=",")
        first = traj.first_frame
        handle.writelines(f"{first + i},0,{line}\n" for i, line in enumerate(lines))
    return Path(path)
