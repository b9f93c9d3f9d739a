"""Atomic outputs: write to a temporary file (or folder) beside the output, then rename.

An interrupted run leaves either the old output or the new one, never a mix or a truncated file.
A command claims its outputs (:func:`claim_output`): an exclusive lock, so that two mocaptk
processes never write the same output, and the clean-up of what a killed run left behind.
Files and folders get the permissions the umask gives (like ``touch`` / ``mkdir``).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from .errors import OutputError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _cannot_write(target: Path, exc: OSError, *, hint: str = "") -> OutputError:
    if exc.errno == errno.ENOSPC:
        return OutputError(f"{target}: no space left on device (nothing was written)")
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        return OutputError(f"{target}: cannot write (a part of the folder path is a file, not a folder)")
    return OutputError(f"{target}: cannot write ({exc.strerror or exc}){hint}")


#: Free space (bytes) below which a writer's own error is taken for a full disk.
_NEARLY_FULL = 1 << 20


def _disk_full(exc: BaseException, folder: Path) -> bool:
    """True when ``exc`` comes from a full disk: ENOSPC, or a library's own error (USD's
    ``Tf.ErrorException``...) raised while ``folder``'s filesystem has (nearly) no space left."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if not isinstance(exc, Exception) or isinstance(exc, OutputError):
        return False
    try:
        stat = os.statvfs(folder)
    except OSError:
        return False
    return stat.f_bavail * stat.f_frsize < _NEARLY_FULL


def reserve(path: str | os.PathLike[str], size: int) -> None:
    """Allocate ``size`` bytes for the file ``path`` now, so that a full disk is an ``OSError``
    (ENOSPC) here rather than a SIGBUS when a memory map of it is written."""
    with open(path, "r+b") as handle:
        try:
            os.posix_fallocate(handle.fileno(), 0, size)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL):  # filesystems without it
                raise


#: Outputs this process holds the lock of: absolute path -> open lock file descriptor.
_claims: dict[Path, int] = {}
#: Folders the locks' creation made (absolute path -> their new folders, deepest first): removed
#: again if the command leaves them empty (a failed run leaves no empty output folder behind).
_made: dict[Path, list[Path]] = {}


def _lock_file(target: Path) -> Path:
    return target.parent / f".{target.name}.lock"


def _lock(target: Path, *, hint: str = "") -> bool:
    """Take the exclusive lock on ``target`` (False: this process holds it already)."""
    key = Path(os.path.abspath(target))
    if key in _claims:
        return False
    lock = _lock_file(key)
    made = [p for p in (key.parent, *key.parent.parents) if not p.exists()]
    while True:
        try:
            key.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise _cannot_write(target, exc, hint=hint) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            _remove_empty(made)
            raise OutputError(f"{target}: is being written by another mocaptk process") from None
        # the previous holder removes the lock file when done: a lock on a removed file is no lock
        with contextlib.suppress(FileNotFoundError):
            if os.path.samestat(os.fstat(fd), os.stat(lock)):
                _claims[key] = fd
                _made[key] = made
                return True
        os.close(fd)


def _remove_empty(folders: list[Path]) -> None:
    """Remove ``folders`` (deepest first) that are empty; a folder holding anything stays."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


def _unlock(target: Path) -> None:
    key = Path(os.path.abspath(target))
    fd = _claims.pop(key, None)
    if fd is not None:
        with contextlib.suppress(OSError):
            os.unlink(_lock_file(key))  # before closing: a waiting process then sees a removed file
        os.close(fd)
        _remove_empty(_made.pop(key, []))


def release_claims() -> None:
    """Release every output lock this process holds (the CLI does at the end of a command)."""
    for key in reversed(list(_claims)):  # the last first: the folder an earlier claim made is empty then
        _unlock(key)


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one step (Linux ``renameat2(RENAME_EXCHANGE)``): a
    reader sees one or the other at every moment. False where the system or filesystem lacks it."""
    import ctypes

    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):  # not Linux / glibc < 2.28
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):  # e.g. a filesystem without it
        return False
    raise OSError(code, os.strerror(code), os.fspath(b))


def _aside(out_dir: Path) -> Path:
    """Where ``staged_folder`` moves the old folder during a ``--force`` swap."""
    return out_dir.parent / f".{out_dir.name}.old"


