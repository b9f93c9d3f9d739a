"""End-to-end score of camera-aware against camera-blind layouts (docs/layout-methods.md table).

For each rig and marker count: the hybrid layout chosen on the sample session without a rig and
with ``--rig`` (its costs: the session filmed through the rig as placed by ``mocaptk plan``); then
the sample's held-out performance (its ground truth) is captured through the rig with only the
layout's markers (``mocaptk synth``'s capture: normals of the ICT mesh, 0.3 mm detection noise,
1 % dropouts, 0.2 % ghosts, robust triangulation, spikes removed, gaps <= 6 frames filled), the
dense face is reconstructed by the evaluation's ridge fitted on the session, and scored against
the true dense markers (RMSE mm over every frame and marker, mean of ``--seeds`` capture seeds,
3 by default). "Exact" is the same layout with its markers measured exactly (no cameras). The
"per seed" column pairs the two layouts' captures of each seed: the mean change, its standard
error over the seeds, and in how many seeds the camera-aware layout scores lower.

Rigs: ``cara`` and ``room`` (the presets, as ``synth`` uses them) and ``cara-right`` (only the
two Cara cameras on the subject's right: a badly placed rig, from a rig file).

    python benchmarks/bench_camera_layouts.py [--counts 20,30,48] [--seeds 3] [--session S.c3d] [--out table.md]

``--session``: another ``mocaptk synth`` session (with its ``_performance_truth.npz``), e.g. one
made with ``--wide-zone`` (markers under the chin, on the eyelids and inner lips).

Needs ICT-FaceKit (../shared/data) for the mesh normals of the performance.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_c3d"


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", default="20,30,48")
    parser.add_argument("--rigs", default="cara,room,cara-right")
    parser.add_argument("--session", type=Path, default=SAMPLE / "dense_halfface.c3d")
    parser.add_argument("--seeds", type=int, default=3, help="capture seeds per layout")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()

    from mocaptk.acquisition import cara_rig, load_face_model, load_ground_truth, read_trajectories, room_rig, save_rig
    from mocaptk.acquisition.synth_session import marker_normals
    from mocaptk.clustering.compare import rig_aware
    from mocaptk.clustering.end_to_end import capture_layout, end_to_end_errors, rmse
    from mocaptk.clustering.methods import LayoutProblem, select_layout
    from mocaptk.clustering.neutral import neutral_pose

    started, cpu0 = time.perf_counter(), cpu_seconds()
    session = read_trajectories(args.session)
    truth = load_ground_truth(args.session.with_name(args.session.stem + "_performance_truth.npz"))
    assert tuple(truth.labels) == tuple(session.labels)
    true_positions = truth.positions
    normals = marker_normals(load_face_model(), truth)
    neutral = neutral_pose(session.positions)
    blind = LayoutProblem(session.positions - neutral[None], neutral, labels=session.labels,
                          segments=tuple((t.start, t.end) for t in session.takes))
    folder = Path(tempfile.mkdtemp())
    right = folder / "cara_right.json"
    save_rig(cara_rig().subset([1, 3]), right)
    rigs = {"cara": ("cara", cara_rig()), "room": ("room", room_rig()),
            "cara-right": (str(right), cara_rig().subset([1, 3]))}
    lines = ["| rig | markers | camera-blind end-to-end mm | camera-aware end-to-end mm | change | "
             "per seed: change ± s.e., aware lower | exact: blind / aware mm | markers changed |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in args.rigs.split(","):
        spec, production = rigs[name]
        aware = rig_aware(session, spec)(blind)
        for count in [int(c) for c in args.counts.split(",")]:
            layouts = {kind: select_layout(problem, count, method="hybrid").layout
                       for kind, problem in (("blind", blind), ("aware", aware))}
            per_seed, scores, exact = {}, {}, {}
            for kind, layout in layouts.items():
                per_seed[kind] = np.array([rmse(end_to_end_errors(
                    session.positions, layout, capture_layout(production, true_positions, normals, layout, seed=s),
                    true_positions)) for s in range(args.seeds)])
                scores[kind] = float(np.mean(per_seed[kind]))
                exact[kind] = rmse(end_to_end_errors(session.positions, layout, true_positions[:, layout],
                                                     true_positions))
            paired = 100.0 * (per_seed["aware"] / per_seed["blind"] - 1.0)
            error = paired.std(ddof=1) / np.sqrt(paired.size) if paired.size > 1 else float("nan")
            wins = int(np.sum(per_seed["aware"] < per_seed["blind"]))
            changed = int(np.setdiff1d(layouts["aware"], layouts["blind"]).size)
            change = 100.0 * (scores["aware"] / scores["blind"] - 1.0)
            lines.append(f"| {name} | {count} | {scores['blind']:.4f} | {scores['aware']:.4f} | {change:+.1f} % | "
                         f"{paired.mean():+.2f} ± {error:.2f} %, {wins} of {paired.size} | "
                         f"{exact['blind']:.4f} / {exact['aware']:.4f} | {changed} |")
            print(lines[-1], flush=True)
    wall, cpu = time.perf_counter() - started, cpu_seconds() - cpu0
    footer = (f"\n{wall:.0f} s wall, {cpu:.0f} CPU-s, load average {os.getloadavg()[0]:.1f} "
              f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})\n")
    table = "\n".join(lines) + "\n" + footer
    print(table)
    if args.out:
        args.out.write_text(table)


if __name__ == "__main__":
    main()
