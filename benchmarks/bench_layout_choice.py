"""Benchmark: the hybrid's layout choice (``relayout``, what ``mocaptk cluster`` adds to the
paper's clusters) on a 200-marker x 72,000-frame session, this tree against a named baseline
revision in the same run.

The session is ``bench_scaling.py``'s (the bundled capture tiled and repeated, 0.5 % gaps; made
if missing). Each side runs in its own process: the paper's clustering once, then ``relayout``
(method hybrid) ``--repeat`` times, best CPU time kept; the sides alternate ``--rounds`` times.
The baseline is ``git archive`` of ``--baseline`` (default ``ff81b33``, before the issue-17
layout-choice cuts) imported instead of this tree. Both must choose the same layout (winning contender and
representatives).

    python benchmarks/bench_layout_choice.py [--baseline REV] [--rounds 3] [--repeat 3]
        [--folder /work/scratch/scaling]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("acquisition", "clustering", "retarget")


def child(session: Path, repeat: int) -> None:
    """Print {cpu, wall (of the best of ``repeat``), tree, winner, layout} of ``relayout``."""
    from mocaptk.clustering.methods.session_layout import relayout
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session, load_session

    traj, source = load_session(str(session))
    paper = cluster_session(traj, options=ClusterOptions(method="paper"), source=source)
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        wall, cpu = time.perf_counter(), time.process_time()
        result = relayout(paper, method="hybrid")
        best = min(best, (time.process_time() - cpu, time.perf_counter() - wall))
    import mocaptk.clustering as stage  # which tree was imported
    layout = result.layout
    print(json.dumps({"cpu": best[0], "wall": best[1], "tree": str(Path(stage.__file__).parents[1]),
                      "winner": layout.parameters.get("winner"),
                      "layout": sorted(c.representative for c in layout.clusters if c.mirrored_from is None)}))


def baseline_tree(revision: str, folder: Path) -> Path:
    """``revision`` extracted into ``folder`` as an importable ``mocaptk`` (stages linked in)."""
    archive = folder / "tree.tar"
    subprocess.run(["git", "-C", str(REPO), "archive", "-o", str(archive), revision], check=True)
    with tarfile.open(archive) as tar:
        tar.extractall(folder, filter="data")
    for stage in STAGES:
        (folder / "mocaptk" / stage).symlink_to(folder / stage, target_is_directory=True)
    return folder


def run_side(tree: Path | None, session: Path, repeat: int) -> dict:
    env = dict(os.environ)
    if tree is not None:  # the baseline's mocaptk first on the path, ahead of the editable install
        env["PYTHONPATH"] = os.pathsep.join([str(tree)] + env.get("PYTHONPATH", "").split(os.pathsep))
    out = subprocess.run([sys.executable, __file__, "--child", str(session), str(repeat)], env=env,
                         cwd=tempfile.gettempdir(), capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="ff81b33", help="git revision of the baseline")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--folder", type=Path, default=Path("/work/scratch/scaling"))
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)  # internal: SESSION REPEAT
    args = parser.parse_args()
    if args.child:
        child(Path(args.child[0]), int(args.child[1]))
        return
    session = args.folder / "session_200x72000.c3d"
    if not session.exists():
        args.folder.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_scaling.py"), "--make",
                        str(session), "200", "72000"], check=True)
    print(f"load average at start: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as scratch:
        tree = baseline_tree(args.baseline, Path(scratch))
        rows = []
        for _ in range(args.rounds):
            old, new = run_side(tree, session, args.repeat), run_side(None, session, args.repeat)
            assert old["tree"] != new["tree"], "the baseline tree was not the one imported"
            if (old["winner"], old["layout"]) != (new["winner"], new["layout"]):
                raise SystemExit(f"layouts differ: baseline {old['winner']}, this tree {new['winner']}")
            rows.append((old, new))
            print(f"baseline {old['cpu']:.3f} CPU-s ({old['wall']:.3f} s wall), this tree "
                  f"{new['cpu']:.3f} CPU-s ({new['wall']:.3f} s wall): {old['cpu'] / new['cpu']:.2f}x",
                  flush=True)
    best_old, best_new = min(r[0]["cpu"] for r in rows), min(r[1]["cpu"] for r in rows)
    print(f"relayout (hybrid, {rows[0][1]['winner']}): best {best_old:.3f} -> {best_new:.3f} CPU-s, "
          f"{best_old / best_new:.2f}x against {args.baseline}; same layout")
    print(f"load average at end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
