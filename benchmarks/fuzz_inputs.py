"""Structure-aware fuzzing of every non-marker input a user hands mocaptk, through the commands
that read them (``benchmarks/fuzz_readers.py`` covers the marker files byte by byte).

Kinds and the commands each case runs (in-process ``mocaptk.cli.main`` in an isolated worker):

- ``layout``: layout.json -> ``solve --model`` (38 of 40 cases), ``plan``, ``evaluate``;
- ``model``: model.npz (header and arrays) -> ``solve --model`` (solve's mesh: the marker
  surface, the default face on 1 case in 100: fitting it costs 5 CPU-s and reads no input);
- ``takes``: a takes JSON -> ``cluster --takes`` (3 of 4 cases), ``evaluate --takes``;
- ``regions_json``, ``regions_csv``: a regions file -> ``cluster --regions``;
- ``rig``: a camera rig JSON -> ``triangulate`` (17 of 20 cases), ``plan --rig`` (1 of 10),
  ``cluster --rig`` (1 of 20);
- ``sidecar``: a batch sidecar ``<stem>.mocaptk.json`` -> batch's per-session preparation
  (``session_argv``, ``input_files``), then the command it makes (every 20th case);
- ``session``: header values of a session (C3D parameters POINT:RATE/UNITS/SCALE/LABELS, TRC
  header fields) -> ``info``, and ``cluster`` every 5th case.

``cluster`` runs with ``--method paper`` except on every 20th case (the default hybrid method
costs 10x more CPU and reads the inputs the same way). Seeds are made by our own commands from the bundled sample (a layout, a model, a rig) and the
sample's own takes/regions files. A JSON case mutates one or more nodes of the parsed seed (a value
replaced by an interesting one: null, booleans, 0, -1, 1e308, 1e-300, NaN, a 5,000-digit integer,
a 5,000-character or control-character string, an empty or wrong-typed container, a deep nest), a
key removed, an item duplicated; or the text is cut. Each case must end in exit 0 or in one line
``mocaptk: error: ...`` (exit 2) of at most 300 characters that names a file; anything else is a
finding: a traceback (another exception), a Python warning, a crash, a hang (no answer within the
time bound), a longer or unnamed error line, a ``mocaptk: warning:`` / ``note:`` line over 300
characters.

Usage::

    python benchmarks/fuzz_inputs.py --cases 2000 --kinds layout,model --json fuzz_inputs.json
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_c3d"
KINDS = ("layout", "model", "takes", "regions_json", "regions_csv", "rig", "sidecar", "session")
MAX_LINE = 300

#: The worker runs one case per stdin line ({"argv", "cwd", "case", "sidecar"?}) and answers a line.
WORKER = r"""
import contextlib, io, json, os, resource, sys, traceback, warnings
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
from mocaptk.cli import main
from mocaptk.errors import MocaptkError
print(json.dumps({"ready": True}), flush=True)

def run(argv):
    err, out = io.StringIO(), io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stderr(err), \
            contextlib.redirect_stdout(out):
        warnings.simplefilter("always")
        try:
            main(argv)
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException as exc:
            code = "traceback"
            err.write("".join(traceback.format_exception(exc))[-2000:])
    leaks = [f"{w.category.__name__}: {w.message} ({os.path.basename(w.filename)}:{w.lineno})"
             for w in caught]
    return code, err.getvalue(), leaks

def sidecar(case):
    from pathlib import Path
    from mocaptk.batch.sessions import input_files, session_argv
    session = Path(case["session"])
    try:
        argv = session_argv(case["command"], session, Path(case["out"]), [])
        input_files(case["command"], argv, session)
    except MocaptkError as exc:
        return None, str(exc)
    return argv, None

for line in sys.stdin:
    case = json.loads(line)
    os.chdir(case["cwd"])
    if case.get("sidecar"):
        try:
            argv, error = sidecar(case)
        except BaseException as exc:
            print(json.dumps({"code": "traceback", "stderr": "".join(traceback.format_exception(exc))[-2000:],
                              "warnings": []}), flush=True)
            continue
        if argv is None:
            print(json.dumps({"code": 2, "stderr": f"mocaptk: error: {error}\n", "warnings": []}), flush=True)
            continue
        if not case["run"]:
            print(json.dumps({"code": 0, "stderr": "", "warnings": [], "prepared": True}), flush=True)
            continue
        case["argv"] = argv
    code, stderr, leaks = run(case["argv"])
    print(json.dumps({"code": code, "stderr": stderr[-4000:], "warnings": leaks}), flush=True)
