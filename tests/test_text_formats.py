"""Text marker formats (Vicon Nexus CSV, TRC, column CSV) and format detection, on the real files in
../shared/data/csv_trc and ../shared/data/facial_mocap, checked against independent expectations."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mocaptk import Take, Trajectories
from mocaptk.acquisition.formats import detect_format, read_trajectories, write_trajectories
from mocaptk.acquisition.generic_csv import read_generic_csv
from mocaptk.acquisition.trc import read_trc
from mocaptk.acquisition.vicon_csv import read_vicon_csv
from mocaptk.errors import InputFileError, OptionError, OutputError

from conftest import SHARED_DATA, shared_path

# Every file under csv_trc/: (markers, frames, rate Hz) or the error it must give.
# Marker counts: TRC files keep unlabelled coordinate triples past the labels (10002-*: NumMarkers 0;
# Gait/SprintCalib/UpperLimbStatic: more data columns than labels) as extra markers.
EXPECTED = {
    "btkdata/10002-20130626160334-Unnamed.trc": (10, 882, 400.0),
    "btkdata/10002-20130731010438-Unnamed.trc": (37, 1313, 400.0),
    "btkdata/Anto.trc": (34, 128, 100.0),
    "btkdata/Empty.trc": "file is empty",
    "btkdata/Gait.trc": (105, 487, 100.0),
    "btkdata/Knee.trc": (71, 200, 200.0),
    "btkdata/Res16bits.trc": (44, 100, 100.0),
    "btkdata/SprintCalib.trc": (70, 337, 250.0),
    "btkdata/SprintMotion.trc": (59, 788, 250.0),
    "btkdata/Truncated.trc": "truncated TRC header",
    "btkdata/UpperLimbStatic.trc": (36, 146, 100.0),
    "btkdata/MOTEK/T.trc": (41, 89, 30.0),
    "btkdata/MOTEK/ballet_reduced.trc": (41, 100, 30.0),
    "btkdata/MOTEK/readme_trc.txt": "unrecognised content",
    "pyomeca/LICENSE.md": "unrecognised content",
    "pyomeca/analogs.csv": "no Trajectories section",
    "pyomeca/markers.csv": (51, 580, 100.0),
    "pyomeca/markers.trc": (51, 93, 100.0),  # header says 652 frames: the published file was cut
    "pyomeca/markers_without_header.csv": "give the rate",
}


def _csv_trc_files() -> list[str]:
    root = SHARED_DATA / "csv_trc"
    if not root.is_dir():
        return sorted(EXPECTED)
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def test_expectation_table_covers_every_shared_file():
    root = SHARED_DATA / "csv_trc"
    if not root.is_dir():
        pytest.skip("shared data not available")
    assert sorted(EXPECTED) == _csv_trc_files()


@pytest.mark.parametrize("name", _csv_trc_files())
def test_every_csv_trc_file_reads_or_fails_clearly(name):
    path = shared_path("csv_trc", name)
    expected = EXPECTED[name]
    if isinstance(expected, str):
        with pytest.raises(InputFileError, match=expected) as info:
            read_trajectories(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
        return
    traj = read_trajectories(path)
    assert (traj.n_markers, traj.n_frames, traj.rate) == expected
    assert traj.positions.dtype == np.float64 and traj.positions.shape == (expected[1], expected[0], 3)
    assert np.isfinite(traj.positions).any(axis=(0, 2)).sum() >= 1


def _naive_trc(path: Path) -> tuple[dict[str, str], list[str], np.ndarray]:
    """Independent minimal TRC parse: header keywords, labels, rows of floats (NaN for empty)."""
    lines = path.read_text().splitlines()
    sep = "\t" if "\t" in lines[0] else ","
    header = dict(zip(lines[1].split(sep), lines[2].split(sep)))
    labels = [c.strip() for c in lines[3].split(sep)[2:] if c.strip()]
    rows = [line.split(sep) for line in lines[5:] if line.strip(sep + " \r\n")]
    return header, labels, rows


@pytest.mark.parametrize("name", [n for n, e in EXPECTED.items() if n.endswith(".trc") and not isinstance(e, str)])
def test_trc_values_match_header_and_file_text(name):
    path = shared_path("csv_trc", name)
    traj = read_trc(path)
    header, labels, rows = _naive_trc(path)
    assert traj.rate == float(header["DataRate"])
    assert traj.metadata["original_units"] == header["Units"].strip() == "mm"
    declared = int(header["NumFrames"])
    assert traj.n_frames == len(rows)
    assert (declared == traj.n_frames) == (not any("NumFrames" in n for n in traj.metadata["notes"]))
    assert list(traj.labels[:len(labels)]) == labels
    assert traj.first_frame == int(rows[0][0])
    # every cell of the file text, read naively, equals the parsed value
    for f in (0, len(rows) // 2, len(rows) - 1):
        cells = rows[f][2:2 + 3 * traj.n_markers]
        cells += [""] * (3 * traj.n_markers - len(cells))
        naive = np.array([float(c) if c.strip() else np.nan for c in cells]).reshape(-1, 3)
        np.testing.assert_array_equal(traj.positions[f], naive)


def test_trc_hand_checked_values():
    knee = read_trc(shared_path("csv_trc", "btkdata", "Knee.trc"))
    np.testing.assert_array_equal(knee.positions[0, 0], [256.84422, 113.24970, 121.77992])
    assert knee.labels[0] == "genou1_ NewMarker" and knee.labels[3] == "genou1_NewMarker3"
    unnamed = read_trc(shared_path("csv_trc", "btkdata", "10002-20130731010438-Unnamed.trc"))
    assert unnamed.metadata["header"]["NumMarkers"] == "0" and unnamed.labels[:2] == ("M01", "M02")
    row3 = unnamed.positions[2]  # file line 9: marker 6 and 8 are empty cells
    np.testing.assert_array_equal(row3[4], [-617.16675, 87.09780, 384.07642])
    assert np.isnan(row3[5]).all() and np.isnan(row3[7]).all()
    np.testing.assert_array_equal(row3[6], [-28.78496, 617.50635, 30.54635])
    comma = read_trc(shared_path("csv_trc", "pyomeca", "markers.trc"))
    np.testing.assert_array_equal(comma.positions[0, 0], [733.7041, 80.9832, 191.8668])
    assert comma.labels[0] == "ASISl" and "NumFrames 652" in comma.metadata["notes"][0]


def test_vicon_csv_equals_its_c3d_source():
    """pyomeca/markers.csv is the Nexus export of ezc3d-testFiles/Vicon.c3d."""
    csv_traj = read_trajectories(shared_path("csv_trc", "pyomeca", "markers.csv"))
    c3d_traj = read_trajectories(shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d"))
    assert csv_traj.metadata["format"] == "vicon_csv" and c3d_traj.metadata["format"] == "c3d"
    assert csv_traj.labels == c3d_traj.labels
    assert (csv_traj.rate, csv_traj.first_frame, csv_traj.n_frames) == (
        c3d_traj.rate, c3d_traj.first_frame, c3d_traj.n_frames)
    np.testing.assert_array_equal(np.isnan(csv_traj.positions), np.isnan(c3d_traj.positions))
    assert np.isnan(csv_traj.positions).any()  # the file does have gaps
    # the CSV keeps 6 significant digits: half a unit in the 6th digit
    np.testing.assert_allclose(csv_traj.positions, c3d_traj.positions, rtol=5.01e-6, atol=1e-4)
    assert csv_traj.metadata["subjects"] == ["Daphnee", "boite"]
    stripped = read_trajectories(shared_path("csv_trc", "pyomeca", "markers.csv"), strip_prefixes=True)
    assert stripped.labels[0] == "gauche_ext"


def test_vicon_csv_with_devices_first_other_sections_after_and_no_units_row(tmp_path):
    markers = shared_path("csv_trc", "pyomeca", "markers.csv").read_text()
    devices = shared_path("csv_trc", "pyomeca", "analogs.csv").read_text()  # a Devices section
    model = "Model Outputs\n100\n,,Daphnee:LAnkleAngles,,\nFrame,Sub Frame,X,Y,Z\n,,deg,deg,deg\n1,0,1,2,3\n"
    combined = tmp_path / "combined.csv"
    combined.write_text(devices.rstrip("\r\n") + "\n\n" + markers.rstrip("\n") + "\n\n" + model)
    reference = read_vicon_csv(shared_path("csv_trc", "pyomeca", "markers.csv"))
    traj = read_trajectories(combined)
    assert traj.labels == reference.labels and traj.rate == 100.0
    np.testing.assert_array_equal(traj.positions, reference.positions)
    lines = markers.splitlines()
    assert lines[4].startswith(",,mm,mm,mm")
    no_units = tmp_path / "old_export.csv"
    no_units.write_text("\n".join(lines[:4] + lines[5:]) + "\n")
    old = read_trajectories(no_units)
    assert old.metadata["original_units"] == "mm"
    np.testing.assert_array_equal(old.positions, reference.positions)


def test_headerless_nexus_export_with_rate_equals_full_export():
    full = read_vicon_csv(shared_path("csv_trc", "pyomeca", "markers.csv"))
    bare = read_trajectories(shared_path("csv_trc", "pyomeca", "markers_without_header.csv"), rate=100)
    assert bare.metadata["format"] == "generic_csv" and bare.labels[:2] == ("M01", "M02")
    assert bare.first_frame == full.first_frame == 1
    np.testing.assert_array_equal(bare.positions, full.positions)


def test_blenderface_real_facial_tracking():
    path = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    with pytest.raises(InputFileError, match="rate"):
        read_trajectories(path)
    traj = read_trajectories(path, rate=50, units="m")
    assert traj.n_markers == 16 and traj.n_frames == 1714
    assert traj.labels[:3] == ("CL7", "BL7", "CR7")
    assert 0.49 < np.isnan(traj.positions[..., 0]).mean() < 0.51
    # file line 801 (frame 800): CL7 = -0.18874520063400269;-0.2221827507019043;-0.11583328247070312
    np.testing.assert_allclose(traj.positions[799, 0],
                               np.array([-0.18874520063400269, -0.2221827507019043, -0.11583328247070312]) * 1000)
    assert np.isnan(traj.positions[798]).all()
    assert [(t.name, t.start, t.end) for t in traj.takes] == [
        ("posed_neutral", 799, 985), ("posed_disgust", 985, 1200), ("posed_happy", 1200, 1415),
        ("posed_fear", 1415, 1650)]


ROUND_TRIP = ["pyomeca/markers.csv", "pyomeca/markers.trc", "btkdata/Knee.trc",
              "btkdata/10002-20130731010438-Unnamed.trc"]  # gaps, comma TRC, unlabelled markers


@pytest.mark.parametrize("name", ROUND_TRIP)
@pytest.mark.parametrize("suffix", [".csv", ".trc"])
def test_round_trip_through_csv_and_trc(name, suffix, tmp_path):
    original = read_trajectories(shared_path("csv_trc", name))
    out = write_trajectories(original, tmp_path / f"copy{suffix}")
    again = read_trajectories(out)
    assert again.metadata["format"] == ("vicon_csv" if suffix == ".csv" else "trc")
    assert (again.labels, again.rate, again.first_frame) == (original.labels, original.rate, original.first_frame)
    np.testing.assert_array_equal(np.isnan(again.positions), np.isnan(original.positions))
    np.testing.assert_allclose(again.positions, original.positions, rtol=1e-9, atol=1e-12)


def _synthetic(frames=40, markers=4, rate=60.0, first_frame=7) -> Trajectories:
    rng = np.random.default_rng(3)
    pos = rng.normal(0, 50, (frames, markers, 3))
    pos[5:9, 1] = np.nan
    return Trajectories(pos, [f"Anna:M{i}" for i in range(markers)], rate, first_frame,
                        metadata={"takes": [Take("neutral", 0, 10), Take("smile", 10, 40, "mouth")]})


def test_takes_survive_vicon_csv_but_not_trc(tmp_path):
    session = _synthetic()
    back = read_trajectories(write_trajectories(session, tmp_path / "s.csv"))
    assert back.takes == session.takes and back.first_frame == 7
    assert read_trajectories(write_trajectories(session, tmp_path / "s.trc")).takes == []


def test_units_conversion_and_override(tmp_path):
    session = _synthetic()
    metres = tmp_path / "m.trc"
    write_trajectories(session, metres)
    text = metres.read_text().splitlines()
    values = text[2].split("\t")
    values[4] = "m"
    text[2] = "\t".join(values)
    metres.write_text("\n".join(text) + "\n")
    np.testing.assert_allclose(read_trc(metres).positions, session.positions * 1000, atol=1e-3)
    assert read_trc(metres).metadata["original_units"] == "m"
    np.testing.assert_allclose(read_trc(metres, units="cm").positions, session.positions * 10, atol=1e-4)
    values[4] = "furlong"
    metres.write_text("\n".join(text[:2] + ["\t".join(values)] + text[3:]) + "\n")
    with pytest.raises(InputFileError, match="unknown length units 'furlong'"):
        read_trc(metres)
    with pytest.raises(OptionError, match="unknown length units"):
        read_trajectories(shared_path("csv_trc", "pyomeca", "markers.csv"), units="parsec")
    with pytest.raises(OptionError, match="text files only"):
        read_trajectories(shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d"), units="m")


@pytest.mark.parametrize("text, delimiter", [
    ("Frame,Time,NOSE_x,NOSE_y,NOSE_z,CHIN_x,CHIN_y,CHIN_z\n", ","),
    ("Frame\tTime\tNOSE X\tNOSE Y\tNOSE Z\tCHIN X\tCHIN Y\tCHIN Z\n", "\t"),
    ("Frame;Time;NOSE.x;NOSE.y;NOSE.z;CHIN.x;CHIN.y;CHIN.z\n", ";"),
])
def test_generic_csv_header_styles_and_time_column(text, delimiter, tmp_path):
    rows = []
    for f in range(6):
        cells = [str(f + 1), f"{f / 120:.6f}", f"{f}.5", "2", "3", "NA" if f == 2 else "4", "", "6"]
        if delimiter == ";":
            cells = [c.replace(".", ",") for c in cells]
        rows.append(delimiter.join(cells))
    path = tmp_path / "cols.txt"
    path.write_text(text + "\n".join(rows) + "\n")
    assert detect_format(path) == "generic_csv"
    traj = read_generic_csv(path)
    assert traj.labels == ("NOSE", "CHIN") and math.isclose(traj.rate, 120.0, rel_tol=1e-4)
    assert traj.metadata["units_assumed"] is True
    np.testing.assert_array_equal(traj.positions[3, 0], [3.5, 2, 3])
    assert np.isnan(traj.positions[2, 1]).all() and np.isnan(traj.positions[:, 1, 1]).all()


def test_generic_csv_frame_jumps_units_in_header_and_bad_columns(tmp_path):
    path = tmp_path / "jump.csv"
    path.write_text("frame,A_x (m),A_y (m),A_z (m)\n10,1,2,3\n11,1,2,3\n14,2,2,2\n")
    traj = read_generic_csv(path, rate=100)
    assert traj.n_frames == 5 and traj.first_frame == 10 and traj.metadata["original_units"] == "m"
    assert np.isnan(traj.positions[2:4]).all() and traj.positions[4, 0, 0] == 2000
    path.write_text("frame,A_x,A_y\n1,2,3\n")
    with pytest.raises(InputFileError, match="lacks one of its x/y/z"):
        read_generic_csv(path, rate=100)
    path.write_text("frame,A_x,A_y,A_z\n1,2,oops,3\n")
    with pytest.raises(InputFileError, match="line 2, column 2: not a number: 'oops'"):
        read_generic_csv(path, rate=100)


def test_detection_is_by_content_not_extension(tmp_path):
    disguised = tmp_path / "really_nexus.trc"
    disguised.write_bytes(shared_path("csv_trc", "pyomeca", "markers.csv").read_bytes())
    assert detect_format(disguised) == "vicon_csv"
    c3d_as_csv = tmp_path / "binary.csv"
    c3d_as_csv.write_bytes(shared_path("c3d", "ezc3d-testFiles", "Vicon.c3d").read_bytes())
    assert detect_format(c3d_as_csv) == "c3d"
    trc_as_txt = tmp_path / "x.txt"
    trc_as_txt.write_bytes(shared_path("csv_trc", "btkdata", "Anto.trc").read_bytes())
    assert detect_format(trc_as_txt) == "trc"


def test_npz_from_our_tools(tmp_path):
    session = _synthetic()
    np.savez(tmp_path / "s.npz", positions=session.positions, labels=np.array(session.labels), rate=60.0)
    back = read_trajectories(tmp_path / "s.npz")
    assert back.labels == session.labels and back.metadata["format"] == "npz"
    np.testing.assert_array_equal(back.positions, session.positions)
    np.savez(tmp_path / "other.npz", weights=np.zeros(3))
    with pytest.raises(InputFileError, match="lacks positions"):
        read_trajectories(tmp_path / "other.npz")


@pytest.mark.parametrize("content, problem", [
    (b"\xff\xfeT\x00r\x00", r"not UTF-8 text \(UTF-16"),  # the documented message, not "binary content"
    ("Trajectories\n100\n".encode("utf-16-be"), r"not UTF-8 text \(UTF-16"),
    ("PathFileType\t4\t(X/Y/Z)\n".encode("utf-16-le"), r"not UTF-8 text \(UTF-16"),
    ("Trajectories\n100\n,,Ä:M\nFrame,Sub Frame,X,Y,Z\n".encode("latin-1"), "not UTF-8"),
    (b"Trajectories\n100\n", "truncated"),
    (b"Trajectories\n100\n,,\nFrame,Sub Frame\n,,\n1,0\n", "no markers"),
    (b"Trajectories\n100\n,,A,,,A,,\nFrame,Sub Frame,X,Y,Z,X,Y,Z\n,,mm,mm,mm,mm,mm,mm\n1,0,1,2,3,4,5,6\n",
     "duplicate marker labels: A"),
    (b"Trajectories\n100\n,,A,,\nFrame,Sub Frame,X,Y,Z\n,,yd,yd,yd\n1,0,1,2,3\n", "unknown length units 'yd'"),
    (b"PathFileType\t4\t(X/Y/Z)\tx\nDataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\n"
     b"100\t100\t1\t0\tmm\nFrame#\tTime\n\t\n\n1\t0.0\n", "no markers"),
    (b"Trajectories\n0\n,,A,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1,2,3\n", "frame rate"),
])
def test_malformed_text_files(content, problem, tmp_path):
    path = tmp_path / "bad.csv"
    path.write_bytes(content)
    with pytest.raises(InputFileError, match=problem) as info:
        read_trajectories(path)
    assert str(info.value).startswith(str(path))


def test_writer_refuses_overwrite_and_unknown_extension(tmp_path):
    session = _synthetic()
    target = tmp_path / "s.csv"
    write_trajectories(session, target)
    before = target.read_bytes()
    with pytest.raises(OutputError, match="already exists"):
        write_trajectories(session, target, force=False)
    assert target.read_bytes() == before
    with pytest.raises(OptionError, match="unknown output extension"):
        write_trajectories(session, tmp_path / "s.xlsx")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv"]
