"""``python -m mocaptk`` — same as the ``mocaptk`` command."""

from .cli import entry

entry()