"""


# -- seeds -------------------------------------------------------------------------------------------
def make_seeds(folder: Path) -> dict[str, Path]:
    """A small session, a capture, and our own commands' layout, model and rig (in ``folder``)."""
    from mocaptk.acquisition.cameras import cara_rig, save_rig
    from mocaptk.acquisition.formats import read_trajectories, write_trajectories
    from mocaptk.cli import main
    from mocaptk.trajectories import Trajectories

    full = read_trajectories(SAMPLE / "dense_halfface.c3d")
    step = 8  # 856 frames at 7.5 Hz: every take, fast to cluster
    session = Trajectories(full.positions[::step], full.labels, full.rate / step, 1, None, {"takes": []})
    write_trajectories(session, folder / "session.c3d")
    write_trajectories(session.frames(0, 200), folder / "session.trc")
    perf = read_trajectories(SAMPLE / "dense_halfface_performance.c3d")
    write_trajectories(perf.frames(0, 40), folder / "capture.c3d")
    takes = json.loads((SAMPLE / "dense_halfface_takes.json").read_text())
    for take in takes["takes"]:
        take["start"], take["end"] = take["start"] // step, -(-take["end"] // step)
    (folder / "takes.json").write_text(json.dumps(takes))
    shutil.copy(SAMPLE / "dense_halfface_regions.json", folder / "regions.json")
    regions = json.loads((folder / "regions.json").read_text())
    (folder / "regions.csv").write_text("label,region\n" + "".join(
        f"{label},{name}\n" for name, labels in regions.items() for label in labels))
    rig = cara_rig()
    save_rig(rig, folder / "rig.json")
    import numpy as np

    from mocaptk.acquisition.projection import project_points

    points = perf.positions[:20, ::4]  # 20 frames of 35 markers: triangulate reads the rig cheaply
    np.savez(folder / "obs.npz", points2d=np.stack([project_points(c, points)[0] for c in rig.cameras]),
             labels=np.array(perf.labels[::4]), rate=np.array(perf.rate), camera_names=np.array(rig.names))
    for argv in (["cluster", str(folder / "session.c3d"), "--formats", "none", "--out", str(folder / "lay"),
                  "-q", "--force"],
                 ["solve", str(folder / "lay" / "layout.json"), str(folder / "capture.c3d"), "--out",
                  str(folder / "solved"), "--formats", "npz", "-q", "--force"]):
        try:
            main(argv)
        except SystemExit as exc:
            assert not exc.code, argv
    (folder / "session.mocaptk.json").write_text(json.dumps(
        {"factor": 1.2, "step": 3, "regions": "regions.json", "takes": "takes.json", "mirror": True,
         "method": "paper", "rigid": ["FOREHEAD_BROW_01_C", "NOSE_02_C", "EYE_12_L"], "formats": "none"}))
    return {"session": folder / "session.c3d", "trc": folder / "session.trc", "capture": folder / "capture.c3d",
            "layout": folder / "lay" / "layout.json", "model": folder / "solved" / "model.npz",
            "takes": folder / "takes.json", "regions_json": folder / "regions.json",
            "regions_csv": folder / "regions.csv", "rig": folder / "rig.json", "obs": folder / "obs.npz",
            "sidecar": folder / "session.mocaptk.json"}


# -- mutations ---------------------------------------------------------------------------------------
class Raw(str):
    """JSON text to splice in as is (a 5,000-digit integer, 1e400, a deep nest)."""


def interesting(rng: random.Random, labels: list[str]) -> object:
    """A value that readers mishandle: wrong types, extremes, long or odd text, deep nests."""
    choices = [
        None, True, False, 0, -1, 1, 2, 3, 0.5, -0.0, 1e308, -1e308, 1e-300, 1e-45, 2 ** 63, -(2 ** 63),
        float("nan"), float("inf"), float("-inf"), Raw("1e400"), Raw("9" * 5000), "", " ", "x" * 5000,
        "A\tB", "A\nB", "\u0000", "é", "../../etc/passwd", "/dev/zero", "L", "R", "C", "mm", "paper",
        [], {}, [None], [1, 2], [1e308, 1e308, 0], [1e-300, 0, 0], [0, 0, 0], ["x"], [[1, 2, 3]],
        {"a": 1}, Raw("[" * 3000 + "]" * 3000), Raw("{\"a\":" * 200 + "1" + "}" * 200),
    ]
    if labels:
        choices += [rng.choice(labels), [rng.choice(labels)], labels[:3], [labels[0]] * 2]
    return rng.choice(choices)


