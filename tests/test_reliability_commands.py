"""Every command on one small session: inputs never modified, outputs never overwritten without
``--force``, re-runs byte-identical, and layout/rig files identical across ``PYTHONHASHSEED``.

One module-scoped pipeline (planted session -> info, convert, clean, cluster (+rig), evaluate,
sweep, rig, triangulate); each step hashes every input file before and after it runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from clustering_synthetic import planted_session, save_session
from conftest import REPO


def digest(paths: list[Path]) -> dict[str, str]:
    """sha256 of each file (a folder: of each file inside it, sorted)."""
    out = {}
    for path in paths:
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for file in files:
            out[str(file)] = hashlib.sha256(file.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """The input files: planted session (.npz), its takes, a camera rig and 2-D observations."""
    from mocaptk.acquisition.cameras import cara_rig, save_rig
    from mocaptk.acquisition.projection import project_markers

    folder = tmp_path_factory.mktemp("inputs")
    traj, _ = planted_session(seed=5, per_group=3, frames=240)
    session, takes = save_session(traj, folder / "session.npz")
    rig = cara_rig()
    save_rig(rig, folder / "cameras.json")
    # the planted cloud, moved in front of the head-mounted cameras (+Z forward, ~10 cm away)
    points = traj.positions[:6] - np.nanmean(traj.positions[0], axis=0) + [0.0, 0.0, 100.0]
    obs = project_markers(rig, points, pixel_noise=0.2, rng=1)
    np.savez(folder / "obs.npz", points2d=obs, labels=np.array(traj.labels), rate=traj.rate,
             camera_names=np.array(rig.names))
    for path in folder.iterdir():
        path.chmod(0o444)  # a command that tried to write an input would fail loudly, too
    return {"session": session, "takes": takes, "cameras": folder / "cameras.json",
            "obs": folder / "obs.npz"}


def command_table(inp: dict[str, Path], out: Path) -> list[tuple[str, list, list[Path], list[Path]]]:
    """(name, argv without --force, input paths, output paths) for every command."""
    s, t = inp["session"], inp["takes"]
    return [
        ("convert", ["convert", s, out / "conv.c3d"], [s], [out / "conv.c3d"]),
        ("convert-trc", ["convert", s, out / "conv.trc"], [s], [out / "conv.trc"]),
        ("convert-csv", ["convert", s, out / "conv.csv"], [s], [out / "conv.csv"]),
        ("clean", ["clean", out / "conv.c3d", out / "clean.csv", "--no-stabilize", "--lowpass", "20",
                   "--report", out / "clean.json"], [out / "conv.c3d"], [out / "clean.csv", out / "clean.json"]),
        ("cluster", ["cluster", s, "--takes", t, "--no-stabilize", "--out", out / "L", "--quiet",
                     "--formats", "none"], [s, t], [out / "L"]),
        ("evaluate", ["evaluate", s, "--layout", out / "L" / "layout.json", "--takes", t, "--seeds", "2",
                      "--folds", "3", "--out", out / "eval.json", "--quiet"],
         [s, t, out / "L" / "layout.json"], [out / "eval.json"]),
        ("sweep", ["sweep", s, "--factors", "1.0,1.2", "--takes", t, "--no-stabilize", "--folds", "3",
                   "--out", out / "S", "--quiet"], [s, t], [out / "S"]),
        ("rig", ["rig", out / "L" / "layout.json", "--session", s, "--out", out / "R", "--formats",
                 "json,fbx,glb", "--subdivisions", "0", "--quiet"], [s, out / "L" / "layout.json"], [out / "R"]),
        ("triangulate", ["triangulate", inp["cameras"], inp["obs"], out / "tri.trc", "--quiet"],
         [inp["cameras"], inp["obs"]], [out / "tri.trc"]),
    ]


@pytest.fixture(scope="module")
def pipeline(inputs, tmp_path_factory):
    """Run every command once (in order); returns the table and each run's result."""
    from mocaptk.cli import main

    out = tmp_path_factory.mktemp("out")
    table = command_table(inputs, out)
    results = {}
    for name, argv, ins, outs in table:
        before = digest(ins)
        try:
            main([os.fspath(a) for a in argv])
            code = 0
        except SystemExit as exc:
            code = exc.code
        results[name] = (code, before, digest(ins), digest(outs))
    return table, results


def test_every_command_succeeds_and_leaves_its_inputs_untouched(pipeline):
    table, results = pipeline
    for name, _, ins, outs in table:
        code, before, after, written = results[name]
        assert code in (0, None), name
        assert before == after, f"{name} modified an input"
        assert written, f"{name} wrote nothing"
    assert (table[4][3][0] / "layout.json").is_file()
    assert {"rig.json", "rig.fbx", "rig.glb"} <= {p.name for p in table[7][3][0].iterdir()}


def test_no_output_is_overwritten_without_force_and_reruns_are_identical(pipeline, run_cli):
    table, results = pipeline
    for name, argv, ins, outs in table:
        written = results[name][3]
        refused = run_cli(*argv)
        assert refused.exit_code == 2, (name, refused.stderr)
        lines = refused.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mocaptk: error:") and "--force" in lines[0], name
        assert digest(outs) == written, f"{name} touched its outputs without --force"
    # with --force: same bytes again (everything but pictures/PDF, whose renderers we do not own)
    for name, argv, ins, outs in table:
        if name in ("cluster", "rig"):
            continue  # re-run across processes below
        again = run_cli(*argv, "--force")
        assert again.exit_code == 0, (name, again.stderr)
        assert digest(outs) == results[name][3], f"{name} is not deterministic"
        assert digest(ins) == results[name][1]
    hidden = [p for _, _, _, outs in table for o in outs for p in
              (o.parent.iterdir() if o.parent.is_dir() else []) if p.name.endswith((".part", ".part.c3d"))]
    assert not hidden, f"temporary files left behind: {hidden}"


#: Runs ``mocaptk`` commands one after the other in one interpreter (one start-up for both).
RUN_COMMANDS = """
import json, sys
from mocaptk.cli import main
for argv in json.loads(sys.argv[1]):
    try:
        main(argv)
    except SystemExit as exc:
        if exc.code:
            raise
"""


def test_layout_and_rig_bytes_identical_across_processes_and_hash_seeds(pipeline, tmp_path):
    """cluster + rig again in a fresh interpreter with another PYTHONHASHSEED: same bytes."""
    table, _ = pipeline
    runs = []
    for index, folder in ((4, tmp_path / "L"), (7, tmp_path / "R")):
        argv = [os.fspath(a) for a in table[index][1]]
        argv[argv.index("--out") + 1] = os.fspath(folder)
        runs.append(argv)
    runs[1][1] = os.fspath(tmp_path / "L" / "layout.json")
    env = {**os.environ, "PYTHONHASHSEED": "4242"}
    done = subprocess.run([sys.executable, "-c", RUN_COMMANDS, json.dumps(runs)], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    for index, folder, names in ((4, tmp_path / "L", ("layout.json",)),
                                 (7, tmp_path / "R", ("rig.json", "rig.fbx", "rig.glb"))):
        reference = table[index][3][0]
        for name in names:
            assert (folder / name).read_bytes() == (reference / name).read_bytes(), \
                f"{name} differs in another process (PYTHONHASHSEED=4242)"


def test_synth_refuses_existing_outputs_before_working(run_cli, tmp_path):
    target = tmp_path / "s.c3d"
    target.write_bytes(b"old")
    result = run_cli("synth", target, "--rig", "none", "--quiet")
    assert result.exit_code == 2 and "--force" in result.stderr and result.stderr.count("\n") == 1
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.c3d"]
