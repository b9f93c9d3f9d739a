"""C3D reading over every public C3D file in ../shared/data/c3d, against independent expectations:
the peer reader matrix (ezc3d 1.7.2 / py-c3d), py-c3d's point values, ezc3d's values vs our own
numpy reader, and equality across processor/storage variants of the same c3d.org sample."""

from __future__ import annotations

import csv
import functools
import warnings

import numpy as np
import pytest
from conftest import SHARED_DATA, shared_path

from mocaptk.acquisition import c3d_raw
from mocaptk.acquisition.c3d_read import UNIT_SCALES, read_c3d
from mocaptk.errors import InputFileError

C3D_DIR = SHARED_DATA / "c3d"
FILES = sorted(p.relative_to(C3D_DIR).as_posix() for p in C3D_DIR.rglob("*")
               if p.suffix.lower() == ".c3d") if C3D_DIR.is_dir() else ["<shared data absent>"]
#: Files neither peer reads; each must give this one-line problem.
UNREADABLE = {
    "btkdata/others/Empty.c3d": "empty file (0 bytes)",
    "btkdata/others/badParameterOffset.c3d": "bad parameter section",
    "btkdata/others/mocap36.c3d": "bad parameter section",
    "btkdata/c3d.org/sample18/bad_parameter_section.c3d": "bad parameter section",
}
#: Peers report 0 points (analog / rotation only): mocaptk refuses "zero markers" clearly.
NO_POINTS = {"btkdata/others/1123x01EMG.c3d", "ezc3d-testFiles/C3DRotationExample.c3d",
             "ezc3d-testFiles/Kistler.c3d"}
#: Point data without POINT parameters: peers see 0 points; the header declares 40 points of
#: 701 frames at 30 Hz (float), which fill the data section exactly.
HEADER_ONLY = {"btkdata/c3d.org/sample20/phasespace_sample.c3d": (40, 701, 30.0)}
#: Neither peer reads it (ezc3d: MIPS unsupported; py-c3d: header scale != POINT:SCALE).
MAC_SAMPLE = "btkdata/c3d.org/sample06/MACsample.c3d"
UNICODE_COPY = "btkdata/others/Я могу есть стекло/оно мне не вредит.c3d"  # byte copy of shd01


def _load_matrix() -> dict[str, dict[str, str]]:
    path = C3D_DIR / "peer_reader_matrix.tsv"
    if not path.is_file():
        return {}
    with open(path, encoding="utf-8") as handle:
        return {row["file"]: row for row in csv.DictReader(handle, delimiter="\t")}


MATRIX = _load_matrix()
ABSENT = ["<shared data absent>"]
PY_C3D_READS = [f for f in FILES if MATRIX.get(f, {}).get("py-c3d") == "OK"] or ABSENT
EZC3D_READS = [f for f in FILES if MATRIX.get(f, {}).get("ezc3d") == "OK"
               and f not in NO_POINTS] or ABSENT


def matrix() -> dict[str, dict[str, str]]:
    shared_path("c3d", "peer_reader_matrix.tsv")
    return MATRIX


@functools.cache
def read(rel: str):
    """read_c3d result or the InputFileError (each file is read once per session)."""
    try:
        return read_c3d(shared_path("c3d", rel))
    except InputFileError as exc:
        return exc


@functools.cache
def py_c3d(rel: str) -> tuple[np.ndarray, float, int, np.ndarray] | None:
    """(points (F, N, 3) file units NaN-masked, rate, n_points, residuals (F, N) NaN-masked)
    from py-c3d, or None."""
    import c3d

    try:
        with warnings.catch_warnings(), open(shared_path("c3d", rel), "rb") as handle:
            warnings.simplefilter("ignore")
            reader = c3d.Reader(handle)
            frames = [points.copy() for _, points, _ in reader.read_frames()]
            rate, used = float(reader.point_rate), int(reader.point_used)
    except Exception:  # py-c3d fails with many exception types
        return None
    points = np.array(frames).reshape(len(frames), used, 5)
    xyz = points[..., :3].astype(np.float64)
    xyz[points[..., 3] < 0] = np.nan
    residuals = np.where(points[..., 3] < 0, np.nan, points[..., 3])
    return xyz, rate, used, residuals


