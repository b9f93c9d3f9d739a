"""The generator's sets of the bed: 2 identities x (full face, half face)."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def shared_data() -> Path:
    """``$MOCAPTK_SHARED_DATA``, else ``shared/data`` beside the repository (or beside its worktree folder)."""
    if os.environ.get("MOCAPTK_SHARED_DATA"):
        return Path(os.environ["MOCAPTK_SHARED_DATA"])
    for base in (REPO.parent, REPO.parent.parent):
        if (base / "shared" / "data").is_dir():
            return base / "shared" / "data"
    return REPO.parent / "shared" / "data"


def ict_tarball() -> Path:
    return shared_data() / "face_mesh" / "ict_facekit" / "ict_facekit_FaceXModel_subset.tar.xz"

#: name → options of :func:`testbed.session.write_set`.
SETS = {
    "tb-full-a": {"identity_seed": 11, "count": 180, "half": False, "marker_seed": 3},
    "tb-full-b": {"identity_seed": 23, "count": 180, "half": False, "marker_seed": 8},
    "tb-half-a": {"identity_seed": 11, "count": 100, "half": True, "marker_seed": 5},
    "tb-half-b": {"identity_seed": 23, "count": 100, "half": True, "marker_seed": 13},
}
#: The studio bench's set: tb-full-a's actor with 4 headband markers (``hb0_R`` ... ``hb3_L``) that only the head moves.
STUDIO_SETS = {"tb-full-a-hb": {**SETS["tb-full-a"], "rigid": True}}


def ensure_set(face_tarball: Path, folder: Path, name: str) -> Path:
    """``folder/name`` with the set's files (made once)."""
    out = folder / name
    if not (out / "performance_truth.npz").exists():
        from .ict import load_ict
        from .session import write_set
        write_set(load_ict(face_tarball), out, **{**SETS, **STUDIO_SETS}[name])
    return out
