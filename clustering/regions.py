"""Facial regions: read from a file, derived from label prefixes, or segmented from the neutral pose.

A region map is ``{region name: [marker labels]}`` with every label in at most one region.
"""

from __future__ import annotations

import colorsys
import csv
import os
import re
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mocaptk.acquisition.orientation import face_axes, label_pairs
from mocaptk.acquisition.text_io import UTF16_PROBLEM, looks_utf16
from mocaptk.errors import InputFileError, quoted, shorten
from mocaptk.jsonio import parse_json, read_input_bytes

#: The six facial regions of the paper, top to bottom.
FACIAL_REGIONS = ("forehead_brow", "eye", "nose", "cheek", "mouth", "chin")
#: RGB (0-1) of the six facial regions: the same in regions.png, the guide and the report.
REGION_COLOURS: dict[str, tuple[float, float, float]] = {
    "forehead_brow": (0.20, 0.45, 0.85),
    "eye": (0.55, 0.30, 0.80),
    "nose": (0.90, 0.55, 0.10),
    "cheek": (0.20, 0.65, 0.35),
    "mouth": (0.85, 0.20, 0.25),
    "chin": (0.60, 0.45, 0.25),
    "stabilization": (0.20, 0.20, 0.20),  # head markers: dark, as the report's black squares
}
#: The face outside every region ("other").
OTHER_COLOUR = (0.40, 0.50, 0.60)
#: Colours of regions of other names (a user's regions file), picked by the name: stable everywhere.
_MORE_COLOURS = ((0.10, 0.60, 0.65), (0.80, 0.40, 0.60), (0.45, 0.55, 0.15), (0.95, 0.75, 0.15),
                 (0.35, 0.25, 0.55), (0.70, 0.30, 0.10), (0.25, 0.35, 0.45), (0.55, 0.75, 0.85))


def region_colour(region: str, *, tint: float = 0.0) -> tuple[float, float, float]:
    """RGB of a region; ``tint`` in [-1, 1] lightens (>0) or darkens (<0) it."""
    base = REGION_COLOURS.get(region) or (OTHER_COLOUR if region == "other" else
                                          _MORE_COLOURS[zlib.crc32(region.encode("utf-8", "replace")) % 8])
    h, light, s = colorsys.rgb_to_hls(*base)
    light = light + tint * (1.0 - light) if tint > 0 else light * (1.0 + tint)
    return colorsys.hls_to_rgb(h, min(max(light, 0.0), 1.0), s)

#: ``MOUTH_03``, ``FOREHEAD_BROW_05_L``, ``Anna:NOSE_1_C``: region words, a number, optional side tag.
_PREFIX_LABEL = re.compile(r"^(?:.*:)?([A-Za-z]+(?:_[A-Za-z]+)*)_\d+(?:_[LRCM])?$")


def read_regions(path: str | os.PathLike[str], labels: Sequence[str]) -> dict[str, list[str]]:
    """Read a regions file: JSON ``{"region": ["LABEL", ...]}`` or CSV rows ``label,region``.

    Raises :class:`InputFileError` for a malformed file, a label in two regions, or labels that
    are not markers of the session (``labels``).
    """
    path = Path(path)
    data = read_input_bytes(path, what="a regions file",
                            head_problem=lambda head: UTF16_PROBLEM if looks_utf16(head[:8192]) else None)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:  # e.g. a CSV saved by Excel in Latin-1 / Windows-1252
        raise InputFileError(path, f"not UTF-8 text (bad byte at offset {exc.start}): re-save it as UTF-8") from None
    regions: dict[str, list[str]] = {}
    if text.lstrip().startswith("{"):
        for name, members in parse_json(text, path).items():
            if not isinstance(members, list) or not all(isinstance(m, str) for m in members):
                raise InputFileError(path, f"region {quoted(name)} must be a list of marker labels")
            if not members:
                raise InputFileError(path, f"region {quoted(name)} lists no markers (remove it, or list its labels)")
            regions[str(name)] = list(members)
    else:
        # any cell length: the whole file is in memory already (csv's default limit is 131,072)
        csv.field_size_limit(max(csv.field_size_limit(), len(text) + 1))
        rows = [row for row in csv.reader(text.splitlines()) if row and any(c.strip() for c in row)]
        if rows and [c.strip().lower() for c in rows[0][:2]] == ["label", "region"]:
            rows = rows[1:]
        for number, row in enumerate(rows, start=1):
            if len(row) < 2 or not row[0].strip() or not row[1].strip():
                raise InputFileError(path, f"row {number}: expected 'label,region', got {quoted(','.join(row))}")
            regions.setdefault(row[1].strip(), []).append(row[0].strip())
    if not regions:
        raise InputFileError(path, "no regions defined")
    for name, members in regions.items():  # a line break would split every message naming it
        odd = next((t for t in (name, *members)
                    if any((ch.isspace() and ch != " ") or ord(ch) < 32 or 127 <= ord(ch) < 160 for ch in t)), None)
        if odd is not None:
            raise InputFileError(path, f"{quoted(odd)} holds a control character or a line break")
    seen: dict[str, str] = {}
    for name, members in regions.items():
        for label in members:
            if label in seen:
                raise InputFileError(path, f"marker {quoted(label)} is in two regions ({quoted(seen[label])}, "
                                     f"{quoted(name)})")
            seen[label] = name
    known = set(labels)
    unknown = [label for label in seen if label not in known]
    if unknown:
        raise InputFileError(path, f"{len(unknown)} labels are not markers of the session: "
                             + ", ".join(shorten(label, 40) for label in unknown[:5])
                             + (" ..." if len(unknown) > 5 else ""))
    return regions


