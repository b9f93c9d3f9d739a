"""The README's commands work, in order, on a fresh copy of the bundled sample.

Convention (also stated in a comment at the top of README.md):

- Every ```` ```bash ```` fenced block of README.md is run, in the order it appears, in one fresh
  temporary folder holding a copy of ``sample_c3d/`` (so ``sample_c3d/...`` paths work and later
  blocks see what earlier ones wrote), with ``scripts/`` and ``benchmarks/`` linked from the repo.
- A block is a chain of commands (``&&``, ``;``, newlines, ``\\`` continuations). Only the
  ``mocaptk ...`` and ``python ...`` commands run, with this interpreter (``python -m mocaptk``):
  the environment set-up around them (``python3 -m venv``, ``. .venv/bin/activate``, ``pip install``,
  ``bash scripts/install-readers.sh``) is what made this interpreter, and ``python -m pytest`` is
  this test suite itself. Any other command fails the test, so nothing is skipped silently.
- Commands that need other data (``../shared``, a farm, Blender) or take minutes go in
  ```` ```text ```` blocks, which are not run. Other code-block languages are refused.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from conftest import REPO, SAMPLES

README = REPO / "README.md"

#: Set-up commands: they build the environment this interpreter already is.
SETUP_PREFIXES = (("python3", "-m", "venv"), (".", ".venv/bin/activate"), ("source", ".venv/bin/activate"),
                  ("pip", "install"), ("python", "-m", "pip", "install"), ("bash", "scripts/install-readers.sh"))
#: The test suite itself (running it from here would recurse).
SELF = (("python", "-m", "pytest"),)
#: Languages a README code block may have; only bash is run.
KNOWN_LANGUAGES = {"bash", "text", "json", "python"}

FENCE = re.compile(r"^```(\w*)\s*\n(.*?)^```\s*$", re.S | re.M)


def fenced_blocks(text: str) -> list[tuple[str, str]]:
    """``(language, body)`` of every fenced code block, in order."""
    return [(m.group(1), m.group(2)) for m in FENCE.finditer(text)]


def block_commands(body: str) -> list[list[str]]:
    """The commands of a shell block as argument lists (comments dropped, continuations joined)."""
    joined = re.sub(r"\\\n", " ", body)
    commands = []
    for line in joined.splitlines():
        line = line.split(" #", 1)[0] if not line.lstrip().startswith("#") else ""
        for part in re.split(r"&&|;|\|\|", line):
            words = shlex.split(part)
            if words:
                commands.append(words)
    return commands


def starts_with(words: list[str], prefixes) -> bool:
    return any(tuple(words[:len(p)]) == p for p in prefixes)


def runnable(words: list[str]) -> list[str] | None:
    """The argument list to run for a README command, or None for set-up (AssertionError: unknown)."""
    if starts_with(words, SETUP_PREFIXES) or starts_with(words, SELF):
        return None
    if words[0] == "mocaptk":
        return [sys.executable, "-m", "mocaptk", *words[1:]]
    if words[0] in ("python", "python3"):
        return [sys.executable, *words[1:]]
    raise AssertionError(f"README ```bash command {shlex.join(words)!r} is neither mocaptk, python nor set-up; "
                         "put it in a ```text block or teach tests/test_readme.py about it")


def test_readme_code_blocks_are_known_languages():
    """A ```sh or unlabelled block would escape the README test: every block says what it is."""
    blocks = fenced_blocks(README.read_text(encoding="utf-8"))
    assert blocks, "README.md has no code blocks"
    assert [lang for lang, _ in blocks if lang not in KNOWN_LANGUAGES] == []
    assert any(lang == "bash" for lang, _ in blocks)


def test_readme_bash_blocks_run_in_order(tmp_path):
    """Every command of every ```bash block exits 0, run in order on a fresh copy of the sample."""
    shutil.copytree(SAMPLES, tmp_path / SAMPLES.name, ignore=shutil.ignore_patterns("*_layout", "solved"))  # not a user's earlier outputs
    for name in ("scripts", "benchmarks"):
        (tmp_path / name).symlink_to(REPO / name, target_is_directory=True)
    commands = [words for lang, body in fenced_blocks(README.read_text(encoding="utf-8")) if lang == "bash"
                for words in block_commands(body)]
    ran = 0
    for words in commands:
        argv = runnable(words)
        if argv is None:
            continue
        proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, (f"README command failed (exit {proc.returncode}): {shlex.join(words)}\n"
                                      f"--- stdout\n{proc.stdout[-3000:]}\n--- stderr\n{proc.stderr[-3000:]}")
        assert "Traceback" not in proc.stderr, shlex.join(words)
        ran += 1
    assert ran >= 2, "the README's bash blocks ran fewer than 2 commands"
