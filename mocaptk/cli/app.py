"""The Typer application object every command module registers on."""

from __future__ import annotations

import typer

from mocaptk import __version__

app = typer.Typer(
    name="mocaptk",
    help="Facial optical motion capture: dense sessions to optimized marker layouts and rigs.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"mocaptk {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """Facial optical motion capture: dense sessions to optimized marker layouts and rigs."""
