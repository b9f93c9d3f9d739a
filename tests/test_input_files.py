"""Every non-marker input a user hands mocaptk is checked where it is read (issue 33): layout.json,
model.npz, takes and regions files, camera rigs, batch sidecars and a session's header values.
A bad one is one ``InputFileError`` line naming the file, at most 300 characters; never a
traceback, a Python warning, a hang or a read of ``/dev/zero`` until memory runs out.
Each case is one the fuzz campaign (``benchmarks/fuzz_inputs.py``) or the first-hour run found."""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import SAMPLES

from mocaptk.acquisition.cameras import cara_rig, load_rig, save_rig
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.clustering.layout import read_layout
from mocaptk.clustering.reconstruction_models import fit_model, load_model, save_model
from mocaptk.clustering.regions import read_regions
from mocaptk.clustering.takes import read_takes
from mocaptk.errors import MAX_LINE, InputFileError, MocaptkError, OptionError
from mocaptk.jsonio import read_json
from mocaptk.trajectories import Trajectories

DEEP = "[" * 5000 + "]" * 5000
BIG_INT = '{"takes": ' + "9" * 5000 + "}"


def one_line(exc: MocaptkError, path: Path) -> str:
    text = str(exc)
    assert "\n" not in text and len(text) <= MAX_LINE and str(path) in text, text
    return text


@pytest.fixture(scope="module")
def session() -> Trajectories:
    return read_trajectories(SAMPLES / "dense_halfface.c3d")


@pytest.fixture(scope="module")
def layout_doc() -> dict:
    """A minimal valid layout.json of the sample's markers."""
    return {"format": "mocaptk.layout", "version": 1, "units": "mm",
            "source": {"path": "dense_halfface.c3d"}, "parameters": {"factor": 1.1, "stabilized": False},
            "regions": [{"name": "mouth", "markers": ["MOUTH_01_L"], "mean_correlation": 0.5,
                         "threshold": 0.6, "samples": 10}],
            "clusters": [{"representative": "MOUTH_01_L", "region": "mouth", "members": ["MOUTH_01_L"],
                          "member_correlation": {"MOUTH_01_L": 3.0}, "position": [1.0, 2.0, 3.0],
                          "side": "L", "mirrored_from": None}]}


@pytest.mark.parametrize("text, problem", [(DEEP, "nested deeper than 64 levels"),
                                           (BIG_INT, "a number too long")])
@pytest.mark.parametrize("reader", ["json", "takes", "layout", "regions", "rig"])
def test_deep_json_and_huge_integers_are_one_line(tmp_path, text, problem, reader):
    path = tmp_path / "input.json"
    path.write_text('{"a": ' + DEEP + "}" if reader in ("regions", "rig") and text == DEEP else text)
    read = {"json": read_json, "takes": lambda p: read_takes(p, 100), "layout": read_layout,
            "regions": lambda p: read_regions(p, ["A"]), "rig": load_rig}[reader]
    with pytest.raises(InputFileError) as info:
        read(path)
    assert problem in one_line(info.value, path)


def test_model_header_deep_or_huge_is_one_line(tmp_path):
    path = tmp_path / "model.npz"
    for text in (DEEP, BIG_INT):
        write_npz(path, {"header": np.frombuffer(text.encode(), np.uint8)})
        with pytest.raises(InputFileError) as info:
            load_model(path)
        one_line(info.value, path)


def test_dev_zero_is_refused_at_once_not_read_until_memory_runs_out():
    start = time.monotonic()
    with pytest.raises(InputFileError, match="/dev/zero: binary content"):
        read_takes("/dev/zero", 100)
    assert time.monotonic() - start < 5  # one block read, not gigabytes


def test_oversized_json_is_refused_before_it_is_parsed(tmp_path):
    path = tmp_path / "big.json"
    path.write_text('{"takes": [' + " " * 3000 + "]}")
    with pytest.raises(InputFileError, match="more than 0 MB"):
        read_json(path, limit=1000)


def test_regions_csv_with_a_200_kb_cell_is_one_short_line(tmp_path, session):
    path = tmp_path / "regions.csv"
    path.write_text("label,region\n" + "X" * 200_000 + ",mouth\n")
    with pytest.raises(InputFileError) as info:
        read_regions(path, session.labels)
    assert "not markers of the session" in one_line(info.value, path)
    path.write_text("label,region\n" + "X" * 200_000 + "\n")  # one cell: the row is quoted, cut
    with pytest.raises(InputFileError) as info:
        read_regions(path, session.labels)
    assert "row 1: expected 'label,region'" in one_line(info.value, path)


