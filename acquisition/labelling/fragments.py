"""Trajectory fragments of an unlabelled capture: the unit a label is voted for.

A fragment is a run of consecutive frames in which one column holds a point (capture software
breaks a trajectory at every occlusion; a column may hold several fragments one after another).
Untracked per-frame clouds (each frame's points in arbitrary columns) are first linked into
fragments here: a point continues the previous frame's nearest point when the two are mutual
nearest neighbours, well inside the marker spacing and clearly nearer than any other point.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Link clouds only within this fraction of the template's median marker spacing ...
LINK_SPACING = 0.35
#: ... and only when the second-nearest point is at least this many times farther.
LINK_RATIO = 2.0
#: A capture whose column steps exceed LINK_SPACING × spacing this often is untracked clouds.
CLOUD_JUMPS = 0.2


def column_fragments(positions: np.ndarray) -> np.ndarray:
    """(F, N) fragment id of every point (runs of points per column), -1 where no point."""
    present = ~np.isnan(positions).any(axis=2)
    starts = present & ~np.vstack([np.zeros((1, present.shape[1]), dtype=bool), present[:-1]])
    # number runs column by column: cumulative count of run starts in column-major order
    ids = np.cumsum(starts.T.ravel()).reshape(present.shape[1], -1).T - 1
    return np.where(present, ids, -1).astype(np.int32)


def looks_untracked(positions: np.ndarray, spacing_mm: float) -> bool:
    """True when the columns jump between markers frame to frame (per-frame clouds)."""
    step = np.linalg.norm(np.diff(positions, axis=0), axis=2)
    step = step[np.isfinite(step)]
    return bool(step.size) and float((step > LINK_SPACING * spacing_mm).mean()) > CLOUD_JUMPS


def link_clouds(positions: np.ndarray, spacing_mm: float) -> np.ndarray:
    """(F, N) fragment ids linking untracked clouds frame to frame (see module doc)."""
    n_frames, n_cols = positions.shape[:2]
    ids = np.full((n_frames, n_cols), -1, dtype=np.int32)
    radius = LINK_SPACING * spacing_mm
    next_id = 0
    prev_cols = np.empty(0, dtype=np.int64)
    prev_tree = None
    for f in range(n_frames):
        cols = np.flatnonzero(~np.isnan(positions[f]).any(axis=1))
        pts = positions[f, cols]
        if len(cols) and prev_tree is not None and len(prev_cols) >= 2:
            dist, near = prev_tree.query(pts, k=2)
            tree = cKDTree(pts)
            back_d, back = tree.query(positions[f - 1, prev_cols], k=min(2, len(cols)))
            back = back if back.ndim == 1 else back[:, 0]
            mutual = back[near[:, 0]] == np.arange(len(cols))
            ok = mutual & (dist[:, 0] <= radius) & (dist[:, 1] >= LINK_RATIO * dist[:, 0])
            ids[f, cols[ok]] = ids[f - 1, prev_cols[near[ok, 0]]]
        else:
            tree = cKDTree(pts) if len(cols) else None
        fresh = cols[ids[f, cols] < 0]
        ids[f, fresh] = np.arange(next_id, next_id + len(fresh))
        next_id += len(fresh)
        prev_cols, prev_tree = cols, tree
    return ids
