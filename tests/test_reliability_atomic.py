"""Atomic outputs: a run killed with SIGKILL while writing leaves the old file (or none), never a
truncated one; its temporary file is hidden (``.NAME.*.part``) and never has the output's name.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO

from mocaptk import Trajectories
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.atomic import atomic_open, atomic_path, write_text
from mocaptk.errors import OutputError

FRAMES = 40_000


@pytest.fixture(scope="module")
def big_session(tmp_path_factory) -> Path:
    """An .npz session whose text export is ~60 MB (~0.7 s to write on a fast machine: 8 MB
    was written between two polls of the killer)."""
    rng = np.random.default_rng(0)
    traj = Trajectories(rng.normal(0, 100, (FRAMES, 40, 3)), [f"M{i:02d}" for i in range(40)], 100.0)
    path = tmp_path_factory.mktemp("big") / "big.npz"
    np.savez(path, positions=traj.positions, labels=np.array(traj.labels), rate=traj.rate)
    return path


def kill_while_writing(argv: list[str], folder: Path, *, min_bytes: int = 1 << 18) -> None:
    """Start ``mocaptk ARGV`` and SIGKILL it once its temporary output holds ``min_bytes``."""
    proc = subprocess.Popen([sys.executable, "-m", "mocaptk", *argv], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    try:
        while time.monotonic() < deadline:
            parts = [p for p in folder.iterdir() if ".part" in p.name]
            if parts and parts[0].stat().st_size >= min_bytes:
                break
            if proc.poll() is not None:
                pytest.fail(f"finished before it could be killed: {proc.stderr.read().decode()[-300:]}")
            time.sleep(0.02)
        else:
            pytest.fail("no temporary output appeared")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL


@pytest.mark.parametrize("suffix", [".csv", ".trc"])
def test_convert_killed_mid_write_keeps_the_old_file(big_session, tmp_path, suffix):
    target = tmp_path / f"out{suffix}"
    target.write_bytes(b"the previous, complete output\n")
    kill_while_writing(["convert", str(big_session), str(target), "--force"], tmp_path)
    assert target.read_bytes() == b"the previous, complete output\n"
    leftovers = [p.name for p in tmp_path.iterdir() if p != target and p.name != f".{target.name}.lock"]
    assert leftovers and all(n.startswith(f".{target.name}.") and n.endswith(".part") for n in leftovers)


def test_convert_killed_mid_write_without_old_file_leaves_no_output(big_session, tmp_path, run_cli):
    target = tmp_path / "fresh.trc"
    kill_while_writing(["convert", str(big_session), str(target)], tmp_path)
    assert not target.exists()
    # the next run is not confused by the hidden leftover and writes a complete file
    done = run_cli("convert", big_session, target)
    assert done.exit_code == 0, done.stderr
    assert read_trajectories(target).positions.shape == (FRAMES, 40, 3)
    assert [p.name for p in tmp_path.iterdir()] == [target.name]  # and it removed the leftovers


def test_error_inside_a_write_leaves_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "data.txt"
    write_text(target, "old")
    with pytest.raises(RuntimeError), atomic_open(target, "w") as handle:
        handle.write("new, half written")
        raise RuntimeError("disk full, say")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["data.txt"]
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "fig.png") as tmp:
        tmp.write_bytes(b"\x89PNG partial")
        raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["data.txt"]


def test_existing_output_needs_force_and_folders_are_refused(tmp_path):
    target = tmp_path / "a.json"
    write_text(target, "{}")
    with pytest.raises(OutputError, match="already exists"):
        write_text(target, "[]", force=False)
    assert target.read_text() == "{}"
    with pytest.raises(OutputError, match="is a folder"):
        write_text(tmp_path, "x")
    blocked = tmp_path / "file"
    blocked.write_text("x")
    with pytest.raises(OutputError, match="cannot write"):
        write_text(blocked / "sub" / "out.txt", "x")  # parent is a file


def test_atomic_output_permissions_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        target = write_text(tmp_path / "x.txt", "x")
    finally:
        os.umask(old)
    assert os.stat(target).st_mode & 0o777 == 0o640


WRITING_METHODS = {"savefig", "savez", "savez_compressed", "save", "output", "write_text", "write_bytes",
                   "tofile", "to_csv", "screenshot", "export", "write"}
ATOMIC_CONTEXTS = {"atomic_open", "atomic_path", "staged_folder"}


def _stray_writes(path: Path) -> list[str]:
    """Calls that write files outside a ``with atomic_open/atomic_path/staged_folder`` block."""
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: list[str] = []

    def name_of(call: ast.expr) -> str:
        func = call.func if isinstance(call, ast.Call) else call
        return func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")

    def visit(node: ast.AST, inside: bool) -> None:
        if isinstance(node, (ast.With, ast.AsyncWith)):
            inside = inside or any(isinstance(item.context_expr, ast.Call)
                                   and name_of(item.context_expr) in ATOMIC_CONTEXTS for item in node.items)
        if isinstance(node, ast.Call) and not inside:
            name = name_of(node)
            mode = node.args[1] if name == "open" and len(node.args) > 1 else next(
                (k.value for k in node.keywords if k.arg == "mode"), None) if name == "open" else None
            writes_open = isinstance(mode, ast.Constant) and any(c in str(mode.value) for c in "wax+")
            names_target = bool(node.args) or any(k.arg in {"filename", "fname", "path", "file"}
                                                  for k in node.keywords)  # not screenshot(return_img=True)
            is_method = isinstance(node.func, ast.Attribute) and name in WRITING_METHODS and names_target
            receiver = node.func.value if isinstance(node.func, ast.Attribute) else None
            to_handle = isinstance(receiver, ast.Name) and receiver.id in {"handle", "os", "sys", "pipe", "stream"}
            if writes_open or (is_method and not to_handle and name != "write"):
                where = path.relative_to(REPO) if path.is_relative_to(REPO) else path.name
                found.append(f"{where}:{node.lineno}: {name}()")
        for child in ast.iter_child_nodes(node):
            visit(child, inside)

    visit(tree, False)
    return found


def test_no_output_bypasses_the_atomic_helpers():
    """Every file-writing call in the package sits inside an atomic block (or is mocaptk.atomic)."""
    sources = [p for folder in ("mocaptk", "acquisition", "clustering", "retarget")
               for p in sorted((REPO / folder).rglob("*.py")) if p.name != "atomic.py"]
    stray = [hit for path in sources for hit in _stray_writes(path)]
    assert not stray, stray


def test_the_stray_write_check_catches_direct_writes(tmp_path):
    sample = tmp_path / "module.py"
    sample.write_text("from pathlib import Path\nimport numpy as np\n"
                      "def f(p, fig, image):\n"
                      "    Path(p).write_text('x')\n    fig.savefig(p)\n    np.savez(p, a=1)\n"
                      "    with open(p, 'w') as h:\n        h.write('x')\n"
                      "    with atomic_path(p) as tmp:\n        fig.savefig(tmp)\n"
                      "    image = fig.screenshot(return_img=True)\n")
    assert [hit.split(": ")[1] for hit in _stray_writes(sample)] == \
        ["write_text()", "savefig()", "savez()", "open()"]
