"""One camera's images: a folder of photos / a PNG sequence, or a video file, read as 8-bit grey.

Photos are taken in name order (natural: ``2`` before ``10``); a video is sampled every
``step`` frames. All images of one camera must have the same size.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mocaptk.errors import InputFileError

from .scratch import Scratch
from .stored_png import read_stored, stored_size

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


@dataclass(frozen=True)
class ImageSource:
    """A folder of images or a video file of one camera."""

    path: Path
    step: int = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if not self.path.exists():
            raise InputFileError(self.path, "no such file or folder")
        if self.path.is_dir() and not self.files():
            raise InputFileError(self.path, f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")

    @property
    def is_video(self) -> bool:
        return not self.path.is_dir()

    def files(self) -> list[Path]:
        return sorted((p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                      key=_natural_key)

    def frames(self) -> Iterator[tuple[str, np.ndarray]]:
        """``(name, grey uint8 image)`` of every photo, or every ``step``-th video frame."""
        size = None
        for name, image in (self._video() if self.is_video else self._photos()):
            size = self.check_size(name, (image.shape[1], image.shape[0]), size)
            yield name, image

    def check_size(self, name: str, shape: tuple[int, int],
                   size: tuple[int, int] | None) -> tuple[int, int]:
        """``shape``: image ``name``'s (width, height) px, returned; raises InputFileError when
        it is not ``size`` (the camera's first image's; None: this is the first)."""
        if size is not None and shape != size:
            raise InputFileError(self.path, f"{name} is {shape[0]}x{shape[1]} px, the first "
                                            f"image is {size[0]}x{size[1]}: one camera's images "
                                            "must share one size")
        return shape

    def _photos(self) -> Iterator[tuple[str, np.ndarray]]:
        for file in self.files():
            yield file.name, read_grey(file)

    def jpeg_frames(self) -> Iterator[tuple[str, np.ndarray]] | None:
        """An MJPG video's every ``step``-th frame as its JPEG bytes, unread: the caller decodes
        them on its threads with :func:`decode_jpeg` (libjpeg decodes the grey channel alone,
        ~2.3 CPU-ms against FFmpeg's 4.8 with its colour conversion). None for a folder, another
        codec, or packets that libjpeg cannot decode (FFmpeg then reads them as any video)."""
        if not self.is_video:
            return None
        capture = cv2.VideoCapture(os.fspath(self.path))
        fourcc = (int(capture.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF).to_bytes(4, "little").upper()
        ok, packet = (fourcc == b"MJPG" and capture.set(cv2.CAP_PROP_FORMAT, -1)
                      and capture.read()) or (False, None)
        if not ok or decode_jpeg(packet.reshape(-1)) is None:
            capture.release()
            return None
        return self._packets(capture, packet)

    def _packets(self, capture: cv2.VideoCapture, packet: np.ndarray) -> Iterator[tuple[str, np.ndarray]]:
        try:
            index, ok = 0, True
            while ok:
                if index % self.step == 0:
                    yield f"frame {index}", packet.reshape(-1).copy()
                ok, packet = capture.read()
                index += 1
        finally:
            capture.release()

    def _video(self) -> Iterator[tuple[str, np.ndarray]]:
        capture = cv2.VideoCapture(os.fspath(self.path))
        try:
            ok, frame = capture.read()
            if not ok:
                raise InputFileError(self.path, "cannot decode this as an image folder or a video")
            index = 0
            while ok:
                if index % self.step == 0:
                    yield f"frame {index}", cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                ok, frame = capture.read()
                index += 1
        finally:
            capture.release()


def read_grey(file: Path, *, scratch: Scratch | None = None) -> np.ndarray:
    """One photo as an 8-bit grey image. An uncompressed grey PNG (``synth --images``) is copied
    out of the file (:mod:`.stored_png`), anything else decoded by OpenCV (which releases the
    GIL). With ``scratch`` the image lives in its buffer until the next read into it."""
    scratch = scratch or Scratch()
    try:
        with open(file, "rb") as handle:
            size = stored_size(handle.read(33))
            total = os.fstat(handle.fileno()).st_size
            # only a file the size of its rows is read whole (a deflated one goes to OpenCV as
            # is), so what is allocated is never more than the file holds
            rows = size[1] * (size[0] + 1) if size is not None else 0
            if size is not None and rows <= total <= rows * 1.01 + 4096:
                data = scratch.array("file", (total,), np.uint8)
                handle.seek(0)
                if handle.readinto(data) == total:
                    image = scratch.array("image", size[::-1], np.uint8)
                    if read_stored(memoryview(data), image,
                                   scratch.array("rows", (size[1], size[0] + 1), np.uint8)):
                        return image
                    return _decoded(file, cv2.imdecode(data, cv2.IMREAD_GRAYSCALE))
    except OSError as exc:
        raise InputFileError(file, f"cannot read this image ({exc.strerror})") from None
    except cv2.error:  # OpenCV refuses, e.g. a header claiming more pixels than it allows
        raise InputFileError(file, "cannot decode this image") from None
    try:
        return _decoded(file, cv2.imread(os.fspath(file), cv2.IMREAD_GRAYSCALE))
    except cv2.error:
        raise InputFileError(file, "cannot decode this image") from None


def decode_jpeg(data: np.ndarray) -> np.ndarray | None:
    """One JPEG frame's bytes as an 8-bit grey image (None: not decodable)."""
    return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE) if data.size else None


def _decoded(file: Path, image: np.ndarray | None) -> np.ndarray:
    if image is None:
        raise InputFileError(file, "cannot decode this image")
    return image


def camera_sources(paths: list[Path]) -> list[Path]:
    """Per-camera folders / videos: ``paths``, or the sub-folders of one folder of camera folders."""
    if len(paths) == 1 and paths[0].is_dir():
        subfolders = sorted(p for p in paths[0].iterdir() if p.is_dir() and not p.name.startswith("."))
        if subfolders:
            return subfolders
    return paths
