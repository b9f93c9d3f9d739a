"""Camera calibration from board views: per-camera intrinsics (OpenCV) and rig extrinsics by
bundle adjustment (scipy ``least_squares``, sparse Jacobian), with OpenCV's chained
``stereoCalibrate`` as the baseline and the starting point.

A *view* is one board detection in one image: ``(name, ids (K,), pixels (K, 2) px)``. For a
rig, view ``j`` of every camera is the same instant (synchronised frames); the world frame is
camera 0's, and the board's squares fix the scale (mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from .boards import Board
from .cameras import Camera, CameraRig
from .wand import Wand, wand_ends

#: A view whose RMS reprojection error exceeds this many times the median of the others (and
#: ``MIN_OUTLIER_PX``) is dropped and the camera refitted: a misdetected or blurred board.
OUTLIER_FACTOR = 3.0
MIN_OUTLIER_PX = 0.5
#: Fewer views than this cannot constrain focal length, principal point and distortion.
MIN_VIEWS = 3
#: The wand's pixels are weighted by the ratio of the corners' to the blobs' noise, both measured
#: on the fit's own residuals and refitted until the ratio moves less than this fraction ...
NOISE_RATIO_TOLERANCE = 0.02
#: ... or this many fits were made.
MAX_NOISE_FITS = 4
#: Distortion model: (k1, k2, p1, p2) with k3 = 0, as Qualisys' calibrations; enough for
#: non-fisheye lenses and stable with few views.
INTRINSIC_FLAGS = cv2.CALIB_FIX_K3


@dataclass
class View:
    """One board detection: image ``name``, corner ``ids (K,)``, ``pixels (K, 2)`` px."""

    name: str
    ids: np.ndarray
    pixels: np.ndarray

    @property
    def found(self) -> bool:
        return len(self.ids) >= 6


@dataclass
class Intrinsics:
    """One camera's intrinsics fit and its per-view record."""

    matrix: np.ndarray
    distortion: np.ndarray
    image_size: tuple[int, int]
    rms: float
    view_rms: dict[str, float]  # kept views
    dropped: dict[str, str]  # view name -> reason
    poses: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # board -> camera


def calibrate_intrinsics(board: Board, views: Sequence[View], image_size: tuple[int, int], *,
                         min_views: int = MIN_VIEWS) -> Intrinsics:
    """Fit ``K`` and distortion to the found views, dropping outlier views one at a time.

    Raises ValueError when fewer than ``min_views`` usable views remain.
    """
    objects = board.object_points()
    dropped = {v.name: "board not found" for v in views if not v.found}
    # a partial board whose corners lie on one line has no homography (OpenCV asserts)
    dropped.update({v.name: "corners on one line" for v in views if v.found and _on_a_line(objects[v.ids])})
    kept = [v for v in views if v.name not in dropped]
    while True:
        if len(kept) < min_views:
            raise ValueError(f"the board was found in {len(kept)} usable view(s), "
                             f"at least {min_views} are needed")
        rms, matrix, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
            [objects[v.ids].astype(np.float32) for v in kept],
            [v.pixels.astype(np.float32) for v in kept], image_size, None, None,
            flags=INTRINSIC_FLAGS)
        errors = per_view.ravel()
        worst = int(np.argmax(errors))
        others = np.delete(errors, worst)
        limit = max(OUTLIER_FACTOR * float(np.median(others)), MIN_OUTLIER_PX)
        if errors[worst] <= limit or len(kept) == min_views:
            break
        dropped[kept[worst].name] = f"outlier: {errors[worst]:.2f} px RMS (limit {limit:.2f})"
        del kept[worst]
    return Intrinsics(matrix=matrix, distortion=dist.ravel()[:5], image_size=tuple(image_size),
                      rms=float(rms), view_rms={v.name: float(e) for v, e in zip(kept, errors)},
                      dropped=dropped,
                      poses={v.name: (r.ravel(), t.ravel()) for v, r, t in zip(kept, rvecs, tvecs)})


