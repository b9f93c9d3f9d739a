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
# (pipeline order: files -> capture -> cleaning -> layout -> evaluation -> rig).
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


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: run the CLI; a user mistake or running out of memory is one line on stderr and
    exit code 2."""
    args = list(argv) if argv is not None else sys.argv[1:]
    try:
        app(args=args, prog_name="mocaptk")
    except MocaptkError as exc:
        print(f"mocaptk: error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
    except MemoryError as exc:  # input or options too large for this machine: no traceback
        command = next((a for a in args if not a.startswith("-")), "")
        detail = f" ({exc})" if str(exc) else ""
        print(f"mocaptk: error: out of memory while running 'mocaptk {command}'{detail}; "
              "use a smaller input or smaller option values, or a machine with more memory", file=sys.stderr)
        sys.exit(2)
