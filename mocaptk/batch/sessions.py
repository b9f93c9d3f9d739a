"""What a batch covers: the session files, each session's options and the argv of its command.

A session's options come from, in increasing priority: the batch's command line, a folder-wide
``mocaptk.json`` beside the session, and the session's own ``<stem>.mocaptk.json``. Paths in a
sidecar are relative to the sidecar's folder. Every path handed to a worker is absolute, so the
workers of a farm read the same files (shared storage) whatever their working folder.
"""

from __future__ import annotations

import functools
import glob
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mocaptk.errors import InputFileError, OptionError, quoted

#: suffix of a session's own options file and the name of a folder-wide one
SIDECAR_SUFFIX = ".mocaptk.json"
FOLDER_SIDECAR = "mocaptk.json"
SIDECAR_FORMAT = "mocaptk.session-options"


@dataclass(frozen=True)
class BatchCommand:
    """How batch runs one command: where its outputs go inside ``DIR/<stem>/``.

    ``out_file``: the command's ``--out`` is this file in the session folder (None: the folder);
    ``stdout_file``: the command prints its result (``--json``) and batch saves it under this name;
    ``layout_argument``: the command's first argument is a layout (``solve LAYOUT CAPTURE``): the
    matched files are its captures and the layout comes from ``--layout`` (batch line or sidecar);
    ``per_session``: required options a session's sidecar may give instead of the batch line.
    """

    name: str
    out_file: str | None = None
    stdout_file: str | None = None
    fixed: tuple[str, ...] = ("--quiet",)
    layout_argument: bool = False
    per_session: tuple[str, ...] = ()


COMMANDS: dict[str, BatchCommand] = {
    "cluster": BatchCommand("cluster"),
    "evaluate": BatchCommand("evaluate", out_file="evaluation.json"),
    "compare": BatchCommand("compare"),
    "info": BatchCommand("info", stdout_file="info.json", fixed=("--json",)),
    "solve": BatchCommand("solve", layout_argument=True),
    "label": BatchCommand("label", out_file="labelled.c3d", per_session=("--template",)),
}
#: batch's own option naming a ``layout_argument`` command's layout (a sidecar's "layout" key)
LAYOUT_OPTION = "--layout"

#: options batch itself sets for every session: a sidecar or the batch line may not
CONTROLLED = ("--out", "--force", "--quiet", "--json", "--help")
#: a sidecar key for batch itself, not for the command: the session's own --timeout (seconds, 0: none)
TIMEOUT_KEY = "timeout"


def _controlled(param) -> bool:
    return any(name in CONTROLLED for name in param.opts)


@functools.lru_cache(maxsize=None)
def click_command(name: str):
    """The click command behind ``mocaptk NAME``, built as the CLI builds it for a call of that
    command (only its module imported; its parameters drive option parsing)."""
    from mocaptk.cli import command_line

    return command_line([name]).commands[name]


def _option_table(command) -> dict[str, Any]:
    """``{"--factor": option, ...}`` including secondary names (``--no-mirror``)."""
    table = {}
    for param in command.params:
        if param.param_type_name == "option":
            for name in (*param.opts, *param.secondary_opts):
                table[name] = param
    return table


def _is_path(param) -> bool:
    return param.type_descriptor.annotation is Path


def find_sessions(patterns: list[str]) -> list[Path]:
    """Absolute session paths matching the glob ``patterns`` (``**`` recurses), in sorted order.

    Sidecar files are not sessions. A pattern that matches no file, or two sessions with the
    same stem (their outputs would share ``DIR/<stem>/``), raise :class:`OptionError`.
    """
    if not patterns:
        raise OptionError("no session pattern given (e.g. 'sessions/*.c3d')")
    found: dict[Path, None] = {}
    for pattern in patterns:
        matches = [Path(p).absolute() for p in sorted(glob.glob(os.path.expanduser(pattern), recursive=True))]
        files = [p for p in matches if p.is_file() or (p.exists() and not p.is_dir())]
        files = [p for p in files if not p.name.endswith(SIDECAR_SUFFIX) and p.name != FOLDER_SIDECAR]
        if not files:
            raise OptionError(f"no session file matches {pattern!r}")
        found.update(dict.fromkeys(files))
    by_stem: dict[str, Path] = {}
    for path in sorted(found):
        if path.stem in by_stem:
            raise OptionError(f"two sessions share the name {path.stem!r} ({by_stem[path.stem]}, {path}): "
                              "their outputs would both go in DIR/" + path.stem + "/; rename one or "
                              "run them in separate batches")
        by_stem[path.stem] = path
    return sorted(found)


