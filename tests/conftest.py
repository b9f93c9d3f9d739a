"""Shared test fixtures: the real third-party data in ../shared/data and an in-process CLI runner."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data"))
SAMPLES = REPO / "sample_c3d"


def shared_path(*parts: str) -> Path:
    """Path under ../shared/data; skips the calling test when it is absent (a user's clone)."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not available: {SHARED_DATA}")
    return SHARED_DATA


def fuzz_readers():
    """``benchmarks/fuzz_readers.py`` as a module: its isolated, memory-capped reader ``Worker``."""
    import importlib.util
    import sys

    if "fuzz_readers" not in sys.modules:  # its dataclasses look their module up by name
        spec = importlib.util.spec_from_file_location("fuzz_readers", REPO / "benchmarks" / "fuzz_readers.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules["fuzz_readers"] = module
        spec.loader.exec_module(module)
    return sys.modules["fuzz_readers"]


@dataclass
class CliResult:
    exit_code: int
    stdout: str
    stderr: str


@pytest.fixture
def run_cli(capsys):
    """Run ``mocaptk ARGS...`` in-process; returns exit code, stdout and stderr."""
    from mocaptk.cli import main

    def run(*args: str | os.PathLike[str]) -> CliResult:
        capsys.readouterr()
        try:
            main([os.fspath(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        out = capsys.readouterr()
        return CliResult(code, out.out, out.err)

    return run


@pytest.fixture
def identity_actor(run_cli, tmp_path, monkeypatch) -> Path:
    """``tmp_path/actor.c3d`` (+ ``actor_truth.npz``): bench_retarget's full-face actor, an ICT
    identity that is not the generic rig's face (``synth --full --identity 1.5,-1.0,0.8``)."""
    monkeypatch.setenv("MOCAPTK_ICT_FACEKIT", str(shared_path("face_mesh", "ict_facekit",
                                                              "ict_facekit_FaceXModel_subset.tar.xz")))
    actor = tmp_path / "actor.c3d"
    done = run_cli("synth", actor, "--full", "--identity", "1.5,-1.0,0.8", "--spacing", "10", "--rig", "none",
                   "--seed", "11", "--noise", "0.2", "--expressions", "5", "--rest", "1.5", "--hold", "2.0",
                   "--quiet", "--force")
    assert done.exit_code == 0, done.stderr
    return actor
