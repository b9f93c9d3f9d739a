"""Atomic file output: write to a temporary file in the same folder, then rename.

An interrupted run leaves either the old file or the new one, never a truncated one.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import OutputError


def _cannot_write(target: Path, exc: OSError) -> OutputError:
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        return OutputError(f"{target}: cannot write (a part of the folder path is a file, not a folder)")
    return OutputError(f"{target}: cannot write ({exc.strerror or exc})")


def check_writable(path: str | os.PathLike[str], *, force: bool) -> Path:
    """Return ``path`` as a Path; refuse an existing file unless ``force``."""
    target = Path(path)
    if target.exists() and not force:
        raise OutputError(f"{target}: already exists (use --force to overwrite)")
    if target.is_dir():
        raise OutputError(f"{target}: is a folder, expected a file path")
    return target


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb", *, force: bool = True,
                encoding: str | None = None) -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; rename it into place on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    ``encoding`` defaults to UTF-8 for text modes; text is written with ``\\n`` newlines.
    """
    target = check_writable(path, force=force)
    folder = target.parent if str(target.parent) else Path(".")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=folder)
    except OSError as exc:
        raise _cannot_write(target, exc) from None
    text = "b" not in mode
    try:
        with os.fdopen(fd, mode, encoding=(encoding or "utf-8") if text else None,
                       newline="\n" if text else None) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str], *, force: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` for libraries that write by file name.

    The temporary keeps ``path``'s extension (some writers dispatch on it); it is renamed
    into place when the block ends without error, and removed otherwise.
    """
    target = check_writable(path, force=force)
    folder = target.parent if str(target.parent) else Path(".")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".part{target.suffix}",
                                        dir=folder)
        os.close(fd)
    except OSError as exc:
        raise _cannot_write(target, exc) from None
    try:
        yield Path(tmp_name)
        with open(tmp_name, "rb+") as handle:
            os.fsync(handle.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        raise


def write_bytes(path: str | os.PathLike[str], data: bytes, *, force: bool = True) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_open(path, "wb", force=force) as handle:
        handle.write(data)
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str, *, force: bool = True) -> Path:
    """Atomically write UTF-8 ``text`` to ``path``."""
    return write_bytes(path, text.encode("utf-8"), force=force)
