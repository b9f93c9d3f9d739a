"""``numba.njit`` with an on-disk cache, shared by the compiled kernels of this stage.

Imports numba: import this module only from the kernel modules, which are imported on first
use, so that ``import mocaptk.acquisition`` and commands that never compile do not load numba.
"""

from __future__ import annotations

import numba

# False once numba found no writable cache folder: kernels are then compiled in every process.
CACHED = True


def compiled(signature=None, **options):
    """``numba.njit(signature, cache=True, **options)`` when numba finds a writable cache folder
    (next to the module, else the user's cache folder), else without the cache (compiled once
    per process; sets :data:`CACHED` to False). With a ``signature`` the function is compiled
    (or loaded from the cache) when it is defined, for that one signature only."""
    def decorate(function):
        global CACHED
        args = () if signature is None else (signature,)
        try:
            return numba.njit(*args, cache=True, **options)(function)
        except RuntimeError:  # "cannot cache function ...: no locator available"
            CACHED = False
            return numba.njit(*args, **options)(function)
    return decorate
