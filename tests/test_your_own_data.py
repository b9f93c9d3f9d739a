"""docs/your-own-data.md: its commands, run as written on the real blenderFace file."""

from __future__ import annotations

import json
import re
import shlex
import shutil

import pytest
from conftest import REPO, shared_path

PAGE = REPO / "docs" / "your-own-data.md"


def page_commands() -> list[list[str]]:
    block = re.search(r"```\n(.*?)```", PAGE.read_text(), re.S).group(1)
    return [shlex.split(line) for line in block.splitlines() if line.strip()]


def test_the_page_gives_one_consistent_command_set():
    commands = page_commands()
    assert [c[1] for c in commands] == ["info", "cluster", "evaluate"]
    for command in commands:  # the same rate and units everywhere; blenderFace is head-relative
        assert command[command.index("--rate") + 1] == "25" and command[command.index("--units") + 1] == "187.6"
    assert "--no-stabilize" in commands[1]
    for doc in ("formats.md", "method.md"):  # the other pages point here and agree on the numbers
        text = (REPO / "docs" / doc).read_text()
        assert "187.6" in text and "--units 190" not in text, doc


@pytest.mark.slow
def test_the_page_commands_run_on_blenderface(run_cli, tmp_path, monkeypatch):
    shutil.copy(shared_path("facial_mocap", "blenderface", "Subject_01.csv"), tmp_path)
    monkeypatch.chdir(tmp_path)
    for command in page_commands():
        result = run_cli(*command[1:])
        assert result.exit_code == 0, (command, result.stderr)
        assert "Traceback" not in result.stderr
        for line in result.stderr.splitlines():  # each warning once: not again in the printed summary
            if line.startswith("mocaptk: warning: "):
                assert (result.stdout + result.stderr).count(line[len("mocaptk: warning: "):]) == 1, line
    assert "25 Hz" in run_cli(*page_commands()[0][1:]).stdout
    layout = json.loads((tmp_path / "s01_layout" / "layout.json").read_text())
    assert layout["parameters"]["stabilized"] is False and len(layout["clusters"]) >= 3
    assert (tmp_path / "s01_eval" / "evaluation.json").is_file()
