"""Help texts read alike: upper-case argument placeholders, no doubled '...' (issue 33's first hour)."""

from __future__ import annotations

import re

import pytest

from conftest import SAMPLES

from mocaptk.cli import COMMANDS


@pytest.mark.parametrize("command", [c for c in COMMANDS if c != "batch"])
def test_usage_placeholders_are_upper_case(run_cli, command):
    usage = next(line for line in run_cli(command, "--help").stdout.splitlines() if "Usage:" in line)
    placeholders = re.findall(r"\{([^}]*)\}", usage)
    assert placeholders and all(p.split(".")[0].isupper() for p in placeholders), usage
    assert "......" not in usage and "...}" not in usage, usage


def test_cluster_help_names_every_method_and_what_force_replaces(run_cli):
    from mocaptk.clustering.methods import method_names

    text = " ".join(run_cli("cluster", "--help").stdout.replace("│", " ").split())
    assert all(name in text for name in method_names())
    assert "evaluation.json" in text  # --force replaces the folder, evaluate's results with it


def test_help_shows_plain_value_types_not_typer_internals(run_cli):
    """`clean` showed "<int range> [x>=0]", list arguments "<list[Path]>" (issue 33's first hour)."""
    for command in COMMANDS:
        text = run_cli(command, "--help").stdout
        assert "range>" not in text and "[x>=" not in text and "<list[" not in text, command
    text = " ".join(run_cli("clean", "--help").stdout.replace("│", " ").split())
    assert "--fill-max-gap <int ≥ 0>" in text


def test_command_docstrings_wrap_evenly():
    """The overview took two source lines of a first paragraph as a broken line (cluster, plan,
    retarget), and batch's help kept a 130-character source line (a broken wrap)."""
    import inspect

    from mocaptk.cli import command_line

    for name, command in command_line().commands.items():
        doc = inspect.cleandoc(command.callback.__doc__ or "")
        assert "\n" not in doc.split("\n\n")[0], name  # the one line `mocaptk --help` shows
        assert max(len(line) for line in doc.splitlines()) <= 96, name


def test_rig_means_a_camera_rig_everywhere_solve_bakes_with_bake_rig(run_cli):
    """`--rig` was a camera rig in cluster / compare / plan / synth and a face rig in solve."""
    solve = " ".join(run_cli("solve", "--help").stdout.replace("│", " ").split())
    assert "--bake-rig" in solve and "--rig " not in solve
    for command in ("cluster", "compare", "plan"):
        text = " ".join(run_cli(command, "--help").stdout.replace("│", " ").split())
        assert "--rig" in text and "Camera rig" in text, command


def test_solve_keeps_the_old_rig_spelling(run_cli, tmp_path):
    """The hidden alias parses (it reaches the same check as --bake-rig)."""
    for flag in ("--rig", "--bake-rig"):
        done = run_cli("solve", SAMPLES / "none.json", SAMPLES / "dense_halfface_performance.c3d",
                       "--model", tmp_path / "m.npz", flag, "--out", tmp_path / "o")
        assert done.exit_code == 2 and "no such option" not in done.stderr, done.stderr
