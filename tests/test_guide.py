"""guide.pdf: the expected pages, renders with pdftoppm, and the 1:1 page is really 1:1."""

from __future__ import annotations

import dataclasses
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


@pytest.fixture(scope="module")
def one_to_one_page(guide):
    """Page 3 (the 1:1 page) rendered at 254 dpi (10 px/mm), grey levels (H, W)."""
    folder, pdf, _ = guide
    if shutil.which("pdftoppm") is None:
        pytest.skip("poppler-utils (pdftoppm) not installed")
    import matplotlib.image as mpimg

    subprocess.run(["pdftoppm", "-png", "-r", "254", "-f", "3", "-l", "3", str(pdf),
                    str(folder / "scale")], check=True)
    return mpimg.imread(next(folder.glob("scale-*.png")))[..., :3].mean(axis=2)


def _longest_dark_run(lines: np.ndarray) -> int:
    """Longest run of dark (< 0.2) pixels along any of ``lines`` (K, N), pixels."""
    runs = [0]
    for line in lines < 0.2:
        edges = np.flatnonzero(np.diff(np.concatenate([[0], line.astype(int), [0]])))
        runs.extend(edges[1::2] - edges[0::2])
    return int(max(runs))


def test_one_to_one_page_scale_bar_is_50_mm(one_to_one_page):
    image = one_to_one_page
    assert image.shape[1] == pytest.approx(2100, abs=2)  # A4 width at 10 px/mm
    # the bar is near the bottom: 50 mm at 10 px/mm
    assert _longest_dark_run(image[int(0.8 * len(image)):]) == pytest.approx(500, abs=3)


def test_pair_names_share_a_number_with_the_side():
    from mocaptk.retarget.guide import pair_names

    labels = ["A_L", "MID_C", "B_L", "A_R", "B_R"]
    names = pair_names(labels, ["L", "C", "L", "R", "R"], [None, None, None, "A_L", "B_L"])
    assert names == ["1L", "2", "3L", "1R", "3R"]


def label_overlaps(boxes: np.ndarray, dots: np.ndarray, radius: float) -> int:
    """Pairs of label boxes that overlap, plus labels that cover a marker dot."""
    n = 0
    for i in range(len(boxes)):
        a = boxes[i]
        for b in boxes[i + 1:]:
            n += a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
        near = np.clip(dots, a[:2], a[2:])  # nearest point of the box to every dot
        n += int((np.linalg.norm(near - dots, axis=1) < radius).sum())
    return n


def test_labels_never_overlap_on_the_dense_sample():
    """The 139 dense markers of the sample (~1 cm apart, far more crowded than a layout): the old
    fixed offset (up-right of the dot) overlaps; the placer leaves no label on a label or a dot."""
    from conftest import SAMPLES

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.retarget.guide import DOT_MM, place_labels

    traj = read_trajectories(SAMPLES / "dense_halfface.c3d")
    neutral = traj.positions[0]
    keep = np.isfinite(neutral).all(axis=1)
    dots = np.column_stack([neutral[keep, 0], -neutral[keep, 1]])  # page: y down
    names = [f"{k + 1}{'L' if x > 2 else ''}" for k, x in enumerate(neutral[keep, 0])]
    sizes = np.array([(1.35 * len(n) + 0.4, 2.2) for n in names])
    old = np.column_stack([dots + [1.4, -3.4], dots + [1.4, -3.4] + sizes])
    assert label_overlaps(old, dots, DOT_MM) > 10
    boxes, leader = place_labels(dots, sizes)
    assert label_overlaps(boxes, dots, DOT_MM) == 0
    reach = np.linalg.norm(np.clip(dots, boxes[:, :2], boxes[:, 2:]) - dots, axis=1)
    assert reach.max() < 30 and leader.sum() < len(dots) / 2  # most labels stay beside their dot


def test_one_to_one_page_labels_do_not_overlap_in_the_pdf(guide):
    folder, pdf, rows = guide
    if shutil.which("pdftotext") is None:
        pytest.skip("poppler-utils (pdftotext) not installed")
    html = subprocess.run(["pdftotext", "-bbox", "-f", "3", "-l", "3", str(pdf), "-"], capture_output=True,
                          text=True, check=True).stdout
    names = {r.name for r in rows}
    words = [(float(a), float(b), float(c), float(d)) for a, b, c, d, w in re.findall(
        r'xMin="([\d.]+)" yMin="([\d.]+)" xMax="([\d.]+)" yMax="([\d.]+)">([^<]+)<', html) if w in names]
    assert len(words) == len(rows)
    boxes = np.array(words)
    assert label_overlaps(boxes, np.empty((0, 2)), 0.0) == 0


