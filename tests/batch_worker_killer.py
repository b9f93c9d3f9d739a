"""Dask worker preload for tests/test_batch.py: a worker that runs a task of a session whose name
contains ``kill-me`` kills its own process (SIGKILL) 0.2 s later, mid-session, as the kernel's
OOM killer or a node failure would. Used only by the test's ``dask worker --preload``; nothing in
mocaptk knows it."""

from __future__ import annotations

import os
import signal
import threading

from distributed import WorkerPlugin


class KillOnSession(WorkerPlugin):
    """Kill this worker process 0.2 s after a ``kill-me`` task started executing."""

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and "kill-me" in str(key):
            threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGKILL)).start()


async def dask_setup(worker):
    await worker.plugin_add(KillOnSession(), name="kill-on-session")
