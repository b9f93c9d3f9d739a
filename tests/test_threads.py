"""One BLAS thread for every command (mocaptk/threads.py): the same bytes whoever runs it (alone,
in-process beside threaded work, or as a batch worker, which dask starts with one thread)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from mocaptk.threads import command_threads

SAMPLE = Path(__file__).resolve().parents[1] / "sample_c3d"


def _blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


def test_a_command_runs_blas_on_one_thread_and_restores_the_callers():
    variable = os.environ.get("OPENBLAS_NUM_THREADS")
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        if before == {1}:
            pytest.skip("this machine's BLAS runs one thread anyway")
        with command_threads():
            assert _blas_threads() == {1}
            assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
        assert _blas_threads() == before
    assert os.environ.get("OPENBLAS_NUM_THREADS") == variable


def test_blas_loaded_during_the_command_starts_with_one_thread():
    """The CLI imports numpy lazily: a library that loads inside the command reads the variable."""
    code = ("from mocaptk.threads import command_threads\n"
            "with command_threads():\n"
            "    import numpy, scipy.linalg\n"
            "    from threadpoolctl import threadpool_info\n"
            "    print(sorted({l['num_threads'] for l in threadpool_info() if l['user_api'] == 'blas'}))\n")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[1]"


def test_a_bad_thread_count_is_one_line(run_cli, monkeypatch):
    monkeypatch.setenv("MOCAPTK_BLAS_THREADS", "two")
    result = run_cli("info", SAMPLE / "dense_halfface.c3d")
    assert result.exit_code == 2
    assert result.stderr.strip() == "mocaptk: error: MOCAPTK_BLAS_THREADS must be a whole number >= 1, got 'two'"


@pytest.mark.slow
def test_solve_gives_the_same_bytes_whatever_threads_the_caller_runs(run_cli, tmp_path):
    """The sample's solve (139 dense markers: large enough for threaded BLAS to change the sums)
    in-process beside a caller running 2 BLAS threads and under 1: byte-identical model.npz."""
    lay = tmp_path / "lay"
    assert run_cli("cluster", SAMPLE / "dense_halfface.c3d", "--method", "paper", "--formats", "none",
                   "--out", lay, "--quiet").exit_code == 0
    outputs = []
    for threads in (2, 1):
        with threadpool_limits(limits=threads, user_api="blas"):
            out = tmp_path / f"solve{threads}"
            result = run_cli("solve", lay / "layout.json", SAMPLE / "dense_halfface_performance.c3d",
                             "--session", SAMPLE / "dense_halfface.c3d", "--formats", "none", "--out", out,
                             "--quiet")
            assert result.exit_code == 0, result.stderr
            outputs.append({p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.suffix in (".npz", ".c3d")})
    assert outputs[0] == outputs[1]
    assert np.load(tmp_path / "solve1" / "model.npz").files  # a real model was compared


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_threads_are_sized_by_the_cpus_this_process_may_use():
    """Under ``taskset`` (or a cpuset) to one CPU, the kernels' threads (triangulate,
    reconstruct), detect's default and batch's local workers all count one CPU, not the machine's."""
    code = ("import os\n"
            "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})\n"
            "from mocaptk.threads import machine_workers\n"
            "from mocaptk.batch.engine import machine_workers as batch_workers\n"
            "from mocaptk.threads import worker_threads\n"
            "print(machine_workers(), worker_threads()._max_workers, batch_workers is machine_workers)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1", "True"]
