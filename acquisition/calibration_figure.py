"""Check pictures: detected board corners against their reprojections; panels side by side."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

#: Residual vectors are drawn this many times longer than they are (sub-pixel errors).
ARROW_GAIN = 100.0
PANEL_HEIGHT = 960


def corner_panel(gray: np.ndarray, detected: np.ndarray, reprojected: np.ndarray,
                 title: str) -> np.ndarray:
    """One BGR panel: ``detected`` corners (green rings), ``reprojected`` (red dots), and the
    residual from one to the other x :data:`ARROW_GAIN` (yellow), both ``(K, 2)`` px."""
    scale = PANEL_HEIGHT / gray.shape[0]
    image = cv2.cvtColor(cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA),
                         cv2.COLOR_GRAY2BGR)
    image = (image * 0.6).astype(np.uint8)  # dimmed, so the marks stand out
    for d, r in zip(detected * scale, reprojected * scale):
        tip = d + (r - d) * ARROW_GAIN
        cv2.line(image, _pt(d), _pt(tip), (0, 230, 255), 1, cv2.LINE_AA)
        cv2.circle(image, _pt(d), 7, (0, 220, 0), 1, cv2.LINE_AA)
        cv2.circle(image, _pt(r), 2, (0, 0, 255), -1, cv2.LINE_AA)
    for row, text in enumerate(title.split("\n")):
        cv2.putText(image, text, (10, 28 + 26 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.7,
                    (255, 255, 255), 2, cv2.LINE_AA)
    return image


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


CORNER_LEGEND = (f"green ring: detected corner   red dot: reprojection   yellow: residual "
                 f"x{ARROW_GAIN:g}")


def mosaic(panels: Sequence[np.ndarray], *, legend: str = CORNER_LEGEND) -> np.ndarray:
    """Panels side by side (same height), with a ``legend`` strip below."""
    row = np.hstack([np.pad(p, ((0, 0), (0, 6), (0, 0)), constant_values=255) for p in panels])
    strip = np.full((40, row.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, legend, (10, 27), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([row, strip])
