"""Acquisition: marker files (C3D, CSV, TRC), synthetic captures, cameras, triangulation, cleaning.

Public API is listed in ``__all__``; the CLI calls only these names.
"""

__all__: list[str] = []
