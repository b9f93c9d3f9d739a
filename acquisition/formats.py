"""One entry point for marker files: detect the format by content, read to / write from Trajectories.

Formats: ``c3d`` (binary C3D), ``vicon_csv`` (Nexus CSV export), ``trc``, ``generic_csv`` (one
column per coordinate, or headerless numbers), ``npz`` (``positions``/``labels``/``rate`` arrays
written by our tools). Detection looks at the bytes, never at the file name.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np

from mocaptk.errors import InputFileError, MocaptkError, OptionError, unreadable
from mocaptk.trajectories import Trajectories

FORMATS = ("c3d", "vicon_csv", "trc", "generic_csv", "npz")
#: Output format for each file extension accepted by :func:`write_trajectories`.
WRITE_EXTENSIONS = {".c3d": "c3d", ".csv": "vicon_csv", ".trc": "trc"}

_SNIFF_BYTES = 8192


def detect_format(path: str | os.PathLike[str]) -> str:
    """The format of ``path`` from its first bytes: one of :data:`FORMATS`.

    Raises :class:`InputFileError` for a missing, unreadable, empty or unrecognised file.
    """
    try:
        with open(path, "rb") as handle:
            head = handle.read(_SNIFF_BYTES)
    except OSError as exc:
        raise unreadable(path, exc) from None
    if not head.strip():
        raise InputFileError(path, "file is empty")
    if head.startswith(b"PK\x03\x04"):
        return "npz"
    # C3D: byte 2 is the 0x50 key; byte 1 (parameter block number) is a small, non-printable number
    if len(head) >= 2 and head[1] == 0x50 and (head[0] < 0x20 or head[0] >= 0x7F):
        return "c3d"
    from .text_io import UTF16_PROBLEM, looks_utf16

    if looks_utf16(head):
        raise InputFileError(path, UTF16_PROBLEM)
    if b"\x00" in head:
        raise InputFileError(path, "binary content that is not C3D: not a motion-capture file")
    text = head.decode("utf-8", errors="replace")
    first = next((line for line in text.splitlines() if line.strip()), "")
    first_cell = first.replace("\t", ",").split(",", 1)[0].strip().lstrip("\ufeff")
    if first_cell == "PathFileType":
        return "trc"
    from .vicon_csv import SECTION_NAMES

    if first_cell in SECTION_NAMES:
        return "vicon_csv"
    from .generic_csv import is_number, sniff_delimiter

    lines = [line for line in text.splitlines() if line.strip()][:10]
    if sniff_delimiter(lines) != " " or (  # whitespace-separated: only rows of numbers
            all(len(line.split()) >= 3 for line in lines) and all(map(is_number, lines[-1].split()))):
        return "generic_csv"
    raise InputFileError(path, "unrecognised content: not C3D, Vicon CSV, TRC or a column CSV file")


def read_trajectories(path: str | os.PathLike[str], *, fmt: str | None = None, units: str | None = None,
                      strip_prefixes: bool = False, rate: float | None = None) -> Trajectories:
    """Read any supported marker file (format detected by content unless ``fmt`` is given).

    Parameters
    ----------
    path : file path
    fmt : one of :data:`FORMATS`, optional
    units : str, optional
        Units of the numbers in a text file (mm, cm, m, in, or mm per unit), overriding what the
        file says; not allowed for C3D/npz (their units are part of the data).
    strip_prefixes : drop ``Subject:`` label prefixes.
    rate : float, optional
        Frame rate (Hz) for column CSV files without a time column (overrides the time column).

    Returns
    -------
    Trajectories in mm; ``metadata["format"]`` names the format read.
    """
    fmt = fmt or detect_format(path)
    if fmt not in FORMATS:
        raise OptionError(f"unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    if units is not None and fmt in ("c3d", "npz"):
        declared = "C3D, which declares its units (POINT:UNITS)" if fmt == "c3d" else "npz, which holds mm"
        raise OptionError(f"--units applies to text files only; {os.fspath(path)} is {declared}")
    if rate is not None and not (np.isfinite(rate) and rate > 0):
        raise OptionError(f"the frame rate must be a positive number of Hz, got {rate}")
    if rate is not None and fmt != "generic_csv":
        raise OptionError(f"--rate applies to column CSV files only; {os.fspath(path)} is {fmt} "
                          "(which stores its rate)")
    try:
        if fmt == "c3d":
            from .c3d_read import read_c3d

            return read_c3d(path, strip_prefixes=strip_prefixes, model_outputs=False)
        if fmt == "vicon_csv":
            from .vicon_csv import read_vicon_csv

            traj = read_vicon_csv(path, units=units)
        elif fmt == "trc":
            from .trc import read_trc

            traj = read_trc(path, units=units)
        elif fmt == "generic_csv":
            from .generic_csv import read_generic_csv

            traj = read_generic_csv(path, units=units, rate=rate)
        else:
            traj = _read_npz(path)
        return traj.strip_prefixes() if strip_prefixes else traj
    except (InputFileError, OptionError):
        raise
    except MocaptkError as exc:  # e.g. a zero frame rate or clashing labels after stripping prefixes
        raise InputFileError(path, str(exc)) from None
    except MemoryError as exc:  # the file is within the size limits but this machine cannot hold it
        detail = f" ({exc})" if str(exc) else ""
        raise InputFileError(path, f"out of memory while reading it{detail}; close other programs or "
                                   "use a machine with more memory") from None


def _read_npz(path: str | os.PathLike[str]) -> Trajectories:
    """``positions (F, M, 3)`` mm, ``labels (M,)``, ``rate`` and optional ``first_frame`` arrays."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputFileError(path, f"unreadable .npz archive ({exc})") from None
    missing = [key for key in ("positions", "labels", "rate") if key not in arrays]
    if missing:
        raise InputFileError(path, f".npz lacks {', '.join(missing)}: not a marker file")
    return Trajectories(arrays["positions"], [str(x) for x in arrays["labels"]], float(arrays["rate"]),
                        first_frame=int(arrays.get("first_frame", 0)),
                        metadata={"source": os.fspath(path), "format": "npz", "original_units": "mm"})


def output_format(path: str | os.PathLike[str], fmt: str | None = None) -> str:
    """The format :func:`write_trajectories` uses for ``path`` (``fmt`` or by extension)."""
    if fmt is not None:
        if fmt not in WRITE_EXTENSIONS.values():
            raise OptionError(f"cannot write format {fmt!r} (writable: c3d, vicon_csv, trc)")
        return fmt
    suffix = Path(path).suffix.lower()
    if suffix not in WRITE_EXTENSIONS:
        raise OptionError(f"{os.fspath(path)}: unknown output extension {suffix or '(none)'!r} "
                          "(use .c3d, .csv or .trc)")
    return WRITE_EXTENSIONS[suffix]


def write_trajectories(traj: Trajectories, path: str | os.PathLike[str], *, fmt: str | None = None,
                       force: bool = True) -> Path:
    """Write ``traj`` as C3D, Nexus CSV or TRC (by ``fmt`` or the extension), atomically.

    Refuses to overwrite an existing file unless ``force``. Takes survive C3D and CSV (Events
    section); TRC has no place for them.
    """
    fmt = output_format(path, fmt)
    if fmt == "c3d":
        from .c3d_write import write_c3d

        return write_c3d(traj, path, force=force)
    if fmt == "vicon_csv":
        from .vicon_csv import write_vicon_csv

        return write_vicon_csv(traj, path, force=force)
    from .trc import write_trc

    return write_trc(traj, path, force=force)