def peers_read(rel: str) -> bool:
    row = matrix().get(rel, {})
    return row.get("ezc3d") == "OK" or row.get("py-c3d") == "OK"


def mm_per_unit(traj) -> float:
    return UNIT_SCALES.get(traj.metadata["original_units"].strip().lower(), 1.0)


@pytest.mark.parametrize("rel", FILES)
def test_reads_every_file_a_peer_reads_and_refuses_the_rest(rel):
    shared_path("c3d", rel)
    key = "btkdata/others/shd01.c3d" if rel == UNICODE_COPY else rel
    result = read(rel)
    if key in UNREADABLE:
        assert not peers_read(key)
        assert isinstance(result, InputFileError)
        assert str(result) == f"{shared_path('c3d', rel)}: {result.problem}"
        assert "\n" not in str(result) and result.problem.startswith(UNREADABLE[key])
        return
    if key in NO_POINTS:
        assert isinstance(result, InputFileError) and "no 3-D marker data" in result.problem
        return
    assert not isinstance(result, Exception), result
    assert key in matrix() and (peers_read(key) or key == MAC_SAMPLE)
    row = matrix()[key]
    if key in HEADER_ONLY:
        expected = HEADER_ONLY[key]
    elif row["ezc3d"] == "OK":
        expected = (int(row["points"]), int(row["frames"]), float(row["rate"]))
    elif key == MAC_SAMPLE:  # values cross-checked in test_mac_sample_is_plausible
        expected = (33, 180, 60.0)
    else:  # ezc3d fails (MIPS, float OFFSET, BKIN): py-c3d's counts
        pts, rate, used, _ = py_c3d(key)
        expected = (used, len(pts), rate)
    assert (result.n_markers, result.n_frames, result.rate) == expected
    assert result.metadata["format"] == "c3d" and len(set(result.labels)) == result.n_markers
    assert np.isfinite(result.positions).any()


@pytest.mark.parametrize("rel", PY_C3D_READS)
def test_point_values_equal_py_c3d(rel):
    shared_path("c3d", rel)
    traj = read(rel)
    if rel in NO_POINTS:
        assert isinstance(traj, InputFileError)
        return
    expected, _, _, residuals = py_c3d(rel)
    got = traj.positions / mm_per_unit(traj)
    assert got.shape == expected.shape
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-3 / mm_per_unit(traj))
    # residual word: low byte x |SCALE| (C3D spec; ezc3d 1.7 decodes it differently)
    np.testing.assert_allclose(traj.residuals / mm_per_unit(traj), residuals, rtol=1e-5, atol=1e-6)


#: ezc3d reads these without error but gets the analog layout (and so the points) wrong.
EZC3D_MISREADS = {"btkdata/c3d.org/sample28/dynamic.C3D", "btkdata/c3d.org/sample28/standing.C3D",
                  "btkdata/c3d.org/sample28/type1.C3D", "btkdata/others/561xxa01_anonym.C3D"}


@pytest.mark.parametrize("rel", EZC3D_READS)
def test_ezc3d_and_own_reader_agree(rel):
    """Our numpy reader supplies the points of every file; where ezc3d reads a file right, it
    gives the same values and labels; where ezc3d misreads, ``reader="ezc3d"`` noticed and
    fell back to our reader (values checked vs py-c3d)."""
    import ezc3d

    shared_path("c3d", rel)
    traj = read(rel)
    assert traj.metadata["reader"] == "mocaptk" and not any(
        "ezc3d" in note for note in traj.metadata["notes"])
    theirs = read_c3d(shared_path("c3d", rel), reader="ezc3d")
    if rel in EZC3D_MISREADS or rel in HEADER_ONLY:  # ezc3d: wrong values / no points
        assert theirs.metadata["reader"] == "mocaptk"
        reason = "frame layout" if rel in EZC3D_MISREADS else "no POINT parameters"
        assert any(reason in note for note in theirs.metadata["notes"])
        return
    assert theirs.metadata["reader"] == "ezc3d"
    np.testing.assert_array_equal(np.isnan(traj.positions), np.isnan(theirs.positions))
    np.testing.assert_allclose(traj.positions, theirs.positions, rtol=1e-6, atol=1e-9)
    params = ezc3d.c3d(str(shared_path("c3d", rel)))["parameters"]["POINT"]
    labels = [lab for key in ["LABELS", "LABELS2", "LABELS3"] if key in params
              for lab in params[key]["value"]][:traj.n_markers]
    for theirs, ours in zip(labels, traj.labels):
        if theirs.strip():  # duplicates get a suffix
            assert ours == theirs.strip() or ours.startswith(theirs.strip() + "_")
        else:  # empty labels are named after the point number
            assert ours == f"M{traj.labels.index(ours) + 1:03d}"


