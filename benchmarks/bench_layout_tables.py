"""The held-out tables of docs/layout-methods.md ("Default vs the baselines", issue 13).

Run: ``python benchmarks/bench_layout_tables.py --work DIR [sample synth-full head-motion
blenderface blenderface-winners multi-actor multi-actor-blenderface]`` (default: all). Synthetic sessions are written
into ``DIR`` by ``mocaptk synth`` the first time (the ``--full`` capture through the Cara rig takes
minutes) and reused. Prints markdown tables: held-out RMSE / p95 / worst single lost marker (mm)
of the default (hybrid) beside the paper's layout, k-means, random (5 seeds) and farthest-point
at equal count, plus the hybrid before issue 13 (``hybrid v1``: no k-means contender), measured
with ``compare``'s protocol (:func:`mocaptk.clustering.compare.compare_methods`).

``blenderface-winners``: per leave-one-take-out fold, the contender each hybrid version chose and
the held-out RMSE of every contender (why v2 loses to v1 on blenderFace). ``multi-actor``: one
layout for two synthetic actors (different faces and performances, one dense marker layout) and
for blenderFace S01 + S02, each actor's held-out error beside its own layout's
(:mod:`mocaptk.clustering.multi_actor`).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data"))
BLENDERFACE = SHARED / "facial_mocap" / "blenderface"
BASELINES = ("paper", "kmeans", "random", "farthest-point")
#: the hybrid before issue 13: no k-means contender, only the thin-shell layout refined
HYBRID_V1 = {"contenders": ("clusters", "thin-shell", "qr", "greedy"), "refine": ("thin-shell",)}
SECTIONS = ("sample", "synth-full", "head-motion", "blenderface", "blenderface-winners", "multi-actor",
            "multi-actor-blenderface")


def synth(work: Path, name: str, *args: str) -> Path:
    """``mocaptk synth WORK/NAME.c3d ARGS`` unless already there; returns the session path."""
    target = work / f"{name}.c3d"
    if not (work / f"{name}_performance.c3d").is_file():
        subprocess.run([sys.executable, "-m", "mocaptk", "synth", str(target), "-q", "--force", *args],
                       check=True)
    return target


def cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def table(rows, counts) -> str:
    """Markdown: one line per method, RMSE / p95 / 1 lost per count; the default's margins."""
    cell = {(r.method, r.count): r for r in rows}
    methods = list(dict.fromkeys(r.method for r in rows))
    lines = ["| method | " + " | ".join(f"{c} markers" for c in counts) + " |",
             "|---|" + "---|" * len(counts)]
    best = {c: min(r.rmse_mm for r in rows if r.count == c and r.error is None) for c in counts}
    for m in methods:
        out = []
        for c in counts:
            r = cell.get((m, c))
            if r is None or r.error is not None:
                out.append("—")
                continue
            rmse = f"**{r.rmse_mm:.3f}**" if r.rmse_mm == best[c] else f"{r.rmse_mm:.3f}"
            out.append(f"{rmse} / {r.p95_mm:.3f} / {r.lost_rmse_mm:.3f}")
        lines.append(f"| {m} | " + " | ".join(out) + " |")
    for base in ("kmeans", "random", "farthest-point", "paper"):
        out = []
        for c in counts:
            ours, other = cell.get(("hybrid", c)), cell.get((base, c))
            ok = ours is not None and other is not None and ours.error is None and other.error is None
            out.append(f"{100 * (ours.rmse_mm / other.rmse_mm - 1):+.0f} %" if ok else "—")
        lines.append(f"| *hybrid vs {base}* | " + " | ".join(f"*{o}*" for o in out) + " |")
    return "\n".join(lines)


def compare_section(title: str, session, test, counts, *, seed: int = 0) -> None:
    from mocaptk.clustering.compare import compare_methods

    started, cpu = time.perf_counter(), cpu_seconds()
    rows = compare_methods(session, test=test, counts=counts, methods=("hybrid", *BASELINES), seed=seed)
    v1 = compare_methods(session, test=test, counts=counts, methods=("hybrid",), seed=seed,
                         options={"hybrid": HYBRID_V1})
    for r in v1:
        r.method = "hybrid v1"
    print(f"\n### {title}\n\n{table(rows + v1, [c for c in counts if c < session.n_markers])}")
    print(f"\n({time.perf_counter() - started:.0f} s wall, {cpu_seconds() - cpu:.0f} s CPU, "
          f"load {os.getloadavg()[0]:.1f})", flush=True)


def load(path: Path, test: Path | None, **options):
    from mocaptk.clustering.pipeline import load_session_and_test
    traj, perf, _ = load_session_and_test(path, test, **options)
    return traj, perf


def blenderface_options() -> dict:
    return {"stabilized": False, "rate": 25.0, "units": "187"}


