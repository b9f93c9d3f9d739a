"""Synthetic dense sessions with planted structure for the clustering tests (ground truth known)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mocaptk import Take, Trajectories

#: region -> (centre (x, y, z) mm of the region, number of planted groups)
REGIONS = {"forehead_brow": ((25.0, 60.0, 10.0), 3), "nose": ((0.0, 10.0, 30.0), 2),
           "mouth": ((15.0, -30.0, 20.0), 3)}


def planted_session(*, per_group: int = 4, frames: int = 600, noise: float = 0.05, seed: int = 0,
                    gaps: float = 0.0, takes: bool = True) -> tuple[Trajectories, dict[str, int]]:
    """Half face + midline: groups of markers each driven by one hidden 3-D signal plus noise.

    Returns the session (labels ``REGION_NN_L``; the first marker of every group is on the
    midline, tagged ``_C``) and ``{label: group id}``. One take per region moves only that
    region's groups (the others rest, with noise), like the paper's per-region captures.
    """
    rng = np.random.default_rng(seed)
    labels, group_of, rest, region_of = [], {}, [], []
    group_id = 0
    for region, (centre, n_groups) in REGIONS.items():
        for g in range(n_groups):
            anchor = np.array(centre) + rng.normal(scale=8.0, size=3)
            for k in range(per_group):
                number = g * per_group + k + 1
                midline = k == 0
                pos = anchor + rng.normal(scale=3.0, size=3)
                if midline:
                    pos[0] = 0.0
                else:
                    pos[0] = abs(pos[0]) + 5.0
                label = f"{region.upper()}_{number:02d}_{'C' if midline else 'L'}"
                labels.append(label)
                group_of[label] = group_id
                rest.append(pos)
                region_of.append(region)
            group_id += 1
    rest_arr = np.array(rest)
    n_markers = len(labels)
    groups = np.array([group_of[label] for label in labels])
    t = np.arange(frames)
    signals = np.zeros((frames, group_id, 3))
    region_names = list(REGIONS)
    take_list = []
    per_take = frames // len(region_names)
    for r, region in enumerate(region_names):
        start, end = r * per_take, (r + 1) * per_take if r < len(region_names) - 1 else frames
        take_list.append(Take(region, start, end, region))
        region_groups = sorted({groups[i] for i in range(n_markers) if region_of[i] == region})
        for g in region_groups:
            freq = rng.uniform(0.01, 0.05, size=3)
            phase = rng.uniform(0, 2 * np.pi, size=3)
            amp = rng.uniform(1.0, 4.0, size=3)
            signals[start:end, g] = amp * np.sin(2 * np.pi * freq * t[start:end, None] + phase)
    if not takes:  # everything moves all the time
        for g in range(group_id):
            freq, phase = rng.uniform(0.01, 0.05, size=3), rng.uniform(0, 2 * np.pi, size=3)
            signals[:, g] = rng.uniform(1.0, 4.0, size=3) * np.sin(2 * np.pi * freq * t[:, None] + phase)
    scale = rng.uniform(0.6, 1.4, size=(n_markers, 1))  # members move with different amplitude
    positions = rest_arr[None] + signals[:, groups] * scale[None] + rng.normal(scale=noise,
                                                                               size=(frames, n_markers, 3))
    if gaps:
        positions[rng.random((frames, n_markers)) < gaps] = np.nan
    meta = {"takes": take_list if takes else []}
    return Trajectories(positions, labels, 60.0, metadata=meta), group_of


def save_session(traj: Trajectories, path: Path) -> tuple[Path, Path]:
    """Write ``traj`` as a mocaptk ``.npz`` at ``path`` and its takes as ``takes.json`` beside it."""
    np.savez(path, positions=traj.positions, labels=np.array(traj.labels), rate=traj.rate)
    takes = path.with_name("takes.json")
    takes.write_text(json.dumps({"takes": [t.as_dict() for t in traj.takes]}))
    return path, takes
