"""Deterministic JSON: sorted keys, rounded floats, no NaN — outputs diff cleanly."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import write_text
from .errors import InputFileError, unreadable


#: Types :func:`to_plain` returns unchanged (exact types: subclasses take the slow path).
_UNCHANGED = (str, int, bool, type(None))
#: Types json's encoder writes as :func:`dumps` does.
_SCALARS = (*_UNCHANGED, float)
#: Scalars whose JSON text holds no bracket or comma (rows of them are split on "], [").
_NUMBERS = (int, float, bool, type(None))


def to_plain(value: Any, *, digits: int = 6) -> Any:
    """Convert numpy scalars/arrays, tuples and paths to JSON types; round floats.

    Non-finite floats become ``None`` (JSON has no NaN).
    """
    if isinstance(value, dict):  # plain values without a call each (tens of thousands of gap records)
        return {str(k): v if type(v) in _UNCHANGED else to_plain(v, digits=digits)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):  # plain items without a call each (mesh rows, weights)
        return [v if type(v) in _UNCHANGED else _plain_float(v, digits) if type(v) is float
                else to_plain(v, digits=digits) for v in value]
    if isinstance(value, np.ndarray):
        return _array_to_plain(value, digits)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return _plain_float(float(value), digits)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def _plain_float(f: float, digits: int) -> float | None:
    """``f`` rounded to ``digits`` decimals, ``0.0`` for any zero, None if not finite."""
    if not math.isfinite(f):
        return None
    r = round(f, digits)
    return 0.0 if r == 0 else r


def _array_to_plain(array: np.ndarray, digits: int) -> Any:
    """Vectorized :func:`to_plain` for numeric arrays (large meshes and weight tables)."""
    if array.dtype.kind in "iub":
        return array.tolist()
    if array.dtype.kind == "f" and np.isfinite(array).all():
        return (np.round(array.astype(np.float64), digits) + 0.0).tolist()  # + 0.0: no "-0.0"
    return to_plain(array.tolist(), digits=digits)


def dumps(obj: Any, *, digits: int = 6) -> str:
    """Serialize ``obj`` deterministically: sorted keys, 2-space indent, trailing newline.

    Lists of scalars stay on one line (one vertex / weight row per line), which keeps large
    files readable in a diff and lets the fast C encoder do the bulk of the work.
    """
    return _encode(to_plain(obj, digits=digits), "") + "\n"


def _encode(value: Any, indent: str) -> str:
    if isinstance(value, dict):
        if not value:
            return "{}"
        inner = indent + "  "
        items = (f"{inner}{json.dumps(key, ensure_ascii=False)}: {_encode(value[key], inner)}"
                 for key in sorted(value))
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        inner = indent + "  "
        if all(type(v) is list for v in value) and all(type(x) in _NUMBERS for v in value for x in v):
            # rows of numbers (vertices, faces, weights): one C-encoder call for all rows
            rows = json.dumps(value, allow_nan=False, separators=(", ", ": "))[1:-1]
            return "[\n" + inner + rows.replace("], [", "],\n" + inner + "[") + "\n" + indent + "]"
        if all(type(v) is dict and all(type(x) in _SCALARS for x in v.values()) for v in value):
            # records of scalars (tens of thousands of gap records): one C-encoder call for all
            return "[\n" + _records(value, inner) + "\n" + indent + "]"
        return "[\n" + ",\n".join(inner + _encode(v, inner) for v in value) + "\n" + indent + "]"
    return json.dumps(value, ensure_ascii=False, allow_nan=False, separators=(", ", ": "))


def _record(value: dict, indent: str) -> str:
    """:func:`_encode` of a dict of scalars in one call of json's C encoder (an indent makes json
    use its Python encoder): the item separator carries the line break and indent."""
    if not value:
        return "{}"
    inner = indent + "  "
    body = json.dumps(value, ensure_ascii=False, allow_nan=False, sort_keys=True,
                      separators=(",\n" + inner, ": "))
    return "{\n" + inner + body[1:-1] + "\n" + indent + "}"


def _records(values: list[dict], indent: str) -> str:
    r"""``indent`` + :func:`_record` of each of ``values`` joined by ",\n", in one C-encoder call:
    encoded text never holds a raw line break, so "},\n<indent>  {" only joins two records."""
    if not all(values):  # an empty record has no body to split
        return ",\n".join(indent + _record(v, indent) for v in values)
    inner = indent + "  "
    text = json.dumps(values, ensure_ascii=False, allow_nan=False, sort_keys=True,
                      separators=(",\n" + inner, ": "))
    head, tail = indent + "{\n" + inner, "\n" + indent + "}"
    return head + text[2:-2].replace("},\n" + inner + "{", tail + ",\n" + head) + tail


def write_json(path: str | os.PathLike[str], obj: Any, *, digits: int = 6,
               force: bool = True) -> Path:
    """Atomically write ``obj`` as deterministic JSON."""
    return write_text(path, dumps(obj, digits=digits), force=force)


#: Largest JSON / small text input read (a layout, takes, regions, camera rig, sidecar, rig.json).
MAX_INPUT_BYTES = 256 << 20
#: Deepest nesting of a JSON input (ours nest 5 levels; deeper only exhausts the stack).
MAX_DEPTH = 64


def read_input_bytes(path: str | os.PathLike[str], *, limit: int = MAX_INPUT_BYTES,
                     what: str = "a JSON file", head_problem: Callable[[bytes], str | None] | None = None
                     ) -> bytes:
    """The bytes of a small text input (JSON or CSV), read in blocks: a file over ``limit`` bytes,
    or holding NUL bytes (``/dev/zero``, a binary file), is refused before it fills memory.
    ``head_problem(first block)``: a more precise problem to report first (e.g. UTF-16 text)."""
    blocks, size = [], 0
    try:
        with open(path, "rb") as handle:
            while block := handle.read(min(1 << 20, limit + 1 - size)):
                problem = head_problem(block) if head_problem is not None and not blocks else None
                if problem:
                    raise InputFileError(path, problem)
                if b"\0" in block:
                    raise InputFileError(path, f"binary content (NUL bytes): not {what}")
                blocks.append(block)
                size += len(block)
                if size > limit:
                    raise InputFileError(path, f"more than {limit >> 20} MB: larger than {what} "
                                               "mocaptk reads")
    except OSError as exc:
        raise unreadable(path, exc) from None
    return b"".join(blocks)


def parse_json(text: str, path: str | os.PathLike[str]) -> Any:
    """``json.loads(text)``; invalid JSON, nesting deeper than :data:`MAX_DEPTH` and integers of
    more than 4,300 digits raise :class:`InputFileError` naming ``path``."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"invalid JSON: {exc.msg} (line {exc.lineno})") from None
    except RecursionError:
        raise InputFileError(path, f"invalid JSON: nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as exc:  # an integer beyond Python's digit limit (int_max_str_digits)
        raise InputFileError(path, f"invalid JSON: a number too long ({str(exc).split(';')[0]})") from None
    _check_depth(data, path)
    return data


def _check_depth(data: Any, path: str | os.PathLike[str]) -> None:
    """Refuse nesting deeper than :data:`MAX_DEPTH` (iteratively: no recursion on deep input)."""
    stack = [(data, 1)]
    while stack:
        value, depth = stack.pop()
        items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
        for item in items:
            if isinstance(item, (dict, list)):
                if depth >= MAX_DEPTH:
                    raise InputFileError(path, f"invalid JSON: nested deeper than {MAX_DEPTH} levels")
                stack.append((item, depth + 1))


def read_json(path: str | os.PathLike[str], *, limit: int = MAX_INPUT_BYTES) -> Any:
    """Parse a JSON input file; unreadable, oversized or invalid files raise
    :class:`InputFileError`."""
    data = read_input_bytes(path, limit=limit)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(path, "not UTF-8 text: not a JSON file") from None
    return parse_json(text, path)
