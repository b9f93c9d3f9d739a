"""One thread policy for mocaptk's linear algebra (threadpoolctl): BLAS runs on one thread; and
the one count of CPUs that a command's own threads and batch's workers are sized by.

mocaptk's matrix work is many small solves and products (a ridge fit per held-out fold and gap
pattern, layout searches, per-frame solves), where BLAS threads only contend with each other and
with the machine's other work: on a loaded 2-core machine ``evaluate`` took 83.6 s wall with
OpenBLAS's default threads against 7.5 s with one (docs/performance.md). And a result must not
depend on who ran it: dask starts batch workers with ``OPENBLAS_NUM_THREADS=1``, so a command run
alone with more BLAS threads summed in another order (``solve``'s model.npz differed by 1e-12).

So every command runs under :func:`command_threads` (entered by the CLI's ``main``, which batch
workers call too), and library code doing small-matrix work wraps it in :func:`one_thread` (or
decorates it with :data:`single_threaded`) for callers outside the CLI. The compiled kernels'
threads (triangulate, reconstruct: :func:`worker_threads`) are not BLAS: one per usable CPU
(:func:`machine_workers`), as detect's pool and batch's local workers.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from functools import lru_cache
from typing import TYPE_CHECKING

from threadpoolctl import threadpool_limits

if TYPE_CHECKING:  # concurrent.futures is imported on first use (every command imports this module)
    from concurrent.futures import ThreadPoolExecutor

#: Environment variables BLAS libraries read when they load (OpenBLAS, MKL, BLIS).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: A command's BLAS threads: 1 unless this variable says otherwise (then results may differ from a
#: batch's in the last bits; benchmarks/bench_threads.py compares the two).
THREADS_VARIABLE = "MOCAPTK_BLAS_THREADS"


def one_thread() -> threadpool_limits:
    """BLAS limited to one thread inside the ``with`` block (libraries already loaded)."""
    return threadpool_limits(limits=1, user_api="blas")


#: Decorator form of :func:`one_thread`.
single_threaded = threadpool_limits.wrap(limits=1, user_api="blas")


def machine_workers() -> int:
    """Threads or worker processes that can run at once: one per CPU this process may use (its
    affinity, which ``taskset``, a cgroup cpuset or a SLURM allocation narrow; else the
    machine's count). Every command's parallel work is sized by it."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def worker_threads() -> ThreadPoolExecutor:
    """:func:`machine_workers` threads for compiled kernels that release the GIL, started once
    per process (starting them per call cost more CPU than a small call); a forked child starts
    its own. Callers run one share of the work themselves and submit the others here (never a
    task that waits on this pool)."""
    return _threads_of(os.getpid())


@lru_cache(maxsize=1)
def _threads_of(pid: int) -> ThreadPoolExecutor:
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(machine_workers(), thread_name_prefix="mocaptk-worker")


@contextlib.contextmanager
def command_threads() -> Iterator[None]:
    """One BLAS thread (or :data:`THREADS_VARIABLE`'s count) for a whole command: libraries that
    load later read it from the environment (the CLI imports numpy lazily), those already loaded
    (an in-process caller, a batch runner) are limited by threadpoolctl; both are restored
    afterwards."""
    count = os.environ.get(THREADS_VARIABLE, "1")
    if not (count.isdigit() and int(count) >= 1):
        from mocaptk.errors import OptionError
        raise OptionError(f"{THREADS_VARIABLE} must be a whole number >= 1, got {count!r}")
    saved = {name: os.environ.get(name) for name in BLAS_THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(BLAS_THREAD_VARIABLES, count))
    try:
        if "numpy" in sys.modules:  # threadpoolctl only sees loaded libraries
            with threadpool_limits(limits=int(count), user_api="blas"):
                yield
        else:
            yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
