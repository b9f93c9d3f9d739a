"""guide.pdf: the expected pages, renders with pdftoppm, and the 1:1 page is really 1:1."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from mocaptk.retarget.guide import guide_markers, write_guide_pdf
from mocaptk.retarget.renders import render_view
from mocaptk.surface_mesh import marker_surface_mesh


@pytest.fixture(scope="module")
def guide(tmp_path_factory):
    """A guide for 30 markers on a face-like cap 150 mm wide (two clusters per region)."""
    folder = tmp_path_factory.mktemp("guide")
    az, el = np.meshgrid(np.radians(np.arange(-70, 71, 10.0)), np.radians(np.arange(-50, 56, 10.0)))
    az, el = az.ravel(), el.ravel()
    pts = np.column_stack([75 * np.sin(az) * np.cos(el), 100 * np.sin(el),
                           90 * np.cos(az) * np.cos(el)])
    vertices, faces = marker_surface_mesh(pts)
    joints = np.arange(0, len(pts), 6)[:30]
    regions = ["forehead_brow", "eye", "nose", "cheek", "mouth", "chin"]
    cluster_regions = [regions[k % 6] for k in range(len(joints))]
    owner = np.argmin(np.linalg.norm(vertices[:, None] - vertices[joints][None], axis=2), axis=1)
    numbers = list(range(1, len(joints) + 1))
    front = render_view(vertices, faces, owner, cluster_regions, vertices[joints], numbers,
                        folder / "front.png", view="front", size=(525, 600))
    profile = render_view(vertices, faces, owner, cluster_regions, vertices[joints], numbers,
                          folder / "profile.png", view="profile", size=(525, 600))
    labels = [f"M_{k:02d}_{'L' if vertices[j, 0] > 2 else 'R' if vertices[j, 0] < -2 else 'C'}"
              for k, j in enumerate(joints)]
    rows = guide_markers(labels, cluster_regions, [lab[-1] for lab in labels], vertices[joints],
                         [[lab, f"D_{k}a", f"D_{k}b"] for k, lab in enumerate(labels)],
                         nose_tip=vertices[np.argmax(vertices[:, 2])])
    pdf = write_guide_pdf(folder / "guide.pdf", rows, front_png=front, profile_png=profile,
                          outline=vertices, title="test guide", notes=["note line"])
    return folder, pdf, rows


def test_guide_rows_describe_positions_from_the_nose(guide):
    _, _, rows = guide
    assert [r.number for r in rows] == list(range(1, len(rows) + 1)) and len(rows) > 20
    for r in rows:
        assert r.replaces == tuple(m for m in (f"D_{r.number - 1}a", f"D_{r.number - 1}b"))
        np.testing.assert_allclose(r.position - r.from_nose, rows[0].position - rows[0].from_nose)


def test_guide_pdf_pages_and_render(guide):
    folder, pdf, _ = guide
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF")
    if shutil.which("pdfinfo") is None or shutil.which("pdftoppm") is None:
        pytest.skip("poppler-utils (pdfinfo, pdftoppm) not installed")
    info = subprocess.run(["pdfinfo", str(pdf)], capture_output=True, text=True, check=True).stdout
    assert re.search(r"^Pages:\s+4$", info, re.M)  # front, profile, 1:1, table (one page)
    run = subprocess.run(["pdftoppm", "-png", "-r", "30", str(pdf), str(folder / "page")],
                         capture_output=True, text=True)
    assert run.returncode == 0 and run.stderr == ""
    assert len(list(folder.glob("page-*.png"))) == 4
    text = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True,
                          text=True).stdout
    for words in ("Front view", "Profile view", "1:1 scale", "must measure 50 mm", "M_00_",
                  "2: D_0a, D_0b", "nose tip"):
        assert words in text


def test_one_to_one_page_scale_bar_is_50_mm(guide):
    folder, pdf, _ = guide
    if shutil.which("pdftoppm") is None:
        pytest.skip("poppler-utils (pdftoppm) not installed")
    import matplotlib.image as mpimg

    subprocess.run(["pdftoppm", "-png", "-r", "254", "-f", "3", "-l", "3", str(pdf),
                    str(folder / "scale")], check=True)
    image = mpimg.imread(next(folder.glob("scale-*.png")))[..., :3].mean(axis=2)
    assert image.shape[1] == pytest.approx(2100, abs=2)  # A4 width at 10 px/mm
    dark = image < 0.2
    runs = []
    for row in dark[int(0.8 * len(dark)):]:  # the bar is near the bottom
        padded = np.concatenate([[0], row.astype(int), [0]])
        edges = np.flatnonzero(np.diff(padded))
        runs.extend(edges[1::2] - edges[0::2])
    assert max(runs) == pytest.approx(500, abs=3)  # 50 mm at 10 px/mm