def split_batch_line(command: str, tokens: list[str], *, base: Path) -> tuple[list[str], list[str]]:
    """The batch line's free tokens as (session patterns, options for ``command``).

    Options are checked against the command's own (a value follows its option, or ``--x=v``);
    path values are made absolute (relative to ``base``) so every worker finds the same file.
    """
    table = _option_table(click_command(command))
    patterns: list[str] = []
    options: list[str] = []
    i = 0
    while i < len(tokens):
        token = tokens[i]
        i += 1
        if not token.startswith("-") or token == "-":
            patterns.append(token)
            continue
        name, eq, value = token.partition("=")
        param = table.get(name)
        layout = param is None and name == LAYOUT_OPTION and COMMANDS[command].layout_argument
        if param is None and not layout:
            raise OptionError(f"mocaptk {command} has no option {name} (see mocaptk {command} --help)")
        if not layout and _controlled(param):
            raise OptionError(f"{name} is set by batch for every session; give it to batch itself")
        if not layout and (param.is_flag or param.count):
            options.append(token)
            continue
        if not eq:
            if i >= len(tokens):
                raise OptionError(f"option {name} needs a value")
            value = tokens[i]
            i += 1
        options += [name, _absolute(value, base) if layout or _is_path(param) else value]
    return patterns, options


def check_command_line(command: str, options: list[str]) -> None:
    """Parse ``mocaptk COMMAND <a session> OPTIONS`` as the command would (types, choices), so a
    bad value fails once, before any cluster starts, instead of once per session."""
    import typer

    if COMMANDS[command].layout_argument and LAYOUT_OPTION not in options:
        options = [*options, LAYOUT_OPTION, "layout.json"]  # a sidecar may give each session's
    for name in COMMANDS[command].per_session:
        if name not in options:
            options = [*options, name, "given-by-a-sidecar"]
    argv = _command_argv(command, Path("session"), Path("out"), options)
    try:
        click_command(command).make_context(command, argv[1:])
    except typer.TyperException as exc:
        raise OptionError(f"mocaptk {command}: {exc.format_message()}") from None


def _absolute(value: str, base: Path) -> str:
    path = Path(os.path.expanduser(value))
    return str(path if path.is_absolute() else (base / path).absolute())


def _sidecar_tokens(command: str, path: Path) -> list[str]:
    """The options a sidecar file gives ``command`` (keys the command lacks but another batch
    command has are left to that command; unknown keys are an error)."""
    from mocaptk.jsonio import read_json

    doc = read_json(path)
    if not isinstance(doc, dict):
        raise InputFileError(path, 'expected a JSON object {"option": value, ...}')
    if doc.get("format", SIDECAR_FORMAT) != SIDECAR_FORMAT or doc.get("version", 1) != 1:
        raise InputFileError(path, f"not a session options file (expected format {SIDECAR_FORMAT!r} "
                                   "version 1)")
    own = _option_table(click_command(command))
    known = set(own)
    for other in COMMANDS:
        known |= set(_option_table(click_command(other)))
    tokens: list[str] = []
    for key, value in sorted(doc.items()):
        if key in ("format", "version"):
            continue
        if key == TIMEOUT_KEY:
            _timeout_value(path, value)
            continue
        name = "--" + key.replace("_", "-")
        if name not in known:
            raise InputFileError(path, f"unknown option {quoted(key)} (no batch command has {quoted(name)[1:-1]})")
        param = own.get(name)
        if param is None and name == LAYOUT_OPTION and COMMANDS[command].layout_argument:
            if not isinstance(value, str) or not value or "\0" in value:
                raise InputFileError(path, f"'layout' must be a file name, got {quoted(value)}")
            tokens += [name, _absolute(value, path.parent)]
            continue
        if param is None:
            continue
        if _controlled(param):
            raise InputFileError(path, f"{key!r} is set by batch for every session")
        tokens += _option_tokens(path, name, param, value)
    try:  # a bad value names this file, not only the option
        check_command_line(command, tokens)
    except OptionError as exc:
        raise InputFileError(path, str(exc)) from None
    return tokens


