"""Reusable arrays of one thread (``detect``'s per-image buffers).

A fresh 1 MB array costs more in page faults than a pass over it (cv2.threshold of a 1280x720
frame: 0.40 CPU-ms into a new array, 0.13 into a reused one), so the per-image work of
``detect`` writes into buffers kept by the thread that does it.
"""

from __future__ import annotations

import numpy as np


class Scratch:
    """Named buffers, each grown to the largest size asked for; not for sharing between threads."""

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray] = {}

    def array(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """A C-contiguous ``shape`` array of ``dtype`` (contents undefined) in buffer ``name``;
        valid until the next call for the same name."""
        dtype = np.dtype(dtype)
        size = int(np.prod(shape)) * dtype.itemsize
        buffer = self._buffers.get(name)
        if buffer is None or buffer.nbytes < size:
            buffer = self._buffers[name] = np.empty(size, np.uint8)
        return buffer[:size].view(dtype).reshape(shape)
