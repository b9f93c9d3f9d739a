"""Option values converted without pydantic, so a command starts fast.

Typer (0.2x) converts every option value through a pydantic ``TypeAdapter``; importing pydantic
and building the adapters costs about 0.3 CPU-s on every ``mocaptk`` call. The plain types our
commands use (str, int, float, Path and lists of them) are converted here instead. A value
this does not convert plainly (a typo, ``1_000``, ``inf``, a path that is not readable) goes to
Typer's own conversion, so the value and every error message are exactly Typer's.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args, get_origin

try:  # Typer's coercion layer (0.2x); with another Typer this module changes nothing
    from typer._click.exceptions import BadParameter
    from typer._coercion import RuntimeParam, build_runtime_param
    from typer._param_types import coerce_cli_path
    from typer.core import _TyperParameter
except ImportError:  # pragma: no cover - depends on the installed Typer
    RuntimeParam = None

_INT = re.compile(r"[+-]?[0-9]+")
_FLOAT = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")
_PLAIN_PATH_FLAGS = ("exists", "resolve_path", "allow_dash", "path_type", "parser", "click_type")


class _NotPlain(Exception):
    """The value needs Typer's own conversion."""


def _leaf(annotation: Any, info: Any, value: Any) -> Any:
    """``value`` converted as Typer converts it, for a plain leaf type; else :class:`_NotPlain`."""
    if annotation in (str, bool) and type(value) is annotation:
        return value
    if annotation in (int, float) and info.min is None and info.max is None and not info.clamp:
        if isinstance(value, str):
            if (_INT if annotation is int else _FLOAT).fullmatch(value):
                return annotation(value)
        elif isinstance(value, int if annotation is int else (int, float)) and not isinstance(value, bool):
            return annotation(value)
    if annotation is int and info.min is not None and info.max is None and not info.clamp:
        number = _leaf(int, _Unbounded, value)
        if number >= info.min:
            return number
    if annotation is Path and not any(getattr(info, flag, None) for flag in _PLAIN_PATH_FLAGS):
        if isinstance(value, str) and value:
            value = Path(value)
        if isinstance(value, Path):
            return value
    raise _NotPlain


class _Unbounded:
    min = max = clamp = None


@dataclass(frozen=True)
class PlainRuntimeParam(RuntimeParam if RuntimeParam is not None else object):
    """Typer's runtime conversion for one parameter, done here for plain values."""

    def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
        try:
            if get_origin(self.annotation) is list:
                (item,) = get_args(self.annotation)
                items = value if isinstance(value, (list, tuple)) else [value]
                return [self._path(_leaf(item, self.parameter_info, v), param, ctx) for v in items]
            return self._path(_leaf(self.annotation, self.parameter_info, value), param, ctx)
        except (_NotPlain, BadParameter):  # Typer converts it, or words the error
            full = build_runtime_param(param.type_descriptor)
            return full._coerce_value(value, param=param, ctx=ctx)

    def _path(self, value: Any, param: Any, ctx: Any) -> Any:
        if not isinstance(value, Path):
            return value
        # Typer's own checks (readable etc.); a Path in means no pydantic conversion
        return coerce_cli_path(value, self.parameter_info, path_type=Path, param=param, ctx=ctx)


def install(params: Iterable[Any]) -> None:
    """Convert the plain values of these click parameters here rather than through pydantic."""
    if RuntimeParam is None:
        return
    for param in params:
        if isinstance(param, _TyperParameter) and param._runtime_param is None:
            desc = param.type_descriptor
            if desc.file_annotation is None:
                param._runtime_param = PlainRuntimeParam(parameter_info=desc.parameter_info,
                                                         annotation=desc.annotation)