def _recover(target: Path) -> None:
    """Undo what a killed run left beside ``target`` (the caller holds the lock): put an old folder
    moved aside back if the new one never arrived, else remove it; remove temporary parts."""
    parent = target.parent
    if not parent.is_dir():
        return
    aside = _aside(target)
    if aside.is_dir():
        if target.exists():
            shutil.rmtree(aside, ignore_errors=True)
        else:
            os.replace(aside, target)
    for leftover in parent.glob(f".{target.name}.*.part"):
        if leftover.is_dir():
            shutil.rmtree(leftover, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                leftover.unlink()
    for leftover in parent.glob(f".{target.stem}.*.part{target.suffix}"):
        with contextlib.suppress(OSError):
            leftover.unlink()


def recover_output(path: str | os.PathLike[str]) -> None:
    """Tidy what a killed writer of ``path`` left (parts, a folder moved aside, its lock file);
    a live writer's output (locked by another process) is left alone."""
    target = Path(path)
    try:
        took = _lock(target)
    except OutputError:
        return
    try:
        _recover(target)
    finally:
        if took:
            _unlock(target)


def claim_output(path: str | os.PathLike[str], *, force: bool, folder: bool = False, hint: str = "") -> Path:
    """Check, lock and tidy an output before a command's slow part; returns it as a Path.

    Refuses an existing file (``folder=False``) or a non-empty folder (``folder=True``) unless
    ``force``; takes the exclusive lock on it for the rest of the command (:func:`release_claims`, or
    the end of the process, lets it go); cleans up after a killed earlier run. ``hint`` is added to a
    cannot-write message (e.g. ``"; use --out to write elsewhere"``).
    """
    target = Path(path)
    _lock(target, hint=hint)
    try:
        _recover(target)
        if folder:
            _check_folder(target, force=force)
        else:
            check_writable(target, force=force)
        _probe(target, hint=hint)
    except BaseException:
        _unlock(target)
        raise
    return target


def _probe(target: Path, *, hint: str) -> None:
    """Refuse, before any work, an output whose folder takes no new file (read-only, full)."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    except OSError as exc:
        raise _cannot_write(target, exc, hint=hint) from None
    os.close(fd)
    os.unlink(name)


def _check_folder(out_dir: Path, *, force: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not force:
        raise OutputError(f"{out_dir}: folder exists and is not empty (use --force to overwrite)")


@contextlib.contextmanager
def staged_folder(out_dir: Path, *, force: bool) -> Iterator[Path]:
    """A temporary sibling folder that becomes ``out_dir`` when the block ends without error.

    An existing, non-empty ``out_dir`` is refused unless ``force``; with ``force`` the whole folder is
    replaced in one rename (the old one is moved aside first, then removed; a run killed in between
    is recovered by the next :func:`claim_output`). On failure nothing changes.
    """
    took = _lock(out_dir)
    try:
        _recover(out_dir)
        _check_folder(out_dir, force=force)
        parent = out_dir.parent
        try:
            staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".part", dir=parent))
            os.chmod(staging, 0o777 & ~_umask())
        except OSError as exc:
            raise _cannot_write(out_dir, exc) from None
        try:
            yield staging
            if not out_dir.is_dir():
                os.replace(staging, out_dir)
            elif _exchange(staging, out_dir):  # the old folder now sits at the staging path
                shutil.rmtree(staging, ignore_errors=True)  # a leftover is removed by the next run
            else:  # two renames: a run killed between them is recovered by the next claim
                aside = _aside(out_dir)
                os.replace(out_dir, aside)
                os.replace(staging, out_dir)
                shutil.rmtree(aside, ignore_errors=True)
        except BaseException as exc:
            shutil.rmtree(staging, ignore_errors=True)
            _recover(out_dir)  # the old folder back, if the swap itself failed
            if _disk_full(exc, parent):
                raise _cannot_write(out_dir, OSError(errno.ENOSPC, "no space")) from None
            if isinstance(exc, OutputError) and str(staging) in str(exc):  # name the real output
                raise OutputError(str(exc).replace(str(staging), str(out_dir))) from None
            raise
    finally:
        if took:
            _unlock(out_dir)


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
        os.chmod(tmp_name, 0o666 & ~_umask())
        os.replace(tmp_name, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        if _disk_full(exc, folder):
            raise _cannot_write(target, OSError(errno.ENOSPC, "no space")) from None
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
        os.chmod(tmp_name, 0o666 & ~_umask())
        os.replace(tmp_name, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        if _disk_full(exc, folder):
            raise _cannot_write(target, OSError(errno.ENOSPC, "no space")) from None
        raise


def write_bytes(path: str | os.PathLike[str], data: bytes, *, force: bool = True) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_open(path, "wb", force=force) as handle:
        handle.write(data)
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str, *, force: bool = True) -> Path:
    """Atomically write UTF-8 ``text`` to ``path``."""
    return write_bytes(path, text.encode("utf-8"), force=force)
