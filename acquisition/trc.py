"""TRC (Motion Analysis "Track Row Column") marker files, tab- or comma-separated: reader and writer.

Layout::

    PathFileType  4  (X/Y/Z)  name.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    100       100         652        51          mm     100           1                   652
    Frame#    Time        LABEL1  .  .  LABEL2  .  .
              X1  Y1  Z1  X2  Y2  Z2
    (optional blank line)
    1         0.000       x  y  z  x  y  z        <- empty cells are gaps

Coordinate triples without a label (``NumMarkers`` 0, or more data columns than labels, as in
exported unlabelled clouds) are kept as markers named by their column number: ``M01``, ``M34``...
TRC has no place for takes: they are not written (``metadata["takes"]`` is lost).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_open
from mocaptk.errors import InputFileError
from mocaptk.trajectories import Trajectories

from .text_io import (check_labels, format_rows, mm_per_unit, numbered_labels, parse_lines, positions_mm,
                      rate_from_times, read_text, rows_by_frame)

_HEADER_KEYS = ("DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
                "OrigDataStartFrame", "OrigNumFrames")


def read_trc(path: str | os.PathLike[str], *, units: str | None = None) -> Trajectories:
    """Read a TRC file.

    Parameters
    ----------
    path : file path
    units : str, optional
        Units of the numbers in the file, overriding the ``Units`` header keyword.

    Returns
    -------
    Trajectories
        Positions in mm; ``rate`` from ``DataRate`` (else ``CameraRate``, else the Time column);
        ``first_frame`` = first ``Frame#``; ``metadata["header"]`` holds the header keywords,
        ``metadata["notes"]`` records a frame count that disagrees with the header.
    """
    lines = read_text(path).splitlines()
    if not lines[0].startswith("PathFileType"):
        raise InputFileError(path, "not a TRC file (first line does not start with PathFileType)")
    delimiter = "\t" if "\t" in lines[0] else ","
    if len(lines) < 5:
        raise InputFileError(path, f"truncated TRC header ({len(lines)} of 5 header lines)")
    rows = [line.split(delimiter) for line in lines[:5]]  # header rows
    keys = [k.strip() for k in rows[1]]
    values = [v.strip() for v in rows[2]]
    header = {k: v for k, v in zip(keys, values) if k}
    if "NumMarkers" not in header or not ({"DataRate", "CameraRate"} & header.keys()):
        raise InputFileError(path, "TRC header lacks NumMarkers or DataRate (truncated header?)")
    try:
        n_declared = int(float(header["NumMarkers"]))
        n_frames_declared = int(float(header["NumFrames"])) if "NumFrames" in header else None
    except (ValueError, OverflowError):
        raise InputFileError(path, f"bad TRC header values: {rows[2][:5]}") from None
    names = [cell.strip() for cell in rows[3][2:]]
    labels = [name for name in names if name]
    data_start = 5
    while data_start < len(lines) and not lines[data_start].replace(delimiter, "").strip():
        data_start += 1
    data_lines = lines[data_start:]
    if not data_lines:
        raise InputFileError(path, "TRC file has no data rows")
    trailing = " \t\r" + delimiter
    last_cell = max(max(line.rstrip(trailing).count(delimiter) for line in data_lines), 1)
    # unlabelled coordinate triples past the labels (or NumMarkers 0) are kept as extra markers
    # a NumMarkers beyond the labels and data columns is only noted (a corrupt count must not
    # allocate 10^9 empty markers)
    n_markers = max(len(labels), -(-(last_cell - 1) // 3))
    labels += numbered_labels(n_markers - len(labels), start=len(labels) + 1, total=n_markers)
    check_labels(labels, path=path)
    table = parse_lines(data_lines, 2 + 3 * n_markers, delimiter=delimiter, path=path,
                        first_line=data_start + 1)
    first_number, table = rows_by_frame(table[:, 0], table, path=path)
    rate_text = header.get("DataRate") or header.get("CameraRate", "")
    try:
        rate = float(rate_text)
    except ValueError:
        rate = rate_from_times(table[:, 1], path=path)
    file_units = header.get("Units", "") or "mm"
    scale = mm_per_unit(units) if units is not None else mm_per_unit(file_units, source=path)
    positions = positions_mm(table[:, 2:].reshape(len(table), n_markers, 3), scale)
    notes = []
    if n_frames_declared is not None and n_frames_declared != len(positions):
        notes.append(f"header says NumFrames {n_frames_declared}, file has {len(positions)} frames")
    if n_declared and n_declared != n_markers:
        notes.append(f"header says NumMarkers {n_declared}, file has {n_markers} markers")
    meta = {"source": os.fspath(path), "format": "trc", "original_units": units or file_units,
            "header": header, "notes": notes,
            "subjects": sorted({lab.split(":", 1)[0] for lab in labels if ":" in lab})}
    return Trajectories(positions, labels, rate, first_frame=first_number, metadata=meta)


def write_trc(traj: Trajectories, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``traj`` as a tab-separated TRC file in mm (takes are not stored: TRC has no place).

    ``Frame#`` runs from ``first_frame``; ``Time`` is seconds from the first written frame;
    gaps are empty cells. Atomic: an error leaves no partial file.
    """
    n, m = traj.n_frames, traj.n_markers
    first = traj.first_frame
    header_values = [f"{traj.rate:g}", f"{traj.rate:g}", str(n), str(m), "mm", f"{traj.rate:g}",
                     str(first), str(n)]
    frame_numbers = range(first, first + n)
    times = [f"{t:.6f}" for t in (np.arange(n) / traj.rate).tolist()]
    lines = format_rows(traj.positions.reshape(n, 3 * m), delimiter="\t")
    with atomic_open(path, "w", force=force) as handle:
        handle.write(f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}\n")
        handle.write("\t".join(_HEADER_KEYS) + "\n")
        handle.write("\t".join(header_values) + "\n")
        handle.write("\t".join(["Frame#", "Time"] + [c for lab in traj.labels for c in (lab, "", "")]) + "\n")
        handle.write("\t".join(["", ""] + [f"{a}{i + 1}" for i in range(m) for a in "XYZ"]) + "\n")
        handle.write("\n")
        handle.writelines(f"{number}\t{time}\t{line}\n"
                          for number, time, line in zip(frame_numbers, times, lines))
    return Path(path)