def _nodes(value: object, path: tuple = ()) -> list[tuple]:
    """Paths of every node of a parsed JSON value."""
    out = [path]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _nodes(v, (*path, k))
    elif isinstance(value, list):
        for i, v in enumerate(value[:40]):  # long lists: their first items stand for the rest
            out += _nodes(v, (*path, i))
    return out


def _set(root: object, path: tuple, fn) -> object:
    if not path:
        return fn(root)
    parent = root
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = fn(parent[path[-1]])
    return root


def mutate_json(value: object, rng: random.Random, labels: list[str]) -> object:
    """1-3 structural mutations of a parsed JSON value (in place where possible)."""
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        nodes = _nodes(value)
        path = rng.choice(nodes[1:] or nodes)
        op = rng.random()
        if op < 0.6:
            value = _set(value, path, lambda _: interesting(rng, labels))
        elif op < 0.75 and path:  # delete
            parent = value
            for key in path[:-1]:
                parent = parent[key]
            del parent[path[-1]]
        elif op < 0.85:  # duplicate a list item / add a key
            def grow(node):
                if isinstance(node, list) and node:
                    node.append(json.loads(json.dumps(rng.choice(node))))
                elif isinstance(node, dict):
                    node[rng.choice(["extra", "", "x" * 300, "format"])] = interesting(rng, labels)
                return node
            value = _set(value, path, grow)
        else:  # a number scaled / negated, a string's type changed
            def twist(node):
                if isinstance(node, bool):
                    return not node
                if isinstance(node, (int, float)):
                    return rng.choice([node * 1e300, -node, node + 0.5, node * 1e-300, int(node) * 10 ** 20 + 1])
                if isinstance(node, str):
                    return rng.choice([node * 50, node.upper(), node + "\t", [node], len(node)])
                return node
            value = _set(value, path, twist)
    return value


def dump_json(value: object) -> str:
    """JSON text of ``value`` with :class:`Raw` parts spliced in (NaN / Infinity as Python writes them)."""
    raws: list[str] = []

    def swap(v):
        if isinstance(v, Raw):
            raws.append(str(v))
            return f"@@RAW{len(raws) - 1}@@"
        if isinstance(v, dict):
            return {k: swap(x) for k, x in v.items()}
        if isinstance(v, list):
            return [swap(x) for x in v]
        return v

    text = json.dumps(swap(value))
    for i, raw in enumerate(raws):
        text = text.replace(f'"@@RAW{i}@@"', raw)
    return text


def text_damage(data: bytes, rng: random.Random) -> bytes:
    """A byte-level fault: cut, flipped bytes, a NUL, a UTF-16 or Latin-1 re-save, a BOM."""
    op = rng.randrange(6)
    if op == 0:
        return data[: rng.randrange(len(data) + 1)]
    if op == 1:
        buf = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            if buf:
                buf[rng.randrange(len(buf))] = rng.randrange(256)
        return bytes(buf)
    if op == 2:
        return data.decode("utf-8", "replace").encode("utf-16")
    if op == 3:
        return b"\xef\xbb\xbf" + data
    if op == 4:
        return data.replace(b",", b";", rng.randint(1, 50))
    return data + b"\x00" * rng.randint(1, 4)


def mutate_csv(text: str, rng: random.Random, labels: list[str]) -> str:
    rows = [line.split(",") for line in text.splitlines()]
    for _ in range(rng.choice((1, 1, 2, 3))):
        i = rng.randrange(len(rows))
        op = rng.randrange(7)
        if op == 0 and rows[i]:
            rows[i][rng.randrange(len(rows[i]))] = str(interesting(rng, labels))[:250_000]
        elif op == 1:
            rows.insert(rng.randrange(len(rows)), list(rows[i]))
        elif op == 2:
            rows[i] = rows[i][:1]
        elif op == 3:
            rows[i] = rows[i] + ["extra"] * rng.randint(1, 3)
        elif op == 4:
            rows[i] = ['"' + rows[i][0], *rows[i][1:]]
        elif op == 5:
            rows[i] = ["x" * 200_000, "mouth"]
        else:
            del rows[i]
            if not rows:
                rows = [[""]]
    return "\n".join(",".join(r) for r in rows) + "\n"


