"""Command-line interface: ``mocaptk COMMAND ...``.

Each command lives in its own module and registers itself on :data:`app` when imported; heavy
imports happen inside the command functions, and a call imports only its own command's module,
so ``mocaptk info`` starts fast.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from mocaptk.errors import MocaptkError

from .app import app

# The order of `mocaptk --help` (pipeline order: files -> capture -> cleaning -> layout ->
# evaluation -> rig; then batch); each command is defined in the module of its name.
COMMANDS = ("info", "convert", "synth", "calibrate", "detect", "reconstruct", "triangulate", "label",
            "clean", "cluster", "sweep", "evaluate", "compare", "rig", "plan", "solve", "retarget", "batch")


def _register(names: Sequence[str]) -> None:
    """Import the modules of the commands ``names`` (registering them on :data:`app`), in
    ``--help`` order whatever was imported before."""
    for name in names:
        importlib.import_module(f"{__name__}.{name}")
    app.registered_commands.sort(key=lambda c: COMMANDS.index(c.callback.__module__.rsplit(".", 1)[1]))


def command_line(args: Sequence[str] | None = None):
    """The click command tree of :data:`app`, with help that shows no ``<bool>`` beside plain flags.

    Given the ``args`` of a call naming a command (``info FILE``), only that command is built;
    otherwise (``--help``, a misspelt command) all of them."""
    import typer
    import typer.main

    from .coercion import install

    named = next((a for a in args or () if not a.startswith("-")), None)
    _register([named] if named in COMMANDS else COMMANDS)
    command = typer.main.get_command(app)
    names = command.context_settings["help_option_names"]
    for sub in [command, *command.commands.values()]:
        help_option = sub.get_help_option(typer.Context(sub, help_option_names=names))  # made once, cached
        for param in [*sub.params, help_option]:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = ""  # a flag takes no value: show none
            _plain_type_label(param)
        install([*sub.params, help_option])
    return command


def _plain_type_label(param) -> None:
    """Help shows ``<path>...`` for a list and ``<int ≥ 0>`` for a bounded number, not Typer's
    ``<list[Path]>`` / ``<int range> [x>=0]``."""
    desc = getattr(param, "type_descriptor", None)
    if desc is None or (param.param_type_name == "option" and param.metavar is not None):
        return  # an option's own metavar wins (an argument's names it in the usage line)
    if desc.is_list:
        (item,) = getattr(desc.annotation, "__args__", (str,))
        label = f"<{'path' if item is Path else getattr(item, '__name__', 'str')}>..."
    elif desc.is_ranged:
        bounds = [f"≥ {param.min}" if param.min is not None else "", f"≤ {param.max}" if param.max is not None else ""]
        label = f"<{desc.ranged_type_name} {', '.join(b for b in bounds if b)}>"
        param._get_number_range_help_str = lambda: None  # the bounds are in the label
    else:
        return
    param.display_type_rich = lambda ctx: label


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
    from mocaptk.threads import command_threads

    try:
        with command_threads():  # one BLAS thread: the same results alone and in batch, no contention
            code = command_line(args)(args=args, prog_name="mocaptk", standalone_mode=False)
    except MocaptkError as exc:
        print(f"mocaptk: error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # click's UsageError / BadParameter, raised while parsing
        from mocaptk.errors import shorten

        print(f"mocaptk: error: {shorten(usage_line(exc))}", file=sys.stderr)
        sys.exit(2)
    except typer.Abort as exc:
        if isinstance(exc.__cause__, KeyboardInterrupt):  # Ctrl-C before a command's own handling
            print("mocaptk: interrupted", file=sys.stderr)
            sys.exit(130)
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
        from mocaptk.atomic import release_claims

        release_claims()
    if code:
        sys.exit(code)


def entry() -> None:
    """The ``mocaptk`` program (console script and ``python -m mocaptk``): :func:`main`, then the
    process ignores Ctrl-C / SIGTERM while it exits (the command is over: a late signal during the
    interpreter's teardown would otherwise end it as killed, exit code -2, not the command's own),
    and its imported objects are left out of the teardown's last cyclic collection."""
    import gc
    import signal

    try:
        main()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
        # that collection walks every object the imports made (numba's typing tables after
        # `detect`: ~0.2 of its 1.2 fixed CPU-s) in a process about to exit; outputs are closed
        gc.freeze()
