"""The printable marker placement guide, ``guide.pdf`` (fpdf2), and its PNG views.

Pages (A4 portrait; the 1:1 page grows to A3 if the face does not fit):

1. front view of the face - influence regions shaded, every layout marker numbered and
   coloured by region - with a region legend;
2. profile view (the character's left side);
3. the **1:1 page**: marker positions projected on the front (X-Y) plane at true size in mm,
   named, with the midline, the nose tip cross and 50 mm scale bars, horizontal and vertical, to
   check the print ("must measure 50 mm"), for building a placement mask; labels never overlap
   (a leader line joins a label moved away from a crowded marker);
4+. the marker table, pairs together: name, rig joint, label, region, side, position from the
   nose tip (mm right/left of the midline, above/below the tip, in front/behind) and every dense
   marker it replaces (its cluster; the count, then the labels, wrapped; past
   :data:`REPLACES_MAX_LINES` lines the first labels and how many more).

Names: a marker and its mirror image share a number, told apart by side (``16L`` / ``16R``), so a
technician places pairs together; other markers have a plain number. Numbers follow the layout
order; the table gives each marker's rig joint (layout order, 1 = first cluster). Landmarks: the
nose tip = the most forward dense marker; the midline = the sagittal plane through the nose tip
(x = nose tip's x in the rig frame). When the most forward marker is not at a nose's height (a
capture without nose markers, e.g. blenderFace: its most forward one is on the upper lip), the
pages call it the "front marker" instead (``landmark``).
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mocaptk.atomic import atomic_path

from mocaptk.clustering.regions import REGION_COLOURS, region_colour

__all__ = ["GuideMarker", "guide_markers", "pair_names", "place_labels", "write_guide_pdf"]

A4 = (210.0, 297.0)
A3 = (297.0, 420.0)
MARGIN = 12.0
SCALE_BAR_MM = 50.0
#: Page height below the face kept for the scale bars and the note (mm).
BARS_ZONE = 75.0
#: 1:1 page: marker dot radius and the label font size (pt; a digit is ~1.4 mm wide, 2.6 mm high).
DOT_MM = 1.5
LABEL_PT = 7
#: Table rows list at most this many lines of replaced dense markers (the rest is counted).
REPLACES_MAX_LINES = 40
#: Region name of the stabilization (head) markers: drawn as squares, listed last, no rig joint.
STABILIZATION = "stabilization"
#: Creation date written into the PDF, fixed so the same input gives the same bytes.
_FIXED_DATE = datetime.datetime(2024, 1, 1, tzinfo=datetime.timezone.utc)


@dataclass(frozen=True)
class GuideMarker:
    """One row of the guide: ``position`` (3,) mm rig frame; ``from_nose`` (3,) mm
    (+x = character's left, +y = up, +z = forward) relative to the nose tip; ``number`` the
    layout order (= rig joint), ``name`` what the guide prints (``16L``, ``16R`` or ``7``)."""

    number: int
    name: str
    label: str
    region: str
    side: str
    position: np.ndarray
    from_nose: np.ndarray
    replaces: tuple[str, ...]


def pair_names(labels: Sequence[str], sides: Sequence[str],
               mirrored_from: Sequence[str | None]) -> list[str]:
    """Guide names: a marker and its mirror share a number (first come, first numbered) with its
    side (``16L`` / ``16R``); a marker without a mirror has a plain number."""
    index = {label: k for k, label in enumerate(labels)}
    partner: dict[int, int] = {}
    for k, source in enumerate(mirrored_from):
        if source in index:
            partner[k], partner[index[source]] = index[source], k
    number: dict[int, int] = {}
    for k in range(len(labels)):
        if k not in number:
            number[k] = len(set(number.values())) + 1
            if k in partner:
                number[partner[k]] = number[k]
    return [f"{number[k]}{sides[k]}" if k in partner else str(number[k]) for k in range(len(labels))]


def guide_markers(labels: Sequence[str], regions: Sequence[str], sides: Sequence[str],
                  positions: np.ndarray, members: Sequence[Sequence[str]],
                  nose_tip: np.ndarray, mirrored_from: Sequence[str | None] | None = None,
                  stabilization: Sequence[tuple[str, str, np.ndarray]] = (),
                  ) -> list[GuideMarker]:
    """Guide rows for the layout markers (positions (J, 3) mm, rig frame); ``mirrored_from``:
    per marker, the label it mirrors (None: measured), for the pair names; ``stabilization``:
    ``(label, side, position)`` of the head markers a capture is posed from, named ``H1``, ``H2``
    ... (region :data:`STABILIZATION`, no rig joint: number 0)."""
    names = pair_names(labels, sides, mirrored_from or [None] * len(labels))
    out = []
    for k, (label, region, side, pos, group) in enumerate(zip(labels, regions, sides,
                                                              np.asarray(positions), members)):
        out.append(GuideMarker(k + 1, names[k], label, region, side, np.asarray(pos, float),
                               np.asarray(pos, float) - nose_tip,
                               tuple(m for m in group if m != label)))
    for k, (label, side, pos) in enumerate(stabilization):
        out.append(GuideMarker(0, f"H{k + 1}", label, STABILIZATION, side, np.asarray(pos, float),
                               np.asarray(pos, float) - nose_tip, ()))
    return out


def _overlaps(box: np.ndarray, boxes: np.ndarray) -> bool:
    """Does ``box`` (x0, y0, x1, y1) intersect any of ``boxes`` (N, 4)?"""
    if not len(boxes):
        return False
    return bool(np.any((box[0] < boxes[:, 2]) & (boxes[:, 0] < box[2])
                       & (box[1] < boxes[:, 3]) & (boxes[:, 1] < box[3])))


def place_labels(points: np.ndarray, sizes: np.ndarray, *, dot: float = DOT_MM, gap: float = 0.3,
                 reach: float = 30.0, bounds: tuple[float, float, float, float] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Boxes for labels beside marker dots, none overlapping another label or any dot.

    ``points`` (N, 2) mm page coordinates (y down), ``sizes`` (N, 2) label width/height mm. Tries
    the eight places around each dot, then rings further out (a leader line then joins label and
    dot), most crowded markers first. Returns boxes (N, 4) ``x0, y0, x1, y1`` and ``leader`` (N,)
    bool. A label that finds no free place within ``reach`` mm keeps the nearest place (rare).
    """
    points = np.asarray(points, float)
    sizes = np.asarray(sizes, float)
    dots = np.column_stack([points - dot - gap, points + dot + gap])
    crowd = (np.linalg.norm(points[:, None] - points[None], axis=2) < 8.0).sum(axis=1)
    order = np.lexsort((np.arange(len(points)), -crowd))
    boxes = np.zeros((len(points), 4))
    leader = np.zeros(len(points), bool)
    placed: list[np.ndarray] = []
    for k in order:
        (x, y), (w, h) = points[k], sizes[k]
        near = dot + gap
        candidates = [(x + near, y - near - h), (x + near, y - h / 2), (x + near, y + near),
                      (x - w / 2, y - near - h), (x - w / 2, y + near), (x - near - w, y - near - h),
                      (x - near - w, y - h / 2), (x - near - w, y + near)]
        for radius in np.arange(4.0, reach, 1.5):
            for angle in np.radians(np.arange(0, 360, 22.5)):
                cx, cy = x + radius * np.cos(angle), y - radius * np.sin(angle)
                candidates.append((cx - w / 2, cy - h / 2))
        others = np.delete(dots, k, axis=0)
        chosen = None
        for i, (x0, y0) in enumerate(candidates):
            box = np.array([x0, y0, x0 + w, y0 + h])
            if bounds is not None and (x0 < bounds[0] or y0 < bounds[1] or box[2] > bounds[2]
                                       or box[3] > bounds[3]):
                continue
            if not _overlaps(box, others) and not _overlaps(box, np.array(placed).reshape(-1, 4)):
                chosen, leader[k] = box, i >= 8
                break
        if chosen is None:
            x0, y0 = candidates[0]
            chosen = np.array([x0, y0, x0 + w, y0 + h])
        boxes[k] = chosen
        placed.append(chosen)
    return boxes, leader


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
                    landmark: str = "nose tip", force: bool = True) -> Path:
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
    landmark : what the reference point the rows are measured from is called.
    """
    from fpdf import FPDF

    pdf = FPDF(orientation="P", unit="mm", format="A4")
    pdf.set_auto_page_break(auto=False)
    pdf.set_creation_date(_FIXED_DATE)  # byte-stable output for the same input
    pdf.set_title("mocaptk marker placement guide")
    pdf.set_creator("mocaptk")

    _view_page(pdf, title, "Front view", front_png, markers, notes)
    _view_page(pdf, title, "Profile view (character's left side)", profile_png, markers, ())
    _scale_page(pdf, title, markers, outline, landmark)
    _table_pages(pdf, title, markers, landmark)
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


def _scale_page(pdf, title: str, markers: list[GuideMarker], outline: np.ndarray, landmark: str) -> None:
    nose = markers[0].position - markers[0].from_nose
    pts = np.array([m.position[:2] for m in markers])
    ring = np.asarray(outline, float)[:, :2]
    lo = np.minimum(pts.min(axis=0), ring.min(axis=0))
    hi = np.maximum(pts.max(axis=0), ring.max(axis=0))
    span = hi - lo
    size = A4 if span[0] + 2 * MARGIN + 20 <= A4[0] and span[1] + 2 * MARGIN + 22 + BARS_ZONE <= A4[1] else A3
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
    pdf.cell(10, 3, landmark)
    dots = np.array([page(m.position[:2]) for m in markers])
    pdf.set_font("helvetica", "B", LABEL_PT)
    text_h = LABEL_PT * 0.3528 * 0.9  # cap height + descent of the digits, mm
    sizes = np.array([(pdf.get_string_width(m.name) + 0.4, text_h) for m in markers])
    boxes, leader = place_labels(dots, sizes, bounds=(MARGIN, MARGIN + 16, width - MARGIN,
                                                      height - MARGIN - BARS_ZONE + 10))
    pdf.set_line_width(0.15)
    pdf.set_draw_color(110, 110, 110)
    for (x, y), box, long in zip(dots, boxes, leader):
        if long:  # from the dot's rim to the nearest point of its label
            tx, ty = np.clip(x, box[0], box[2]), np.clip(y, box[1], box[3])
            d = np.hypot(tx - x, ty - y)
            pdf.line(x + (tx - x) * DOT_MM / d, y + (ty - y) * DOT_MM / d, tx, ty)
    for m, (x, y), box in zip(markers, dots, boxes):
        r, g, b = (int(255 * c) for c in region_colour(m.region, tint=-0.2))
        pdf.set_fill_color(r, g, b)
        if m.region == STABILIZATION:  # a head marker: a square, never mistaken for a face dot
            pdf.rect(x - DOT_MM, y - DOT_MM, 2 * DOT_MM, 2 * DOT_MM, style="F")
        else:
            pdf.ellipse(x - DOT_MM, y - DOT_MM, 2 * DOT_MM, 2 * DOT_MM, style="F")
        pdf.text(box[0] + 0.2, box[3] - 0.35, m.name)  # baseline just above the box's bottom
    bx, by = MARGIN + 16, height - MARGIN - 18
    _scale_bars(pdf, bx, by)
    pdf.set_font("helvetica", "", 7)
    pdf.set_xy(bx + SCALE_BAR_MM + 8, by - 2)
    pair = next((m.name[:-1] for m in markers if m.name.endswith("L") and m.region != STABILIZATION), None)
    middle = next((m.name for m in markers if m.name.isdigit() and m.side == "C"), None)
    mirror = (f"A marker and its mirror share a number ({pair}L / {pair}R)" if pair else "") + \
        (f"{'; a' if pair else 'A'} number alone ({middle}) sits on the midline" if middle else "") + \
        (". " if pair or middle else "")
    pdf.multi_cell(width - bx - SCALE_BAR_MM - 8 - MARGIN, 3.5, align="L", text=_ascii(
        "Front projection, true size: markers on the sides of the face sit further apart on the "
        "skin than on paper. Dashed: face outline and midline. Character's left is on the "
        f"right, as seen facing the performer. {mirror}"
        "Squares H1, H2 ...: head (stabilization) markers on skin that does not move, placed like "
        "the others; every capture needs them. Check both bars before cutting a mask."))  # left-aligned: even spacing


def _scale_bars(pdf, bx: float, by: float) -> None:
    """A horizontal 50 mm bar from (bx, by) and a vertical one left of it, each "must measure 50 mm"."""
    pdf.set_draw_color(0, 0, 0)
    pdf.set_fill_color(0, 0, 0)
    pdf.rect(bx, by, SCALE_BAR_MM, 2.0, style="F")
    vx, vy = bx - 12.0, by - 4.0 - SCALE_BAR_MM  # apart from the horizontal bar: each measures alone
    pdf.rect(vx, vy, 2.0, SCALE_BAR_MM, style="F")
    pdf.set_line_width(0.15)  # thin ticks: the bars' printed ends stay at 0 and 50 mm
    for k in range(6):
        pdf.line(bx + 10 * k, by - 1.5, bx + 10 * k, by + 3.5)
        pdf.line(vx - 1.5, vy + 10 * k, vx + 3.5, vy + 10 * k)
    pdf.set_font("helvetica", "B", 9)
    pdf.set_xy(bx, by + 4)
    pdf.cell(SCALE_BAR_MM, 5, "must measure 50 mm", align="C")
    label_w = pdf.get_string_width("must measure 50 mm")
    cx, cy = vx + 7.0, vy + SCALE_BAR_MM / 2
    with pdf.rotation(90, cx, cy):  # reads bottom to top, beside the bar
        pdf.text(cx - label_w / 2, cy + 1.2, "must measure 50 mm")


def _table_pages(pdf, title: str, markers: list[GuideMarker], landmark: str) -> None:
    pdf.set_font("helvetica", "", 7)
    # the label and region columns as wide as their longest text (labels were cut: "FOREHEAD_BROW_18...")
    label_w = min(max(31.0, max(pdf.get_string_width(_ascii(m.label)) for m in markers) + 2.0), 60.0)
    region_w = min(max(19.0, max(pdf.get_string_width(_ascii(m.region)) for m in markers) + 2.0), 40.0)
    cols = [("#", 8), ("joint", 8), ("label", label_w), ("region", region_w), ("side", 6), ("from midline", 16),
            ("vs nose tip" if landmark == "nose tip" else "vs front pt", 16), ("depth", 16),
            ("replaces: count, dense markers of its cluster", 116 - label_w - region_w)]
    line_h = 3.4
    width, height = A4
    # pairs together (16L, 16R), in number order
    rows = sorted(markers, key=lambda m: (m.region == STABILIZATION, int(m.name.strip("HLRC")), m.name))
    wrapped: dict[str, list[str]] = {}
    first = True
    while rows or first:
        first = False
        pdf.add_page(format="A4")
        _header(pdf, title, f"Markers (mm from the {landmark})")
        y = MARGIN + 15
        pdf.set_font("helvetica", "B", 7)
        x = MARGIN
        for name, w in cols:
            pdf.set_xy(x, y)
            pdf.cell(w, 4.6, name, border="B")
            x += w
        y += 5.1
        pdf.set_font("helvetica", "", 7)
        while rows:
            m = rows[0]
            lateral, vertical, depth = _describe(m.from_nose)
            if m.name not in wrapped:  # once per row, also when it moves to the next page
                wrapped[m.name] = _replaces_lines(pdf, m.replaces, cols[-1][1] - 1) \
                    if m.region != STABILIZATION else ["head (stabilization) marker: every capture needs it"]
            lines = wrapped[m.name]
            row_h = line_h * len(lines) + 1.2
            if y + row_h > height - MARGIN:
                break
            rows.pop(0)
            values = [m.name, str(m.number) if m.number else "-", m.label, m.region, m.side,
                      lateral, vertical, depth]
            r, g, b = (int(255 * c) for c in region_colour(m.region, tint=0.75))
            pdf.set_fill_color(r, g, b)
            pdf.rect(MARGIN, y, sum(w for _, w in cols), row_h, style="F")
            x = MARGIN
            for (_, w), value in zip(cols, values):
                pdf.set_xy(x, y + 0.6)
                pdf.cell(w, line_h, _fit(pdf, _ascii(value), w - 1))
                x += w
            for i, line in enumerate(lines):
                pdf.set_xy(x, y + 0.6 + i * line_h)
                pdf.cell(cols[-1][1], line_h, line)
            y += row_h


def _replaces_lines(pdf, replaces: Sequence[str], width: float, *,
                    max_lines: int = REPLACES_MAX_LINES) -> list[str]:
    """The 'replaces' cell: count and labels wrapped to ``width`` mm; past ``max_lines`` lines the
    first labels, then how many more (a row taller than a page would never be placed)."""
    if not replaces:
        return ["-"]
    lines = _wrap(pdf, _ascii(f"{len(replaces)}: " + ", ".join(replaces)), width)
    if len(lines) <= max_lines:
        return lines
    measure = _Measure(pdf, width)
    shown, units = [""], 0
    space = measure.units(" ")
    for k, label in enumerate(replaces):  # whole labels, filling max_lines - 1 lines
        word = (f"{len(replaces)}: " if k == 0 else "") + _ascii(label) + ","
        size = measure.units(word)
        if not shown[-1]:
            shown[-1], units = word, size
        elif measure.fits(units + space + size, f"{shown[-1]} {word}"):
            shown[-1], units = f"{shown[-1]} {word}", units + space + size
        elif len(shown) < max_lines - 1:
            shown.append(word)
            units = size
        else:
            return shown + [f"... and {len(replaces) - k} more (layout.json lists them all)"]
    return shown


def _wrap(pdf, text: str, width: float) -> list[str]:
    """``text`` broken after commas into lines of at most ``width`` mm in the current font."""
    measure = _Measure(pdf, width)
    lines, units = [""], 0
    space = measure.units(" ")
    for word in text.split(" "):
        size = measure.units(word)
        if not lines[-1]:
            lines[-1], units = word, size
        elif measure.fits(units + space + size, f"{lines[-1]} {word}"):
            lines[-1], units = f"{lines[-1]} {word}", units + space + size
        else:
            lines.append(word)
            units = size
    return lines


def _fit(pdf, text: str, width: float) -> str:
    """Shorten ``text`` with '...' to fit ``width`` mm in the current font."""
    measure = _Measure(pdf, width)
    if measure.fits(measure.units(text), text):
        return text
    while text and pdf.get_string_width(text + "...") > width:
        text = text[:-1]
    return text + "..."


class _Measure:
    """Does a string fit ``width`` mm in the pdf's current font? For a core font (fixed glyph
    widths, no stretching or spacing) from glyph-width sums kept per word, the same sum fpdf2's
    ``get_string_width`` takes through its text-shaping layers (~0.2 ms a call; a 10,000-marker
    table measures ~40,000 strings); that function decides a width within 1e-6 mm of the limit
    (rounding) and every other font."""

    def __init__(self, pdf, width: float) -> None:
        self.pdf, self.width = pdf, width
        core = not pdf.is_ttf_font and pdf.font_stretching == 100 and not pdf.char_spacing
        self.glyphs = pdf.current_font.cw if core else None
        self.mm_per_unit = pdf.font_size_pt * 0.001 / pdf.k

    def units(self, text: str) -> int:
        """Summed glyph widths of ``text`` (font units; 0 when not a core font)."""
        if self.glyphs is None:
            return 0
        return sum(self.glyphs[c] for c in self.pdf.normalize_text(text))

    def fits(self, units: int, text: str) -> bool:
        """``text`` (of summed glyph widths ``units``) is at most ``width`` mm wide."""
        if self.glyphs is not None and abs(units * self.mm_per_unit - self.width) > 1e-6:
            return units * self.mm_per_unit < self.width
        return self.pdf.get_string_width(text) <= self.width


def _ascii(text: str) -> str:
    """Core PDF fonts are Latin-1; replace anything else."""
    return str(text).encode("latin-1", "replace").decode("latin-1")


def _convex_hull(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    return points[ConvexHull(points).vertices]


