"""The printable marker placement guide, ``guide.pdf`` (fpdf2), and its PNG views.

Pages (A4 portrait; the 1:1 page grows to A3 if the face does not fit):

1. front view of the face - influence regions shaded, every layout marker numbered and
   coloured by region - with a region legend;
2. profile view (the character's left side);
3. the **1:1 page**: marker positions projected on the front (X-Y) plane at true size in mm,
   numbered, with the midline, the nose tip cross and a 50 mm scale bar to check the print
   ("must measure 50 mm"), for building a placement mask;
4+. the marker table: number, label, region, side, position from the nose tip (mm right/left
   of the midline, above/below the tip, in front/behind) and the dense markers it replaces
   (its cluster; the count, then as many labels as fit).

Numbers are the layout order (1 = first cluster), the same in every view, the table and the
rig's joints. Landmarks: the nose tip = the most forward dense marker; the midline = the
sagittal plane through the nose tip (x = nose tip's x in the rig frame).
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path

from .renders import REGION_COLOURS, region_colour

__all__ = ["GuideMarker", "guide_markers", "write_guide_pdf"]

A4 = (210.0, 297.0)
A3 = (297.0, 420.0)
MARGIN = 12.0
SCALE_BAR_MM = 50.0
#: Creation date written into the PDF, fixed so the same input gives the same bytes.
_FIXED_DATE = datetime.datetime(2024, 1, 1, tzinfo=datetime.timezone.utc)


@dataclass(frozen=True)
class GuideMarker:
    """One row of the guide: ``position`` (3,) mm rig frame; ``from_nose`` (3,) mm
    (+x = character's left, +y = up, +z = forward) relative to the nose tip."""

    number: int
    label: str
    region: str
    side: str
    position: np.ndarray
    from_nose: np.ndarray
    replaces: tuple[str, ...]


def guide_markers(labels: Sequence[str], regions: Sequence[str], sides: Sequence[str],
                  positions: np.ndarray, members: Sequence[Sequence[str]],
                  nose_tip: np.ndarray) -> list[GuideMarker]:
    """Guide rows for the layout markers (positions (J, 3) mm, rig frame)."""
    out = []
    for k, (label, region, side, pos, group) in enumerate(zip(labels, regions, sides,
                                                              np.asarray(positions), members)):
        out.append(GuideMarker(k + 1, label, region, side, np.asarray(pos, float),
                               np.asarray(pos, float) - nose_tip,
                               tuple(m for m in group if m != label)))
    return out


def _describe(offset: np.ndarray) -> tuple[str, str, str]:
    """'12 L' / '3 above' / '20 behind' (mm, rounded) of an offset from the nose tip."""
    x, y, z = (float(v) for v in offset)
    lateral = "midline" if abs(x) < 2.0 else f"{abs(x):.0f} {'L' if x > 0 else 'R'}"
    vertical = "level" if abs(y) < 2.0 else f"{abs(y):.0f} {'above' if y > 0 else 'below'}"
    depth = "level" if abs(z) < 2.0 else f"{abs(z):.0f} {'front' if z > 0 else 'behind'}"
    return lateral, vertical, depth


def write_guide_pdf(path: str | os.PathLike[str], markers: list[GuideMarker], *,
                    front_png: str | os.PathLike[str], profile_png: str | os.PathLike[str],
                    outline: np.ndarray, title: str, notes: Sequence[str] = (),
                    force: bool = True) -> Path:
    """Write ``guide.pdf``.

    Parameters
    ----------
    markers : guide rows (see :func:`guide_markers`)
    front_png, profile_png : the rendered views
    outline : (K, 3) mm
        Points whose front projection outlines the face on the 1:1 page (e.g. the dense
        markers); drawn as their convex hull.
    title : str
        First line of every page (session / layout name).
    notes : lines printed under the legend on page 1 (mesh, RMSE ...).
    """
    from fpdf import FPDF

    pdf = FPDF(orientation="P", unit="mm", format="A4")
    pdf.set_auto_page_break(auto=False)
    pdf.set_creation_date(_FIXED_DATE)  # byte-stable output for the same input
    pdf.set_title("mocaptk marker placement guide")
    pdf.set_creator("mocaptk")

    _view_page(pdf, title, "Front view", front_png, markers, notes)
    _view_page(pdf, title, "Profile view (character's left side)", profile_png, markers, ())
    _scale_page(pdf, title, markers, outline)
    _table_pages(pdf, title, markers)
    with atomic_path(path, force=force) as tmp:
        pdf.output(str(tmp))
    return Path(path)


def _header(pdf, title: str, heading: str) -> None:
    pdf.set_font("helvetica", "B", 14)
    pdf.set_xy(MARGIN, MARGIN)
    pdf.cell(0, 7, _ascii(heading))
    pdf.set_font("helvetica", "", 8)
    pdf.set_xy(MARGIN, MARGIN + 7)
    pdf.cell(0, 5, _ascii(title))


def _view_page(pdf, title: str, heading: str, png: str | os.PathLike[str],
               markers: list[GuideMarker], notes: Sequence[str]) -> None:
    pdf.add_page(format="A4")
    _header(pdf, title, heading)
    width, height = A4
    image_h = height - 2 * MARGIN - 50
    image_w = image_h * 1050 / 1200
    pdf.image(str(png), x=(width - image_w) / 2, y=MARGIN + 14, w=image_w, h=image_h)
    y = MARGIN + 16 + image_h
    x = MARGIN
    pdf.set_font("helvetica", "", 9)
    used = sorted({m.region for m in markers}, key=lambda r: list(REGION_COLOURS).index(r)
                  if r in REGION_COLOURS else 99)
    for region in used:
        count = sum(m.region == region for m in markers)
        r, g, b = (int(255 * c) for c in region_colour(region))
        pdf.set_fill_color(r, g, b)
        pdf.rect(x, y + 1, 4, 4, style="F")
        pdf.set_xy(x + 5, y)
        pdf.cell(40, 6, _ascii(f"{region} ({count})"))
        x += 46
        if x > width - MARGIN - 40:
            x, y = MARGIN, y + 6
    y += 8
    pdf.set_font("helvetica", "", 8)
    for line in notes:
        pdf.set_xy(MARGIN, y)
        pdf.cell(0, 4, _ascii(line))
        y += 4


def _scale_page(pdf, title: str, markers: list[GuideMarker], outline: np.ndarray) -> None:
    nose = markers[0].position - markers[0].from_nose
    pts = np.array([m.position[:2] for m in markers])
    ring = np.asarray(outline, float)[:, :2]
    lo = np.minimum(pts.min(axis=0), ring.min(axis=0))
    hi = np.maximum(pts.max(axis=0), ring.max(axis=0))
    span = hi - lo
    size = A4 if span[0] + 2 * MARGIN <= A4[0] and span[1] + 2 * MARGIN + 40 <= A4[1] else A3
    pdf.add_page(format=size)
    width, height = size
    _header(pdf, title, f"1:1 scale placement page (print at 100 %, {'A4' if size == A4 else 'A3'})")
    # as seen facing the performer (like the front render): character's left (+x) on the
    # page's right, up = page up; 1 mm on the face = 1 mm on paper
    ox = width / 2 - (lo[0] + hi[0]) / 2
    oy = MARGIN + 22 + hi[1]

    def page(p: np.ndarray) -> tuple[float, float]:
        return float(ox + p[0]), float(oy - p[1])

    hull = _convex_hull(ring)
    pdf.set_draw_color(150, 150, 150)
    pdf.set_line_width(0.3)
    pdf.set_dash_pattern(dash=2, gap=1.5)
    pdf.polygon([page(p) for p in hull], style="D")
    x_mid, _ = page(nose[:2])
    pdf.line(x_mid, oy - hi[1] - 5, x_mid, oy - lo[1] + 5)
    pdf.set_dash_pattern()
    nx, ny = page(nose[:2])
    pdf.set_draw_color(0, 0, 0)
    pdf.line(nx - 4, ny, nx + 4, ny)
    pdf.line(nx, ny - 4, nx, ny + 4)
    pdf.set_font("helvetica", "", 6)
    pdf.set_xy(nx + 1, ny + 0.5)
    pdf.cell(10, 3, "nose tip")
    for m in markers:
        x, y = page(m.position[:2])
        r, g, b = (int(255 * c) for c in region_colour(m.region, tint=-0.2))
        pdf.set_fill_color(r, g, b)
        pdf.ellipse(x - 1.5, y - 1.5, 3.0, 3.0, style="F")
        pdf.set_font("helvetica", "B", 7)
        pdf.set_xy(x + 1.4, y - 3.4)
        pdf.cell(6, 3, str(m.number))
    # scale bar
    bx, by = MARGIN + 5, height - MARGIN - 18
    pdf.set_draw_color(0, 0, 0)
    pdf.set_fill_color(0, 0, 0)
    pdf.set_line_width(0.4)
    pdf.rect(bx, by, SCALE_BAR_MM, 2.0, style="F")
    pdf.set_line_width(0.15)  # thin ticks: the bar's printed ends stay at 0 and 50 mm
    for k in range(6):
        pdf.line(bx + 10 * k, by - 1.5, bx + 10 * k, by + 3.5)
    pdf.set_font("helvetica", "B", 9)
    pdf.set_xy(bx, by + 4)
    pdf.cell(SCALE_BAR_MM, 5, "must measure 50 mm", align="C")
    pdf.set_font("helvetica", "", 7)
    pdf.set_xy(bx + SCALE_BAR_MM + 8, by - 2)
    pdf.multi_cell(width - bx - SCALE_BAR_MM - 8 - MARGIN, 3.5, _ascii(
        "Front projection, true size: markers on the sides of the face sit further apart on the "
        "skin than on paper. Dashed: face outline and midline. Character's left is on the "
        "right, as seen facing the performer. Check the bar before cutting a mask."))


def _table_pages(pdf, title: str, markers: list[GuideMarker]) -> None:
    cols = [("#", 7), ("label", 34), ("region", 20), ("side", 7), ("from midline", 17),
            ("vs nose tip", 18), ("depth", 17),
            ("replaces: count, dense markers of its cluster", 66)]
    row_h = 4.6
    width, height = A4
    rows = list(markers)
    first = True
    while rows or first:
        first = False
        pdf.add_page(format="A4")
        _header(pdf, title, "Markers (mm from the nose tip)")
        y = MARGIN + 15
        pdf.set_font("helvetica", "B", 7)
        x = MARGIN
        for name, w in cols:
            pdf.set_xy(x, y)
            pdf.cell(w, row_h, name, border="B")
            x += w
        y += row_h + 0.5
        pdf.set_font("helvetica", "", 7)
        while rows and y + row_h <= height - MARGIN:
            m = rows.pop(0)
            lateral, vertical, depth = _describe(m.from_nose)
            shown = f"{len(m.replaces)}: " + ", ".join(m.replaces) if m.replaces else ""
            values = [str(m.number), m.label, m.region, m.side, lateral, vertical, depth,
                      shown or "-"]
            r, g, b = (int(255 * c) for c in region_colour(m.region, tint=0.75))
            pdf.set_fill_color(r, g, b)
            x = MARGIN
            for (_, w), value in zip(cols, values):
                pdf.set_xy(x, y)
                text = _fit(pdf, _ascii(value), w - 1)
                pdf.cell(w, row_h, text, fill=True)
                x += w
            y += row_h


def _fit(pdf, text: str, width: float) -> str:
    """Shorten ``text`` with '...' to fit ``width`` mm in the current font."""
    if pdf.get_string_width(text) <= width:
        return text
    while text and pdf.get_string_width(text + "...") > width:
        text = text[:-1]
    return text + "..."


def _ascii(text: str) -> str:
    """Core PDF fonts are Latin-1; replace anything else."""
    return str(text).encode("latin-1", "replace").decode("latin-1")


def _convex_hull(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    return points[ConvexHull(points).vertices]