def winners(path: Path, counts) -> None:
    """Per fold: the v1 / v2 winner and the held-out RMSE of every contender."""
    from mocaptk.clustering.compare import _gap_free, _problem
    from mocaptk.clustering.evaluation import error_summary, heldout_errors, holdout_splits
    from mocaptk.clustering.methods.hybrid import hybrid_contenders, local_error, local_swaps, hybrid_layout

    traj, _ = load(path, None, **blenderface_options())
    pos = traj.positions
    print(f"\n### {path.stem}: hybrid contenders per left-out take (held-out RMSE mm; v1 / v2 choice)\n")
    for count in counts:
        for (train, held), take in zip(holdout_splits(traj.n_frames, traj.takes, split="takes"), traj.takes):
            problem = _problem(pos, traj, train, {})
            layouts = hybrid_contenders(problem, count)
            for name in ("thin-shell", "kmeans"):
                if name in layouts:
                    layouts[name + "+local"] = local_swaps(problem, layouts[name],
                                                           local_error(problem, scales=(2,)))[0]
            scores = {n: error_summary(heldout_errors(_gap_free(pos[train]), lay, [], test=pos[held]))["rmse_mm"]
                      for n, lay in layouts.items()}
            v1 = hybrid_layout(problem, count, **HYBRID_V1)[1]["winner"]
            v2 = hybrid_layout(problem, count)[1]["winner"]
            text = ", ".join(f"{n} {v:.3f}" for n, v in sorted(scores.items(), key=lambda kv: kv[1]))
            print(f"- {count} markers, {take.name}: v1 {v1} ({scores[v1]:.3f}), v2 {v2} ({scores[v2]:.3f}); {text}")
    print(flush=True)


def multi_actor_tables(work: Path, *, synthetic: bool) -> None:
    """Shared vs own layout per actor: two synthetic actors (--test), or blenderFace S01 + S02."""
    from mocaptk.clustering.multi_actor import actor_rows_as_markdown, compare_actors, load_actors

    sets = []
    if synthetic:
        paths = [synth(work, f"actor{k}", "--rig", "none", "--seed", str(k), "--layout-seed", "0",
                       "--identity", identity) for k, identity in ((1, "1.5,-1,0.5"), (2, "-1,1.5,-0.5"))]
        sets.append(("two `synth` actors (identity 1.5,-1,0.5 / -1,1.5,-0.5, seeds 1 / 2, one layout; "
                     "--test performances)", paths, [p.with_name(p.stem + "_performance.c3d") for p in paths],
                     {"stabilized": True}, [20, 30, 40]))
    elif BLENDERFACE.is_dir():
        sets.append(("blenderFace S01 + S02 (leave one take of an actor out)",
                     [BLENDERFACE / "Subject_01.csv", BLENDERFACE / "Subject_02.csv"], None,
                     blenderface_options(), [3, 4, 6, 8]))
    for title, sessions, tests, options, counts in sets:
        started, cpu = time.perf_counter(), cpu_seconds()
        actors, held, registrations, _ = load_actors(sessions, tests, **options)
        rows = compare_actors(actors, list(registrations), tests=held, counts=counts,
                              methods=("hybrid", "kmeans", "farthest-point"))
        how = "; ".join(f"{n} by {r.by}, scale {r.transform.scale:.3f}, residual {r.residual_mm:.2f} mm"
                        for n, r in registrations.items())
        print(f"\n### One layout for {title}\n\nRegistration: {how}.\n\n{actor_rows_as_markdown(rows)}")
        print(f"({time.perf_counter() - started:.0f} s wall, {cpu_seconds() - cpu:.0f} s CPU, "
              f"load {os.getloadavg()[0]:.1f})", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sections", nargs="*", default=list(SECTIONS))
    parser.add_argument("--work", type=Path, required=True, help="folder for the synthetic sessions")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    for section in args.sections:
        if section == "sample":
            sample = REPO / "sample_c3d"
            traj, perf = load(sample / "dense_halfface.c3d", sample / "dense_halfface_performance.c3d",
                              stabilized=True)
            compare_section("Sample (`sample_c3d/`, --test performance)", traj, perf, [20, 30, 40, 48, 60])
        elif section == "synth-full":
            path = synth(args.work, "full", "--full")
            traj, perf = load(path, path.with_name("full_performance.c3d"), stabilized=True)
            compare_section("`synth --full` (Cara rig, --test performance)", traj, perf, [30, 40, 60, 90])
        elif section == "head-motion":
            path = synth(args.work, "head", "--rig", "room", "--head-motion")
            traj, perf = load(path, path.with_name("head_performance.c3d"), stabilized=True)
            compare_section("`synth --rig room --head-motion` (stabilized, --test performance)",
                            traj, perf, [20, 30, 40, 60])
        elif section in ("blenderface", "blenderface-winners"):
            if not BLENDERFACE.is_dir():
                print(f"\n(blenderFace not found at {BLENDERFACE}: skipped)")
                continue
            for subject in ("Subject_01", "Subject_02"):
                path = BLENDERFACE / f"{subject}.csv"
                if section == "blenderface":
                    traj, _ = load(path, None, **blenderface_options())
                    compare_section(f"blenderFace {subject} (leave one take out)", traj, None, [3, 4, 6, 8])
                else:
                    winners(path, [3, 4, 6, 8])
        elif section in ("multi-actor", "multi-actor-blenderface"):
            multi_actor_tables(args.work, synthetic=section == "multi-actor")
        else:
            parser.error(f"unknown section {section!r} (choose from {', '.join(SECTIONS)})")


if __name__ == "__main__":
    main()