def test_one_to_one_page_vertical_scale_bar_is_50_mm(one_to_one_page):
    image = one_to_one_page
    # the vertical bar is at the left
    assert _longest_dark_run(image[:, : image.shape[1] // 4].T) == pytest.approx(500, abs=3)


def _text_with_replaces(tmp_path, guide, replaces: tuple[str, ...], *pages: str) -> str:
    """pdftotext of a guide whose first row replaces ``replaces`` (``pages``: e.g. -f 4 -l 4)."""
    folder, _, rows = guide
    first = dataclasses.replace(rows[0], replaces=replaces)
    pdf = write_guide_pdf(tmp_path / "g.pdf", [first, *rows[1:]], front_png=folder / "front.png",
                          profile_png=folder / "profile.png", outline=np.array([r.position for r in rows]),
                          title="replaces")
    if shutil.which("pdftotext") is None:
        pytest.skip("poppler-utils (pdftotext) not installed")
    return subprocess.run(["pdftotext", *pages, str(pdf), "-"], capture_output=True, text=True,
                          check=True).stdout


def test_replaces_column_wraps_instead_of_cutting(tmp_path, guide):
    many = tuple(f"DENSE_MARKER_{k:02d}_L" for k in range(40))
    text = _text_with_replaces(tmp_path, guide, many, "-f", "4", "-l", "4")
    assert "..." not in text and all(label in text for label in many)


def test_regions_picture_keeps_its_axis_labels_inside(tmp_path):
    """blenderFace (read as mm, 0.5 mm across): the 'up (mm)' label was cut at the left edge."""
    import matplotlib.image as mpimg
    from conftest import shared_path

    from mocaptk.cli.cluster import write_cluster_pictures
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session, load_session

    csv = shared_path("facial_mocap", "blenderface", "Subject_01.csv")
    traj, source = load_session(csv, rate=50)
    result = cluster_session(traj, options=ClusterOptions(stabilize=False), source=source)
    write_cluster_pictures(result, tmp_path)  # as `mocaptk cluster` draws them
    image = mpimg.imread(tmp_path / "regions.png")[..., :3].mean(axis=2)
    assert (image[:, :3] > 0.95).all() and (image[:, -3:] > 0.95).all()  # nothing cut at the edges
    assert (image[:, 3:40] < 0.5).any()  # and the y label is there


def test_replaces_column_of_a_huge_cluster_is_cut_with_a_count(tmp_path, guide):
    """A 10,000-marker session's cluster replaces over 1,000 markers: its row must still fit a
    page (it used to be retried on new pages forever)."""
    many = tuple(f"DENSE_MARKER_{k:04d}_L" for k in range(2000))
    text = _text_with_replaces(tmp_path, guide, many)
    shown = [label for label in many if label in text]
    assert 50 < len(shown) < len(many) and shown == list(many[:len(shown)])
    assert f"and {len(many) - len(shown)} more (layout.json lists them all)" in text
    assert text.count("\f") < 12  # a handful of pages, not one per retry


def test_view_with_too_many_markers_draws_every_dot_unnumbered(tmp_path):
    """Past MAX_NUMBERED markers (a 10,000-marker session's 458) the dots are one artist, no
    numbers: each dot's centre still shows its region's colour."""
    import matplotlib.image as mpimg

    from mocaptk.retarget.renders import MAX_NUMBERED, _draw_markers, region_colour

    n = MAX_NUMBERED + 1
    grid = np.array([(40 + 30 * (k % 30), 60 + 30 * (k // 30)) for k in range(n)], float)
    regions = ["eye", "mouth", "nose"] * n
    image = np.full((600, 1000, 3), 255, np.uint8)
    _draw_markers(image, grid, np.ones(n, bool), regions[:n], [str(k) for k in range(n)],
                  tmp_path / "v.png", force=True)
    drawn = mpimg.imread(tmp_path / "v.png")[..., :3]
    centres = drawn[grid[:, 1].astype(int), grid[:, 0].astype(int)]
    expected = np.array([region_colour(r, tint=-0.35) for r in regions[:n]])
    assert np.abs(centres - expected).max() < 0.05
    # and no numbers: the black digits would sit up and right of each dot
    dark = [(drawn[y - 16:y - 6, x + 8:x + 22] < 0.3).all(axis=2).sum() for x, y in grid.astype(int)]
    assert max(dark) == 0


def test_long_labels_and_the_mirror_example_read_right(tmp_path, guide):
    """Issue 33: the table cut "FOREHEAD_BROW_18..." (R labels are wider than L), and the 1:1 page's
    example named "16L / 16R" even where 16 is a midline marker."""
    folder, _, rows = guide
    names = ["1L", "1R", "2"] + [f"{k + 3}" for k in range(len(rows) - 3)]
    sides = ["L", "R", "C"] + ["L"] * (len(rows) - 3)
    renamed = [dataclasses.replace(r, name=n, side=s, label=f"FOREHEAD_BROW_{k:02d}_{s}")
               for k, (r, n, s) in enumerate(zip(rows, names, sides))]
    pdf = write_guide_pdf(tmp_path / "g.pdf", renamed, front_png=folder / "front.png",
                          profile_png=folder / "profile.png", outline=np.array([r.position for r in rows]),
                          title="labels")
    if shutil.which("pdftotext") is None:
        pytest.skip("poppler-utils (pdftotext) not installed")
    text = subprocess.run(["pdftotext", str(pdf), "-"], capture_output=True, text=True, check=True).stdout
    assert "FOREHEAD_BROW_01_R" in text and "FOREHEAD_BROW_01..." not in text
    flat = " ".join(text.split())
    assert "(1L / 1R)" in flat and "A number alone" not in flat and "number alone (2) sits on the midline" in flat
    assert "16L / 16R" not in flat
