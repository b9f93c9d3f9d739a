"""What a ``mocaptk`` call imports: only its own command's module, and no pydantic (Typer's
converter, ~0.3 CPU-s); and option values converted without pydantic are exactly Typer's."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from typer._click.exceptions import BadParameter

from mocaptk.cli import COMMANDS, command_line
from mocaptk.cli.coercion import PlainRuntimeParam

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"

#: Typed text a user might give, plain or not (Typer accepts ' 3', '1_000', 'inf'; refuses '3.5' as int).
TEXTS = ["3", "-3", "+3", "0003", "3.0", "3.", ".5", "1e3", "-1E-3", " 3", "1_000", "inf", "nan", "",
         "abc", "0x10", "\u0663", "sample_c3d/dense_halfface.c3d", "no/such/file.c3d", "-"]


def _modules_after(argv: list[str]) -> set[str]:
    code = ("import sys\nfrom mocaptk.cli import main\n"
            f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(' '.join(sorted(sys.modules)))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert run.returncode == 0, run.stderr[-800:]
    return set(run.stdout.split())


@pytest.mark.skipif(not SAMPLE.exists(), reason="bundled sample missing")
def test_info_imports_no_pydantic_and_no_other_command():
    modules = _modules_after(["info", str(SAMPLE)])
    assert "mocaptk.cli.info" in modules
    assert not {m for m in modules if m.split(".")[0] in ("pydantic", "scipy", "matplotlib", "numba", "rich")}
    assert not {f"mocaptk.cli.{name}" for name in COMMANDS if name != "info"} & modules


def test_help_lists_every_command_in_pipeline_order():
    """``info`` registered first (one call), then the overview: all commands, in ``COMMANDS`` order."""
    command_line(["info", "x.c3d"])
    assert list(command_line().commands) == list(COMMANDS)


def _typer_value(param, ctx, value):
    """(value or None, error message or None) of Typer's own conversion."""
    from typer._coercion import build_runtime_param

    try:
        return build_runtime_param(param.type_descriptor)._coerce_value(value, param=param, ctx=ctx), None
    except BadParameter as exc:
        return None, exc.format_message()


def _same(a, b) -> bool:
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("command", COMMANDS)
def test_plain_conversion_equals_typers(command, monkeypatch):
    """Every parameter of every command, with typed text, its default and Python numbers: the
    same value and type, or the same error, as Typer's pydantic conversion."""
    monkeypatch.chdir(REPO)
    cmd = command_line().commands[command]
    ctx = typer.Context(cmd)
    checked = 0
    for param in cmd.params:
        plain = param._runtime_param
        assert isinstance(plain, PlainRuntimeParam), param.name
        list_valued = param.multiple or param.nargs == -1
        values = [(t,) if list_valued else t for t in TEXTS] + [3, 2.5, True, Path("x.c3d")]
        if list_valued:
            values += [tuple(TEXTS[:3]), (str(SAMPLE), "no/such.c3d")]
        if param.default is not None and not callable(param.default):
            values.append(param.default)
        for value in values:
            want, error = _typer_value(param, ctx, value)
            try:
                got = plain._coerce_value(value, param=param, ctx=ctx)
            except BadParameter as exc:
                assert exc.format_message() == error, (param.name, value)
            else:
                assert error is None and _same(got, want), (param.name, value, got, want)
            checked += 1
    assert checked >= len(cmd.params) * len(TEXTS)
