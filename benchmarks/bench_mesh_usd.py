"""``write_mesh_usd`` (solve's mesh.usd) against another tree's, alternating, wall and CPU, in
one run: one file, and value clips of a third of the frames each; the files compared byte for
byte.

    python benchmarks/bench_mesh_usd.py --baseline OLD_TREE [--frames 2000] [--rounds 3]

``OLD_TREE``: a checkout of the code to compare with (``git archive f566eba | tar -x -C
OLD_TREE``), run from its tree (PYTHONPATH) in this environment. The mesh: 9,409 vertices (the
default face's count), frames of noise around a rest shape, two of them with a NaN or an inf
vertex (solve's unsolved rows). Each round runs both trees in child processes (the order
alternates); medians are printed with the 1-minute load.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_detect_command import installed_layout

CHILD = """
import hashlib, json, sys, time
from pathlib import Path
import numpy as np
from mocaptk.retarget.export_usd import write_mesh_usd
vertices, frames, out = 9409, int(sys.argv[1]), Path(sys.argv[2])
rng = np.random.default_rng(0)
rest = (rng.normal(size=(vertices, 3)) * 50).astype(np.float32)
faces = rng.integers(0, vertices, size=(18000, 3))
base = [(rest + rng.normal(size=(vertices, 3))).astype(np.float32) for _ in range(25)]
base[3][10], base[7][20, 1] = np.nan, np.inf
def chunks():
    for start in range(0, frames, 256):
        yield np.stack([base[i % 25] for i in range(start, min(frames, start + 256))])
times = {}
for name, clip in (("one file", None), ("clips", frames // 3)):
    wall, cpu = time.perf_counter(), time.process_time()
    write_mesh_usd(out / f"{name[0]}.usd", rest=rest, faces=faces, frames=chunks(), n_frames=frames,
                   rate=60.0, clip_frames=clip)
    times[name] = (time.perf_counter() - wall, time.process_time() - cpu)
print(json.dumps(times))
"""


def digest(folder: Path) -> str:
    sha = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        sha.update(str(path.relative_to(folder)).encode())
        sha.update(path.read_bytes())
    return sha.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, required=True, help="source tree of the code to compare with")
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    times: dict[str, list] = {"this tree": [], args.baseline.name: []}
    loads, digests = [], {}
    with tempfile.TemporaryDirectory(prefix="bench-usd-") as temp:
        old = installed_layout(args.baseline, Path(temp) / "baseline")
        trees = {"this tree": None, args.baseline.name: old}
        for r in range(args.rounds):
            for who in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                out = Path(temp) / f"{who}-{r}"
                out.mkdir()
                env = dict(os.environ, **({"PYTHONPATH": str(trees[who])} if trees[who] else {}))
                # cwd: not the repository (``python -c`` puts it first on sys.path, before PYTHONPATH)
                child = subprocess.run([sys.executable, "-c", CHILD, str(args.frames), str(out)], env=env,
                                       cwd=temp, capture_output=True, text=True, check=True)
                times[who].append(json.loads(child.stdout))
                digests.setdefault(who, digest(out))
                loads.append(os.getloadavg()[0])
    print(f"{args.frames} frames x 9,409 vertices; median of {args.rounds} rounds, alternating; "
          f"load {min(loads):.1f}-{max(loads):.1f}\n")
    print("| tree | one file: wall s / CPU s | clips: wall s / CPU s |")
    print("|---|---:|---:|")
    for who, runs in times.items():
        cells = [f"{statistics.median(r[k][0] for r in runs):.2f} / {statistics.median(r[k][1] for r in runs):.2f}"
                 for k in ("one file", "clips")]
        print(f"| {who} | {' | '.join(cells)} |")
    print(f"\nfiles byte-identical: {len(set(digests.values())) == 1}")


if __name__ == "__main__":
    main()
