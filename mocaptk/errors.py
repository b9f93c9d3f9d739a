"""Error types every stage raises for user mistakes.

The CLI turns any :class:`MocaptkError` into one line on stderr and exit code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os

#: Longest error line (characters after ``mocaptk: error:``): a quoted cell or row is cut.
MAX_LINE = 300
#: Longest file name in a message (a 5,000-character path is cut in its middle).
MAX_PATH = 120


def shorten(text: str, limit: int = MAX_LINE) -> str:
    """``text`` on one line, at most ``limit`` characters: a longer one keeps its start (where)
    and end (what), with " ... " for the cut middle."""
    text = " ".join(str(text).split())
    if len(text) <= limit:
        return text
    head = (limit - 5) * 2 // 3
    return f"{text[:head]} ... {text[len(text) - (limit - 5 - head):]}"


def quoted(value: object, limit: int = 60) -> str:
    """``repr(value)`` for a message, cut to ``limit`` characters (a whole cell or row can be
    200 kB)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 4] + " ..." + text[-1:]


def warn(message: str, *, kind: str = "warning") -> None:
    """Print ``mocaptk: warning: <message>`` (or ``note``) on stderr: one line, at most
    :data:`MAX_LINE` characters like an error line."""
    import sys

    print(f"mocaptk: {kind}: {shorten(message)}", file=sys.stderr)


class MocaptkError(Exception):
    """A problem the user can fix (bad input, bad option); printed as one line."""

    exit_code = 2

    def __init__(self, message: str) -> None:
        super().__init__(shorten(message))


class InputFileError(MocaptkError):
    """An input file is missing, unreadable or malformed.

    The message always names the file: ``"<path>: <problem>"``.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = " ".join(str(problem).split())
        name = shorten(self.path, MAX_PATH)
        super().__init__(f"{name}: {shorten(self.problem, MAX_LINE - len(name) - 2)}")


class OptionError(MocaptkError):
    """A command-line option or parameter value is invalid."""


class OutputError(MocaptkError):
    """An output cannot be written (exists without --force, folder not writable...)."""


def unreadable(path: str | os.PathLike[str], exc: OSError) -> InputFileError:
    """The :class:`InputFileError` for an ``OSError`` raised while opening or reading ``path``."""
    if isinstance(exc, FileNotFoundError):
        problem = "no such file"
    elif isinstance(exc, IsADirectoryError):
        problem = "is a folder, expected a file"
    elif isinstance(exc, PermissionError):
        problem = "permission denied"
    else:
        problem = f"cannot read ({exc.strerror or exc})"
    return InputFileError(path, problem)


def source_error(source: str | os.PathLike[str] | None, problem: str) -> MocaptkError:
    """A problem of data read from ``source``: :class:`InputFileError` naming the file, or
    :class:`OptionError` for data that came from no file (library callers)."""
    return InputFileError(source, problem) if source else OptionError(problem)
