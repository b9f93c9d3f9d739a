"""Command-line interface: ``mocaptk COMMAND ...``.

Each command lives in its own module and registers itself on :data:`app`; heavy imports
happen inside the command functions so ``mocaptk --help`` stays fast.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from ..errors import MocaptkError
from .app import app

# Command modules register themselves on import; this order is the order of `mocaptk --help`
# (pipeline order: files -> capture -> cleaning -> layout -> evaluation -> rig; then batch).
from . import info  # noqa: E402,F401
from . import convert  # noqa: E402,F401
from . import synth  # noqa: E402,F401
from . import triangulate  # noqa: E402,F401
from . import clean  # noqa: E402,F401
from . import cluster  # noqa: E402,F401
from . import sweep  # noqa: E402,F401
from . import evaluate  # noqa: E402,F401
from . import compare  # noqa: E402,F401
from . import rig  # noqa: E402,F401
from . import plan  # noqa: E402,F401
from . import solve  # noqa: E402,F401
from . import batch  # noqa: E402,F401


def command_line():
    """The click command tree of :data:`app`, with help that shows no ``<bool>`` beside plain flags."""
    import typer
    import typer.main

    command = typer.main.get_command(app)
    names = command.context_settings["help_option_names"]
    for sub in [command, *command.commands.values()]:
        help_option = sub.get_help_option(typer.Context(sub, help_option_names=names))  # made once, cached
        for param in [*sub.params, help_option]:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = ""  # a flag takes no value: show none
    return command


def usage_line(exc) -> str:
    """One line for an option-parse error (``--factor abc``, unknown option, missing argument)."""
    ctx = getattr(exc, "ctx", None)
    where = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
    return " ".join(exc.format_message().split()) + where


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: run the CLI; a user mistake, an option-parse error, a full disk or running out of
    memory is one line on stderr and exit code 2."""
    import errno

    import typer

    args = list(argv) if argv is not None else sys.argv[1:]
    if not args:  # the overview, as for `mocaptk --help`, but a usage exit code
        command_line()(args=["--help"], prog_name="mocaptk", standalone_mode=False)
        sys.exit(2)
    try:
        code = command_line()(args=args, prog_name="mocaptk", standalone_mode=False)
    except MocaptkError as exc:
        print(f"mocaptk: error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # click's UsageError / BadParameter, raised while parsing
        print(f"mocaptk: error: {usage_line(exc)}", file=sys.stderr)
        sys.exit(2)
    except typer.Abort:
        print("mocaptk: error: aborted", file=sys.stderr)
        sys.exit(1)
    except MemoryError as exc:  # input or options too large for this machine: no traceback
        command = next((a for a in args if not a.startswith("-")), "")
        detail = f" ({exc})" if str(exc) else ""
        print(f"mocaptk: error: out of memory while running 'mocaptk {command}'{detail}; "
              "use a smaller input or smaller option values, or a machine with more memory", file=sys.stderr)
        sys.exit(2)
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"mocaptk: error: {where}no space left on device (free some space or use --out)", file=sys.stderr)
        sys.exit(2)
    finally:
        from ..atomic import release_claims

        release_claims()
    if code:
        sys.exit(code)