def _variants(folder: str, names: list[str]):
    return [read(f"btkdata/c3d.org/{folder}/{name}") for name in names]


@pytest.mark.parametrize("folder, names", [
    ("sample01", ["Eb015pi.c3d", "Eb015pr.c3d", "Eb015si.c3d", "Eb015sr.c3d", "Eb015vi.c3d",
                  "Eb015vr.c3d"]),
    ("sample02", ["pc_int.c3d", "pc_real.c3d", "sgi_int.c3d", "sgi_real.c3d", "DEC_INT.C3D",
                  "Dec_real.c3d"]),
])
def test_intel_dec_mips_int_float_variants_are_equal(folder, names):
    shared_path("c3d", "btkdata", "c3d.org", folder)
    trajs = _variants(folder, names)
    ref = trajs[0]
    assert {t.metadata["processor"] for t in trajs} == {"intel", "dec", "mips"}
    assert {t.metadata["storage"] for t in trajs} == {"int", "float"}
    for traj in trajs[1:]:
        assert traj.labels == ref.labels and traj.rate == ref.rate
        np.testing.assert_array_equal(np.isnan(traj.positions), np.isnan(ref.positions))
    if folder == "sample01":
        for traj in trajs[1:]:
            np.testing.assert_allclose(traj.positions, ref.positions, rtol=0, atol=1e-3)
        return
    # sample02: pc_int and sgi_int hold identical integers; DEC_INT and the three float files
    # agree with each other; the two groups differ by exactly one integer step (the files'
    # content, confirmed by py-c3d) in 59 of 9612 values.
    pc_int, pc_real, sgi_int, sgi_real, dec_int, dec_real = (t.positions for t in trajs)
    np.testing.assert_allclose(sgi_int, pc_int, rtol=0, atol=1e-3)
    for other in (sgi_real, dec_int, dec_real):
        np.testing.assert_allclose(other, pc_real, rtol=0, atol=1e-3)
    step = abs(c3d_raw.read_structure(shared_path("c3d", "btkdata", "c3d.org", folder,
                                                  names[0])).scale)
    diff = np.abs(pc_int - pc_real)[~np.isnan(pc_int)]
    assert np.count_nonzero(diff > 1e-3) == 59
    np.testing.assert_allclose(diff[diff > 1e-3], step, rtol=0, atol=1e-3)


def test_mac_sample_is_plausible():
    """MACsample (MIPS, neither peer reads it): 60 Hz walking; POINT:SCALE used, noted."""
    traj = read(MAC_SAMPLE)
    assert not isinstance(traj, Exception), traj
    assert traj.metadata["processor"] == "mips"
    assert any("POINT:SCALE" in note for note in traj.metadata["notes"])
    step = np.linalg.norm(np.diff(traj.positions, axis=0), axis=2)
    assert 1 < np.nanmedian(step) < 30  # mm per frame at 60 Hz
    assert np.nanmax(np.abs(traj.positions)) < 3000


def test_duplicate_labels_are_renamed_deterministically_and_noted():
    traj = read("btkdata/others/Gait.c3d")
    assert "RKNE" in traj.labels and "RKNE_2" in traj.labels
    assert any("RKNE->RKNE_2" in note for note in traj.metadata["notes"])


def test_subjects_descriptions_and_prefix_stripping():
    path = shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d")
    traj = read("ezc3d-testFiles/Vicon.c3d")
    assert traj.labels[0] == "boite:gauche_ext"
    assert traj.metadata["subjects"] == ["boite", "Daphnee"]
    stripped = read_c3d(path, strip_prefixes=True)
    assert stripped.labels[0] == "gauche_ext" and stripped.metadata["subjects"] == ["boite", "Daphnee"]
    np.testing.assert_array_equal(stripped.positions, traj.positions)


