"""Options shared by every command that reads a marker file, so they mean and say the same."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

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
