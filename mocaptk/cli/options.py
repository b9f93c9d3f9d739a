"""Options shared by every command that reads a marker file, so they mean and say the same."""

from __future__ import annotations

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