def test_units_metres_become_millimetres():
    traj = read("ezc3d-testFiles/FP_Type1.c3d")  # POINT:UNITS "m"
    assert traj.metadata["original_units"] == "m"
    raw, res = c3d_raw.read_points(c3d_raw.read_structure(shared_path("c3d", "ezc3d-testFiles",
                                                                      "FP_Type1.c3d")))
    np.testing.assert_allclose(traj.positions, np.where((res < 0)[..., None], np.nan, raw) * 1000)


def test_header_frame_count_repairs_are_noted():
    traj = read("ezc3d-testFiles/Optotrak.c3d")  # header declares 1149 frames, holds 29
    assert traj.n_frames == 29 and any("1149" in n for n in traj.metadata["notes"])


def test_events_match_ezc3d_and_lie_inside_the_trial():
    import ezc3d

    rel = "btkdata/PiG/PiG_Motion-FlatFoot-Full.c3d"
    traj = read(rel)
    event = ezc3d.c3d(str(shared_path("c3d", rel)))["parameters"]["EVENT"]
    times = event["TIMES"]["value"].ravel()  # minutes, seconds, minutes, seconds...
    np.testing.assert_allclose([e["time"] for e in traj.metadata["events"]],
                               times[0::2] * 60 + times[1::2], atol=1e-5)
    assert [e["label"] for e in traj.metadata["events"]] == [
        label.strip() for label in event["LABELS"]["value"]]
    frames = np.array([e["time"] for e in traj.metadata["events"]]) * traj.rate
    assert (frames >= traj.first_frame - 1).all() and (frames <= traj.first_frame + traj.n_frames).all()


def test_saturated_header_without_trial_fields_uses_the_file_size(tmp_path):
    """ezc3d writes all 70,000 frames but caps the header and POINT:FRAMES at 65,535 (and reads
    back only those): mocaptk counts the frames the data section holds."""
    import ezc3d

    rng = np.random.default_rng(3)
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [200.0]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b"]
    points = np.ones((4, 2, 70_000))
    points[:3] = rng.normal(0, 100, (3, 2, 70_000))
    c3d["data"]["points"] = points
    c3d.write(str(tmp_path / "ez.c3d"))
    traj = read_c3d(tmp_path / "ez.c3d")
    assert traj.n_frames == 70_000 and traj.metadata["reader"] == "mocaptk"
    np.testing.assert_allclose(traj.positions, points[:3].transpose(2, 1, 0), rtol=2**-23)


def test_info_json_names_the_reader(run_cli):
    """`info --json` says which reader supplied the points: ours, for every C3D it accepts."""
    import json

    from conftest import SAMPLES

    result = run_cli("info", "--json", SAMPLES / "dense_halfface.c3d")
    assert result.exit_code == 0, result.stderr
    info, = json.loads(result.stdout)["files"]
    assert info["reader"] == "mocaptk" and info["format"] == "c3d"


def test_float_residual_words_decode_as_their_16_bit_integer(tmp_path):
    # float storage keeps the residual word as a number: its integer part is the 16-bit word
    # (low byte x |SCALE| = residual, high byte = cameras); negative or NaN marks a gap
    from mocaptk import Trajectories
    from mocaptk.acquisition.c3d_write import write_c3d

    words = np.array([0.0, -0.0, 3.7, 255.9, 256.0, 300.5, 65535.0, 70000.0, np.inf, -1.0, -5.5, np.nan],
                     np.float32)
    path = write_c3d(Trajectories(np.ones((1, words.size, 3)), [f"M{k}" for k in range(words.size)], 60.0),
                     tmp_path / "words.c3d")
    structure = c3d_raw.read_structure(path)
    assert structure.float_storage and structure.n_points == words.size
    with open(path, "r+b") as handle:
        block = np.fromfile(handle, "<f4", words.size * 4, offset=structure.data_offset).reshape(-1, 4)
        block[:, 3] = words
        handle.seek(structure.data_offset)
        block.tofile(handle)
    traj = read_c3d(path)
    low_byte = [0, 0, 3, 255, 0, 44, 255, 255, 255]  # 70000 and inf: the word's largest, 0xFFFF
    np.testing.assert_array_equal(traj.residuals[0], np.r_[low_byte, [np.nan] * 3] * abs(structure.scale))
    assert np.isnan(traj.positions[0, 9:]).all() and (traj.positions[0, :9] == 1.0).all()
