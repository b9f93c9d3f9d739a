"""Another actor's capture through ``mocaptk solve`` (issue #27, "Cross-actor"): the warning, the
estimated error against the measured one, and ``--adapt-neutral``.

    python benchmarks/bench_cross_actor.py OUT_DIR [--synth]

Pairs: blenderFace Subject_01 <-> Subject_02 (``../shared/data``; read at 25 Hz, units 187.6 as
docs/formats.md says) and, with ``--synth``, the bundled sample's actor against two ``mocaptk synth``
actors of other ICT-FaceKit identities (same markers, same seed). Held-out pairs (``--synth``; not
looked at while the estimate's rule was chosen): the sample against a third identity, and the
first synth actor's own session (its own layout) against the second actor's capture. Each session
gets its default layout (``mocaptk cluster``); the other actor's whole capture is solved from its
layout markers.
Measured error: RMSE over the capture's markers outside the layout, against the capture itself
(blenderFace: real markers) or its noise-free truth (synth).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data"))
#: Identities of the synth actors (ICT-FaceKit's 3 identity coefficients).
IDENTITIES = ("2,0,0", "0,-2,1.5")
#: A third identity, held out from the choice of the estimate's rule.
HELD_OUT_IDENTITY = "-1.5,1.5,-1"
SYNTH = ("--half", "--spacing", "8", "--rig", "cara", "--seed", "7", "--noise", "0.2", "--expressions", "5",
         "--rest", "1.5", "--hold", "2.0", "--performance", "20", "--dropout", "0.01", "--ghosts", "0.002",
         "--max-gap", "6", "--quiet", "--force")


def mocaptk(*args: object) -> None:
    done = subprocess.run([sys.executable, "-m", "mocaptk", *map(str, args)], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mocaptk {' '.join(map(str, args))}: {done.stderr.strip()}")


def measure(layout: Path, capture: Path, truth: np.ndarray | None, out: Path, *extra: str) -> dict:
    """Solve ``capture`` with ``layout``; measured vs estimated error."""
    from mocaptk.acquisition.formats import read_trajectories

    mocaptk("solve", layout, capture, "--out", out, "--force", "--quiet", "--formats", "npz", *extra)
    in_layout = set(json.loads(layout.read_text())["layout"])
    cap = read_trajectories(capture)
    dense = read_trajectories(out / "dense.c3d")
    other = [label for label in dense.labels if label not in in_layout and label in cap.labels]
    reference = cap.positions[:, cap.index(other)] if truth is None else truth[:, [cap.labels.index(m) for m in other]]
    err = np.linalg.norm(dense.positions[:, dense.index(other)] - reference, axis=2)
    summary = json.loads((out / "solve.json").read_text())
    return {"measured_mm": float(np.sqrt(np.nanmean(err ** 2))),
            "estimated_mm": summary["estimated_error_mm"]["mean"],
            "expected_mm": summary["expected_error_mm"]["mean"],
            "consistency_mm": summary["consistency_mm"]["mean"],
            "measured_at_stabilization_mm": summary["measured_error_mm"]["mean"],
            "neutral": summary["neutral"]}


def blenderface(out: Path) -> dict:
    folder = SHARED / "facial_mocap" / "blenderface"
    sessions = {}
    for k in ("01", "02"):
        c3d = out / f"S{k}.c3d"
        mocaptk("convert", folder / f"Subject_{k}.csv", c3d, "--rate", "25", "--units", "187.6", "--force", "-q")
        mocaptk("cluster", c3d, "--no-stabilize", "--out", out / f"S{k}_layout", "--formats", "none", "--force", "-q")
        sessions[k] = c3d
    rows = {}
    for a, b in (("01", "01"), ("01", "02"), ("02", "01")):
        layout = out / f"S{a}_layout" / "layout.json"
        rows[f"blenderFace S{a} -> S{b}"] = pair(layout, sessions[b], None, out / f"s{a}{b}")
    return rows


def synth_actors(out: Path) -> dict:
    from mocaptk.acquisition.synth_session import load_ground_truth

    rows = {}
    base = out / "sample"
    base.mkdir(parents=True, exist_ok=True)
    for name in ("dense_halfface.c3d", "dense_halfface_takes.json", "dense_halfface_regions.json"):
        (base / name).write_bytes((REPO / "sample_c3d" / name).read_bytes())
    mocaptk("cluster", base / "dense_halfface.c3d", "--out", base / "layout", "--formats", "none", "--force", "-q")
    actors = []
    for k, identity in enumerate(IDENTITIES + (HELD_OUT_IDENTITY,)):
        path = out / f"actor{k}.c3d"
        if not path.exists():
            mocaptk("synth", path, *SYNTH, f"--identity={identity}")
        actors.append((path.with_name(f"actor{k}_performance.c3d"),
                       load_ground_truth(path.with_name(f"actor{k}_performance_truth.npz")).positions))
        held_out = " (held out)" if identity == HELD_OUT_IDENTITY else ""
        rows[f"synth sample -> identity {identity}{held_out}"] = pair(base / "layout" / "layout.json",
                                                                     *actors[-1], out / f"id{k}")
    mocaptk("cluster", out / "actor0.c3d", "--out", out / "actor0_layout", "--formats", "none", "--force", "-q")
    rows[f"synth identity {IDENTITIES[0]} -> {IDENTITIES[1]} (held out)"] = pair(
        out / "actor0_layout" / "layout.json", *actors[1], out / "id01")
    return rows


def pair(layout: Path, capture: Path, truth: np.ndarray | None, out: Path) -> dict:
    """One session -> capture pair, plain and with ``--adapt-neutral``."""
    return {"plain": measure(layout, capture, truth, out),
            "adapted": measure(layout, capture, truth, out.with_name(out.name + "a"), "--adapt-neutral")}


def main(argv: list[str]) -> None:
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    rows = blenderface(out) if (SHARED / "facial_mocap").is_dir() else {}
    if "--synth" in argv:
        rows.update(synth_actors(out))
    (out / "cross_actor.json").write_text(json.dumps(rows, indent=2))
    for name, row in rows.items():
        p, a = row["plain"], row["adapted"]
        print(f"{name:52s} measured {p['measured_mm']:.2f} estimated {p['estimated_mm']:.2f} "
              f"({p['estimated_mm'] / p['measured_mm']:.2f}x; expected {p['expected_mm']:.2f}) warned "
              f"{p['neutral'].get('mismatch')} | adapted: measured {a['measured_mm']:.2f} estimated "
              f"{a['estimated_mm']:.2f} ({a['estimated_mm'] / a['measured_mm']:.2f}x)")


if __name__ == "__main__":
    main(sys.argv[1:])
