"""Deterministic JSON: sorted keys, rounded floats, no NaN — outputs diff cleanly."""

from __future__ import annotations

import json
import math
import os
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


def read_json(path: str | os.PathLike[str]) -> Any:
    """Parse a JSON input file; unreadable or invalid files raise :class:`InputFileError`."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise unreadable(path, exc) from None
    except UnicodeDecodeError:
        raise InputFileError(path, "not UTF-8 text: not a JSON file") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFileError(path, f"invalid JSON: {exc.msg} (line {exc.lineno})") from None