def _option_tokens(path: Path, name: str, param, value: Any) -> list[str]:
    """One sidecar entry as command-line tokens (flags from booleans, lists joined by commas)."""
    if param.is_flag:
        if not isinstance(value, bool):
            raise InputFileError(path, f"{name[2:]!r} must be true or false, got {quoted(value)}")
        if value:
            return [name]
        return list(param.secondary_opts[:1])
    if isinstance(value, list) and all(isinstance(v, (str, int, float)) and not isinstance(v, bool)
                                       for v in value):
        value = ",".join(str(v) for v in value)
    if not isinstance(value, (str, int, float)) or isinstance(value, bool):
        raise InputFileError(path, f"{name[2:]!r} must be a text, a number or a list of them, got {quoted(value)}")
    text = str(value)
    if "\0" in text or not text:
        raise InputFileError(path, f"{name[2:]!r} must not be empty or hold a NUL character")
    return [name, _absolute(text, path.parent) if _is_path(param) else text]


def _timeout_value(path: Path, value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
        raise InputFileError(path, f"'timeout' must be a number of seconds >= 0 (0: no limit), got {value!r}")
    return float(value) or None


def session_timeout(session: Path, default: float | None) -> float | None:
    """The session's timeout in seconds (None: no limit): its sidecars' ``timeout`` (the session's
    own wins over its folder's), else ``default`` (the batch's --timeout). A bad sidecar is left to
    the runner to report: here it only falls back to the default."""
    from mocaptk.jsonio import read_json

    timeout = default
    for path in sidecars(session):
        try:
            doc = read_json(path)
            if isinstance(doc, dict) and TIMEOUT_KEY in doc:
                timeout = _timeout_value(path, doc[TIMEOUT_KEY])
        except (InputFileError, OSError):
            continue
    return timeout


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False for a name the system refuses (too long: a sidecar's value)."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False


def sidecars(session: Path) -> list[Path]:
    """The options files that apply to ``session`` (folder-wide first, then its own)."""
    candidates = [session.parent / FOLDER_SIDECAR, session.with_name(session.stem + SIDECAR_SUFFIX)]
    return [p for p in candidates if _is_file(p)]


def session_argv(command: str, session: Path, out_dir: Path, options: list[str]) -> list[str]:
    """argv of the single command for one session (without ``--force``): its output in ``out_dir``.

    ``options`` are the batch line's; the session's sidecars come after them, so they win.
    """
    tokens = list(options)
    for sidecar in sidecars(session):
        tokens += _sidecar_tokens(command, sidecar)
    return _command_argv(command, session, out_dir, tokens)


def _command_argv(command: str, session: Path, out_dir: Path, tokens: list[str]) -> list[str]:
    spec = COMMANDS[command]
    argv = [command, str(session), *tokens, *spec.fixed]
    if spec.layout_argument:  # solve LAYOUT CAPTURE: the last --layout given (a sidecar's) wins
        at = [i for i, token in enumerate(tokens) if token == LAYOUT_OPTION]
        if not at:
            raise InputFileError(session, f"no layout for it: give batch {LAYOUT_OPTION} L.json, or "
                                          f"\"layout\" in {session.stem}{SIDECAR_SUFFIX} beside it")
        rest = [t for i, t in enumerate(tokens) if i not in at and i - 1 not in at]
        argv = [command, tokens[at[-1] + 1], str(session), *rest, *spec.fixed]
    if command == "evaluate" and "--layout" not in tokens:  # default: the layout a cluster batch wrote
        argv += ["--layout", str(out_dir / "layout.json")]
    if spec.stdout_file is None:
        argv += ["--out", str(out_dir / spec.out_file) if spec.out_file else str(out_dir)]
    return argv


def input_files(command: str, argv: list[str], session: Path) -> list[Path]:
    """Files the run reads: the session, its sidecars and every existing path-valued option."""
    table = _option_table(click_command(command))
    files = [session, *sidecars(session)]
    if COMMANDS[command].layout_argument and _is_file(Path(argv[1])):
        files.append(Path(argv[1]))
    for name, value in zip(argv, argv[1:]):
        param = table.get(name)
        if param is not None and not _controlled(param) and _is_path(param) and _is_file(Path(value)):
            files.append(Path(value))
    return list(dict.fromkeys(files))


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