def write_layout_doc(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("change, problem", [
    (lambda d: d.update(sagittal_plane={"point": [0, 0, 0], "normal": [1e-300, 0, 0]}), "sagittal_plane.normal"),
    (lambda d: d.update(sagittal_plane={"point": [0, 0, 0], "normal": [1e308, 1e308, 0]}), "sagittal_plane.normal"),
    (lambda d: d.update(sagittal_plane={"point": [1e300, 0, 0], "normal": [1, 0, 0]}), "sagittal_plane.point"),
    (lambda d: d["source"].update(path="x" * 5000), "source.path is too long"),
    (lambda d: d["source"].update(path=["a"]), "source.path must be a file name"),
    (lambda d: d["parameters"].update(stabilized="yes"), "parameters.stabilized must be true or false"),
    (lambda d: d["parameters"].update(factor=None), None),  # null: not recorded, accepted
])
def test_layout_fields_that_crashed_later_commands_are_checked(tmp_path, layout_doc, change, problem):
    doc = json.loads(json.dumps(layout_doc))
    change(doc)
    path = write_layout_doc(tmp_path / "layout.json", doc)
    if problem is None:
        read_layout(path)
        return
    with pytest.raises(InputFileError) as info:
        read_layout(path)
    assert problem in one_line(info.value, path)


def test_stabilized_layout_without_a_stabilization_record_has_no_rigid_set(tmp_path, layout_doc):
    from mocaptk.clustering.layout import layout_rigid_set

    doc = json.loads(json.dumps(layout_doc))
    doc["parameters"]["stabilized"] = True
    doc["stabilization"] = None
    assert layout_rigid_set(read_layout(write_layout_doc(tmp_path / "layout.json", doc))) is None


# -- model.npz -------------------------------------------------------------------------------------
def write_npz(path: Path, arrays: dict) -> Path:
    np.savez(path, **arrays)  # path ends in .npz: kept as given
    return path


@pytest.fixture(scope="module")
def model_parts(session, tmp_path_factory) -> tuple[dict, dict]:
    """(arrays, header) of a real tapered-ridge model of the sample (12 layout markers)."""
    layout = np.arange(0, session.n_markers, 12)
    model = fit_model(session.positions[::20], layout, kind="tapered-ridge")
    path = save_model(model, tmp_path_factory.mktemp("model") / "model.npz", header={
        "session": {"path": "dense_halfface.c3d"}, "labels": list(session.labels),
        "layout_labels": [session.labels[i] for i in model.layout], "rigid_labels": [], "rigid_reference": None})
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    return arrays, json.loads(bytes(arrays.pop("header")).decode())


@pytest.mark.parametrize("change, problem", [
    (lambda a, h: ["not", "a", "dict"], "not a mocaptk model file"),
    (lambda a, h: a.update(neutral=np.array(1.0)), "neutral has shape ()"),
    (lambda a, h: a.update(error_drop=np.array(0.5)), "error_drop has shape ()"),
    (lambda a, h: a.update(layout=a["layout"][:, None]), "layout has shape"),
    (lambda a, h: a.update(cov=a["cov"][:-1]), "cov has shape"),
    (lambda a, h: a.update(taper_mm=np.array(0.0)), "taper_mm has values out of range"),
    (lambda a, h: a.update(layout=a["layout"] + 10_000), "layout must hold indices"),
    (lambda a, h: a.update(mean=a["mean"].astype("U3")), "mean must hold numbers"),
    (lambda a, h: a.pop("cov"), "no cov array"),
    (lambda a, h: h["layout_labels"].__setitem__(0, None), "header layout_labels must be a list of marker labels"),
    (lambda a, h: h.update(kind="cubic"), "unknown model kind 'cubic'"),
    (lambda a, h: h.update(rigid_labels=["NOPE"]), "rigid_labels must be among its labels"),
])
def test_damaged_model_files_name_the_file_and_the_array(tmp_path, model_parts, change, problem):
    arrays = {k: v.copy() for k, v in model_parts[0].items()}
    header = json.loads(json.dumps(model_parts[1]))
    changed = change(arrays, header)
    header = changed if isinstance(changed, list) else header
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # e.g. taper_mm 0 divided by zero before
        with pytest.raises(InputFileError) as info:
            load_model(path, labelled=True)
    assert problem in one_line(info.value, path)


def test_the_real_model_still_loads(tmp_path, model_parts):
    arrays, header = model_parts
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)})
    model, loaded = load_model(path, labelled=True)
    assert model.kind == "tapered-ridge" and loaded["labels"] == header["labels"]


