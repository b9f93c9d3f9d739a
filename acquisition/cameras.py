"""Pinhole cameras with OpenCV conventions, camera rigs, rig presets and rig files.

A :class:`Camera` maps world points (mm) to pixels like ``cv2.projectPoints``:
``x_cam = R @ X + t`` (``R = Rodrigues(rvec)``, world -> camera), pinhole ``K`` and the
distortion ``(k1, k2, p1, p2, k3)``. Pixel ``(0, 0)`` is the centre of the top-left pixel.
Camera axes: +X right, +Y down, +Z forward (viewing direction).
"""

from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mocaptk.errors import InputFileError, quoted
from mocaptk.jsonio import parse_json, read_input_bytes, write_json

RIG_FORMAT = "mocaptk.camera_rig"
RIG_VERSION = 1

#: Default aim point of the presets: the centre of the ICT-FaceKit face in mm
#: (face looks toward +Z, Y up, origin inside the head).
FACE_CENTER_MM = (0.0, 0.0, 70.0)


#: Largest image side (pixels) and camera distance / focal length (mm, pixels) a rig may give:
#: beyond them, projections overflow.
MAX_PIXELS = 1 << 20
MAX_REACH_MM = 1e7


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera.

    Parameters
    ----------
    name : str
    matrix : (3, 3) float
        Intrinsic matrix ``K`` in px.
    distortion : (5,) float
        OpenCV ``(k1, k2, p1, p2, k3)``.
    rvec : (3,) float
        Rodrigues rotation world -> camera.
    tvec : (3,) float
        Translation world -> camera, mm.
    image_size : (width, height) int
        Image size in px.
    """

    name: str
    matrix: np.ndarray
    distortion: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        values = {
            "matrix": (np.asarray(self.matrix, dtype=np.float64), (3, 3)),
            "distortion": (np.zeros(5) if self.distortion is None
                           else np.asarray(self.distortion, dtype=np.float64).ravel(), None),
            "rvec": (np.asarray(self.rvec, dtype=np.float64).ravel(), (3,)),
            "tvec": (np.asarray(self.tvec, dtype=np.float64).ravel(), (3,)),
        }
        for key, (value, shape) in values.items():
            if shape is not None and value.shape != shape:
                raise ValueError(f"camera {self.name!r}: {key} must have shape {shape}, "
                                 f"got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"camera {self.name!r}: {key} has non-finite values")
            object.__setattr__(self, key, value)
        dist = values["distortion"][0]
        if dist.size > 5:
            raise ValueError(f"camera {self.name!r}: at most 5 distortion coefficients")
        object.__setattr__(self, "distortion", np.pad(dist, (0, 5 - dist.size)))
        size = np.asarray(self.image_size, dtype=np.float64).ravel()
        if size.shape != (2,) or not (np.isfinite(size).all() and (size >= 1).all() and (size <= MAX_PIXELS).all()):
            raise ValueError(f"camera {self.name!r}: image size must be 2 whole numbers of pixels, "
                             f"1..{MAX_PIXELS}")
        width, height = (int(v) for v in size)
        if np.abs(values["tvec"][0]).max() > MAX_REACH_MM or np.abs(values["matrix"][0]).max() > MAX_REACH_MM:
            raise ValueError(f"camera {self.name!r}: tvec or matrix beyond {MAX_REACH_MM:g} (mm / pixels)")
        object.__setattr__(self, "image_size", (width, height))
        object.__setattr__(self, "name", " ".join(str(self.name).split()))  # a tab broke plan.png's text

    @property
    def rotation(self) -> np.ndarray:
        """(3, 3) rotation world -> camera."""
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, mm."""
        return -self.rotation.T @ self.tvec

    @property
    def focal_px(self) -> float:
        """Mean focal length in px (scale from normalized image coordinates to px)."""
        return float((self.matrix[0, 0] + self.matrix[1, 1]) / 2)

    def pixels_from_normalized(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply distortion and intrinsics to normalized image coordinates ``x = X/Z, y = Y/Z``
        (any equal shapes); returns pixel ``(u, v)``. Same model as ``cv2.projectPoints``
        (without its Jacobians, which make it slow for many points)."""
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        m = self.matrix
        return m[0, 0] * xd + m[0, 1] * yd + m[0, 2], m[1, 1] * yd + m[1, 2]

    @classmethod
    def look_at(cls, name: str, *, position: Sequence[float], target: Sequence[float],
                up: Sequence[float] = (0.0, 1.0, 0.0), focal_px: float,
                image_size: tuple[int, int], distortion: Sequence[float] | None = None,
                ) -> Camera:
        """A camera at ``position`` (mm) aimed at ``target`` (mm), image "up" along ``up``.

        The principal point is the image centre.
        """
        position = np.asarray(position, dtype=np.float64)
        forward = np.asarray(target, dtype=np.float64) - position
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(up, dtype=np.float64))
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])  # rows: camera axes in world
        width, height = image_size
        matrix = np.array([[focal_px, 0.0, (width - 1) / 2],
                           [0.0, focal_px, (height - 1) / 2],
                           [0.0, 0.0, 1.0]])
        return cls(name=name, matrix=matrix,
                   distortion=np.zeros(5) if distortion is None else distortion,
                   rvec=cv2.Rodrigues(rotation)[0].ravel(), tvec=-rotation @ position,
                   image_size=(width, height))

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "matrix": self.matrix, "distortion": self.distortion,
                "rvec": self.rvec, "tvec": self.tvec, "image_size": list(self.image_size)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Camera:
        return cls(name=data["name"], matrix=data["matrix"], distortion=data["distortion"],
                   rvec=data["rvec"], tvec=data["tvec"], image_size=tuple(data["image_size"]))


@dataclass(frozen=True, eq=False)
class CameraRig:
    """An ordered set of cameras; ``rate`` is the capture rate in Hz (None: unknown)."""

    cameras: tuple[Camera, ...]
    name: str = "rig"
    rate: float | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        cameras = tuple(self.cameras)
        if not cameras:
            raise ValueError("a camera rig needs at least one camera")
        names = [cam.name for cam in cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate camera names: {names}")
        object.__setattr__(self, "cameras", cameras)
        object.__setattr__(self, "name", " ".join(str(self.name).split()))  # a tab broke plan.png's title

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, index: int) -> Camera:
        return self.cameras[index]

    @property
    def names(self) -> list[str]:
        return [cam.name for cam in self.cameras]

    def subset(self, indices: Sequence[int]) -> CameraRig:
        """A rig with the cameras at ``indices``, in that order."""
        return CameraRig(tuple(self.cameras[i] for i in indices), name=self.name,
                         rate=self.rate, metadata=dict(self.metadata))

    def moved(self, rotation: np.ndarray, translation: Sequence[float]) -> CameraRig:
        """The rig carried along by the rigid motion ``X' = rotation @ X + translation`` (mm):
        every camera sees the moved points where it saw the original ones."""
        rotation = np.asarray(rotation, dtype=np.float64)
        translation = np.asarray(translation, dtype=np.float64)
        cameras = []
        for cam in self.cameras:
            turned = cam.rotation @ rotation.T  # world' -> camera
            cameras.append(dataclasses.replace(cam, rvec=cv2.Rodrigues(turned)[0].ravel(),
                                               tvec=cam.tvec - turned @ translation))
        return CameraRig(tuple(cameras), name=self.name, rate=self.rate, metadata=dict(self.metadata))

    def as_dict(self) -> dict[str, Any]:
        return {"format": RIG_FORMAT, "version": RIG_VERSION, "name": self.name,
                "rate": self.rate, "metadata": self.metadata,
                "cameras": [cam.as_dict() for cam in self.cameras]}


# -- presets -----------------------------------------------------------------------------

def cara_rig(*, center: Sequence[float] = FACE_CENTER_MM, distance: float = 250.0,
             focal_px: float = 700.0, distortion: Sequence[float] = (-0.08, 0.02, 0, 0, 0),
             ) -> CameraRig:
    """Head-mounted 4-camera rig like a Vicon Cara: 1280x720 px sensors, 60 Hz.

    Two cameras above the face looking down, two below looking up, left and right of the
    midline, each ``distance`` mm from ``center`` (the face, looking toward +Z, Y up; about
    15 cm from the nose tip and 25 cm from the cheeks) and aimed at it. The sensors are
    mounted in portrait (720 px wide, 1280 px tall) so the whole face fills the frame.
    Mild barrel distortion like a short lens.
    """
    center = np.asarray(center, dtype=np.float64)
    # unit directions from the face centre to each camera: (left/right, up/down, forward)
    directions = {"cara_upper_left": (0.35, 0.45, 0.82), "cara_upper_right": (-0.35, 0.45, 0.82),
                  "cara_lower_left": (0.35, -0.5, 0.79), "cara_lower_right": (-0.35, -0.5, 0.79)}
    cameras = []
    for name, direction in directions.items():
        unit = np.asarray(direction) / np.linalg.norm(direction)
        cameras.append(Camera.look_at(name, position=center + distance * unit, target=center,
                                      focal_px=focal_px, image_size=(720, 1280),
                                      distortion=distortion))
    return CameraRig(tuple(cameras), name="cara", rate=60.0)


def room_rig(*, n_cameras: int = 10, radius: float = 2500.0,
             center: Sequence[float] = FACE_CENTER_MM, focal_px: float = 3000.0,
             image_size: tuple[int, int] = (2048, 1088)) -> CameraRig:
    """Room rig: ``n_cameras`` on a ring of ``radius`` mm around ``center`` (Y up).

    Cameras alternate between about 0.4 m below and 1.0 m above the head and are spread
    evenly around the ring starting in front of the face (+Z); all aim at ``center``.
    Long lenses (``focal_px``) so a face spans a few hundred px; 120 Hz.
    """
    if n_cameras < 2:
        raise ValueError("a room rig needs at least 2 cameras")
    center = np.asarray(center, dtype=np.float64)
    heights = np.array([1000.0, -400.0, 600.0, 0.0])
    cameras = []
    for i in range(n_cameras):
        angle = 2 * np.pi * i / n_cameras
        position = center + np.array([radius * np.sin(angle), heights[i % len(heights)],
                                      radius * np.cos(angle)])
        cameras.append(Camera.look_at(f"room_{i + 1:02d}", position=position, target=center,
                                      focal_px=focal_px, image_size=image_size,
                                      distortion=(-0.02, 0.0, 0.0, 0.0, 0.0)))
    return CameraRig(tuple(cameras), name="room", rate=120.0)


RIG_PRESETS = {"cara": cara_rig, "room": room_rig}


# -- files -------------------------------------------------------------------------------

def save_rig(rig: CameraRig, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``rig`` as deterministic JSON (``format`` ``mocaptk.camera_rig``, version 1)."""
    return write_json(path, rig.as_dict(), digits=10, force=force)


def load_rig(path: str | os.PathLike[str]) -> CameraRig:
    """Read a rig: mocaptk JSON, or a Qualisys ``.qca.txt`` calibration (by content)."""
    path = Path(path)
    text = read_input_bytes(path, what="a camera rig").decode("utf-8", errors="replace")
    if text.lstrip().startswith("<"):
        return read_qca(path)
    if not text.lstrip().startswith("{"):
        raise InputFileError(path, "not a camera rig JSON or Qualisys .qca.txt")
    data = parse_json(text, path)
    if data.get("format") != RIG_FORMAT:
        raise InputFileError(path, f"not a camera rig (expected format {RIG_FORMAT!r})")
    if data.get("version") != RIG_VERSION:
        raise InputFileError(path, f"unsupported camera rig version {quoted(data.get('version'))}")
    rate = data.get("rate")
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float))
                             or not 0 < rate < 1e6):
        raise InputFileError(path, "malformed camera rig: rate must be a positive number of Hz or null")
    if not isinstance(data.get("metadata") or {}, dict):
        raise InputFileError(path, "malformed camera rig: metadata must be an object")
    try:
        cameras = tuple(Camera.from_dict(cam) for cam in data["cameras"])
        return CameraRig(cameras, name=str(data.get("name", "rig")), rate=rate,
                         metadata=dict(data.get("metadata") or {}))
    except KeyError as exc:
        raise InputFileError(path, f"malformed camera rig: no {quoted(exc.args[0])}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise InputFileError(path, f"malformed camera rig: {exc}") from None


def read_qca(path: str | os.PathLike[str]) -> CameraRig:
    """Read a Qualisys ``.qca.txt`` calibration (QTM XML export) into an OpenCV rig.

    Conventions (as Pose2Sim reads and writes them; checked on the Pose2Sim demo by
    triangulating its real detections): ``<transform>`` holds the camera position
    ``x, y, z`` (mm) and a rotation whose rows ``r11..r33`` are the camera axes in world
    coordinates for a camera frame with Y up and Z backward; we flip Y and Z to OpenCV's
    (Y down, Z forward). Intrinsics and distortion coefficients are stored in sub-pixel
    units (x 64); the principal point is relative to the sensor, so the video window's
    ``left``/``top`` are subtracted; the image size is the inclusive ``fov_video`` window.
    ``radialDistortion1..3`` and ``tangentalDistortion1..2`` become ``(k1, k2, p1, p2, k3)``.
    Cameras keep file order; names are the ``serial`` attributes.
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputFileError(path, f"not a Qualisys calibration XML ({exc})") from None
    flip = np.diag([1.0, -1.0, -1.0])  # Qualisys camera axes (Y up, Z back) -> OpenCV
    cameras = []
    for index, node in enumerate(root.findall("cameras/camera")):
        name = node.get("serial") or f"cam_{index + 1:02d}"
        try:
            fov = _float_attrs(node.find("fov_video"), "left", "top", "right", "bottom")
            intr = node.find("intrinsic")
            fu, fv, cu, cv_ = _float_attrs(intr, "focalLengthU", "focalLengthV",
                                           "centerPointU", "centerPointV")
            k1, k2, k3, p1, p2 = _float_attrs(intr, "radialDistortion1", "radialDistortion2",
                                              "radialDistortion3", "tangentalDistortion1",
                                              "tangentalDistortion2")
            transform = node.find("transform")
            position = np.array(_float_attrs(transform, "x", "y", "z"))
            axes = np.array(_float_attrs(
                transform, *(f"r{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3)))).reshape(3, 3)
        except ValueError as exc:
            raise InputFileError(path, f"camera {name!r}: {exc}") from None
        left, top, right, bottom = fov
        matrix = np.array([[fu / 64, 0.0, cu / 64 - left], [0.0, fv / 64, cv_ / 64 - top],
                           [0.0, 0.0, 1.0]])
        rotation = flip @ axes
        distortion = np.array([k1, k2, p1, p2, k3]) / 64
        cameras.append(Camera(name=name, matrix=matrix, distortion=distortion,
                              rvec=cv2.Rodrigues(rotation)[0].ravel(), tvec=-rotation @ position,
                              image_size=(int(right - left) + 1, int(bottom - top) + 1)))
    if not cameras:
        raise InputFileError(path, "no <cameras>/<camera> entries (not a Qualisys calibration)")
    return CameraRig(tuple(cameras), name=path.name.split(".")[0], rate=None,
                     metadata={"source": str(path), "format": "qualisys_qca"})


def _float_attrs(node: ET.Element | None, *names: str) -> list[float]:
    if node is None:
        raise ValueError("missing element")
    values = []
    for name in names:
        raw = node.get(name)
        if raw is None:
            raise ValueError(f"missing attribute {name!r} in <{node.tag}>")
        try:
            values.append(float(raw))
        except ValueError:
            raise ValueError(f"attribute {name!r} in <{node.tag}> is not a number: {raw!r}"
                             ) from None
    return values
