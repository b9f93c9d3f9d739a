"""Labelling raw captures with a template session's marker names (``mocaptk label``, docs/label.md).

Modules, one job each: :mod:`.template` (the motion model), :mod:`.pose` (pose and expression fit,
RANSAC pose), :mod:`.fragments` (fragments, clouds linked into them), :mod:`.tracker` (per-frame
labelling), :mod:`.vote` (fragment voting), :mod:`.capture` (a whole capture; ``--check``/``--fix``),
:mod:`.report` (``label_report.json``). This file only names what an unlabelled column is.
"""

from __future__ import annotations

import re

#: Names capture software gives points it could not label (Vicon ``*12``), or that our C3D reader
#: gives the columns of a file without any labels (``M001``).
UNNAMED = re.compile(r"^(\*\d+|M\d{3,})$")


def is_unnamed(label: str) -> bool:
    """True for the name of an unlabelled column (see :data:`UNNAMED`)."""
    return UNNAMED.match(label) is not None
