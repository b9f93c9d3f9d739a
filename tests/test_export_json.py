"""rig.json: schema fields, exact round trip, refusals of bad files and bad output paths."""

from __future__ import annotations

import json

import numpy as np
import pytest
from readers.sample_rig import sample_rig

from mocaptk.errors import InputFileError, OutputError
from mocaptk.retarget import read_rig_json, write_rig_json


@pytest.fixture(scope="module")
def rig():
    return sample_rig()


def test_document_fields(rig, tmp_path):
    path = write_rig_json(rig, tmp_path / "rig.json")
    doc = json.loads(path.read_text())
    assert (doc["format"], doc["version"], doc["unit"], doc["up_axis"]) == ("mocaptk.rig", 1, "mm",
                                                                          "Y")
    assert doc["mesh"]["vertex_count"] == rig.vertex_count == len(doc["mesh"]["vertices"])
    assert doc["mesh"]["sha256"] == rig.mesh_sha256()
    root = doc["joints"][0]
    assert (root["name"], root["parent"], root["side"]) == ("face_root", None, "C")
    brow = doc["joints"][1]
    assert brow == {"name": "Brow_L", "parent": "face_root", "side": "L", "region": "brow",
                    "marker": "LBrow", "bind_position": rig.joint_positions[1].tolist()}
    assert doc["weights"]["max_influences"] == 4
    assert len(doc["weights"]["joint_index"]) == rig.vertex_count
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind


def test_round_trip(rig, tmp_path):
    back = read_rig_json(write_rig_json(rig, tmp_path / "rig.json"))
    assert back.joint_names == rig.joint_names
    assert back.joint_sides == rig.joint_sides and back.joint_regions == rig.joint_regions
    assert back.joint_markers == rig.joint_markers
    np.testing.assert_array_equal(back.joint_parents, rig.joint_parents)
    np.testing.assert_array_equal(back.faces, rig.faces)
    np.testing.assert_allclose(back.vertices, rig.vertices, atol=5e-7)
    np.testing.assert_allclose(back.joint_positions, rig.joint_positions, atol=5e-7)
    np.testing.assert_array_equal(back.weight_index, rig.weight_index)
    assert np.abs(back.weight_value - rig.weight_value).max() <= 5e-10
    assert back.mesh_sha256() == rig.mesh_sha256()
    # Writing what was read gives the same bytes.
    again = write_rig_json(back, tmp_path / "again.json")
    assert again.read_bytes() == (tmp_path / "rig.json").read_bytes()


def _edited(tmp_path, rig, edit) -> object:
    path = write_rig_json(rig, tmp_path / "rig.json")
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(format="other"), "not a mocaptk.rig document"),
    (lambda d: d.update(version=99), "unsupported mocaptk.rig version 99"),
    (lambda d: d.update(unit="cm"), "expected unit 'mm'"),
    (lambda d: d["mesh"]["vertices"][3].__setitem__(0, 1.5), "do not match the stored sha256"),
    (lambda d: d["mesh"].update(vertex_count=5), "vertex_count says 5"),
    (lambda d: d["joints"][2].update(parent="nobody"), "unknown parent 'nobody'"),
    (lambda d: d["weights"]["value"][0].__setitem__(0, 0.0), "do not sum to 1"),
    (lambda d: d.pop("joints"), "missing field 'joints'"),
])
def test_bad_rig_files_are_refused(rig, tmp_path, edit, message):
    path = _edited(tmp_path, rig, edit)
    with pytest.raises(InputFileError, match=message) as caught:
        read_rig_json(path)
    assert str(caught.value).startswith(str(path))


def test_unreadable_files(tmp_path):
    with pytest.raises(InputFileError, match="no such file"):
        read_rig_json(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InputFileError, match="invalid JSON"):
        read_rig_json(tmp_path / "bad.json")


def test_bad_output_paths(rig, tmp_path):
    path = write_rig_json(rig, tmp_path / "rig.json")
    with pytest.raises(OutputError, match="already exists"):
        write_rig_json(rig, path, force=False)
    with pytest.raises(OutputError, match="is a folder"):
        write_rig_json(rig, tmp_path)
    with pytest.raises(OutputError, match="cannot write"):
        write_rig_json(rig, path / "inside_a_file.json")
