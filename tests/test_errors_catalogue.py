"""Every entry of docs/errors.md, triggered through the CLI: exit code 2 and ONE line
``mocaptk: error: ...`` containing the documented message (and the file, for file errors).

The table below is the catalogue's test: one row per documented error (ids match docs/errors.md).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from clustering_synthetic import planted_session, save_session
from conftest import REPO

FUZZ = REPO / "tests" / "data" / "fuzz"

from mocaptk import Trajectories
from mocaptk.acquisition.formats import write_trajectories


@pytest.fixture(scope="module")
def f(tmp_path_factory) -> dict[str, Path]:
    """Valid inputs (session, takes, layout, cameras, observations) and broken variants."""
    from mocaptk.acquisition.cameras import cara_rig, save_rig
    from mocaptk.clustering.layout import write_layout
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session, load_session

    d = tmp_path_factory.mktemp("catalogue")
    traj, _ = planted_session(seed=2, per_group=3, frames=120)
    save_session(traj, d / "session.npz")
    session, source = load_session(str(d / "session.npz"))
    result = cluster_session(session, options=ClusterOptions(method="paper", stabilize=False, takes=traj.takes), source=source)
    write_layout(result.layout, d / "layout.json")
    rig = cara_rig()
    save_rig(rig, d / "cameras.json")
    small = Trajectories(np.arange(60.0).reshape(5, 4, 3), ["A", "B", "C", "D"], 100.0)
    for ext in ("c3d", "trc", "csv"):
        write_trajectories(small, d / f"good.{ext}")
    trc = (d / "good.trc").read_text().split("\n")
    w = {  # name -> content of a broken file
        "empty.trc": "", "binary.dat": "\x00\x01junk", "words.txt": "hello world\nthis is prose\n",
        "latin1.trc": None,
        "trc_header.trc": "\n".join(trc[:2]) + "\n",
        "trc_values.trc": "\n".join(trc[:2] + ["x\tx\t5\tfour\tmm"] + trc[3:]),
        "trc_units.trc": "\n".join(trc[:2] + [trc[2].replace("\tmm\t", "\tfurlong\t")] + trc[3:]),
        "trc_nodata.trc": "\n".join(trc[:5]) + "\n",
        "trc_dup.trc": "\n".join(trc[:3] + [trc[3].replace("\tB\t", "\tA\t")] + trc[4:]),
        "trc_cell.trc": "\n".join(trc[:6] + [trc[6].replace("\t0\t", "\tabc\t", 1)] + trc[7:]),
        "trc_order.trc": "\n".join(trc[:6] + [trc[7], trc[6]] + trc[8:]),
        "trc_frames.trc": "\n".join(trc[:-2] + ["1000000000" + trc[-2][1:], ""]),
        "csv_nocoords.csv": "Frame,Time,Speed\n1,0,3\n2,0.01,4\n",
        "csv_incomplete.csv": "Time,NOSE_x,NOSE_y\n0,1,2\n0.01,1,2\n",
        "csv_mixed.csv": "Time,A_x (mm),A_y (mm),A_z (mm),B_x (m),B_y (m),B_z (m)\n0,1,2,3,4,5,6\n0.01,1,2,3,4,5,6\n",
        "csv_dupcol.csv": "Time,A_x,A_y,A_z,A_x\n0,1,2,3,4\n0.01,1,2,3,4\n",
        "csv_norate.csv": "A_x,A_y,A_z\n1,2,3\n1,2,3\n",
        "csv_time.csv": "Time,A_x,A_y,A_z\n0,1,2,3\n0.01,1,2,3\n0.5,1,2,3\n",
        "csv_single.csv": "Time,A_x,A_y,A_z\n0,1,2,3\n",
        "csv_noframes.csv": "Time,A_x,A_y,A_z\n",
        "vicon_nosection.csv": "Devices\n100\n,,\n",
        "vicon_trunc.csv": "Trajectories\n100\n",
        "vicon_rate.csv": "Trajectories\nfast\n\n,,A,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1,2,3\n",
        "vicon_xyz.csv": "Trajectories\n100\n\n,,A,,\nFrame,Sub Frame,X,Y,Q\n,,mm,mm,mm\n1,0,1,2,3\n",
        "vicon_nodata.csv": "Trajectories\n100\n\n,,A,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n",
        "npz_bad.npz": None, "npz_lacks.npz": None,
        "bad.json": "{nope", "list.json": "[1, 2]",
        "regions_two.json": json.dumps({"nose": ["NOSE_01_C"], "mouth": ["NOSE_01_C"]}),
        "regions_unknown.json": json.dumps({"nose": ["NOT_A_MARKER"]}),
        "regions_empty.json": "{}",
        "regions_notlist.json": json.dumps({"nose": "NOSE_01_C"}),
        "regions_row.csv": "NOSE_01_C\n",
        "regions_nomarkers.json": json.dumps({"eye": []}),
        "takes_fraction.json": json.dumps({"takes": [{"name": "a", "start": 0.5, "end": 10}]}),
        "takes_outside.json": json.dumps({"takes": [{"name": "a", "start": 0, "end": 100000}]}),
        "takes_fields.json": json.dumps({"takes": [{"name": "a"}]}),
        "layout_other.json": json.dumps({"format": "something-else"}),
        "layout_version.json": None, "layout_malformed.json": None,
        "rig_other.json": json.dumps({"format": "nope"}),
        "landmarks_two.json": json.dumps({"A": 1, "B": 2}), "landmarks_neg.json": json.dumps({"A": -1}),
        "mesh.xyz": "1 2 3\n", "mesh_empty.obj": "# no faces\n",
    }
    for name, text in w.items():
        if text is not None:
            (d / name).write_text(text, encoding="utf-8")
    (d / "latin1.trc").write_bytes("\n".join(trc).replace("\tA\t", "\tÄ\t").encode("latin-1"))
    (d / "regions_latin1.csv").write_bytes("label,region\nNOSE_01_C,fr\u00e9nt\n".encode("latin-1"))
    body = np.array([[0, 0, 0], [0, 1200, 0], [200, 600, 0], [-200, 600, 0]], float)[None] + np.zeros((30, 1, 3))
    write_trajectories(Trajectories(body, ["LASI", "RKNE", "LANK", "RSHO"], 100.0), d / "body.trc")
    (d / "utf16.trc").write_bytes("\n".join(trc).encode("utf-16"))
    (d / "label_long.trc").write_text("\n".join(trc[:3] + [trc[3].replace("\tA\t", "\t" + "A" * 300 + "\t")]
                                                + trc[4:]))
    long = write_trajectories(Trajectories(np.ones((1000, 1, 3)), ["A"], 100.0), d / "long.trc")
    rows = long.read_text().split("\n")
    (d / "wide_row.trc").write_text("\n".join(rows[:9] + [rows[9] + "\t1" * 30_000] + rows[10:]))
    good = (d / "good.c3d").read_bytes()
    data_start = (int.from_bytes(good[16:18], "little") - 1) * 512
    (d / "cut.c3d").write_bytes(good[:data_start + 100])  # cut inside the point data
    (d / "params.c3d").write_bytes(good[:600])  # cut inside the parameter section
    (d / "npz_bad.npz").write_bytes(b"PK\x03\x04 not really a zip")
    np.savez(d / "npz_lacks.npz", positions=np.zeros((2, 1, 3)))
    doc = json.loads((d / "layout.json").read_text())
    (d / "layout_version.json").write_text(json.dumps({**doc, "version": 999}))
    (d / "layout_malformed.json").write_text(json.dumps({**doc, "clusters": 5}))
    np.savez(d / "obs_none.npz", other=np.zeros(3))
    for cam in ("cam0", "cam1"):  # two cameras of one blank photo each; a wand file of three
        (d / "cam_images" / cam).mkdir(parents=True)
        (d / "cam_images" / cam / "view_000.png").write_bytes(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    from mocaptk.acquisition.detections_file import pack, save_detections
    save_detections(pack([[(np.zeros((2, 2)), np.zeros(2, bool), np.ones(2))]] * 3, ["a", "b", "c"]),
                    d / "wand_3cams.npz", force=False)
    np.savez(d / "obs_shape.npz", points2d=np.zeros((len(rig.names), 2, 3)))
    np.savez(d / "obs_cams.npz", points2d=np.zeros((1, 2, 3, 2)))
    np.savez(d / "obs_names.npz", points2d=np.zeros((len(rig.names), 2, 3, 2)),
             camera_names=np.array([f"x{i}" for i in range(len(rig.names))]))
    np.savez(d / "obs_labels.npz", points2d=np.zeros((len(rig.names), 2, 3, 2)), labels=np.array(["a", "a", "b"]))
    np.savez(d / "obs_rate.npz", points2d=np.zeros((len(rig.names), 2, 3, 2)), rate=-1.0)
    (d / "cam_other.json").write_text(json.dumps({"format": "nope"}))
    # for label: a template without labels, 2 points a frame, the session in metres, another "face"
    write_trajectories(small.replace(labels=["*0", "*1", "*2", "*3"]), d / "unlabelled.c3d")
    write_trajectories(session.select(list(session.labels[:2])).replace(residuals=None), d / "two_points.c3d")
    write_trajectories(session.replace(positions=session.positions / 1000, residuals=None), d / "session_metres.c3d")
    rng = np.random.default_rng(0)
    cloud = rng.uniform(-18, 18, (1, session.n_markers, 3)) + rng.normal(0, 0.3, (60, session.n_markers, 3))
    write_trajectories(Trajectories(cloud, [f"*{k}" for k in range(session.n_markers)], 100.0), d / "other_face.c3d")
    cams = json.loads((d / "cameras.json").read_text())
    cams["cameras"][0]["image_size"] = "@@"
    (d / "cam_values.json").write_text(json.dumps(cams).replace('"@@"', "[1e400, 720]"))
    (d / "deep.json").write_text('{"takes": ' + "[" * 5000 + "]" * 5000 + "}")
    (d / "bigint.json").write_text('{"takes": ' + "9" * 5000 + "}")
    (d / "nul.json").write_bytes(b'{"takes": \x00\x01}')
    (d / "takes_short.json").write_text(json.dumps({"takes": [{"name": "t", "start": 0, "end": 1}]}))
    from mocaptk.clustering.reconstruction_models import MODEL_FORMAT

    identity = {"sha256": json.loads((d / "layout.json").read_text())["source"].get("sha256")}
    for name, header in (("model_version.npz", {"format": MODEL_FORMAT, "version": 999, "session": identity}),
                         ("model_malformed.npz", {"format": MODEL_FORMAT, "version": 1, "kind": "ridge",
                                                  "session": identity})):
        np.savez(d / name, header=np.frombuffer(json.dumps(header).encode(), np.uint8))
    (d / "existing.trc").write_text("keep")
    (d / "full").mkdir()
    (d / "full" / "keep.txt").write_text("keep")
    (d / "stem").mkdir()
    (d / "stem" / "keep.c3d").write_text("keep")  # same stem as full/keep.txt (batch refuses)
    (d / "afile").write_text("x")
    (d / "cmp").mkdir()
    (d / "cmp" / "compare.md").write_text("an earlier comparison")
    from mocaptk.clustering.reconstruction_models import fit_model, save_model

    save_model(fit_model(session.positions, [0, 1, 2], kind="ridge"), d / "other_model.npz",
               header={"session": {"sha256": "0" * 64}})
    return {p.name: p for p in d.iterdir()} | {"dir": d}


def S(f):  # the valid session
    return f["session.npz"]


# (id in docs/errors.md, argv builder, fragment of the message)  -- {file} is replaced by argv[1]
CATALOGUE = [
    # -- any input file
    ("E-FILE-MISSING", lambda f: ["info", f["dir"] / "missing.c3d"], "{file}: no such file"),
    ("E-FILE-FOLDER", lambda f: ["info", f["full"]], "is a folder, expected a file"),
    ("E-FILE-EMPTY", lambda f: ["info", f["empty.trc"]], "file is empty"),
    ("E-FILE-BINARY", lambda f: ["info", f["binary.dat"]], "binary content that is not C3D"),
    ("E-FILE-UNKNOWN", lambda f: ["info", f["words.txt"]], "unrecognised content"),
    ("E-TEXT-UTF8", lambda f: ["info", f["latin1.trc"]], "not UTF-8 text (bad byte at offset"),
    ("E-TEXT-UTF16", lambda f: ["info", f["utf16.trc"]], "not UTF-8 text (UTF-16: re-save or export it as UTF-8)"),
    ("E-C3D-TRUNC", lambda f: ["info", f["cut.c3d"]], "truncated C3D file"),
    ("E-C3D-PARAMS", lambda f: ["info", f["params.c3d"]], "bad parameter section"),
    ("E-C3D-UNITS-NUMBER", lambda f: ["info", FUZZ / "c3d_units_numeric.c3d"],
     "{file}: POINT:UNITS is a number (28013), not text such as 'mm'"),
    ("E-NPZ-UNREADABLE", lambda f: ["info", f["npz_bad.npz"]], "unreadable .npz archive"),
    ("E-NPZ-LACKS", lambda f: ["info", f["npz_lacks.npz"]], ".npz lacks labels, rate"),
    # -- TRC
    ("E-TRC-HEADER", lambda f: ["info", f["trc_header.trc"]], "truncated TRC header"),
    ("E-TRC-VALUES", lambda f: ["info", f["trc_values.trc"]], "bad TRC header values"),
    ("E-TRC-NODATA", lambda f: ["info", f["trc_nodata.trc"]], "TRC file has no data rows"),
    ("E-UNITS-FILE", lambda f: ["info", f["trc_units.trc"]], "unknown length units 'furlong'"),
    ("E-LABELS-DUP", lambda f: ["info", f["trc_dup.trc"]], "duplicate marker labels: A"),
    ("E-LABEL-LONG", lambda f: ["info", f["label_long.trc"]], "a marker label of 300 characters, more than 255"),
    ("E-TEXT-TABLE", lambda f: ["info", f["wide_row.trc"]], "columns, but the file holds only"),
    ("E-TEXT-CELL", lambda f: ["info", f["trc_cell.trc"]], "not a number: 'abc'"),
    ("E-FRAMES-ORDER", lambda f: ["info", f["trc_order.trc"]], "frame numbers are not strictly increasing"),
    ("E-FRAMES-SPAN", lambda f: ["info", f["trc_frames.trc"]], "frame numbers run from 0 to 1000000000"),
    # -- column CSV
    ("E-CSV-NOCOORDS", lambda f: ["info", f["csv_nocoords.csv"]], "no coordinate columns found"),
    ("E-CSV-INCOMPLETE", lambda f: ["info", f["csv_incomplete.csv"]], "marker 'NOSE' lacks one of its x/y/z"),
    ("E-CSV-MIXED", lambda f: ["info", f["csv_mixed.csv"]], "coordinate columns mix units: m, mm"),
    ("E-CSV-DUPCOL", lambda f: ["info", f["csv_dupcol.csv"]], "duplicate column 'A_x'"),
    ("E-CSV-NORATE", lambda f: ["info", f["csv_norate.csv"]], "no time column to derive the frame rate"),
    ("E-CSV-TIME", lambda f: ["info", f["csv_time.csv"]], "time column is not uniformly increasing"),
    ("E-CSV-ONETIME", lambda f: ["info", f["csv_single.csv"]], "from a single time value"),
    ("E-CSV-NODATA", lambda f: ["info", f["csv_noframes.csv"]], "no data rows"),
    # -- Vicon CSV
    ("E-VICON-SECTION", lambda f: ["info", f["vicon_nosection.csv"]], "Vicon CSV has no Trajectories section"),
    ("E-VICON-TRUNC", lambda f: ["info", f["vicon_trunc.csv"]], "Trajectories section is truncated"),
    ("E-VICON-RATE", lambda f: ["info", f["vicon_rate.csv"]], "expected the frame rate"),
    ("E-VICON-XYZ", lambda f: ["info", f["vicon_xyz.csv"]], "expected X,Y,Z columns"),
    ("E-VICON-NODATA", lambda f: ["info", f["vicon_nodata.csv"]], "Trajectories section has no data rows"),
    # -- reading options
    ("E-OPT-UNITS", lambda f: ["info", "--units", "furlong", f["good.trc"]], "unknown length units 'furlong'"),
    ("E-OPT-RATE", lambda f: ["info", "--rate", "-5", f["csv_norate.csv"]], "frame rate must be a positive number"),
    ("E-OPT-UNITS-DECLARED", lambda f: ["convert", f["good.c3d"], f["dir"] / "u.trc", "--units", "cm"],
     "--units applies to text files only; {file} is C3D, which declares its units (POINT:UNITS)"),
    ("E-OPT-RATE-DECLARED", lambda f: ["info", f["good.c3d"], "--rate", "50"],
     "--rate applies to column CSV files only; {file} is c3d (which stores its rate)"),
    # -- outputs
    ("E-OUT-EXISTS", lambda f: ["convert", f["good.trc"], f["existing.trc"]], "already exists (use --force"),
    ("E-OUT-EXT", lambda f: ["convert", f["good.trc"], f["dir"] / "out.xyz"], "unknown output extension '.xyz'"),
    ("E-OUT-CANNOT", lambda f: ["convert", f["good.trc"], f["afile"] / "x.trc", "--force"], "cannot write"),
    ("E-OUT-NOTEMPTY", lambda f: ["cluster", S(f), "--out", f["full"]], "folder exists and is not empty"),
    ("E-OUT-SWEEP-NOTEMPTY", lambda f: ["sweep", S(f), "--out", f["full"]], "folder exists and is not empty"),
    ("E-OPT-PARSE", lambda f: ["cluster", S(f), "--factor", "abc"], "Invalid value for '--factor'"),
    # -- clean
    ("E-CLEAN-RIGID", lambda f: ["clean", f["good.trc"], f["dir"] / "c.trc", "--no-stabilize", "--rigid", "A,B,C"],
     "--rigid needs --stabilize"),
    ("E-CLEAN-LOWPASS", lambda f: ["clean", f["good.trc"], f["dir"] / "c.trc", "--no-stabilize", "--lowpass", "80"],
     "low-pass cut-off must be between 0 and 50 Hz"),
    ("E-STAB-FEW", lambda f: ["clean", f["good.trc"], f["dir"] / "c.trc", "--rigid", "A,B"],
     "stabilization needs at least 3 distinct rigid markers"),
    ("E-RIGID-DETECT", lambda f: ["cluster", FUZZ / "face_in_metres_read_as_mm.trc", "--formats",
                                  "none", "--out", f["dir"] / "rd"],
     "{file}: cannot detect 3 rigid head markers (no third marker far from the first two); "
     "name them with --rigid A,B,C, or use --no-stabilize"),
    ("E-LABELS-UNKNOWN", lambda f: ["clean", f["good.trc"], f["dir"] / "c.trc", "--rigid", "A,B,Z"],
     "rigid markers not in the session: Z"),
    ("E-RIGID-NO-STABILIZE", lambda f: ["cluster", f["good.trc"], "--rigid", "A,B,Z", "--no-stabilize",
                                        "--out", f["dir"] / "rn"], "it cannot go with --no-stabilize"),
    # -- cluster / sweep / evaluate inputs and options
    ("E-CLU-FACTOR", lambda f: ["cluster", S(f), "--factor", "0", "--out", f["dir"] / "o1"], "--factor must be > 0"),
    ("E-CLU-STEP", lambda f: ["cluster", S(f), "--step", "0", "--out", f["dir"] / "o2"], "--step must be >= 1"),
    ("E-CLU-NODATA", lambda f: ["cluster", FUZZ / "cluster_no_data.trc", "--out", f["dir"] / "om"],
     "{file}: need at least 2 markers with data, the session has 0"),
    ("E-CLU-SAMPLES", lambda f: ["cluster", FUZZ / "cluster_short_take.csv", "--no-stabilize", "--out", f["dir"] / "on"],
     "{file}: region 'forehead_brow': only 1 frames sampled with --step 5; use a smaller step"),
    ("E-CLU-NOT-FACE", lambda f: ["cluster", f["body.trc"], "--out", f["dir"] / "oo"],
     "{file}: not a face capture: it spans 1.2 m (a face is 100-250 mm); 4 of its 4 labels name body"),
    ("E-CLU-STEP-BIG", lambda f: ["cluster", S(f), "--step", "100000", "--out", f["dir"] / "o3"],
     "is not smaller than the session's"),
    ("E-CLU-METHOD", lambda f: ["cluster", S(f), "--method", "magic", "--out", f["dir"] / "o4"], "unknown --method 'magic'"),
    ("E-CLU-FILL-GAPS", lambda f: ["cluster", S(f), S(f), "--fill-gaps", "--out", f["dir"] / "o4f"],
     "--fill-gaps takes one session"),
    ("E-CLU-MARKERS", lambda f: ["cluster", S(f), "--markers", "0", "--out", f["dir"] / "o4m"], "--markers must be >= 1"),
    ("E-CLU-MARKERS-REGIONS", lambda f: ["cluster", S(f), "--markers", "1", "--method", "paper", "--no-stabilize",
                                         "--formats", "none", "--out", f["dir"] / "o4r"], "fewer than the"),
    ("E-CLU-MARKERS-MANY", lambda f: ["cluster", S(f), "--markers", "9999", "--method", "paper", "--no-stabilize",
                                      "--formats", "none", "--out", f["dir"] / "o4n"], "cannot give 9999 markers"),
    ("E-CLU-INFLUENCES", lambda f: ["cluster", S(f), "--max-influences", "9", "--out", f["dir"] / "o5"],
     "--max-influences must be 1..8"),
    ("E-REGIONS-JSON", lambda f: ["cluster", S(f), "--regions", f["bad.json"], "--out", f["dir"] / "o6"], "invalid JSON"),
    ("E-REGIONS-TWO", lambda f: ["cluster", S(f), "--regions", f["regions_two.json"], "--out", f["dir"] / "o7"],
     "is in two regions"),
    ("E-REGIONS-UNKNOWN", lambda f: ["cluster", S(f), "--regions", f["regions_unknown.json"], "--out", f["dir"] / "o8"],
     "labels are not markers of the session"),
    ("E-REGIONS-EMPTY", lambda f: ["cluster", S(f), "--regions", f["regions_empty.json"], "--out", f["dir"] / "o9"],
     "no regions defined"),
    ("E-REGIONS-LIST", lambda f: ["cluster", S(f), "--regions", f["regions_notlist.json"], "--out", f["dir"] / "oa"],
     "must be a list of marker labels"),
    ("E-REGIONS-NOMARKERS", lambda f: ["cluster", S(f), "--regions", f["regions_nomarkers.json"],
                                       "--out", f["dir"] / "oj"], "region 'eye' lists no markers"),
    ("E-REGIONS-UTF8", lambda f: ["cluster", S(f), "--regions", f["regions_latin1.csv"], "--out", f["dir"] / "ok"],
     "not UTF-8 text (bad byte at offset"),
    ("E-TAKES-FRAME", lambda f: ["cluster", S(f), "--takes", f["takes_fraction.json"], "--out", f["dir"] / "ol"],
     "take 1 ('a'): start 0.5 is not a whole frame number"),
    ("E-REGIONS-ROW", lambda f: ["cluster", S(f), "--regions", f["regions_row.csv"], "--out", f["dir"] / "ob"],
     "expected 'label,region'"),
    ("E-REGIONS-MISSING", lambda f: ["cluster", S(f), "--regions", f["dir"] / "nope.json", "--out", f["dir"] / "oc"],
     "nope.json"),
    ("E-TAKES-SHAPE", lambda f: ["cluster", S(f), "--takes", f["list.json"], "--out", f["dir"] / "od"], 'expected {"takes"'),
    ("E-TAKES-FIELDS", lambda f: ["cluster", S(f), "--takes", f["takes_fields.json"], "--out", f["dir"] / "oe"],
     "needs name, start and end"),
    ("E-TAKES-OUTSIDE", lambda f: ["cluster", S(f), "--takes", f["takes_outside.json"], "--out", f["dir"] / "of"],
     "is outside the"),
    ("E-SWEEP-FACTORS", lambda f: ["sweep", S(f), "--factors", "a:b", "--out", f["dir"] / "og"],
     "--factors: expected START:STOP:STEP"),
    ("E-SWEEP-FACTORS-POS", lambda f: ["sweep", S(f), "--factors", "0,1", "--out", f["dir"] / "oh"],
     "--factors: factors must be finite and > 0"),
    ("E-SWEEP-FACTORS-MANY", lambda f: ["sweep", S(f), "--factors", "0.1:1e6:1e-7", "--out", f["dir"] / "oi"],
     "at most 500 per sweep"),
    ("E-LAYOUT-JSON", lambda f: ["evaluate", S(f), "--layout", f["bad.json"]], "invalid JSON"),
    ("E-LAYOUT-FORMAT", lambda f: ["evaluate", S(f), "--layout", f["layout_other.json"]], "not a mocaptk.layout file"),
    ("E-LAYOUT-VERSION", lambda f: ["evaluate", S(f), "--layout", f["layout_version.json"]], "unsupported layout version"),
    ("E-LAYOUT-MALFORMED", lambda f: ["evaluate", S(f), "--layout", f["layout_malformed.json"]], "malformed layout"),
    ("E-EVAL-MARKERS", lambda f: ["evaluate", f["good.trc"], "--layout", f["layout.json"], "--out", f["dir"] / "e.json"],
     "layout markers are not in good.trc"),
    ("E-EVAL-TEST", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--test", f["good.trc"],
                               "--out", f["dir"] / "e2.json"], "lacks"),
    ("E-EVAL-FOLDS", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--folds", "1",
                                "--out", f["dir"] / "e3.json"], "need at least 2 folds"),
    ("E-EVAL-SPLIT", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--split", "coin",
                                "--out", f["dir"] / "e4.json"], "unknown split 'coin'"),
    ("E-EVAL-RIDGE", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--ridge", "-1",
                                "--out", f["dir"] / "e5.json"], "ridge must be >= 0"),
    ("E-EVAL-SEEDS", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--seeds", "0",
                                "--out", f["dir"] / "e6.json"], "--seeds must be >= 1, got 0"),
    # -- rig
    ("E-RIG-INFLUENCES", lambda f: ["rig", f["layout.json"], "--session", S(f), "--max-influences", "0"],
     "--max-influences must be 1..8"),
    ("E-RIG-FALLOFF", lambda f: ["rig", f["layout.json"], "--session", S(f), "--falloff", "-1"], "--falloff must be >= 0"),
    ("E-RIG-SUBDIV", lambda f: ["rig", f["layout.json"], "--session", S(f), "--subdivisions", "7"],
     "--subdivisions must be 0..3"),
    ("E-RIG-FORMATS", lambda f: ["rig", f["layout.json"], "--session", S(f), "--formats", "obj"], "unknown rig format"),
    ("E-RIG-LANDMARKS-FEW", lambda f: ["rig", f["layout.json"], "--session", S(f), "--landmarks", f["landmarks_two.json"]],
     "need at least 3 marker/vertex pairs"),
    ("E-RIG-LANDMARKS-SHAPE", lambda f: ["rig", f["layout.json"], "--session", S(f), "--landmarks",
                                         f["landmarks_neg.json"]], 'expected {"marker label": vertex index'),
    ("E-RIG-LANDMARKS-JSON", lambda f: ["rig", f["layout.json"], "--session", S(f), "--landmarks", f["bad.json"]],
     "invalid JSON"),
    ("E-RIG-ANIMATE-MARKERS", lambda f: ["rig", f["layout.json"], "--session", S(f), "--animate",
                                         f["good.trc"], "--out", f["dir"] / "r0"],
     "layout markers"),
    ("E-MESH-MISSING", lambda f: ["rig", f["layout.json"], "--session", S(f), "--mesh", f["dir"] / "face.obj",
                                  "--out", f["dir"] / "r1"], "mesh file not found"),
    ("E-MESH-FORMAT", lambda f: ["rig", f["layout.json"], "--session", S(f), "--mesh", f["mesh.xyz"],
                                 "--out", f["dir"] / "r2"], "unsupported mesh format '.xyz'"),
    ("E-MESH-EMPTY", lambda f: ["rig", f["layout.json"], "--session", S(f), "--mesh", f["mesh_empty.obj"],
                                "--out", f["dir"] / "r3"], "the file holds no triangle mesh"),
    ("E-MESH-SPACE", lambda f: ["rig", f["layout.json"], "--session", S(f), "--keep-mesh-space",
                                "--out", f["dir"] / "r4"], "--keep-mesh-space needs --mesh"),
    # -- triangulate
    ("E-TRI-MINVIEWS", lambda f: ["triangulate", f["cameras.json"], f["obs_none.npz"], f["dir"] / "t.trc",
                                  "--min-views", "1"], "--min-views must be >= 2"),
    ("E-TRI-THRESHOLD", lambda f: ["triangulate", f["cameras.json"], f["obs_none.npz"], f["dir"] / "t.trc",
                                   "--threshold", "0"], "--threshold must be > 0 px"),
    ("E-CAM-FORMAT", lambda f: ["triangulate", f["cam_other.json"], f["obs_none.npz"], f["dir"] / "t.trc"],
     "not a camera rig"),
    ("E-CAM-UNREADABLE", lambda f: ["triangulate", f["words.txt"], f["obs_none.npz"], f["dir"] / "t.trc"],
     "not a camera rig JSON or Qualisys .qca.txt"),
    ("E-OBS-UNREADABLE", lambda f: ["triangulate", f["cameras.json"], f["words.txt"], f["dir"] / "t.trc"],
     "cannot read observations .npz"),
    ("E-OBS-NONE", lambda f: ["triangulate", f["cameras.json"], f["obs_none.npz"], f["dir"] / "t.trc"],
     "no 'points2d' array"),
    ("E-OBS-SHAPE", lambda f: ["triangulate", f["cameras.json"], f["obs_shape.npz"], f["dir"] / "t.trc"],
     "points2d must have shape (cameras, frames, markers, 2)"),
    ("E-OBS-CAMERAS", lambda f: ["triangulate", f["cameras.json"], f["obs_cams.npz"], f["dir"] / "t.trc"],
     "points2d has 1 cameras, the rig has"),
    ("E-OBS-NAMES", lambda f: ["triangulate", f["cameras.json"], f["obs_names.npz"], f["dir"] / "t.trc"],
     "do not match the rig's"),
    ("E-OBS-LABELS", lambda f: ["triangulate", f["cameras.json"], f["obs_labels.npz"], f["dir"] / "t.trc"],
     "labels must be 3 unique names"),
    ("E-OBS-RATE", lambda f: ["triangulate", f["cameras.json"], f["obs_rate.npz"], f["dir"] / "t.trc"],
     "rate must be > 0 Hz"),
    # -- synth
    ("E-SYN-RIG", lambda f: ["synth", f["dir"] / "s.c3d", "--rig", "drone"], "--rig must be one of"),
    ("E-SYN-HEAD", lambda f: ["synth", f["dir"] / "s.c3d", "--rig", "cara", "--head-motion"], "--head-motion needs"),
    ("E-SYN-TIMING", lambda f: ["synth", f["dir"] / "s.c3d", "--expressions", "0"], "--expressions must be"),
    ("E-SYN-NOISE", lambda f: ["synth", f["dir"] / "s.c3d", "--noise", "-1"], "--noise/--gaps/--max-gap must be"),
    ("E-SYN-IDENTITY", lambda f: ["synth", f["dir"] / "s.c3d", "--identity", "a,b"], "--identity must be"),
    # -- compare
    ("E-CMP-COUNTS", lambda f: ["compare", S(f), "--counts", "a,b", "--out", f["dir"] / "c1"],
     "--counts must be comma-separated whole numbers"),
    ("E-CMP-COUNTS-POS", lambda f: ["compare", S(f), "--counts", "0,5", "--out", f["dir"] / "c2"],
     "--counts must be positive whole numbers"),
    ("E-CMP-RESTARTS", lambda f: ["compare", S(f), "--restarts", "0", "--out", f["dir"] / "c3"],
     "--restarts must be >= 1"),
    ("E-OUT-COMPARE-EXISTS", lambda f: ["compare", S(f), "--out", f["cmp"], "--methods", "random"],
     "compare.md: already exists (use --force"),
    ("E-CMP-METHODS", lambda f: ["compare", S(f), "--methods", "magic", "--out", f["dir"] / "c4"], "unknown method(s) magic"),
    # -- batch (stops before any session runs; a session's own error goes in batch.json)
    ("E-BATCH-NOMATCH", lambda f: ["batch", f["dir"] / "none*.c3d", "--do", "info", "--out", f["dir"] / "b"],
     "no session file matches"),
    ("E-BATCH-DO", lambda f: ["batch", S(f), "--do", "dance", "--out", f["dir"] / "b"], "--do must be one of"),
    ("E-BATCH-OPTION", lambda f: ["batch", S(f), "--do", "cluster", "--wobble", "--out", f["dir"] / "b"],
     "mocaptk cluster has no option --wobble"),
    ("E-BATCH-CONTROLLED", lambda f: ["batch", S(f), "--do", "info", "--out", f["dir"] / "b", "--json"],
     "--json is set by batch for every session"),
    ("E-BATCH-VALUE", lambda f: ["batch", S(f), "--do", "cluster", "--factor", "abc", "--out", f["dir"] / "b"],
     "mocaptk cluster: Invalid value for '--factor'"),
    ("E-BATCH-STEM", lambda f: ["batch", f["full"] / "keep.txt", f["dir"] / "stem" / "keep.c3d",
                                "--do", "info", "--out", f["dir"] / "b"], "two sessions share the name 'keep'"),
    ("E-BATCH-WORKERS", lambda f: ["batch", S(f), "--do", "info", "--workers", "0", "--out", f["dir"] / "b"],
     "--workers must be >= 1"),
    ("E-BATCH-TIMEOUT", lambda f: ["batch", S(f), "--do", "info", "--timeout", "-1", "--out", f["dir"] / "b"],
     "--timeout must be >= 0"),
    ("E-BATCH-SCHEDULER", lambda f: ["batch", S(f), "--do", "info", "--scheduler", "tcp://127.0.0.1:9",
                                     "--connect-timeout", "1", "--out", f["dir"] / "b"],
     "--scheduler tcp://127.0.0.1:9: no Dask scheduler answered within 1 s"),
    # -- solve
    ("E-SOLVE-KIND", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s1", "--model-kind",
                                "spline"], "unknown --model-kind 'spline'"),
    ("E-SOLVE-LACKS", lambda f: ["solve", f["layout.json"], f["good.c3d"], "--out", f["dir"] / "s2"],
     "good.c3d: lacks"),
    ("E-SOLVE-NOT-SESSION", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s3", "--session",
                                       f["good.c3d"]], "is not the session layout.json was made from"),
    ("E-SOLVE-MODEL-FILE", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s4", "--model",
                                      f["binary.dat"]], "binary.dat: not a mocaptk model file"),
    ("E-MODEL-VERSION", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s6", "--model",
                                   f["model_version.npz"]], "model version 999 is not supported"),
    ("E-MODEL-MALFORMED", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s7", "--model",
                                     f["model_malformed.npz"]], "model_malformed.npz: malformed model file: no "),
    # -- any JSON input (takes, regions, layout, camera rig, sidecar, a model's header)
    ("E-JSON-DEEP", lambda f: ["cluster", S(f), "--takes", f["deep.json"], "--out", f["dir"] / "j1"],
     "deep.json: invalid JSON: nested deeper than 64 levels"),
    ("E-JSON-NUMBER", lambda f: ["cluster", S(f), "--takes", f["bigint.json"], "--out", f["dir"] / "j2"],
     "bigint.json: invalid JSON: a number too long"),
    ("E-JSON-BINARY", lambda f: ["cluster", S(f), "--takes", f["nul.json"], "--out", f["dir"] / "j3"],
     "nul.json: binary content (NUL bytes)"),
    ("E-EVAL-FOLDS-TAKES", lambda f: ["evaluate", S(f), "--layout", f["layout.json"], "--takes",
                                      f["takes_short.json"], "--folds", "2", "--out", f["dir"] / "e9.json"],
     "takes_short.json: too few frames"),
    ("E-CAM-VALUES", lambda f: ["triangulate", f["cam_values.json"], f["obs_none.npz"], f["dir"] / "t.trc"],
     "cam_values.json: malformed camera rig: camera 'cara_upper_left': image size must be 2 whole numbers"),
    # -- plan, label, retarget, reconstruct, detect, calibrate: their options checked before any work
    ("E-PLAN-NOISE", lambda f: ["plan", f["layout.json"], "--rig", "cara", "--noise", "-1", "--out",
                                f["dir"] / "p1"], "--noise must be >= 0 mm"),
    ("E-RETARGET-FORMATS", lambda f: ["retarget", f["layout.json"], S(f), "--character", "arkit", "--formats", "xyz", "--out",
                                      f["dir"] / "r1"], "unknown --formats xyz"),
    ("E-RECON-OPTIONS", lambda f: ["reconstruct", f["cameras.json"], f["obs_none.npz"], "--tolerance", "0",
                                   "--out", f["dir"] / "rc.c3d"], "--tolerance, --link and --rate must be > 0"),
    ("E-DETECT-AREA", lambda f: ["detect", f["dir"], "--min-area", "0", "--out", f["dir"] / "d.npz"],
     "--min-area must be >= 1"),
    ("E-CAL-CORNERS", lambda f: ["calibrate", f["dir"], "--corners", "abc", "--out", f["dir"] / "c.json"],
     "--corners must be COLSxROWS inner corners"),
    ("E-CAL-WAND-OPTIONS", lambda f: ["calibrate", f["dir"], "--wand", f["obs_none.npz"], "--out", f["dir"] / "c.json"],
     "--wand and --wand-length go together"),
    ("E-CAL-WAND-CAMERAS", lambda f: ["calibrate", f["cam_images"], "--board", "charuco", "--synced", "--wand",
                                      f["wand_3cams.npz"], "--wand-length", "400", "--out", f["dir"] / "c.json"],
     "wand_3cams.npz: 3 cameras, but 2 are calibrated"),
    ("E-SOLVE-MODEL-SESSION", lambda f: ["solve", f["layout.json"], S(f), "--out", f["dir"] / "s5", "--model",
                                         f["other_model.npz"]], "the model was trained on another session"),
    ("E-SOLVE-UNLABELLED", lambda f: ["solve", f["layout.json"], f["unlabelled.c3d"], "--out", f["dir"] / "s8"],
     "its points are unlabelled (*N): give --label"),
    # -- label
    ("E-LABEL-MODE", lambda f: ["label", S(f), "--template", S(f), "--out", f["dir"] / "l.c3d", "--mode", "x"],
     "--mode must be auto, fragments or clouds"),
    ("E-LABEL-FIX", lambda f: ["label", S(f), "--template", S(f), "--fix", "--out", f["dir"] / "l.c3d"],
     "--fix needs --check"),
    ("E-LABEL-TEMPLATE-UNLABELLED", lambda f: ["label", S(f), "--template", f["unlabelled.c3d"], "--out",
                                               f["dir"] / "l.c3d"], "unlabelled.c3d: the template has no marker labels"),
    ("E-LABEL-FEW-POINTS", lambda f: ["label", f["two_points.c3d"], "--template", S(f), "--out", f["dir"] / "l.c3d"],
     "{file}: fewer than 3 points in every frame"),
    ("E-LABEL-SPACING", lambda f: ["label", f["session_metres.c3d"], "--template", S(f), "--out",
                                   f["dir"] / "l.c3d"], "times as far apart as the template's markers"),
    ("E-LABEL-NO-MATCH", lambda f: ["label", f["other_face.c3d"], "--template", S(f), "--out", f["dir"] / "l.c3d"],
     "{file}: only 0.0% of its points match the template"),
    ("E-LABEL-CHECK-UNLABELLED", lambda f: ["label", f["unlabelled.c3d"], "--template", S(f), "--check"],
     "{file}: only 0 of its labels are template markers"),
]


@pytest.mark.parametrize("entry", CATALOGUE, ids=[e[0] for e in CATALOGUE])
def test_error_through_the_cli(run_cli, f, entry):
    _, build, fragment = entry
    argv = build(f)
    result = run_cli(*argv)
    assert result.exit_code == 2, result.stderr[-600:]
    lines = result.stderr.strip().splitlines()
    # one error line, last; anything before it is a one-line note/warning of the same command
    assert lines[-1].startswith("mocaptk: error: ") and "Traceback" not in result.stderr
    assert all(re.match(r"mocaptk: (note|warning): ", line) for line in lines[:-1]), result.stderr
    assert fragment.replace("{file}", str(argv[1])) in lines[-1], lines[-1]


def test_catalogue_document_lists_every_tested_error():
    doc = (REPO / "docs" / "errors.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"`(E-[A-Z0-9-]+)`", doc))
    tested = {e[0] for e in CATALOGUE}
    assert tested == documented, (sorted(tested - documented), sorted(documented - tested))


def test_out_of_memory_is_one_line(run_cli, tmp_path, monkeypatch):
    """A real MemoryError (numpy cannot allocate petabytes for 10^13 Hz of synthetic takes) ends as
    one line and exit code 2 from ``main``, not a traceback."""
    from conftest import shared_path

    monkeypatch.setenv("MOCAPTK_ICT_FACEKIT", str(shared_path("face_mesh", "ict_facekit",
                                                              "ict_facekit_FaceXModel_subset.tar.xz")))
    result = run_cli("synth", tmp_path / "s.c3d", "--rate", "1e13", "--performance", "0", "--rig", "none")
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr
    assert lines[0].startswith("mocaptk: error: out of memory while running 'mocaptk synth' (Unable to allocate")
    assert list(tmp_path.iterdir()) == []