# -- camera rig, session header values, sidecars -----------------------------------------------------
@pytest.mark.parametrize("key, value, problem", [
    ("image_size", "[1e400, 720]", "image size must be 2 whole numbers"),
    ("image_size", "[0.5, 720]", "image size must be 2 whole numbers"),
    ("tvec", "[1e300, 0, 0]", "tvec or matrix beyond"),
    ("rvec", "[1, 2]", "rvec must have shape (3,)"),
])
def test_camera_rig_values_that_overflowed_are_refused(tmp_path, key, value, problem):
    path = save_rig(cara_rig(), tmp_path / "rig.json")
    doc = json.loads(path.read_text())
    doc["cameras"][0][key] = "@@"
    path.write_text(json.dumps(doc).replace('"@@"', value))
    with pytest.raises(InputFileError) as info:
        load_rig(path)
    assert problem in one_line(info.value, path)


@pytest.mark.parametrize("rate", [1e-45, 1e300])
def test_absurd_session_rates_are_refused(rate):
    with pytest.raises(MocaptkError, match="frame rate .* is outside"):
        Trajectories(np.zeros((2, 1, 3)), ["A"], rate)


def test_control_characters_in_labels_become_spaces():
    traj = Trajectories(np.zeros((2, 2, 3)), ["A\tB", "C\nD"], 100.0)
    assert traj.labels == ("A B", "C D")


def test_sidecar_value_error_names_the_sidecar(tmp_path):
    from mocaptk.batch.sessions import session_argv

    session = tmp_path / "s.c3d"
    session.write_bytes(b"")
    sidecar = tmp_path / "s.mocaptk.json"
    for doc, problem in (({"step": "abc"}, "--step"), ({"regions": "a\u0000b"}, "must not be empty or hold a NUL"),
                         ({"factor": {"a": 1}}, "must be a text, a number or a list")):
        sidecar.write_text(json.dumps(doc))
        with pytest.raises(InputFileError) as info:
            session_argv("cluster", session, tmp_path / "o", [])
        assert problem in one_line(info.value, sidecar)


def test_long_messages_are_cut_in_the_middle_keeping_where_and_what():
    exc = InputFileError("/data/" + "d" * 5000 + "/take.json", "row 3: " + "x" * 200_000 + " is not a number")
    text = str(exc)
    assert len(text) <= MAX_LINE and text.startswith("/data/ddd") and text.endswith("is not a number")
    assert len(str(OptionError("y" * 10_000))) == MAX_LINE


def test_takes_too_short_for_the_folds_name_the_takes_file(run_cli, tmp_path):
    """evaluate's "too few frames (N) for 2 folds" came from the takes file without naming it."""
    session = SAMPLES / "dense_halfface.c3d"
    layout = tmp_path / "layout.json"
    doc = {"format": "mocaptk.layout", "version": 1, "units": "mm", "source": {"path": session.name},
           "parameters": {}, "regions": [],
           "clusters": [{"representative": "MOUTH_01_L", "region": "mouth", "members": ["MOUTH_01_L"],
                         "member_correlation": {}, "position": [0, 0, 0], "side": "L"}]}
    layout.write_text(json.dumps(doc))
    takes = tmp_path / "takes.json"
    takes.write_text(json.dumps({"takes": [{"name": "t", "start": 0, "end": 1}]}))
    result = run_cli("evaluate", session, "--layout", layout, "--takes", takes, "--folds", "2",
                     "--out", tmp_path / "e.json")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"mocaptk: error: {takes}: too few frames"), lines[0]


