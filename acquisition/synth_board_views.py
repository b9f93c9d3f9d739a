"""Rendered calibration-board views for a simulated rig, with the true board poses.

Rays of the true camera (OpenCV distortion undone with iterated ``cv2.undistortPoints``) are
traced onto the board plane every ``GRID_STEP`` px and interpolated between; the board's texture
is sampled ``SUPERSAMPLE`` x ``SUPERSAMPLE`` times per pixel and box-averaged: the exact projection of the
board with antialiased edges, no corner positions drawn by hand.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np

from .boards import Board
from .cameras import Camera, CameraRig

SUPERSAMPLE = 3
GRID_STEP = 4  # px between exactly traced rays (linear interpolation between them)
BACKGROUND = 70  # grey level around the board
#: The board's white / black as the sensor records them (not saturated).
WHITE, BLACK = 215, 30


def aim_point(rig: CameraRig) -> np.ndarray:
    """Where the rig looks: the point closest to all optical axes (least squares), mm."""
    centers = np.stack([cam.center for cam in rig])
    axes = np.stack([cam.rotation[2] for cam in rig])
    projector = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    return np.linalg.solve(projector.sum(0), np.einsum("cij,cj->i", projector, centers))


def board_poses(rig: CameraRig, board: Board, n_views: int, *, seed: int = 0,
                spread_mm: float | None = None, max_tilt_deg: float = 40.0) -> np.ndarray:
    """``(n_views, 6)`` board -> world poses (Rodrigues vector, translation mm): the board's
    centre near the rig's common aim point (the mean camera target), facing a randomly chosen
    camera with a random tilt of up to ``max_tilt_deg`` and spin."""
    rng = np.random.default_rng(seed)
    aim = aim_point(rig)
    width, height = board.size_mm()
    spread = spread_mm if spread_mm is not None else 0.3 * max(width, height)
    poses = []
    for view in range(n_views):
        camera = rig[view % len(rig)]
        facing = camera.center - aim
        facing /= np.linalg.norm(facing)  # board normal (+Z of the board faces away: see below)
        tilt = np.deg2rad(rng.uniform(0, max_tilt_deg))
        turn = rng.uniform(0, 2 * np.pi)
        side = np.cross(facing, [0.0, 1.0, 0.0] if abs(facing[1]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        up = np.cross(side, facing)
        normal = np.cos(tilt) * facing + np.sin(tilt) * (np.cos(turn) * side + np.sin(turn) * up)
        # board axes: x, y in its plane, z into the board (away from the camera it faces)
        z = -normal
        spin = rng.uniform(-np.pi, np.pi) * 0.25
        x0 = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
        x0 /= np.linalg.norm(x0)
        y0 = np.cross(z, x0)
        x = np.cos(spin) * x0 + np.sin(spin) * y0
        y = np.cross(z, x)
        rotation = np.column_stack([x, y, z])  # board -> world
        center = aim + rng.uniform(-spread, spread, 3) * [1.0, 1.0, 0.5]
        origin = center - rotation @ np.array([width / 2, height / 2, 0.0])
        poses.append(np.concatenate([cv2.Rodrigues(rotation)[0].ravel(), origin]))
    return np.array(poses)


def board_texture(board: Board, px_per_mm: float) -> np.ndarray:
    """The ChArUco board as a grey image, about ``px_per_mm`` texels per mm: a whole number of
    texels per square, so its width / ``board.size_mm()[0]`` is the exact texel scale."""
    # OpenCV draws squares of min(width / cols, height / rows) texels at truncated offsets: with
    # a fractional square the drawn board was up to 1.7e-4 smaller than the size it was sampled
    # at, a scale error in the truth (room seed 2)
    square = max(1, int(round(board.square * px_per_mm)))
    size = ((board.corners[0] + 1) * square, (board.corners[1] + 1) * square)
    image = board.charuco().generateImage(size, marginSize=0, borderBits=1)
    return (BLACK + image.astype(np.float32) * ((WHITE - BLACK) / 255.0)).astype(np.float32)


def render_board(camera: Camera, board: Board, pose: np.ndarray, texture: np.ndarray, *,
                 noise: float = 2.0, rng: np.random.Generator | None = None) -> np.ndarray:
    """One camera's 8-bit grey image of the board at ``pose`` (board -> world, ``(6,)``)."""
    width, height = camera.image_size
    image = np.full((height, width), float(BACKGROUND), np.float32)
    bounds = _board_box(camera, board, pose)
    if bounds is not None:
        x0, y0, x1, y1 = bounds
        g, s = GRID_STEP, SUPERSAMPLE
        cols, rows = -(-(x1 - x0) // g), -(-(y1 - y0) // g)  # whole coarse cells
        # coarse nodes sit where cv2.resize (half-pixel centres) puts them for g*s upsampling
        nodes = np.stack(np.meshgrid(x0 + (g - 1) / 2 + g * np.arange(cols),
                                     y0 + (g - 1) / 2 + g * np.arange(rows)), -1)
        coarse = _texture_coordinates(camera, board, pose, nodes.reshape(-1, 2),
                                      texture.shape[1] / board.size_mm()[0]).reshape(rows, cols, 2)
        fine = cv2.resize(coarse, (cols * g * s, rows * g * s), interpolation=cv2.INTER_LINEAR)
        samples = cv2.remap(texture, fine[..., 0], fine[..., 1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=float(BACKGROUND))
        block = samples.reshape(rows * g, s, cols * g, s).mean(axis=(1, 3))
        h, w = min(rows * g, height - y0), min(cols * g, width - x0)
        image[y0:y0 + h, x0:x0 + w] = block[:h, :w]
    if noise > 0:
        image += (rng or np.random.default_rng(0)).standard_normal(image.shape, np.float32) * noise
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _texture_coordinates(camera: Camera, board: Board, pose: np.ndarray, pixels: np.ndarray,
                         texels_per_mm: float) -> np.ndarray:
    """Texel coordinates ``(N, 2)`` float32 where the rays of ``pixels (N, 2)`` meet the board
    (far outside the texture when they miss it): distortion undone exactly (iterated
    ``cv2.undistortPoints``), then the plane's homography. Linear interpolation between these
    nodes ``GRID_STEP`` px apart is < 0.001 px off (smooth distortion and perspective)."""
    normalized = cv2.undistortPoints(
        pixels.reshape(-1, 1, 2), camera.matrix, camera.distortion, R=np.eye(3), P=np.eye(3),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-14)).reshape(-1, 2)
    # board -> camera: the plane point (a, b, 0) lies on the ray (x, y, 1) of H @ (a, b, 1)
    rotation = camera.rotation @ cv2.Rodrigues(pose[:3])[0]
    origin = camera.rotation @ pose[3:] + camera.tvec
    inverse = np.linalg.inv(np.column_stack([rotation[:, 0], rotation[:, 1], origin]))
    board_xy = np.column_stack([normalized, np.ones(len(normalized))]) @ inverse.T
    in_front = board_xy[:, 2] > 0  # the ray meets the plane ahead of the camera
    texel = board_xy[:, :2] / np.where(in_front, board_xy[:, 2], 1.0)[:, None] * texels_per_mm - 0.5
    return np.where(in_front[:, None], texel, -1e6).astype(np.float32)


def _board_box(camera: Camera, board: Board, pose: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel box ``(x0, y0, x1, y1)`` around the board's outline in the image, None when the
    board faces away or lies outside."""
    width, height = board.size_mm()
    a, b = np.meshgrid(np.linspace(0, width, 9), np.linspace(0, height, 9))
    outline = np.column_stack([a.ravel(), b.ravel(), np.zeros(a.size)])
    rotation = cv2.Rodrigues(pose[:3])[0]
    world = outline @ rotation.T + pose[3:]
    normal = rotation[:, 2]
    centre = world.mean(0)
    to_camera = camera.center - centre
    if normal @ to_camera > -0.2 * np.linalg.norm(to_camera):  # back or edge-on: unseen
        return None
    depth = world @ camera.rotation[2] + camera.tvec[2]
    if np.any(depth <= 0):
        return None
    pixels, _ = cv2.projectPoints(world, camera.rvec, camera.tvec, camera.matrix, camera.distortion)
    pixels = pixels.reshape(-1, 2)
    image_w, image_h = camera.image_size
    # a margin of background wider than half a coarse cell (cv2.resize clamps at its edges)
    x0, y0 = np.maximum(np.floor(pixels.min(0)).astype(int) - GRID_STEP, 0)
    x1, y1 = np.minimum(np.ceil(pixels.max(0)).astype(int) + GRID_STEP + 1, [image_w, image_h])
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def render_views(camera: Camera, board: Board, poses: np.ndarray, *, px_per_mm: float,
                 noise: float = 2.0, seed: int = 0) -> Iterator[np.ndarray | None]:
    """One camera's image of every board pose; None where it cannot see the board (a plain image)."""
    texture = board_texture(board, px_per_mm)
    rng = np.random.default_rng(seed)
    for pose in poses:
        seen = _board_box(camera, board, pose) is not None
        yield render_board(camera, board, pose, texture, noise=noise, rng=rng) if seen else None


def texture_resolution(rig: CameraRig, board: Board, poses: np.ndarray) -> float:
    """Texels per mm fine enough for the closest camera's supersampled pixels."""
    origins = poses[:, 3:]
    closest = min(float(np.min(np.linalg.norm(origins - cam.center, axis=1))) for cam in rig)
    focal = max(cam.focal_px for cam in rig)
    width, height = board.size_mm()
    return min(SUPERSAMPLE * focal / max(closest - max(width, height), 1.0), 8000 / max(width, height))


#: ChArUco boards sized for the rig presets (inner corners, square mm, marker mm): a hand-held
#: 14 x 10 cm board 25 cm from the Cara cameras, a 70 x 50 cm board 2.5 m from the room ring.
PRESET_BOARDS = {"cara": Board("charuco", (6, 4), 20.0, marker=10.0),
                 "room": Board("charuco", (6, 4), 100.0, marker=50.0)}


def write_board_views(folder, rig: CameraRig, board: Board, *, n_views: int, seed: int = 0,
                      max_tilt_deg: float = 30.0) -> np.ndarray:
    """Render ``n_views`` board poses into ``folder/<camera>/view_NNN.png`` (view k of every
    camera is the same instant) and ``folder/board_truth.npz`` (``poses (V, 6)`` board -> world,
    the board's geometry); returns the poses. ``folder`` must exist (staged by the caller)."""
    from pathlib import Path

    from mocaptk.atomic import write_bytes
    from mocaptk.npz import npz_bytes

    folder = Path(folder)
    poses = board_poses(rig, board, n_views, seed=seed, max_tilt_deg=max_tilt_deg)
    resolution = texture_resolution(rig, board, poses)
    for c, camera in enumerate(rig):
        (folder / camera.name).mkdir()
        plain = np.full(camera.image_size[::-1], BACKGROUND, np.uint8)
        for v, image in enumerate(render_views(camera, board, poses, px_per_mm=resolution, seed=seed + c)):
            write_bytes(folder / camera.name / f"view_{v:03d}.png",
                        cv2.imencode(".png", plain if image is None else image)[1].tobytes())
    write_bytes(folder / "board_truth.npz", npz_bytes({
        "poses": poses, "corners": np.array(board.corners), "square": np.array(board.square),
        "marker": np.array(board.marker), "dictionary": np.array(board.dictionary)}))
    return poses
