"""Many sessions at once: ``mocaptk batch`` runs one command on every session as Dask tasks.

- :mod:`.sessions`: which files a batch covers, each session's options (sidecar files) and the
  exact argv of the single command it runs;
- :mod:`.runner`: the subprocess that runs one session's command exactly like the CLI does;
- :mod:`.supervisor`: the Dask task: drives a runner, kills it on a timeout or when the batch stops;
- :mod:`.journal`: each session's attempts, on the shared output storage (exactly-once effects);
- :mod:`.engine`: the Dask client side (a ``LocalCluster``, a farm's scheduler, dask-jobqueue);
- :mod:`.summary`: ``batch.json`` + ``batch.md``, merged under :mod:`.lock` (shared ``--out``).

Nothing here imports Dask at module level: ``import mocaptk`` never does.
"""

from __future__ import annotations

__all__ = ["engine", "journal", "lock", "runner", "sessions", "summary", "supervisor"]
