"""The layout and regions pictures draw any session without a traceback or a matplotlib warning
(issue 14 items 11, 14): coordinates beyond float range of a front view (OverflowError /
LinAlgError in ``layout_picture``), empty / undecodable / very long region names (UserWarnings)."""

from __future__ import annotations

import warnings

import numpy as np

from mocaptk.clustering.figures import layout_picture, regions_picture
from mocaptk.clustering.layout import Cluster, Layout


def _layout(labels: list[str], position) -> Layout:
    cluster = Cluster(representative=labels[0], region="eye", members=tuple(labels),
                      member_correlation={label: 1.0 for label in labels}, position=tuple(position), side="L")
    return Layout({}, {"factor": 1.1}, (), (cluster,), {})


def test_pictures_of_off_scale_points_and_odd_names(tmp_path):
    rng = np.random.default_rng(0)
    frame = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    labels = [f"M{i}" for i in range(6)]
    cases = {"huge": rng.uniform(0, 1, (6, 3)) * 1.5e308,  # front view overflows to inf
             "one_far": np.vstack([rng.uniform(0, 100, (5, 3)), [[1e308, 1e308, 1e308]]]),
             "gaps": np.full((6, 3), np.nan)}
    names = {"_hidden": labels[:2], "": labels[2:3], "\udcff\x01" + "\u4e2d" * 3 + "x" * 300: labels[3:]}
    for case, points in cases.items():
        neutral = dict(zip(labels, points))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # UserWarning and RuntimeWarning are failures here
            layout_picture(_layout(labels, points[0]), neutral, frame=frame, path=tmp_path / f"{case}_l.png")
            regions_picture(names, neutral, frame=frame, path=tmp_path / f"{case}_r.png")
        assert (tmp_path / f"{case}_l.png").stat().st_size > 1000
