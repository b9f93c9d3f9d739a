"""Help texts read alike: upper-case argument placeholders, no doubled '...' (issue 33's first hour)."""

from __future__ import annotations

import re

import pytest

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
