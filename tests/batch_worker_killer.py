"""Dask worker preload for tests/test_batch.py: a worker that starts a task of a session whose
name contains ``kill-me`` kills its own process (SIGKILL), as the kernel's OOM killer or a node
failure would. Used only by the test's ``dask worker --preload``; nothing in mocaptk knows it."""

from __future__ import annotations

import os
import signal

from distributed import WorkerPlugin


class KillOnSession(WorkerPlugin):
    """Kill this worker process when a ``kill-me`` task starts executing."""

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and "kill-me" in str(key):
            os.kill(os.getpid(), signal.SIGKILL)


async def dask_setup(worker):
    await worker.plugin_add(KillOnSession(), name="kill-on-session")
