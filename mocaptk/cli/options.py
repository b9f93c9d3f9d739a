"""Options shared by every command that reads a marker file, so they mean and say the same."""

from __future__ import annotations

from typing import Annotated

import typer

Units = Annotated[str | None, typer.Option(
    "--units", help="Units of the numbers in a text input (mm, cm, m, in, or mm per file unit), "
                    "overriding the file's; refused for C3D and .npz, which carry their own.")]
Rate = Annotated[float | None, typer.Option(
    "--rate", help="Frame rate (Hz) for a column CSV input without a time column.")]
