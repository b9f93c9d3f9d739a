"""Options shared by every command that reads a marker file, so they mean and say the same, and
where a layout's recorded session is found."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mocaptk.errors import InputFileError

Units = Annotated[str | None, typer.Option(
    "--units", help="Units of the numbers in a text input (mm, cm, m, in, or mm per file unit), "
                    "overriding the file's; refused for C3D and .npz, which carry their own.")]
Rigid = Annotated[str | None, typer.Option(
    "--rigid", metavar="LABELS", help="Comma-separated labels of markers on the rigid part of the head "
                                      "(≥ 3; e.g. headband, temples, nose bridge) used to remove head "
                                      "motion; default: detected as the markers whose distances vary least.")]
Rate = Annotated[float | None, typer.Option(
    "--rate", help="Frame rate (Hz) for a column CSV input without a time column.")]


Quiet = Annotated[bool, typer.Option(
    "--quiet", "-q", help="Print no progress, summary or table (warnings and errors are still shown).")]


def rigid_labels(text: str | None) -> tuple[str, ...] | None:
    """The ``--rigid`` value as labels (None: detect automatically)."""
    if text is None:
        return None
    return tuple(label.strip() for label in text.split(",") if label.strip())


def session_reading(traj, *, rate: float | None, units: str | None) -> dict:
    """What layout.json's ``source.reading`` records of how the session was read: the ``--rate``
    and ``--units`` given (null: the file's own) and its first frame number."""
    return {"rate": rate, "units": units, "first_frame": int(traj.first_frame)}


def recorded_reading(layout, file, *, rate: float | None, units: str | None) -> tuple[float | None, str | None]:
    """``(rate, units)`` to read ``file`` with: each option as given, else as the layout's session
    was read (``source.reading``) when ``file`` is of the session's kind (same suffix), so
    ``evaluate``, ``solve`` and ``rig`` need no repeated ``--rate``/``--units``."""
    reading = layout.source.get("reading") or {}
    recorded = str(layout.source.get("path") or "")
    same_kind = Path(recorded).suffix.lower() == Path(file).suffix.lower() and bool(recorded)
    if not same_kind:
        return rate, units
    return (reading.get("rate") if rate is None else rate), (reading.get("units") if units is None else units)


def session_path(layout_path: Path, source: dict, given: Path | None) -> Path:
    """The training session: ``--session``, else where layout.json's ``source`` records it:
    relative to the layout, at its absolute path, then by file name beside the layout, in the
    folder above it and in the working folder. Of several files found, the first with the
    layout's sha256 (the caller refuses one whose hash differs)."""
    if given is not None:
        return given
    recorded = source.get("path")
    if not recorded:
        raise InputFileError(layout_path, "records no session file; give --session")
    folder = layout_path.parent
    candidates = [folder / source["relative"]] if source.get("relative") else []
    candidates += [Path(source["absolute"])] if source.get("absolute") else []
    candidates += [folder / recorded, folder.parent / recorded, Path(recorded)]
    found = [path for path in dict.fromkeys(candidates) if path.is_file()]
    if len(found) > 1 and source.get("sha256"):
        import hashlib

        def digest(path: Path) -> str:
            with open(path, "rb") as handle:
                return hashlib.file_digest(handle, "sha256").hexdigest()
        found = [path for path in found if digest(path) == source["sha256"]] or found
    if found:
        return found[0]
    # the recorded places, when the layout has them, then the fallbacks every layout gets
    recorded_at = ", ".join(str(p) for p in candidates[:2])
    where = f"where it records it ({recorded_at}), " if source.get("relative") else ""
    raise InputFileError(layout_path, f"its session {recorded} is not {where}beside it, in the folder above "
                         "nor in the working folder; give --session")
