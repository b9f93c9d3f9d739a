"""Geometric regions and sides are symmetric about the sagittal plane (issue 14 item 7): on
blenderFace, CL4 was cheek but CR4 eye, CL7 chin but CR7 cheek, and the BL* markers got side R."""

from __future__ import annotations

from conftest import shared_path

from mocaptk.clustering.symmetry import label_pairs


def test_label_pairs():
    labels = ["CL4", "CR4", "A8", "MOUTH_03_L", "MOUTH_03_R", "LEyeOuter", "REyeOuter", "LIP_01_C", "BL7"]
    assert label_pairs(labels) == [(0, 1), (3, 4), (5, 6)]


def test_blenderface_regions_and_sides_are_symmetric(run_cli, tmp_path):
    import json

    session = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    result = run_cli("cluster", session, "--rate", "25", "--units", "188", "--no-stabilize",
                     "--out", tmp_path / "o", "--formats", "none", "--quiet")
    assert result.exit_code == 0, result.stderr
    layout = json.loads((tmp_path / "o" / "layout.json").read_text())
    region = {m: r["name"] for r in layout["regions"] for m in r["markers"]}
    for left in [label for label in region if len(label) == 3 and label[1] == "L"]:
        right = left[0] + "R" + left[2]
        assert region[left] == region[right], (left, region[left], right, region[right])
    assert region["CL4"] == region["CR4"] == "cheek" and region["CL7"] == region["CR7"]
    sides = {c["representative"]: c["side"] for c in layout["clusters"]}
    for label, side in sides.items():  # the file's L is the viewer's left: the actor's right (#27)
        expected = "C" if label.startswith("A") else {"L": "R", "R": "L"}[label[1]]
        assert side == expected, (label, side)
