"""How low can translation-only skinning go with a layout? Held-out RMSE per region (mm).

Translation-only linear skinning predicts a dense marker's displacement as ``sum_j w_j d_j(t)``
(joint displacements ``d_j``, one weight per joint for x, y and z): linear in the joints' motion.
So least squares with unconstrained real weights per joint (no sum-1, no sign, no cap) bounds
every weight map the rig could have; a general (3, 3J) linear map per marker bounds any linear
predictor. Rows (mouth / the mean of the other regions at the end):

- ``rig``: the rig ``mocaptk rig`` builds (the weights it writes);
- ``lbs, session -> perf``: weights fitted on the layout's session, tested on the performance;
- ``lbs, perf 1st -> 2nd half``: fitted on the performance's first half (the same kind of
  motion), tested on its second half;
- ``linear ...``: the same with a general linear map (not a skinning model);
- ``lbs, perf -> perf``: fitted and tested on the same frames (memorises the test data: a floor,
  not a rig).

    python scripts/skinning_bounds.py LAYOUT.json SESSION PERFORMANCE
"""

from __future__ import annotations

import sys

import numpy as np

from mocaptk.clustering.layout import read_layout
from mocaptk.clustering.pipeline import load_session
from mocaptk.retarget.build import build_rig, dense_cloud, skinning_by_region


def motion(build, cloud) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Joint displacements (F, J, 3), captured dense marker displacements (F, N, 3) mm from the
    build's bind pose (frames where all are seen), and the dense markers' labels (N,)."""
    joints = build.layout.labels
    captured = [cloud.labels[i] for i in np.flatnonzero(cloud.captured)]
    d = cloud.trajectories[:, cloud.index(joints)] - build.cloud.neutral[build.cloud.index(joints)]
    t = (cloud.trajectories[:, cloud.index(captured)]
         - build.cloud.neutral[build.cloud.index(captured)])
    seen = np.isfinite(d).all(axis=(1, 2)) & np.isfinite(t).all(axis=(1, 2))
    return d[seen], t[seen], captured


def fitted_error(train: tuple[np.ndarray, np.ndarray], test: tuple[np.ndarray, np.ndarray], *,
                 general: bool) -> np.ndarray:
    """Per-frame distance (F_test, N) mm of least-squares linear predictions fitted on ``train``:
    one weight per joint (``general=False``, any skinning weights) or a (3, 3J) map."""
    (d, t), (dt, tt) = train, test
    if general:
        x, xt = d.reshape(len(d), -1), dt.reshape(len(dt), -1)
        gram = x.T @ x
        gram += 1e-9 * np.trace(gram) / len(gram) * np.eye(len(gram))  # rank-deficient: mirrored joints
        predicted = (xt @ np.linalg.solve(gram, x.T @ t.reshape(len(t), -1))).reshape(tt.shape)
    else:
        x, xt = (a.transpose(0, 2, 1).reshape(-1, a.shape[1]) for a in (d, dt))  # (F*3, J)
        w = np.linalg.lstsq(x, t.transpose(0, 2, 1).reshape(-1, t.shape[1]), rcond=None)[0]
        predicted = (xt @ w).reshape(len(dt), 3, -1).transpose(0, 2, 1)
    return np.linalg.norm(predicted - tt, axis=2)


def main(argv: list[str]) -> None:
    layout = read_layout(argv[0])
    session, _ = load_session(argv[1])
    perf, _ = load_session(argv[2])
    build = build_rig(layout, session)
    held = dense_cloud(layout, perf, rotation=build.cloud.rotation)
    own = motion(build, build.cloud)[:2]
    d, t, labels = motion(build, held)
    half = len(d) // 2
    region_of = {m: c.region for c in layout.clusters for m in c.members}
    names = np.array([region_of[label] for label in labels])
    regions = sorted(set(names))
    rows = {"rig": {r: v["rmse_mm"] for r, v in skinning_by_region(build, held)["regions"].items()}}
    for label, general in (("lbs", False), ("linear", True)):
        for split, train, test in (("session -> perf", own, (d, t)),
                                   ("perf 1st -> 2nd half", (d[:half], t[:half]),
                                    (d[half:], t[half:])),
                                   ("perf -> perf", (d, t), (d, t))):
            err = fitted_error(train, test, general=general)
            rows[f"{label}, {split}"] = {r: float(np.sqrt(np.mean(err[:, names == r] ** 2)))
                                         for r in regions}
    print(f"{'':30s}" + "".join(f"{r[:13]:>14s}" for r in regions) + f"{'mouth ratio':>13s}")
    for label, rmse in rows.items():
        others = np.mean([v for r, v in rmse.items() if r != "mouth"])
        print(f"{label:30s}" + "".join(f"{rmse[r]:14.2f}" for r in regions)
              + f"{rmse['mouth'] / others:13.2f}")


if __name__ == "__main__":
    main(sys.argv[1:])