def mutate_model(seed: Path, out: Path, rng: random.Random, labels: list[str]) -> None:
    """A model.npz with its header (JSON) or arrays changed: shapes, ranks, dtypes, values, removals."""
    import numpy as np

    with np.load(seed, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    with np.errstate(all="ignore"), warnings.catch_warnings():  # casts that lose values: wanted here
        warnings.simplefilter("ignore")
        data = _damaged_model(arrays, rng, labels)
    out.write_bytes(data)


def _damaged_model(arrays: dict, rng: random.Random, labels: list[str]) -> bytes:
    import io
    import zipfile

    import numpy as np

    op = rng.random()
    if op < 0.35:
        header = json.loads(bytes(arrays["header"]).decode())
        text = dump_json(mutate_json(header, rng, labels))
        arrays["header"] = np.frombuffer(text.encode(), dtype=np.uint8)
    elif op < 0.9:
        for _ in range(rng.choice((1, 1, 2))):
            name = rng.choice(sorted(arrays))
            a = arrays[name]
            change = rng.randrange(9)
            if change == 0:
                arrays[name] = np.asarray(rng.choice([0, 1.5, -1, 1e308, np.nan]))  # a scalar
            elif change == 1:
                arrays[name] = a.reshape(-1)[: max(0, a.size - rng.randint(1, 5))]
            elif change == 2:
                arrays[name] = a.T if a.ndim > 1 else a[None]
            elif change == 3:
                arrays[name] = a.astype(rng.choice(["U3", "bool", "complex128", "int8", "float16"]))
            elif change == 4 and a.size:
                b = np.array(a, dtype=np.float64 if a.dtype.kind == "f" else a.dtype)
                flat = b.reshape(-1)
                pick = rng.randrange(flat.size)
                value = rng.choice([np.nan, np.inf, -1, 1e308, 0, 10 ** 6]) if b.dtype.kind == "f" \
                    else rng.choice([-1, 10 ** 6, 0, 2 ** 31 - 1])
                flat[pick] = np.array(value).astype(b.dtype)  # wraps in a small integer type
                arrays[name] = b
            elif change == 5:
                del arrays[name]
            elif change == 6:
                arrays[name] = np.zeros((0,) + a.shape[1:], dtype=a.dtype)
            elif change == 7:
                arrays[name] = np.concatenate([a, a]) if a.ndim else a
            else:
                arrays[name] = np.zeros(a.shape, dtype=a.dtype)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, a in arrays.items():
            item = io.BytesIO()
            np.lib.format.write_array(item, np.asarray(a), allow_pickle=False)
            archive.writestr(f"{name}.npy", item.getvalue())
    data = buffer.getvalue()
    return text_damage(data, rng) if op >= 0.9 else data


def mutate_session(seeds: dict[str, Path], out_dir: Path, rng: random.Random, labels: list[str]) -> Path:
    """A session whose header values are changed: C3D parameters (by ezc3d) or TRC header fields."""
    if rng.random() < 0.5:
        lines = seeds["trc"].read_text().split("\n")
        head = lines[2].split("\t")
        names = lines[3].split("\t")
        for _ in range(rng.choice((1, 1, 2))):
            if rng.random() < 0.7:
                i = rng.randrange(len(head))
                head[i] = rng.choice(["0", "-1", "1e-45", "1e400", "nan", "inf", "1e308", "9" * 400, "",
                                      "mm", "furlong", "0.001", "100000000", "2.5", "x" * 5000, "\u00e9"])
            else:
                j = rng.randrange(2, len(names))
                names[j] = rng.choice(["", "A\tB", "x" * 5000, names[2], "é", "Frame#", "1"])
        lines[2], lines[3] = "\t".join(head), "\t".join(names)
        path = out_dir / "case.trc"
        path.write_text("\n".join(lines))
        return path
    import ezc3d
    import numpy as np

    c3d = ezc3d.c3d(str(seeds["session"]))
    for _ in range(rng.choice((1, 1, 2))):
        which = rng.randrange(5)
        if which == 0:
            c3d["parameters"]["POINT"]["RATE"]["value"] = np.array(
                [rng.choice([1e-45, 1e38, 1e7, 0.5, 1e-3, 2e-3])])  # ezc3d aborts the process on 0 / NaN (TRC has them)
        elif which == 1:
            c3d["parameters"]["POINT"]["UNITS"]["value"] = [rng.choice(["", "furlong", "m", "cm", "mm ", "x" * 200,
                                                                         "\t", "MM"])]
        elif which == 2:
            c3d["parameters"]["POINT"]["SCALE"]["value"] = np.array(
                [rng.choice([0.0, -1e38, 1e38, float("nan"), 1e-38, 1.0])])
        elif which == 3:
            names = list(c3d["parameters"]["POINT"]["LABELS"]["value"])
            i = rng.randrange(len(names))
            names[i] = rng.choice(["", "A\tB", names[(i + 1) % len(names)], "é" * 20, "x" * 200, " "])
            c3d["parameters"]["POINT"]["LABELS"]["value"] = names
        else:
            c3d["parameters"]["TRIAL"] = {"ACTUAL_START_FIELD": {"value": np.array(
                [rng.choice([0, 65535, 1]), rng.choice([0, 65535])], dtype=np.int64)}} \
                if rng.random() < 0.5 else c3d["parameters"].get("TRIAL", {})
    path = out_dir / "case.c3d"
    if not _write_in_child(c3d, path):  # ezc3d refuses (or aborts on) some values: patch a header word
        data = bytearray(seeds["session"].read_bytes())
        data[rng.randrange(0, 40)] = rng.randrange(256)
        path.write_bytes(bytes(data))
    return path


def _write_in_child(c3d, path: Path) -> bool:
    """``c3d.write(path)`` in a forked child: ezc3d aborts the whole process on some values (it
    stopped the harness once), so only the child dies."""
    pid = os.fork()
    if pid == 0:
        try:
            c3d.write(str(path))
            code = 0
        except BaseException:
            code = 1
        os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0 and path.exists()


# -- cases -------------------------------------------------------------------------------------------
def make_case(kind: str, seeds: dict[str, Path], labels: list[str], seed: int, i: int,
              case_dir: Path) -> dict:
    """Case ``i`` of ``kind``: its input file(s) in ``case_dir`` and the argv / task to run."""
    rng = random.Random(f"{seed}:{kind}:{i}")
    out = str(case_dir / "out")
    s, lay, cap, model = (str(seeds[k]) for k in ("session", "layout", "capture", "model"))
    case: dict = {"cwd": str(case_dir)}
    if kind in ("layout", "takes", "regions_json", "rig", "sidecar"):
        seed_value = json.loads(seeds[kind].read_text())
        if rng.random() < 0.85:
            data = dump_json(mutate_json(seed_value, rng, labels)).encode()
        else:
            data = text_damage(seeds[kind].read_bytes(), rng)
        name = {"sidecar": "session.mocaptk.json"}.get(kind, f"case{seeds[kind].suffix}")
        path = case_dir / name
        path.write_bytes(data)
    elif kind == "regions_csv":
        path = case_dir / "case.csv"
        text = seeds[kind].read_text()
        path.write_bytes(mutate_csv(text, rng, labels).encode() if rng.random() < 0.85
                         else text_damage(text.encode(), rng))
    elif kind == "model":
        path = case_dir / "case.npz"
        mutate_model(seeds["model"], path, rng, labels)
    else:
        path = mutate_session(seeds, case_dir, rng, labels)
    case["case"] = str(path)
    p = str(path)
    # the slow commands (plan, evaluate, cluster with costs) on a share of the cases only
    plan = ["plan", lay, "--session", cap, "--rig", "cara", "--out", out, "-q"]  # a 40-frame session
    evaluate = ["evaluate", s, "--layout", lay, "--seeds", "1", "--folds", "2", "--out", out + "/e.json", "-q"]
    # the paper's method (0.15 CPU-s) for most cluster runs; the default hybrid (1-2 CPU-s) on 1 in 20
    cluster = ["cluster", s, "--formats", "none", "--out", out, "-q", *(["--method", "paper"] if i % 20 else [])]
    # solve's mesh: the default face (5 CPU-s to fit) on 1 case in 100, the marker surface otherwise
    mesh = [] if i % 100 == 1 else ["--surface", "markers", "--subdivisions", "0"]
    if kind == "layout":
        case["argv"] = ({0: [*plan[:1], p, *plan[2:]], 20: [*evaluate[:3], p, *evaluate[4:]]}.get(i % 40)
                        or ["solve", p, cap, "--model", model, "--out", out, "--formats", "npz", "-q", *mesh])
    elif kind == "model":
        case["argv"] = ["solve", lay, cap, "--model", p, "--out", out, "--formats", "npz", "-q", *mesh]
    elif kind == "takes":
        case["argv"] = [*cluster, "--takes", p] if i % 4 else [*evaluate, "--takes", p]
    elif kind in ("regions_json", "regions_csv"):
        case["argv"] = [*cluster, "--regions", p]
    elif kind == "rig":
        triangulate = ["triangulate", p, str(seeds["obs"]), out + "/t.c3d", "-q"]
        case["argv"] = ([*cluster[:7], "--rig", p] if i % 20 == 0  # hybrid: weighs the rig
                        else [*plan[:5], p, *plan[6:]] if i % 10 == 1 else triangulate)
    elif kind == "sidecar":
        session = case_dir / "session.c3d"
        session.symlink_to(seeds["session"])
        for name in ("regions.json", "takes.json"):
            (case_dir / name).symlink_to(seeds["regions_json" if name == "regions.json" else "takes"])
        case.update(sidecar=True, session=str(session), out=out, command="cluster", run=i % 20 == 0)
    else:
        case["argv"] = ["info", p] if i % 5 else [*cluster[:1], p, *cluster[2:]]
    return case


def classify(answer: dict, case: dict) -> str:
    """``ok`` / ``error`` or a finding: traceback, warning, crash, hang, exit, multi_line,
    long_line, unnamed."""
    if answer.get("outcome") in ("hang", "crash"):
        return answer["outcome"]
    if answer["code"] == "traceback":
        return "traceback"
    if answer["warnings"]:
        return "warning"
    lines = [line for line in answer["stderr"].splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("mocaptk: error: ")]
    others = [line for line in lines if not line.startswith(("mocaptk: error: ", "mocaptk: warning: ",
                                                                  "mocaptk: note: "))]
    notes = [line.split(": ", 2)[2] for line in lines if line.startswith(("mocaptk: warning: ", "mocaptk: note: "))]
    if any(len(note) > MAX_LINE for note in notes):  # warnings are cut like errors
        return "long_line"
    if answer["code"] == 0:
        return "ok" if not others else "stray_output"
    if answer["code"] != 2 or len(errors) != 1 or others:
        return "exit"
    message = errors[0][len("mocaptk: error: "):]
    if len(message) > MAX_LINE:
        return "long_line"
    names = [case["case"], Path(case["case"]).name, "session.c3d", "capture.c3d", "layout.json", "model.npz",
             "obs.npz",
             str(Path(case["cwd"]) / "out"), "--",  # the case, another input, the output, or an option
             *(f"{Path(case['cwd'])}/" for _ in (0,))]  # a file a sidecar names (relative to its folder)
    return "error" if any(n in message for n in names) else "unnamed"


def _reader_worker():
    """``benchmarks/fuzz_readers.py``'s worker process (memory-limited, restarted on a crash or hang)."""
    import importlib.util

    if "fuzz_readers" not in sys.modules:  # its dataclasses look their module up by name
        spec = importlib.util.spec_from_file_location("fuzz_readers", Path(__file__).with_name("fuzz_readers.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules["fuzz_readers"] = module
        spec.loader.exec_module(module)
    return sys.modules["fuzz_readers"].Worker


class Worker(_reader_worker()):
    """A CLI subprocess running cases in-process (:data:`WORKER`)."""

    script = WORKER

    def run(self, case: dict, timeout: float) -> dict:
        return self.ask(json.dumps(case), timeout)


def run_kinds(kinds: list[str], seeds: dict[str, Path], labels: list[str], cases: int, *, seed: int,
              timeout: float, workers: int, memory_limit: int, start: int = 0, progress: bool = True,
              partial: Path | None = None) -> dict:
    """Run ``cases`` cases of each of ``kinds``, interleaved (case i of every kind, then i + 1: a
    stopped campaign has as many cases of each); returns the tally and findings per kind (also
    written to ``partial`` every 50 cases)."""
    from concurrent.futures import ThreadPoolExecutor

    order = [(i, kind) for i in range(start, start + cases) for kind in kinds]
    outcomes = {kind: Counter() for kind in kinds}
    findings: dict[str, list] = {kind: [] for kind in kinds}
    began, done = time.perf_counter(), [0]

    def summary() -> dict:
        return {kind: {"cases": sum(outcomes[kind].values()), "outcomes": dict(outcomes[kind]),
                       "findings": findings[kind][:40]} for kind in kinds} | {
            "seconds": round(time.perf_counter() - began, 1), "load": os.getloadavg()[0], "seed": seed}

    queue = iter(order)  # each worker takes the next case: the kinds stay even whatever each costs
    lock = threading.Lock()

    def next_case() -> tuple[int, str] | None:
        with lock:
            return next(queue, None)

    def share(w: int) -> None:
        worker = Worker(memory_limit)
        while (item := next_case()) is not None:
            i, kind = item
            case_dir = Path(tempfile.mkdtemp(prefix=f"fz_{kind}_{i}_"))
            try:
                case = make_case(kind, seeds, labels, seed, i, case_dir)
                answer = worker.run(case, timeout)
                outcome = classify(answer, case)
            finally:
                shutil.rmtree(case_dir, ignore_errors=True)
            outcomes[kind][outcome] += 1
            if outcome not in ("ok", "error"):
                findings[kind].append({"case": i, "outcome": outcome, "argv": case.get("argv"),
                                       "stderr": answer.get("stderr", "")[-1500:],
                                       "warnings": answer.get("warnings")})
            done[0] += 1
            if done[0] % 50 == 0:
                if progress:
                    print(f"  {done[0]} cases, {time.perf_counter() - began:.0f} s  "
                          + "  ".join(f"{k}={dict(v)}" for k, v in outcomes.items()), flush=True)
                if partial is not None:
                    partial.write_text(json.dumps(summary(), indent=1) + "\n")
        worker.close()

    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(share, range(workers)))
    return summary()


def print_merged(runs: list[dict]) -> None:
    """Cases and outcomes per kind, summed over ``runs`` (summaries of disjoint case ranges)."""
    for kind in KINDS:
        tally = Counter()
        for run in runs:
            tally.update(run.get(kind, {}).get("outcomes", {}))
        findings = [f for run in runs for f in run.get(kind, {}).get("findings", [])]
        print(f"{kind:13s} {sum(tally.values()):6d} cases  " + "  ".join(f"{k}={v}" for k, v in sorted(tally.items()))
              + "".join(f"\n    case {f['case']}: {f['outcome']} {(f['stderr'] or str(f['warnings']))[-160:]!r}"
                        for f in findings))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=2000, help="cases per kind")
    parser.add_argument("--kinds", default=",".join(KINDS))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--start", type=int, default=0, help="first case number (to resume)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per case before 'hang' (a loaded machine is slow)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--memory", type=int, default=6 << 30, help="address-space limit per worker (bytes)")
    parser.add_argument("--json", type=Path, help="write the summary here (every 50 cases and at the end)")
    parser.add_argument("--merge", type=Path, nargs="+", help="only add up the summaries of runs over "
                        "disjoint case ranges (--start/--cases) and print the table")
    args = parser.parse_args()
    if args.merge:
        print_merged([json.loads(path.read_text()) for path in args.merge])
        return
    seed_dir = Path(tempfile.mkdtemp(prefix="fz_seeds_"))
    seeds = make_seeds(seed_dir)
    from mocaptk.acquisition.formats import read_trajectories

    labels = list(read_trajectories(seeds["session"]).labels)
    kinds = args.kinds.split(",")
    result = run_kinds(kinds, seeds, labels, args.cases, seed=args.seed, timeout=args.timeout,
                       workers=args.workers, memory_limit=args.memory, start=args.start, partial=args.json)
    for kind in kinds:
        print(f"{kind:13s} {result[kind]['cases']:6d} cases  "
              + "  ".join(f"{k}={v}" for k, v in sorted(result[kind]["outcomes"].items())), flush=True)
        for finding in result[kind]["findings"][:8]:
            print("   ", json.dumps(finding)[:600], flush=True)
    print(f"{result['seconds']:.0f} s, load {result['load']:.1f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    shutil.rmtree(seed_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