def _on_a_line(points: np.ndarray) -> bool:
    """Whether board points ``(K, 3)`` mm spread less than a tenth of their length across."""
    spread = np.linalg.svd(points[:, :2] - points[:, :2].mean(axis=0), compute_uv=False)
    return bool(spread[1] < 0.1 * spread[0])


# -- rig extrinsics -----------------------------------------------------------------------

def _shared(board: Board, a: Sequence[View], b: Sequence[View]) -> tuple[list, list, list]:
    """Object points and both cameras' pixels of the corners seen in the same frame by both."""
    objects, pa, pb = [], [], []
    points = board.object_points()
    for va, vb in zip(a, b):
        if not (va.found and vb.found):
            continue
        common, ia, ib = np.intersect1d(va.ids, vb.ids, return_indices=True)
        if len(common) >= 6 and not _on_a_line(points[common]):
            objects.append(points[common].astype(np.float32))
            pa.append(va.pixels[ia].astype(np.float32))
            pb.append(vb.pixels[ib].astype(np.float32))
    return objects, pa, pb


def _spanning_tree(board: Board, views: Sequence[Sequence[View]]) -> list[tuple[int, int]]:
    """Edges ``(parent, child)`` from camera 0 that maximise the shared corners (Prim)."""
    n = len(views)
    weight = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            weight[i, j] = weight[j, i] = sum(len(o) for o in _shared(board, views[i], views[j])[0])
    tree, inside = [], {0}
    while len(inside) < n:
        score = [(weight[i, j], i, j) for i in inside for j in range(n) if j not in inside]
        best, parent, child = max(score)
        if best == 0:
            raise ValueError(f"camera {child + 1} shares no board view with the other cameras")
        tree.append((parent, child))
        inside.add(child)
    return tree


def chained_stereo(board: Board, views: Sequence[Sequence[View]],
                   intrinsics: Sequence[Intrinsics]) -> list[tuple[np.ndarray, np.ndarray]]:
    """OpenCV-only extrinsics: ``stereoCalibrate`` (intrinsics fixed) along the camera pairs
    sharing the most corners, composed from camera 0. Returns ``(R, t)`` world -> camera."""
    poses: list = [None] * len(views)
    poses[0] = (np.eye(3), np.zeros(3))
    for parent, child in _spanning_tree(board, views):
        objects, pa, pc = _shared(board, views[parent], views[child])
        a, c = intrinsics[parent], intrinsics[child]
        result = cv2.stereoCalibrate(objects, pa, pc, a.matrix, a.distortion, c.matrix,
                                     c.distortion, a.image_size, flags=cv2.CALIB_FIX_INTRINSIC)
        rotation, translation = result[5], result[6].ravel()  # parent camera -> child camera
        r_parent, t_parent = poses[parent]
        poses[child] = (rotation @ r_parent, rotation @ t_parent + translation)
    return poses


