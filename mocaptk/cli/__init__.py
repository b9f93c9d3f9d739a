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
    """Entry point: run the CLI; a user mistake is one line on stderr and exit code 2."""
    try:
        app(args=list(argv) if argv is not None else None, prog_name="mocaptk")
    except MocaptkError as exc:
        print(f"mocaptk: error: {exc}", file=sys.stderr)
        sys.exit(exc.exit_code)
