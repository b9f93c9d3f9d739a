"""Deterministic JSON: sorted keys, rounded floats, no NaN — outputs diff cleanly."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import write_text


def to_plain(value: Any, *, digits: int = 6) -> Any:
    """Convert numpy scalars/arrays, tuples and paths to JSON types; round floats.

    Non-finite floats become ``None`` (JSON has no NaN).
    """
    if isinstance(value, dict):
        return {str(k): to_plain(v, digits=digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v, digits=digits) for v in value]
    if isinstance(value, np.ndarray):
        return to_plain(value.tolist(), digits=digits)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        f = float(value)
        if not math.isfinite(f):
            return None
        r = round(f, digits)
        return 0.0 if r == 0 else r
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def dumps(obj: Any, *, digits: int = 6) -> str:
    """Serialize ``obj`` deterministically (sorted keys, 2-space indent, trailing newline)."""
    return json.dumps(to_plain(obj, digits=digits), sort_keys=True, indent=2,
                      ensure_ascii=False, allow_nan=False) + "\n"


def write_json(path: str | os.PathLike[str], obj: Any, *, digits: int = 6,
               force: bool = True) -> Path:
    """Atomically write ``obj`` as deterministic JSON."""
    return write_text(path, dumps(obj, digits=digits), force=force)