def rotation_matrices(rvecs: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` rotation matrices of Rodrigues vectors ``rvecs (K, 3)``."""
    theta = np.sqrt(np.sum(rvecs * rvecs, axis=1))[:, None, None]
    safe = np.where(theta > 1e-12, theta, 1.0)
    k = rvecs[:, :, None] / safe  # (K, 3, 1) unit axis (any axis when theta = 0)
    zero = np.zeros(len(rvecs))
    cross = np.stack([zero, -rvecs[:, 2], rvecs[:, 1], rvecs[:, 2], zero, -rvecs[:, 0],
                      -rvecs[:, 1], rvecs[:, 0], zero], 1).reshape(-1, 3, 3) / safe
    return (np.cos(theta) * np.eye(3) + np.sin(theta) * cross
            + (1 - np.cos(theta)) * k * k.transpose(0, 2, 1))


def _project(intr: np.ndarray, cam_pose: np.ndarray, board_pose: np.ndarray,
             objects: np.ndarray) -> np.ndarray:
    """Pixels of board points: per observation ``intr (N, 9)`` (fx, fy, cx, cy, k1, k2, p1, p2,
    k3), rotations ``(N, 3, 3)`` and translations ``(N, 3)`` of the board -> world and
    world -> camera poses (``cam_pose``, ``board_pose`` as pairs), ``objects (N, 3)`` mm."""
    world = np.einsum("nij,nj->ni", board_pose[0], objects) + board_pose[1]
    cam = np.einsum("nij,nj->ni", cam_pose[0], world) + cam_pose[1]
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([fx * xd + cx, fy * yd + cy])


@dataclass
class BundleResult:
    rig_poses: list[tuple[np.ndarray, np.ndarray]]  # (R, t) world (camera 0) -> camera
    intrinsics: list[tuple[np.ndarray, np.ndarray]]  # (K, distortion)
    camera_rms: list[float]  # px, all observations of each camera
    initial_rms: float
    final_rms: float
    #: With a wand: the noise measured on the last fit's residuals (px) and the wand pixels' weight.
    corner_sd_px: float | None = None
    wand_sd_px: float | None = None
    wand_weight: float | None = None


def bundle_adjust(board: Board, views: Sequence[Sequence[View]], intrinsics: Sequence[Intrinsics],
                  start: Sequence[tuple[np.ndarray, np.ndarray]], *,
                  refine_intrinsics: bool = True, loss: str = "soft_l1",
                  f_scale: float | None = None, wand: Wand | None = None) -> BundleResult:
    """Refine camera poses (camera 0 fixed: the world frame), board poses per frame and
    (optionally) intrinsics ``fx, fy, cx, cy, k1, k2, p1, p2`` by minimising all reprojection
    errors together; ``start`` gives the initial ``(R, t)`` of every camera. The ``loss``
    (scipy's) is robust by default with ``f_scale`` px = the median per-view RMS of the
    intrinsics fits: corners of steeply tilted views, several times less precise than the rest,
    pulled the rig by up to 0.2 deg on the rendered Cara views.

    A ``wand`` adds its frames as rigid bodies of exactly ``wand.length`` mm (a midpoint and a
    direction each), seen by several cameras at once. Maximum likelihood weighs each pixel by its
    own noise: the blobs' and the corners' standard deviations are measured on the fit's
    residuals (variance components, corrected for each frame's own parameters) and the fit is
    repeated with the wand's pixels weighted by their ratio until it settles; no weight is set
    by hand."""
    if f_scale is None:
        f_scale = float(np.median([r for i in intrinsics for r in i.view_rms.values()] or [1.0]))
    n_cams, points = len(views), board.object_points()
    # board pose per frame (in camera-0 = world coordinates) from the first camera that saw it
    frames: dict[int, np.ndarray] = {}
    for c in range(n_cams):
        r_c, t_c = start[c]
        for f, view in enumerate(views[c]):
            if f in frames or view.name not in intrinsics[c].poses:
                continue
            rb, tb = intrinsics[c].poses[view.name]
            r_world = r_c.T @ cv2.Rodrigues(rb)[0]
            frames[f] = np.concatenate([cv2.Rodrigues(r_world)[0].ravel(), r_c.T @ (tb - t_c)])
    frame_ids = sorted(frames)
    frame_index = {f: i for i, f in enumerate(frame_ids)}
    cam_idx, frm_idx, objs, pixels = [], [], [], []
    for c in range(n_cams):
        for f, view in enumerate(views[c]):
            if view.name in intrinsics[c].poses and f in frame_index:
                cam_idx.append(np.full(len(view.ids), c))
                frm_idx.append(np.full(len(view.ids), frame_index[f]))
                objs.append(points[view.ids])
                pixels.append(view.pixels)
    cam_idx, frm_idx = np.concatenate(cam_idx), np.concatenate(frm_idx)
    objs, pixels = np.concatenate(objs), np.concatenate(pixels)
    n_obs, n_frames = len(cam_idx), len(frame_ids)
    intr0 = np.array([[i.matrix[0, 0], i.matrix[1, 1], i.matrix[0, 2], i.matrix[1, 2],
                       *i.distortion[[0, 1, 2, 3, 4]]] for i in intrinsics])
    n_intr = 8 if refine_intrinsics else 0
    rods0, wand_cam, wand_pt, wand_px = _wand_observations(wand, intrinsics, start)
    n_wand = len(wand_cam)
    x0 = np.concatenate([intr0[:, :n_intr].ravel(),
                         np.concatenate([np.concatenate([cv2.Rodrigues(r)[0].ravel(), t])
                                         for r, t in start[1:]]) if n_cams > 1 else [],
                         np.concatenate([frames[f] for f in frame_ids]), rods0.params.ravel()])
    cam_off, frame_off = n_cams * n_intr, n_cams * n_intr + 6 * (n_cams - 1)
    wand_off = frame_off + 6 * n_frames

    def unpack(x: np.ndarray):
        intr = intr0.copy()
        intr[:, :n_intr] = x[:cam_off].reshape(n_cams, n_intr)
        cams = np.vstack([np.zeros((1, 6)), x[cam_off:frame_off].reshape(-1, 6)])
        return intr, cams, x[frame_off:wand_off].reshape(n_frames, 6), x[wand_off:].reshape(-1, 5)

    def residuals(x: np.ndarray, wand_weight: float) -> np.ndarray:
        intr, cams, boards, rods = unpack(x)
        r_cams, r_boards = rotation_matrices(cams[:, :3]), rotation_matrices(boards[:, :3])
        board = _project(intr[cam_idx], (r_cams[cam_idx], cams[cam_idx, 3:]),
                         (r_boards[frm_idx], boards[frm_idx, 3:]), objs) - pixels
        if not n_wand:
            return board.ravel()
        still = (np.broadcast_to(np.eye(3), (n_wand, 3, 3)), np.zeros((n_wand, 3)))
        seen = _project(intr[wand_cam], (r_cams[wand_cam], cams[wand_cam, 3:]), still,
                        rods0.ends(rods)[wand_pt]) - wand_px
        return np.concatenate([board.ravel(), wand_weight * seen.ravel()])

    sparsity = lil_matrix((2 * n_obs + 2 * n_wand, len(x0)), dtype=np.int8)
    rows = np.arange(n_obs)
    for axis in (0, 1):
        for k in range(n_intr):
            sparsity[2 * rows + axis, cam_idx * n_intr + k] = 1
        moving = cam_idx > 0
        for k in range(6):
            sparsity[2 * rows[moving] + axis, cam_off + (cam_idx[moving] - 1) * 6 + k] = 1
            sparsity[2 * rows + axis, frame_off + frm_idx * 6 + k] = 1
    _wand_sparsity(sparsity, 2 * n_obs, wand_cam, wand_pt, n_intr=n_intr, cam_off=cam_off,
                   wand_off=wand_off)

    def solve(x: np.ndarray, wand_weight: float):
        return least_squares(residuals, x, jac_sparsity=sparsity, x_scale="jac", method="trf",
                             tr_solver="lsmr", loss=loss, f_scale=f_scale, args=(wand_weight,),
                             tr_options={"atol": 1e-12, "btol": 1e-12},
                             xtol=1e-10, ftol=1e-9, gtol=1e-10, max_nfev=100)
    initial = residuals(x0, 1.0)
    wand_weight, fit = 1.0, solve(x0, 1.0)
    corner_sd = wand_sd = None
    for n_fits in range(1, MAX_NOISE_FITS + 1 if n_wand else 0):
        corner_sd = _noise_sd(fit.fun[:2 * n_obs], 6 * n_frames)
        wand_sd = _noise_sd(fit.fun[2 * n_obs:] / wand_weight, 5 * len(rods0.params))
        ratio = corner_sd / wand_sd
        if abs(ratio / wand_weight - 1) < NOISE_RATIO_TOLERANCE or n_fits == MAX_NOISE_FITS:
            break
        wand_weight, fit = ratio, solve(fit.x, ratio)
    intr, cams, _, _ = unpack(fit.x)
    error = fit.fun[:2 * n_obs].reshape(-1, 2)
    camera_rms = [float(np.sqrt(np.mean(np.sum(error[cam_idx == c] ** 2, axis=1))))
                  for c in range(n_cams)]
    return BundleResult(
        rig_poses=[(cv2.Rodrigues(p[:3])[0], p[3:].copy()) for p in cams],
        intrinsics=[(np.array([[i[0], 0, i[2]], [0, i[1], i[3]], [0, 0, 1.0]]), i[4:].copy())
                    for i in intr],
        camera_rms=camera_rms, initial_rms=float(np.sqrt(np.mean(initial[:2 * n_obs] ** 2) * 2)),
        final_rms=float(np.sqrt(np.mean(fit.fun[:2 * n_obs] ** 2) * 2)),
        corner_sd_px=corner_sd, wand_sd_px=wand_sd, wand_weight=wand_weight if n_wand else None)


def _noise_sd(residuals: np.ndarray, n_params: int) -> float:
    """Standard deviation (px) of the noise behind one group's pixel ``residuals`` (x and y
    interleaved): robust (1.4826 x the median absolute residual), scaled up by the group's
    redundancy since ``n_params`` parameters of its own (board or wand poses) absorbed a share."""
    spread = 1.4826 * float(np.median(np.abs(residuals)))
    return spread * float(np.sqrt(len(residuals) / max(len(residuals) - n_params, 1)))


@dataclass
class _Rods:
    """The wand frames as rigid rods of ``length`` mm: per frame ``params (N, 5)`` = midpoint
    (3) and a direction offset (2) in the plane across the starting direction ``axis (N, 3)``
    (``side``, ``up``: its orthonormal complement), so the length is exact and no angle wraps."""

    params: np.ndarray
    axis: np.ndarray
    side: np.ndarray
    up: np.ndarray
    length: float

    @classmethod
    def through(cls, ends: np.ndarray, length: float) -> "_Rods":
        """Rods through triangulated ends ``(N, 2, 3)`` mm (their midpoints and directions)."""
        axis = ends[:, 1] - ends[:, 0]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        side = np.cross(axis, helper)
        side /= np.linalg.norm(side, axis=1, keepdims=True)
        params = np.column_stack([ends.mean(axis=1), np.zeros((len(ends), 2))])
        return cls(params, axis, side, np.cross(axis, side), float(length))

    def ends(self, params: np.ndarray) -> np.ndarray:
        """``(2N, 3)`` mm: end A then end B of every frame."""
        direction = self.axis + params[:, 3:4] * self.side + params[:, 4:5] * self.up
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        half = 0.5 * self.length * direction
        return np.stack([params[:, :3] - half, params[:, :3] + half], axis=1).reshape(-1, 3)


def _wand_observations(wand: Wand | None, intrinsics: Sequence[Intrinsics],
                       start: Sequence[tuple[np.ndarray, np.ndarray]]):
    """The wand's starting rods (through the ends triangulated with the starting rig; frames
    that do not triangulate dropped) and its observations: camera and end index ``(W,)`` (end
    ``2 n`` is frame n's A, ``2 n + 1`` its B) and pixels ``(W, 2)``. Empty without a wand."""
    if wand is None:
        return _Rods.through(np.zeros((0, 2, 3)), 0.0), np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2))
    rig = rig_from_poses([str(c) for c in range(len(start))], [(i.matrix, i.distortion) for i in intrinsics],
                         start, [i.image_size for i in intrinsics])
    ends = wand_ends(wand, rig)
    good = np.isfinite(ends).all(axis=(1, 2))
    pixels = wand.pixels[:, good].reshape(len(rig), -1, 2)
    cam, point = np.nonzero(np.isfinite(pixels[..., 0]))
    return _Rods.through(ends[good], wand.length), cam, point, pixels[cam, point]


def _wand_sparsity(sparsity, first_row: int, cam: np.ndarray, point: np.ndarray, *, n_intr: int,
                   cam_off: int, wand_off: int) -> None:
    """Mark the Jacobian entries of the wand's rows (after ``first_row``): each pixel row depends
    on its camera's intrinsics and pose and its frame's rod (midpoint and direction)."""
    rows = first_row + 2 * np.arange(len(cam))
    for axis in (0, 1):
        for k in range(n_intr):
            sparsity[rows + axis, cam * n_intr + k] = 1
        moving = cam > 0
        for k in range(6):
            sparsity[rows[moving] + axis, cam_off + (cam[moving] - 1) * 6 + k] = 1
        for k in range(5):
            sparsity[rows + axis, wand_off + 5 * (point // 2) + k] = 1


def rig_from_poses(names: Sequence[str], intrinsics: Sequence[tuple[np.ndarray, np.ndarray]],
                   poses: Sequence[tuple[np.ndarray, np.ndarray]], image_sizes: Sequence[tuple[int, int]],
                   *, name: str = "calibrated", metadata: dict | None = None) -> CameraRig:
    """A :class:`CameraRig` from per-camera ``(K, distortion)`` and ``(R, t)`` world -> camera."""
    cameras = tuple(Camera(name=n, matrix=k, distortion=d, rvec=cv2.Rodrigues(r)[0].ravel(),
                           tvec=t, image_size=s)
                    for n, (k, d), (r, t), s in zip(names, intrinsics, poses, image_sizes))
    return CameraRig(cameras, name=name, metadata=metadata or {})


def pose_errors(estimate: CameraRig, truth: CameraRig, *, align: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre errors (mm) and orientation errors (deg) of ``estimate`` against ``truth``:
    both expressed in their own camera 0's frame (no fitted alignment: camera 0's own error lands
    on the others), or with ``align`` after the rigid motion that best lays the estimate's
    camera orientations (chordal mean) and centres (centroid) onto the truth's (a rig's world
    frame is a convention; its relative geometry is what is measured)."""
    def relative(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
        r0, c0 = rig[0].rotation, rig[0].center
        return (np.stack([r0 @ (cam.center - c0) for cam in rig]),
                np.stack([cam.rotation @ r0.T for cam in rig]))
    centers_e, rot_e = relative(estimate)
    centers_t, rot_t = relative(truth)
    if align:  # x_e = A x_t + b: A the rotation nearest to the mean of R_e^T R_t
        u, _, vt = np.linalg.svd(np.einsum("cji,cjk->ik", rot_e, rot_t))
        a = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
        b = centers_e.mean(axis=0) - a @ centers_t.mean(axis=0)
        centers_e, rot_e = (centers_e - b) @ a, rot_e @ a
    centre_mm = np.linalg.norm(centers_e - centers_t, axis=1)
    cos = (np.einsum("cij,cij->c", rot_e, rot_t) - 1) / 2  # trace(Re Rt^T) = 1 + 2 cos(angle)
    return centre_mm, np.degrees(np.arccos(np.clip(cos, -1, 1)))


def pairwise_errors(estimate: CameraRig, truth: CameraRig) -> tuple[np.ndarray, np.ndarray]:
    """Gauge-free errors of ``estimate`` against ``truth``, with no frame chosen and nothing
    fitted: for every camera pair, the error of the distance between their centres (mm) and the
    angle of the error of their relative rotation (deg); each ``(pairs,)``. A rig's centres are
    fixed up to a rigid motion by their distances, its orientations by their relative rotations."""
    i, j = np.triu_indices(len(truth), k=1)

    def pairs(rig: CameraRig) -> tuple[np.ndarray, np.ndarray]:
        centres = np.stack([cam.center for cam in rig])
        rotations = np.stack([cam.rotation for cam in rig])
        return (np.linalg.norm(centres[i] - centres[j], axis=1),
                np.einsum("pab,pcb->pac", rotations[i], rotations[j]))  # R_i R_j^T
    dist_e, rel_e = pairs(estimate)
    dist_t, rel_t = pairs(truth)
    cos = (np.einsum("pab,pab->p", rel_e, rel_t) - 1) / 2
    return np.abs(dist_e - dist_t), np.degrees(np.arccos(np.clip(cos, -1, 1)))