def regions_from_prefixes(labels: Sequence[str]) -> dict[str, list[str]] | None:
    """Regions from label prefixes (``MOUTH_03_L`` → ``mouth``); None unless ALL labels follow it."""
    regions: dict[str, list[str]] = {}
    for label in labels:
        match = _PREFIX_LABEL.match(label)
        if match is None:
            return None
        regions.setdefault(match.group(1).lower(), []).append(label)
    return regions


def face_frame(neutral: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Rows: lateral (the subject's left), up, forward unit axes of the face, from the neutral
    pose ``(M, 3)`` mm and each marker's displacement ``(M,)`` mm, by the geometry alone
    (:func:`~mocaptk.acquisition.orientation.face_axes`: largest extent = up, signed by the
    motion and the face's taper; forward = the way the face bulges; lateral = up × forward)."""
    return face_axes(neutral, displacement)[0]


def geometric_regions(labels: Sequence[str], neutral: np.ndarray, displacement: np.ndarray, *,
                      frame: np.ndarray | None = None) -> dict[str, list[str]]:
    """Segment the neutral pose into the six facial regions by height and distance from the midline.

    In the face frame (:func:`face_frame`), ``u`` = height normalised to 0 (lowest marker) .. 1
    (highest), ``v`` = |lateral offset from the median lateral position| / face height. Bands:
    u >= 0.75 forehead_brow; 0.55-0.75: nose if v < 0.1, eye if v < 0.35, else cheek;
    0.35-0.55: nose if v < 0.12, else cheek; 0.15-0.35: mouth if v < 0.25, else cheek;
    u < 0.15 chin. Mirror pairs named by the labels (``CL4``/``CR4``, see
    :func:`~mocaptk.acquisition.orientation.label_pairs`) share their mean (u, v), so regions are
    symmetric, and the midline lies halfway between them. Markers with a NaN neutral position are
    left out.
    """

    valid = np.isfinite(neutral).all(axis=1)
    frame = face_frame(neutral[valid], displacement[valid]) if frame is None else frame
    local = (neutral[valid] - neutral[valid].mean(axis=0)) @ frame.T
    height = np.ptp(local[:, 1]) or 1.0
    u = (local[:, 1] - local[:, 1].min()) / height
    position = np.cumsum(valid) - 1  # index among the valid markers
    pairs = [(position[i], position[j]) for i, j in label_pairs(labels) if valid[i] and valid[j]]
    # midline: halfway between named mirror pairs (else the median); a pair shares its region
    mid = np.mean([(local[i, 0] + local[j, 0]) / 2 for i, j in pairs]) if pairs else np.median(local[:, 0])
    v = np.abs(local[:, 0] - mid) / height
    for i, j in pairs:
        u[i] = u[j] = (u[i] + u[j]) / 2
        v[i] = v[j] = (v[i] + v[j]) / 2
    names = np.select(
        [u >= 0.75,
         (u >= 0.55) & (v < 0.1), (u >= 0.55) & (v < 0.35), u >= 0.55,
         (u >= 0.35) & (v < 0.12), u >= 0.35,
         (u >= 0.15) & (v < 0.25), u >= 0.15],
        ["forehead_brow", "nose", "eye", "cheek", "nose", "cheek", "mouth", "cheek"],
        default="chin")
    valid_labels = [label for label, ok in zip(labels, valid) if ok]
    return {region: [lab for lab, n in zip(valid_labels, names) if n == region]
            for region in FACIAL_REGIONS if (names == region).any()}


def default_regions(labels: Sequence[str], neutral: np.ndarray, displacement: np.ndarray, *,
                    frame: np.ndarray | None = None) -> tuple[dict[str, list[str]], str]:
    """(regions, how) — from label prefixes when all labels follow them, else geometric (in
    ``frame``, rows lateral, up, forward; default :func:`face_frame`)."""
    by_prefix = regions_from_prefixes(labels)
    if by_prefix is not None:
        return by_prefix, "label prefixes"
    return geometric_regions(labels, neutral, displacement, frame=frame), "geometric segmentation of the neutral pose"


def unassigned(regions: dict[str, list[str]], labels: Sequence[str]) -> list[str]:
    """Labels that are in no region (in session order)."""
    assigned = {label for members in regions.values() for label in members}
    return [label for label in labels if label not in assigned]
