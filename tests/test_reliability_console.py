"""What every command prints: option-parse errors as one ``mocaptk: error:`` line (exit 2), ``-q``
everywhere, no ``<bool>`` beside plain flags in ``--help``, and ``cluster``'s console in order
(a head-relative session is a note, printed once; the rig line after the summary)."""

from __future__ import annotations

import pytest
from clustering_synthetic import planted_session, save_session

from mocaptk.cli import command_line

COMMANDS = sorted(command_line().commands)


def one_error_line(result) -> str:
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("mocaptk: error: "), result.stderr
    return lines[0]


def number_option(command: str) -> str | None:
    """A ``--name`` of ``command`` that takes an int or a float (None: it has none)."""
    import typer

    cmd = command_line().commands[command]
    for param in cmd.params:
        if not getattr(param, "is_flag", True) and param.display_type(typer.Context(cmd)) in ("<int>", "<float>"):
            return next(o for o in param.opts if o.startswith("--"))
    return None


@pytest.mark.parametrize("command", COMMANDS)
def test_option_parse_errors_are_one_line(run_cli, command, tmp_path):
    option = number_option(command)
    if option is not None:
        line = one_error_line(run_cli(command, tmp_path / "x", tmp_path / "y", option, "abc"))
        assert option in line and f"mocaptk {command} --help" in line
    line = one_error_line(run_cli(command, "--no-such-option"))  # or first a missing required option
    assert f"mocaptk {command} --help" in line
    line = one_error_line(run_cli(command))  # every command needs an argument or an option
    assert "Missing" in line


def test_unknown_command_and_no_arguments(run_cli):
    assert "clustr" in one_error_line(run_cli("clustr"))
    overview = run_cli()
    assert overview.exit_code == 2 and "cluster" in overview.stdout


def test_factor_abc_is_one_line(run_cli, tmp_path):
    line = one_error_line(run_cli("cluster", tmp_path / "s.c3d", "--factor", "abc"))
    assert "'--factor'" in line and "abc" not in line.split("'--factor'")[0]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_quiet_and_help_shows_no_bool(run_cli, command):
    opts = [o for p in command_line().commands[command].params for o in p.opts]
    assert "-q" in opts and "--quiet" in opts
    text = run_cli(command, "--help").stdout
    assert "<bool>" not in text and "--quiet" in text


@pytest.fixture(scope="module")
def clustered(tmp_path_factory):
    """A planted session recorded head-relative (as by head-mounted cameras): four still headband
    markers beside the moving face; its takes file."""
    import dataclasses

    import numpy as np

    folder = tmp_path_factory.mktemp("console")
    traj, _ = planted_session(seed=7, per_group=3, frames=240)
    band = np.array([[40.0, 80.0, 0.0], [-40.0, 80.0, 0.0], [60.0, 40.0, -20.0], [-60.0, 40.0, -20.0]])
    still = band + np.random.default_rng(0).normal(scale=0.05, size=(traj.n_frames, 4, 3))
    traj = dataclasses.replace(traj, positions=np.concatenate([traj.positions, still], axis=1),
                               labels=(*traj.labels, "HEAD_01_L", "HEAD_02_R", "HEAD_03_L", "HEAD_04_R"))
    path, takes = save_session(traj, folder / "planted.npz")
    return path, takes, folder


def test_cluster_console_note_once_and_rig_line_after_summary(run_cli, clustered):
    path, takes, folder = clustered
    result = run_cli("cluster", path, "--takes", takes, "--formats", "json", "--out", folder / "out")
    assert result.exit_code == 0, result.stderr
    assert "head-relative" not in result.stderr  # the normal case with head-mounted cameras: no warning
    assert result.stdout.count("already head-relative") == 1
    assert "note: the session is already head-relative" in result.stdout
    lines = result.stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("mocaptk cluster:"))
    rig = next(i for i, line in enumerate(lines) if line.startswith("rig: "))
    assert header == 0 and rig > header
    summary = (folder / "out" / "summary.txt").read_text()
    assert summary.count("already head-relative") == 1
    assert not any("head-relative" in line for line in summary.splitlines() if line.startswith("warning"))


def test_evaluate_spells_farthest_point_as_compare_does(run_cli, clustered):
    path, takes, folder = clustered
    out = folder / "layout_for_eval"
    assert run_cli("cluster", path, "--takes", takes, "--formats", "none", "--out", out, "-q").exit_code == 0
    result = run_cli("evaluate", path, "--layout", out / "layout.json", "--takes", takes, "--seeds", "2")
    assert result.exit_code == 0, result.stderr
    assert "farthest-point" in result.stdout and "farthest_point" not in result.stdout
    assert '"farthest-point"' in (out / "evaluation.json").read_text()