def test_layout_members_the_model_does_not_know_name_the_layout(tmp_path, layout_doc):
    from mocaptk.clustering.layout import check_members

    doc = json.loads(json.dumps(layout_doc))
    doc["clusters"][0]["members"] += ["paper", "EYE_99_R"]
    layout = read_layout(write_layout_doc(tmp_path / "layout.json", doc))
    with pytest.raises(InputFileError) as info:
        check_members(layout, ["MOUTH_01_L", "EYE_99_L"], layout_path=tmp_path / "layout.json",
                      session_name="s.c3d")
    assert "1 layout members are not markers of s.c3d" in one_line(info.value, tmp_path / "layout.json")
    assert "paper" in str(info.value) and "EYE_99_R" not in str(info.value)  # a mirror twin is known


@pytest.mark.parametrize("change, problem", [
    (lambda a: a.update(neutral=np.zeros_like(a["neutral"])), "neutral positions give no marker surface"),
    (lambda a: a.update(error_base=np.array(1e308)), "error_base has values out of range"),
])
def test_model_values_that_crashed_solve_are_refused(tmp_path, model_parts, change, problem):
    arrays = {k: v.copy() for k, v in model_parts[0].items()}
    change(arrays)
    header = np.frombuffer(json.dumps(model_parts[1]).encode(), np.uint8)
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": header})
    with pytest.raises(InputFileError) as info:
        load_model(path, labelled=True)
    assert problem in one_line(info.value, path)


def test_read_trajectories_takes_units_as_a_number_as_documented(tmp_path):
    """docs/formats.md: "a number = millimetres per file unit"; from Python a float raised AttributeError."""
    path = tmp_path / "faces.csv"
    path.write_text("A_x,A_y,A_z\n1,2,3\n2,3,4\n")
    traj = read_trajectories(path, rate=25, units=187.6)
    assert traj.rate == 25 and np.allclose(traj.positions[0, 0], [187.6, 375.2, 562.8])
    with pytest.raises(OptionError, match="unknown length units True"):
        read_trajectories(path, rate=25, units=True)


def test_plug_in_gait_model_outputs_are_not_read_as_markers():
    """POINT:ANGLES / FORCES / MOMENTS / POWERS share the POINT block but are degrees, newtons...:
    they were read as markers in mm; now left out and counted (info shows the note)."""
    from conftest import shared_path

    path = shared_path("c3d", "btkdata", "PiG", "PiG_Calibration-FlatFoot-Full.c3d")
    traj = read_trajectories(path)
    assert traj.n_markers == 137 - 26 and traj.metadata["model_outputs"] == {"ANGLES": 26}
    assert not any(label.endswith("Angles") for label in traj.labels)
    assert any("26 model outputs are not markers" in note for note in traj.metadata["notes"])


def test_small_float_types_in_a_model_are_checked_without_warnings(tmp_path, model_parts):
    arrays = {k: v.copy() for k, v in model_parts[0].items()}
    arrays["cov"] = arrays["cov"].astype(np.float16)
    header = np.frombuffer(json.dumps(model_parts[1]).encode(), np.uint8)
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": header})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            load_model(path, labelled=True)
        except InputFileError as exc:
            one_line(exc, path)


def test_rigid_labels_not_in_the_session_name_the_option(run_cli, tmp_path):
    """A sidecar's "rigid" reaches cluster as --rigid: the error said only "rigid markers not in
    the session" (the campaign's one unnamed sidecar error)."""
    result = run_cli("cluster", SAMPLES / "dense_halfface.c3d", "--rigid", "R,X,NOSE_02_C", "--formats", "none",
                     "--out", tmp_path / "out")
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 2 and lines == ["mocaptk: error: --rigid: 2 labels are not markers of "
                                               "dense_halfface.c3d: R, X"], result.stderr
    assert not (tmp_path / "out").exists()


def test_sidecar_path_too_long_for_the_system_is_an_error_not_a_traceback(tmp_path):
    from mocaptk.batch.sessions import input_files, session_argv

    session = tmp_path / "s.c3d"
    session.write_bytes(b"")
    (tmp_path / "s.mocaptk.json").write_text(json.dumps({"regions": "regions.json" * 50}))
    argv = session_argv("cluster", session, tmp_path / "o", [])
    assert input_files("cluster", argv, session) == [session, tmp_path / "s.mocaptk.json"]


