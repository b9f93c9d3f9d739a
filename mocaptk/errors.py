"""Error types every stage raises for user mistakes.

The CLI turns any :class:`MocaptkError` into one line on stderr and exit code 2;
anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import os


class MocaptkError(Exception):
    """A problem the user can fix (bad input, bad option); printed as one line."""

    exit_code = 2

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class InputFileError(MocaptkError):
    """An input file is missing, unreadable or malformed.

    The message always names the file: ``"<path>: <problem>"``.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = " ".join(str(problem).split())
        super().__init__(f"{self.path}: {self.problem}")


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
