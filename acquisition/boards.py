"""Calibration boards (checkerboard, ChArUco): geometry and corner detection in one image.

Board coordinates are mm in the board plane (``Z = 0``); corner ``i`` of a checkerboard with
``cols x rows`` inner corners is at ``(i % cols, i // cols) * square``. ChArUco corners carry
the ids of ``cv2.aruco.CharucoBoard`` (unique, so a partial view still matches).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Images are searched for a checkerboard at most this large (long side, px), then the corners
#: are scaled back: the sector-based detector is as precise on half-size photos and 4x faster.
DETECT_LONG_SIDE = 1100


@dataclass(frozen=True)
class Board:
    """A planar calibration target.

    kind : ``"checkerboard"`` or ``"charuco"``.
    corners : (cols, rows) inner corners.
    square : square side, mm.
    marker : ArUco marker side, mm (ChArUco only).
    dictionary : OpenCV predefined ArUco dictionary name (ChArUco only).
    """

    kind: str
    corners: tuple[int, int]
    square: float
    marker: float = 0.0
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in ("checkerboard", "charuco"):
            raise ValueError(f"board must be checkerboard or charuco, got {self.kind!r}")
        cols, rows = self.corners
        if cols < 2 or rows < 2:
            raise ValueError(f"a board needs at least 2x2 inner corners, got {cols}x{rows}")
        if not self.square > 0:
            raise ValueError(f"square size must be > 0 mm, got {self.square}")
        if self.kind == "charuco":
            if not 0 < self.marker < self.square:
                raise ValueError(f"marker size must be within (0, square) mm, got {self.marker}")
            if not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")

    @property
    def n_corners(self) -> int:
        return self.corners[0] * self.corners[1]

    def object_points(self) -> np.ndarray:
        """(N, 3) float corner positions in board coordinates, mm (index = corner id)."""
        cols, rows = self.corners
        grid = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2)
        # ChArUco inner corners start one square in from the board's outer edge
        offset = self.square if self.kind == "charuco" else 0.0
        return np.column_stack([grid * self.square + offset, np.zeros(len(grid))])

    def size_mm(self) -> tuple[float, float]:
        """Outer (width, height) of a ChArUco board in mm (squares = inner corners + 1)."""
        return (self.corners[0] + 1) * self.square, (self.corners[1] + 1) * self.square

    def charuco(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board (squares = inner corners + 1 each way)."""
        cols, rows = self.corners
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((cols + 1, rows + 1), self.square, self.marker, dictionary)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corners of the board in one 8-bit grey image.

        Returns ``ids (K,) int`` and ``pixels (K, 2) float`` px (K = 0: not found). A
        checkerboard is all-or-nothing; a ChArUco board may be partial (>= 6 corners kept).
        """
        if self.kind == "checkerboard":
            return _detect_checkerboard(gray, self.corners)
        charuco_corners, charuco_ids, _, _ = cv2.aruco.CharucoDetector(self.charuco()).detectBoard(gray)
        if charuco_ids is None or len(charuco_ids) < 6:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
        order = np.argsort(charuco_ids.ravel())
        return (charuco_ids.ravel()[order].astype(np.int64),
                charuco_corners.reshape(-1, 2)[order].astype(np.float64))


def _detect_checkerboard(gray: np.ndarray, corners: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    scale = min(1.0, DETECT_LONG_SIDE / max(gray.shape))
    small = gray if scale == 1.0 else cv2.resize(gray, None, fx=scale, fy=scale,
                                                  interpolation=cv2.INTER_AREA)
    found, pixels = cv2.findChessboardCornersSB(
        small, corners, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    # pixel centres: (0, 0) is the centre of the top-left pixel at both scales
    pixels = (pixels.reshape(-1, 2).astype(np.float64) + 0.5) / scale - 0.5
    return np.arange(len(pixels)), pixels