def test_regions_with_a_line_break_in_a_name_are_refused(tmp_path, session):
    path = tmp_path / "regions.json"
    for odd in ("\x1d", "\u2028", "\t", "\n"):  # a name str.splitlines() splits: messages broke
        path.write_text(json.dumps({f"mouth{odd}and more": ["MOUTH_01_L"]}))
        with pytest.raises(InputFileError) as info:
            read_regions(path, session.labels)
        assert "holds a control character or a line break" in one_line(info.value, path)


@pytest.mark.parametrize("args, message", [
    (["--formats", "json,forehead_brow_01_c"], "--formats: unknown rig format(s) forehead_brow_01_c"),
    (["--rigid", "A,B"], "--rigid: stabilization needs at least 3 distinct rigid markers, got 2"),
])
def test_cluster_options_a_sidecar_can_set_are_named_before_any_work(run_cli, tmp_path, args, message):
    result = run_cli("cluster", SAMPLES / "dense_halfface.c3d", *args, "--out", tmp_path / "out")
    assert result.exit_code == 2 and result.stderr == f"mocaptk: error: {message}" + result.stderr[
        len(f"mocaptk: error: {message}"):] and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert message in result.stderr and not (tmp_path / "out").exists()


def test_layout_representatives_unknown_to_the_session_name_the_layout(tmp_path, layout_doc):
    from mocaptk.clustering.layout import check_members

    doc = json.loads(json.dumps(layout_doc))
    doc["clusters"][0]["representative"] = "mm"  # a campaign case: solve's report raised KeyError
    layout = read_layout(write_layout_doc(tmp_path / "layout.json", doc))
    with pytest.raises(InputFileError, match="not markers of s.c3d .*: mm"):
        check_members(layout, ["MOUTH_01_L"], layout_path=tmp_path / "layout.json", session_name="s.c3d")


def test_camera_names_with_a_tab_are_read_as_spaces(tmp_path):
    """plan.png drew a camera named "A\\tB" with matplotlib's "Glyph 9 missing" warning."""
    path = save_rig(cara_rig(), tmp_path / "rig.json")
    doc = json.loads(path.read_text())
    doc["cameras"][0]["name"] = "cam\tone"
    path.write_text(json.dumps(doc))
    assert load_rig(path).cameras[0].name == "cam one"


def test_rig_names_with_a_tab_are_read_as_spaces(tmp_path):
    """Fuzz seed 5: a rig named "cara\t" drew plan.png's title with "Glyph 9 missing"."""
    path = save_rig(cara_rig(), tmp_path / "rig.json")
    doc = json.loads(path.read_text())
    doc["name"] = "cara\t"
    path.write_text(json.dumps(doc))
    assert load_rig(path).name == "cara"


@pytest.fixture(scope="module")
def solver_parts(session, tmp_path_factory) -> tuple[dict, dict]:
    """(arrays, header) of a real solve model file (ridge-cv, 12 layout markers, 3 rigid markers)."""
    from types import SimpleNamespace

    from mocaptk.retarget.solve import train_solver

    short = Trajectories(session.positions[::20], session.labels, session.rate / 20, 1, None, {"takes": []})
    labels = [session.labels[i] for i in range(0, session.n_markers, 12)]
    solver = train_solver(SimpleNamespace(labels=labels), short, {"path": "dense_halfface.c3d"},
                          rigid_labels=labels[:3])
    path = save_model(solver.model, tmp_path_factory.mktemp("solver") / "model.npz", header=solver.header(),
                      extra=solver.extra_arrays())
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    return arrays, json.loads(bytes(arrays.pop("header")).decode())


@pytest.mark.parametrize("change, problem", [
    (lambda a, h: a.update(cov=np.zeros((0, 3))), "cov has shape (0, 3)"),  # ridge-cv was not checked
    (lambda a, h: a.update(cv_ridges=np.array(1.0)), "cv_ridges must be a list of numbers"),
    (lambda a, h: a.update(solver_rigid_reference=np.zeros((0, 3))), "solver_rigid_reference must be (3, 3)"),
    (lambda a, h: a.update(solver_cov=a["solver_cov"].astype(np.complex128)), "solver_cov must be"),
    (lambda a, h: a.update(solver_mean=a["solver_mean"] * np.inf), "solver_mean has values out of range"),
    (lambda a, h: a.update(solver_training_consistency=np.zeros(2)), "solver_training_consistency must be ()"),
    (lambda a, h: h.update(fallback_labels=[["x"]]), "fallback_labels must be among its layout_labels"),
    (lambda a, h: a.update(solver_mean=np.full(a["solver_mean"].shape, np.inf, np.float16)), "solver_mean has values"),
    (lambda a, h: a.update(solver_cov=np.zeros_like(a["solver_cov"])), "solver_cov is not a covariance"),  # seed 6
    (lambda a, h: a.update(solver_rigid_reference=np.zeros((3, 3))), "coincide or lie on one line"),  # seeds 5, 6
])
def test_solve_model_arrays_that_crashed_solve_are_refused(tmp_path, solver_parts, change, problem):
    """Fuzz findings (seed 4): IndexError in the ridge-cv pattern solve and in the head poses,
    ComplexWarning in the layout Gaussian."""
    from mocaptk.retarget.solve import load_solver

    arrays = {k: v.copy() for k, v in solver_parts[0].items()}
    header = json.loads(json.dumps(solver_parts[1]))
    change(arrays, header)
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputFileError) as info:
            load_solver(path)
    assert problem in one_line(info.value, path)


def test_the_real_solve_model_still_loads(tmp_path, solver_parts):
    from mocaptk.retarget.solve import load_solver

    arrays, header = solver_parts
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(json.dumps(header).encode(), np.uint8)})
    solver = load_solver(path)
    assert solver.model.kind == "ridge-cv" and len(solver.rigid_labels) == 3 and solver.gaussian is not None


def test_float16_model_arrays_are_read_as_float64(tmp_path, solver_parts):
    """Fuzz seed 5: a float16 cov reached np.linalg.solve (TypeError: float16 is unsupported)."""
    from mocaptk.retarget.solve import load_solver

    arrays = {k: v.astype(np.float16) if k in ("cov", "mean") else v for k, v in solver_parts[0].items()}
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(
        json.dumps(solver_parts[1]).encode(), np.uint8)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            solver = load_solver(path)
        except InputFileError as exc:  # float16 rounding may make the cov out of range: one line is fine
            one_line(exc, path)
        else:
            assert solver.model.cov.dtype == np.float64


def test_warning_lines_are_cut_like_error_lines(run_cli, tmp_path):
    """A 5,000-character region name was quoted whole in cluster's warnings (lines of > 4,000
    characters); warnings keep the 300-character bound of error lines."""
    regions = {"x" * 5000: ["NOSE_02_C"], "rest": [label for label in read_trajectories(
        SAMPLES / "dense_halfface.c3d").labels if label != "NOSE_02_C"]}
    (tmp_path / "regions.json").write_text(json.dumps(regions))
    done = run_cli("cluster", SAMPLES / "dense_halfface.c3d", "--regions", tmp_path / "regions.json", "--method",
                   "paper", "--formats", "none", "--step", "20", "--out", tmp_path / "out", "-q")
    warnings_ = [line for line in done.stderr.splitlines() if line.startswith("mocaptk: warning: ")]
    assert done.exit_code == 0 and warnings_, done.stderr[-500:]
    assert all(len(line) <= len("mocaptk: warning: ") + MAX_LINE for line in warnings_)
    assert any("has only 1 marker" in line for line in warnings_)
    summary = (tmp_path / "out" / "summary.txt").read_text().splitlines()
    assert all(len(line) <= len("warning: ") + MAX_LINE for line in summary if line.startswith("warning: "))


def test_integer_model_arrays_are_read_as_numbers(tmp_path, solver_parts):
    """Fuzz seed 6: an int8 cov reached the in-place ridge (UFuncOutputCastingError traceback)."""
    from mocaptk.retarget.solve import load_solver

    arrays = {k: (np.clip(v, -100, 100).astype(np.int8) if k == "cov" else v) for k, v in solver_parts[0].items()}
    path = write_npz(tmp_path / "model.npz", {**arrays, "header": np.frombuffer(
        json.dumps(solver_parts[1]).encode(), np.uint8)})
    solver = load_solver(path)
    assert solver.model.cov.dtype == np.float64 and solver.model.layout.dtype.kind in "iu"
    assert np.isfinite(solver.model.predict_positions(solver.model.neutral[solver.model.layout][None])).all()
