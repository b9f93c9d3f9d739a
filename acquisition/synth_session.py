"""Synthetic dense facial sessions with ground truth, like the corpus of the paper's §3.1.

A session is one take per facial region (forehead_brow, eye, nose, cheek, mouth, chin): neutral
rest alternating with target expressions (≈2 s each, smooth easing) built from that region's
blendshapes with random intensities, on both sides and sometimes one side only. A separate
*performance* (speech-like jaw/lip visemes, blinks, smiles, brow raises, frowns) is the held-out
test material. Markers follow the ICT-FaceKit mesh through their barycentric anchors.

Everything is in the face model's frame: mm, +X = character's left, +Y up, +Z forward.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from mocaptk.atomic import atomic_open
from mocaptk.errors import InputFileError, OptionError
from mocaptk.jsonio import write_json
from mocaptk.trajectories import Take, Trajectories

from .face_model import FaceModel
from .synth_layout import REGIONS, MarkerLayout

#: Blendshape actions per region take: a name, or a (left, right) pair of names.
REGION_ACTIONS: dict[str, tuple[str | tuple[str, str], ...]] = {
    "forehead_brow": (("browDown_L", "browDown_R"), ("browInnerUp_L", "browInnerUp_R"),
                      ("browOuterUp_L", "browOuterUp_R")),
    "eye": (("eyeBlink_L", "eyeBlink_R"), ("eyeSquint_L", "eyeSquint_R"),
            ("eyeWide_L", "eyeWide_R")),
    "nose": (("noseSneer_L", "noseSneer_R"), ("mouthUpperUp_L", "mouthUpperUp_R")),
    "cheek": (("cheekPuff_L", "cheekPuff_R"), ("cheekSquint_L", "cheekSquint_R"),
              ("mouthSmile_L", "mouthSmile_R"), ("mouthDimple_L", "mouthDimple_R")),
    "mouth": ("mouthFunnel", "mouthPucker", ("mouthLeft", "mouthRight"), "mouthRollLower",
              "mouthRollUpper", "mouthShrugUpper", ("mouthPress_L", "mouthPress_R"),
              ("mouthFrown_L", "mouthFrown_R"), ("mouthStretch_L", "mouthStretch_R"),
              ("mouthSmile_L", "mouthSmile_R"), ("mouthLowerDown_L", "mouthLowerDown_R"),
              ("mouthUpperUp_L", "mouthUpperUp_R")),
    "chin": ("jawOpen", ("jawLeft", "jawRight"), "jawForward", "mouthShrugLower"),
}
#: Pairs that are directions, not sides: never both at once.
_EITHER_OR = {("mouthLeft", "mouthRight"), ("jawLeft", "jawRight")}
#: Rigid head motion turns about this point (≈ the top of the neck), model frame, mm.
HEAD_PIVOT_MM = (0.0, -90.0, 0.0)
GROUND_TRUTH_FORMAT = "mocaptk-synth-truth"
GROUND_TRUTH_VERSION = 1


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What a synthetic session really was.

    Noise-free positions are ``R_f (marker_neutral + weights_f · marker_blendshapes − pivot)
    + pivot + t_f`` (:attr:`positions`): exactly the markers' barycentric interpolation of the
    deformed mesh, posed by the head motion.

    Attributes
    ----------
    labels, regions, sides : tuple of str, length M
    vertices : (M,) int64 ; triangles : (M,) int64 ; barycentric : (M, 3) float64
        Marker anchors on the face model mesh (see :class:`MarkerLayout`).
    blendshape_names : tuple of str, length B
    weights : (F, B) float64
        Blendshape weights per frame.
    marker_neutral : (M, 3) float64
        Markers on the (identity's) neutral face, mm.
    marker_blendshapes : (B, M, 3) float64
        Marker displacement per unit blendshape weight, mm.
    head_rotations : (F, 3, 3) float64 ; head_translations : (F, 3) float64, mm
    head_pivot : (3,) float64, mm
    identity_coefficients : (I,) float64
    rate : float, Hz
    takes : list of Take
    info : dict
        Generator options (seed, noise_mm, ...).
    """

    labels: tuple[str, ...]
    regions: tuple[str, ...]
    sides: tuple[str, ...]
    vertices: np.ndarray
    triangles: np.ndarray
    barycentric: np.ndarray
    blendshape_names: tuple[str, ...]
    weights: np.ndarray
    marker_neutral: np.ndarray
    marker_blendshapes: np.ndarray
    head_rotations: np.ndarray
    head_translations: np.ndarray
    head_pivot: np.ndarray
    identity_coefficients: np.ndarray
    rate: float
    takes: list[Take] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.weights.shape[0])

    @property
    def head_relative_positions(self) -> np.ndarray:
        """(F, M, 3) noise-free positions without the rigid head motion, mm."""
        return self._head_relative(0, self.n_frames)

    @property
    def positions(self) -> np.ndarray:
        """(F, M, 3) noise-free marker positions, mm."""
        return self.positions_between(0, self.n_frames)

    def _head_relative(self, start: int, stop: int) -> np.ndarray:
        out = np.tensordot(self.weights[start:stop], self.marker_blendshapes, axes=1)
        out += self.marker_neutral  # in place: one (F, M, 3) array, not two
        return out

    def positions_between(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, M, 3) noise-free marker positions of frames ``start`` to ``stop - 1``, mm."""
        local = self._head_relative(start, stop)
        local -= self.head_pivot
        out = np.einsum("fij,fmj->fmi", self.head_rotations[start:stop], local)
        del local
        out += self.head_pivot
        out += self.head_translations[start:stop, None, :]
        return out

    def regions_dict(self) -> dict[str, list[str]]:
        """``{region: [labels]}`` (the regions-file content)."""
        return {region: [lab for lab, reg in zip(self.labels, self.regions) if reg == region]
                for region in REGIONS if region in self.regions}

    def trajectories(self) -> Trajectories:
        """The noise-free session as :class:`Trajectories` (with the takes)."""
        return Trajectories(self.positions, self.labels, self.rate,
                            metadata={"takes": list(self.takes), "format": "synthetic truth"})


@dataclass(frozen=True, eq=False)
class SyntheticSession:
    """A synthetic capture: what the system delivers and what really happened."""

    trajectories: Trajectories
    truth: GroundTruth


# -- expression schedules -------------------------------------------------------------------

def _smoothstep(x: np.ndarray) -> np.ndarray:
    """C2-smooth 0→1 easing (quintic smootherstep) on [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _pulse(t: np.ndarray, start: float, end: float, ramp: float) -> np.ndarray:
    """0 outside [start, end], eased up over ``ramp`` s, held at 1, eased down."""
    return _smoothstep((t - start) / ramp) * _smoothstep((end - t) / ramp)


def _action_weights(action: str | tuple[str, str], rng: np.random.Generator,
                    lookup: dict[str, int], out: np.ndarray) -> None:
    """Add one action with a random intensity to the weight vector ``out`` (B,)."""
    intensity = rng.uniform(0.45, 1.0)
    if isinstance(action, str):
        out[lookup[action]] = intensity
    elif action in _EITHER_OR:
        out[lookup[action[int(rng.integers(2))]]] = intensity
    else:
        roll = rng.uniform()
        if roll < 0.55:  # both sides, slightly uneven like a real face
            out[lookup[action[0]]] = intensity
            out[lookup[action[1]]] = intensity * rng.uniform(0.8, 1.0)
        else:  # one side only (asymmetric)
            out[lookup[action[int(roll < 0.775)]]] = intensity


def region_take_weights(model: FaceModel, region: str, *, rng: np.random.Generator,
                        n_expressions: int, rest_seconds: float, expression_seconds: float,
                        rate: float) -> np.ndarray:
    """Blendshape weights ``(F, B)`` of one region take: rest, expression, rest, ..., rest.

    Every action of :data:`REGION_ACTIONS` ``[region]`` appears at least once when
    ``n_expressions`` allows (several actions per expression otherwise); durations vary ±15 %.
    """
    actions = list(REGION_ACTIONS[region])
    lookup = {name: i for i, name in enumerate(model.blendshape_names)}
    order = [actions[i] for i in rng.permutation(len(actions))]
    per_expression = int(np.ceil(len(actions) / n_expressions))
    targets, segments = [], []
    time = rest_seconds * rng.uniform(0.85, 1.15)
    for k in range(n_expressions):
        target = np.zeros(len(model.blendshape_names))
        chosen = [order[(k * per_expression + j) % len(order)] for j in range(per_expression)]
        if rng.uniform() < 0.3:  # sometimes a combination with another action of the region
            chosen = chosen + [actions[int(rng.integers(len(actions)))]]
        for action in chosen:
            _action_weights(action, rng, lookup, target)
        length = expression_seconds * rng.uniform(0.85, 1.15)
        targets.append(target)
        segments.append((time, time + length))
        time += length + rest_seconds * rng.uniform(0.85, 1.15)
    t = np.arange(int(round(time * rate))) / rate
    weights = np.zeros((len(t), len(model.blendshape_names)))
    for target, (start, end) in zip(targets, segments):
        weights += _pulse(t, start, end, 0.3 * (end - start))[:, None] * target
    return np.clip(weights, 0.0, 1.0)


def region_takes_weights(model: FaceModel, *, seed: int = 0, regions: tuple[str, ...] = REGIONS,
                         expressions_per_take: int = 8, rest_seconds: float = 2.0,
                         expression_seconds: float = 2.0,
                         rate: float = 60.0) -> tuple[np.ndarray, list[Take]]:
    """All region takes end to end: weights ``(F, B)`` and the takes (named after their region)."""
    rng = np.random.default_rng([seed, 1])
    parts, takes, start = [], [], 0
    for region in regions:
        if region not in REGION_ACTIONS:
            raise OptionError(f"unknown region {region!r} (known: {', '.join(REGIONS)})")
        part = region_take_weights(model, region, rng=rng, n_expressions=expressions_per_take,
                                   rest_seconds=rest_seconds, expression_seconds=expression_seconds,
                                   rate=rate)
        parts.append(part)
        takes.append(Take(region, start, start + len(part), region))
        start += len(part)
    return np.concatenate(parts), takes


def _keyframed(t: np.ndarray, times: list[float], values: list[float]) -> np.ndarray:
    """Shape-preserving (PCHIP, no overshoot) curve through keyframes, 0 outside them."""
    if len(times) < 2:
        return np.zeros_like(t)
    order = np.argsort(times)
    curve = PchipInterpolator(np.asarray(times)[order], np.asarray(values)[order],
                              extrapolate=False)(t)
    return np.nan_to_num(curve, nan=0.0)


def performance_weights(model: FaceModel, *, seconds: float = 30.0, rate: float = 60.0,
                        seed: int = 0) -> np.ndarray:
    """Blendshape weights ``(F, B)`` of a mixed performance.

    Speech: phrases of syllables (≈4 per second) with jaw opening and a viseme each
    (open, rounded ``oo``, spread ``ee``, closed ``m/b/p``, ``f/v``); between phrases, pauses.
    Emotion episodes (smile or smirk, surprise, frown/anger) of 1.5–4 s; blinks every 2–6 s.
    """
    rng = np.random.default_rng([seed, 2])
    lookup = {name: i for i, name in enumerate(model.blendshape_names)}
    t = np.arange(int(round(seconds * rate))) / rate
    weights = np.zeros((len(t), len(model.blendshape_names)))
    keys: dict[str, tuple[list[float], list[float]]] = {}

    def key(name: str, time: float, value: float) -> None:
        times, values = keys.setdefault(name, ([], []))
        times.append(time)
        values.append(value)

    visemes = {
        "open": {"jawOpen": 1.0, "mouthLowerDown_L": 0.4, "mouthLowerDown_R": 0.4},
        "oo": {"jawOpen": 0.3, "mouthFunnel": 0.8, "mouthPucker": 0.7},
        "ee": {"jawOpen": 0.4, "mouthStretch_L": 0.6, "mouthStretch_R": 0.6,
               "mouthUpperUp_L": 0.2, "mouthUpperUp_R": 0.2},
        "mbp": {"mouthPress_L": 0.7, "mouthPress_R": 0.7, "mouthClose": 0.3, "jawOpen": 0.3},
        "fv": {"jawOpen": 0.2, "mouthRollLower": 0.7, "mouthUpperUp_L": 0.3,
               "mouthUpperUp_R": 0.3},
    }
    speech_names = sorted({name for shape in visemes.values() for name in shape})
    time = rng.uniform(0.3, 0.8)
    for name in speech_names:
        key(name, 0.0, 0.0)
    while time < seconds - 1.0:
        phrase_end = min(time + rng.uniform(1.5, 3.5), seconds - 0.6)
        for name in speech_names:
            key(name, time, 0.0)
        time += 0.12
        while time < phrase_end:
            shape = visemes[list(visemes)[int(rng.integers(len(visemes)))]]
            loud = rng.uniform(0.35, 0.8)
            for name in speech_names:
                key(name, time, loud * shape.get(name, 0.0))
            time += rng.uniform(0.18, 0.32)
        for name in speech_names:
            key(name, time, 0.0)
        time += rng.uniform(0.4, 1.1)
    for name in speech_names:
        key(name, seconds, 0.0)
    for name, (times, values) in keys.items():
        weights[:, lookup[name]] += _keyframed(t, times, values)

    emotions = {
        "smile": {"mouthSmile_L": 0.8, "mouthSmile_R": 0.8, "cheekSquint_L": 0.5,
                  "cheekSquint_R": 0.5, "eyeSquint_L": 0.3, "eyeSquint_R": 0.3},
        "smirk_L": {"mouthSmile_L": 0.7, "cheekSquint_L": 0.4, "mouthDimple_L": 0.3},
        "smirk_R": {"mouthSmile_R": 0.7, "cheekSquint_R": 0.4, "mouthDimple_R": 0.3},
        "surprise": {"browInnerUp_L": 0.9, "browInnerUp_R": 0.9, "browOuterUp_L": 0.8,
                     "browOuterUp_R": 0.8, "eyeWide_L": 0.6, "eyeWide_R": 0.6},
        "anger": {"browDown_L": 0.8, "browDown_R": 0.8, "noseSneer_L": 0.5, "noseSneer_R": 0.5,
                  "mouthFrown_L": 0.4, "mouthFrown_R": 0.4},
        "sad": {"browInnerUp_L": 0.7, "browInnerUp_R": 0.7, "mouthFrown_L": 0.6,
                "mouthFrown_R": 0.6, "mouthShrugLower": 0.4},
    }
    time = rng.uniform(0.5, 2.0)
    while time < seconds - 2.0:
        length = rng.uniform(1.5, 4.0)
        shape = emotions[list(emotions)[int(rng.integers(len(emotions)))]]
        envelope = rng.uniform(0.5, 1.0) * _pulse(t, time, time + length, 0.35 * length)
        for name, value in shape.items():
            weights[:, lookup[name]] += envelope * value
        time += length + rng.uniform(0.5, 2.5)

    time = rng.uniform(0.5, 2.0)
    while time < seconds - 0.5:
        blink = _pulse(t, time, time + rng.uniform(0.18, 0.3), 0.08)
        weights[:, lookup["eyeBlink_L"]] += blink
        weights[:, lookup["eyeBlink_R"]] += blink * rng.uniform(0.9, 1.0)
        time += rng.uniform(2.0, 6.0)
    return np.clip(weights, 0.0, 1.0)


def random_head_motion(n_frames: int, *, rate: float = 60.0, seed: int = 0, rotation_deg: float = 3.0,
                translation_mm: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random rigid head motion: rotations ``(F, 3, 3)`` and translations ``(F, 3)`` mm.

    Each rotation axis (pitch, yaw, roll) and translation axis is a sum of three slow sinusoids
    (0.05–0.6 Hz, random phases) scaled so its peak is about ``rotation_deg`` / ``translation_mm``.
    Rotations turn about :data:`HEAD_PIVOT_MM`.
    """
    rng = np.random.default_rng([seed, 3])
    t = np.arange(n_frames) / rate

    def wander(amplitude: float) -> np.ndarray:
        freq = rng.uniform(0.05, 0.6, size=(3, 3))
        phase = rng.uniform(0.0, 2 * np.pi, size=(3, 3))
        gain = rng.uniform(0.5, 1.0, size=(3, 3))
        curves = (gain[None] * np.sin(2 * np.pi * freq[None] * t[:, None, None] + phase[None])).sum(2)
        return amplitude * curves / gain.sum(axis=1)

    rotations = Rotation.from_rotvec(np.deg2rad(wander(rotation_deg))).as_matrix()
    return rotations, wander(translation_mm)


# -- capture --------------------------------------------------------------------------------

def make_ground_truth(model: FaceModel, layout: MarkerLayout, weights: np.ndarray, *,
                      rate: float, takes: list[Take],
                      identity_coefficients: np.ndarray | None = None,
                      head_rotations: np.ndarray | None = None,
                      head_translations: np.ndarray | None = None,
                      info: dict[str, Any] | None = None) -> GroundTruth:
    """Ground truth of markers ``layout`` on ``model`` animated by ``weights`` ``(F, B)``."""
    n_frames = len(weights)
    identity = (np.zeros(len(model.identity_names)) if identity_coefficients is None
                else np.asarray(identity_coefficients, dtype=np.float64))
    base = model.identity_mesh(identity)
    return GroundTruth(
        labels=layout.labels, regions=layout.regions, sides=layout.sides,
        vertices=layout.vertices, triangles=layout.triangles, barycentric=layout.barycentric,
        blendshape_names=model.blendshape_names,
        # float32 like the saved file, so a loaded truth equals the one in memory
        weights=np.asarray(weights, dtype=np.float32).astype(np.float64),
        marker_neutral=layout.positions(base),
        marker_blendshapes=layout.positions(model.blendshapes),
        head_rotations=(np.broadcast_to(np.eye(3), (n_frames, 3, 3)).copy()
                        if head_rotations is None else head_rotations),
        head_translations=np.zeros((n_frames, 3)) if head_translations is None else head_translations,
        head_pivot=np.array(HEAD_PIVOT_MM), identity_coefficients=identity, rate=float(rate),
        takes=list(takes), info=dict(info or {}),
    )


def observed(truth: GroundTruth, *, noise_mm: float = 0.0, gaps_per_minute: float = 0.0,
             seed: int = 0, name: str = "synthetic") -> Trajectories:
    """What a (direct, camera-free) capture delivers: truth + Gaussian noise + random gaps.

    ``noise_mm`` is the standard deviation per axis; ``gaps_per_minute`` the mean number of
    dropouts per marker per minute, each 2–40 frames long (log-uniform).
    """
    if noise_mm < 0 or gaps_per_minute < 0:
        raise OptionError("noise and gap rate must be ≥ 0")
    rng = np.random.default_rng([seed, 4])
    positions = truth.positions + rng.normal(0.0, noise_mm, size=(truth.n_frames, len(truth.labels), 3))
    n_gaps = rng.poisson(gaps_per_minute * truth.n_frames / truth.rate / 60.0, size=len(truth.labels))
    for marker, count in enumerate(n_gaps):
        for _ in range(count):
            length = int(np.exp(rng.uniform(np.log(2), np.log(40))))
            start = int(rng.integers(0, max(1, truth.n_frames - length)))
            positions[start:start + length, marker] = np.nan
    return Trajectories(positions, truth.labels, truth.rate,
                        metadata={"takes": list(truth.takes), "source": name,
                                  "format": "synthetic", "original_units": "mm"})


def marker_normals(model: FaceModel, truth: GroundTruth) -> Callable[[int, int], np.ndarray]:
    """Outward unit surface normals at the markers, posed like the truth: a function
    ``(start, stop) -> (stop - start, M, 3)`` of a frame range (for a projection block by block).

    The normal of a marker is the area-weighted normal of the face triangles around its vertex,
    recomputed per frame from only those triangles' deformed corners.
    """
    faces = model.face_triangles
    ring = [np.flatnonzero((faces == v).any(axis=1)) for v in truth.vertices]
    owner = np.repeat(np.arange(len(ring)), [len(r) for r in ring])
    # (M, K) sums triangle normals onto their marker
    gather = sp.csr_matrix((np.ones(len(owner)), (owner, np.arange(len(owner)))),
                           shape=(len(ring), len(owner)))
    tris = faces[np.concatenate(ring)]  # (K, 3) triangles around all markers
    used, local = np.unique(tris, return_inverse=True)
    local = local.reshape(tris.shape)
    base = model.identity_mesh(truth.identity_coefficients)[used]
    shapes = model.blendshapes[:, used]

    def normals(start: int, stop: int) -> np.ndarray:
        mesh = base + np.tensordot(truth.weights[start:stop], shapes, axes=1)  # (f, U, 3)
        corner = mesh[:, local]  # (f, K, 3, 3)
        tri_normals = np.cross(corner[:, :, 1] - corner[:, :, 0], corner[:, :, 2] - corner[:, :, 0])
        summed = (gather @ tri_normals.transpose(1, 0, 2).reshape(len(owner), -1))
        summed = summed.reshape(len(ring), stop - start, 3).transpose(1, 0, 2)
        summed = np.einsum("fij,fmj->fmi", truth.head_rotations[start:stop], summed)
        return summed / np.linalg.norm(summed, axis=2, keepdims=True)

    return normals


#: A camera misses a marker whose surface normal is further than this from the direction to it
#: (a marker hemisphere still shows at grazing angles), degrees.
MAX_VIEW_NORMAL_DEG = 85.0


def detection_noise_px(rig: Any, points: np.ndarray, noise_mm: float) -> float:
    """``noise_mm`` of marker position as detection noise in px: the median over the cameras of
    focal length / distance to the centre of ``points`` (..., 3) mm."""
    center = np.nanmean(np.asarray(points, dtype=np.float64).reshape(-1, 3), axis=0)
    return float(np.median([noise_mm * cam.focal_px / np.linalg.norm(cam.center - center)
                            for cam in rig]))


def camera_capture(model: FaceModel, truth: GroundTruth, rig: Any, *, noise_mm: float = 0.3,
                   dropout: float = 0.01, ghost_rate: float = 0.002, seed: int = 0,
                   outlier_threshold_px: float = 4.0, spike_threshold_mm: float = 4.0,
                   ) -> Trajectories:
    """Simulate the cameras: project the truth into ``rig`` (a :class:`CameraRig`), detect, triangulate.

    The markers' surface normals come from the deformed mesh (:func:`marker_normals`); detection
    noise is ``noise_mm`` expressed in pixels per camera (:func:`detection_noise_px`); the rest
    is :func:`capture_points` (with the truth's takes).
    """
    if noise_mm < 0:
        raise OptionError(f"noise must be ≥ 0 mm, got {noise_mm}")
    pixel_noise = detection_noise_px(rig, truth.positions, noise_mm)
    # the positions are passed on unnamed (computed twice), so capture_points can let them go
    return capture_points(rig, truth.positions, marker_normals(model, truth), pixel_noise=pixel_noise,
                          labels=truth.labels, rate=truth.rate, dropout=dropout,
                          ghost_rate=ghost_rate, seed=seed, outlier_threshold_px=outlier_threshold_px,
                          spike_threshold_mm=spike_threshold_mm, takes=truth.takes)


def capture_points(rig: Any, points: np.ndarray,
                   normals: np.ndarray | Callable[[int, int], np.ndarray], *, pixel_noise: float,
                   labels: Sequence[str], rate: float, dropout: float = 0.01,
                   ghost_rate: float = 0.002, seed: int = 0, outlier_threshold_px: float = 4.0,
                   spike_threshold_mm: float = 4.0, takes: Sequence[Take] = ()) -> Trajectories:
    """Capture markers ``points (F, M, 3)`` mm with outward ``normals (F, M, 3)`` (or a function
    of a frame range giving them, see :func:`~.projection.project_markers`) through ``rig``.

    A camera misses a marker whose normal is more than :data:`MAX_VIEW_NORMAL_DEG` from the
    direction to it, that is outside its image or field of view, or that randomly drops out
    (``dropout``); ``ghost_rate`` of the detections are wrong (mislabels, reflections);
    ``pixel_noise`` px of Gaussian detection noise. Triangulation drops views by reprojection
    error; points that still jump more than ``spike_threshold_mm`` from their running median
    are removed (:func:`spike_mask`). Returns the trajectories (gaps NaN, residuals =
    reprojection error px, ``metadata["view_counts"]``, ``metadata["spikes_removed"]``).
    """
    from .projection import project_markers
    from .triangulate import triangulate

    observations = project_markers(rig, points, normals=normals, pixel_noise=pixel_noise,
                                   dropout=dropout, ghost_rate=ghost_rate,
                                   min_view_cos=np.cos(np.deg2rad(MAX_VIEW_NORMAL_DEG)),
                                   rng=np.random.default_rng([seed, 5]))
    del points, normals  # the (C, F, M, 2) detections and the triangulation are the peak
    traj = triangulate(rig, observations, labels=labels, rate=rate,
                       outlier_threshold_px=outlier_threshold_px)
    del observations
    spikes = spike_mask(traj.positions, threshold_mm=spike_threshold_mm)
    positions = np.where(spikes[..., None], np.nan, traj.positions)
    residuals = np.where(spikes, np.nan, traj.residuals)
    meta = dict(traj.metadata)
    meta["spikes_removed"] = int(spikes.sum())
    meta.update({"takes": list(takes), "source": f"synthetic capture ({rig.name})", "format": "synthetic",
                 "original_units": "mm", "pixel_noise": pixel_noise})
    return traj.replace(positions=positions, residuals=residuals, metadata=meta)


#: Values (frames x markers x 3) of one block of :func:`spike_mask` (8 M: 64 MB per copy).
SPIKE_BLOCK_VALUES = 8_000_000


def spike_mask(positions: np.ndarray, *, threshold_mm: float = 4.0, window: int = 7) -> np.ndarray:
    """Where a marker jumps away from its running median, ``(F, M)`` bool.

    ``positions (F, M, 3)`` mm with NaN gaps (bridged linearly for the median only); a point
    farther than ``threshold_mm`` from the median of its ``window`` frames is a spike: what a
    two-view mislabel or reflection leaves after triangulation, which no view check can catch.
    """
    from scipy.ndimage import median_filter

    n_frames, n_markers = positions.shape[:2]
    frames = np.arange(n_frames)
    spikes = np.empty((n_frames, n_markers), dtype=bool)
    step = max(1, SPIKE_BLOCK_VALUES // max(3 * n_frames, 1))
    for lo in range(0, n_markers, step):  # markers are independent: blocks bound the copies
        part = positions[:, lo:lo + step]
        bridged = part.copy()
        for marker in range(part.shape[1]):
            seen = np.isfinite(part[:, marker, 0])
            if 0 < seen.sum() < n_frames:
                for axis in range(3):
                    bridged[~seen, marker, axis] = np.interp(frames[~seen], frames[seen],
                                                             part[seen, marker, axis])
        median = median_filter(np.nan_to_num(bridged), size=(window, 1, 1), mode="nearest")
        with np.errstate(invalid="ignore"):
            spikes[:, lo:lo + step] = np.linalg.norm(part - median, axis=2) > threshold_mm
    return spikes


def dense_session(model: FaceModel, layout: MarkerLayout, *, seed: int = 0,
                  identity_coefficients: np.ndarray | None = None, rate: float = 60.0,
                  expressions_per_take: int = 8, rest_seconds: float = 2.0,
                  expression_seconds: float = 2.0, noise_mm: float = 0.3,
                  gaps_per_minute: float = 1.0, head_motion: bool = False,
                  rotation_deg: float = 3.0, translation_mm: float = 5.0) -> SyntheticSession:
    """The per-region takes session (see :func:`region_takes_weights`), captured directly."""
    weights, takes = region_takes_weights(model, seed=seed, expressions_per_take=expressions_per_take,
                                          rest_seconds=rest_seconds,
                                          expression_seconds=expression_seconds, rate=rate)
    return _session(model, layout, weights, takes, seed=seed, kind="regions",
                    identity_coefficients=identity_coefficients, rate=rate, noise_mm=noise_mm,
                    gaps_per_minute=gaps_per_minute, head_motion=head_motion,
                    rotation_deg=rotation_deg, translation_mm=translation_mm)


def performance_session(model: FaceModel, layout: MarkerLayout, *, seed: int = 0,
                        seconds: float = 30.0, identity_coefficients: np.ndarray | None = None,
                        rate: float = 60.0, noise_mm: float = 0.3, gaps_per_minute: float = 1.0,
                        head_motion: bool = False, rotation_deg: float = 3.0,
                        translation_mm: float = 5.0) -> SyntheticSession:
    """The held-out performance (one take named ``performance``), captured directly."""
    weights = performance_weights(model, seconds=seconds, rate=rate, seed=seed)
    takes = [Take("performance", 0, len(weights))]
    return _session(model, layout, weights, takes, seed=seed + 1_000_003, kind="performance",
                    identity_coefficients=identity_coefficients, rate=rate, noise_mm=noise_mm,
                    gaps_per_minute=gaps_per_minute, head_motion=head_motion,
                    rotation_deg=rotation_deg, translation_mm=translation_mm)


def _session(model: FaceModel, layout: MarkerLayout, weights: np.ndarray, takes: list[Take], *,
             seed: int, kind: str, identity_coefficients: np.ndarray | None, rate: float,
             noise_mm: float, gaps_per_minute: float, head_motion: bool, rotation_deg: float,
             translation_mm: float) -> SyntheticSession:
    if rate <= 0:
        raise OptionError(f"frame rate must be > 0, got {rate}")
    rotations = translations = None
    if head_motion:
        rotations, translations = random_head_motion(len(weights), rate=rate, seed=seed,
                                              rotation_deg=rotation_deg,
                                              translation_mm=translation_mm)
    info = {"generator": "mocaptk.acquisition.synth_session", "kind": kind, "seed": seed,
            "noise_mm": noise_mm, "gaps_per_minute": gaps_per_minute,
            "head_motion": head_motion, "rotation_deg": rotation_deg if head_motion else 0.0,
            "translation_mm": translation_mm if head_motion else 0.0,
            "layout_mode": layout.mode, "spacing_mm": layout.spacing_mm,
            "face_model": "ICT-FaceKit (MIT, USC Institute for Creative Technologies)"}
    truth = make_ground_truth(model, layout, weights, rate=rate, takes=takes,
                              identity_coefficients=identity_coefficients,
                              head_rotations=rotations, head_translations=translations, info=info)
    traj = observed(truth, noise_mm=noise_mm, gaps_per_minute=gaps_per_minute, seed=seed,
                    name=f"synthetic {kind}")
    return SyntheticSession(traj, truth)


def truth_errors(traj: Trajectories, truth: GroundTruth, *, block: int = 4096) -> tuple[float, int]:
    """(sum of squared distances mm², count) of the present positions of ``traj`` from the
    noise-free ``truth`` (same frames and markers), by blocks of frames (no (F, M, 3) copy)."""
    squared, count = 0.0, 0
    for start in range(0, truth.n_frames, block):
        stop = min(start + block, truth.n_frames)
        err = np.sum((traj.positions[start:stop] - truth.positions_between(start, stop)) ** 2, axis=2)
        seen = np.isfinite(err)
        squared, count = squared + float(err[seen].sum()), count + int(seen.sum())
    return squared, count


# -- files ----------------------------------------------------------------------------------

_TRUTH_ARRAYS = ("vertices", "triangles", "barycentric", "weights", "marker_neutral",
                 "marker_blendshapes", "head_rotations", "head_translations", "head_pivot",
                 "identity_coefficients")


def save_ground_truth(truth: GroundTruth, path: str | os.PathLike[str], *,
                      force: bool = True) -> Path:
    """Write ``truth`` as a compressed ``.npz`` (arrays + a JSON header); atomic."""
    header = {"format": GROUND_TRUTH_FORMAT, "version": GROUND_TRUTH_VERSION,
              "labels": list(truth.labels), "regions": list(truth.regions),
              "sides": list(truth.sides), "blendshape_names": list(truth.blendshape_names),
              "rate": truth.rate, "takes": [t.as_dict() for t in truth.takes], "info": truth.info}
    arrays = {name: getattr(truth, name) for name in _TRUTH_ARRAYS}
    arrays["weights"] = arrays["weights"].astype(np.float32)  # 7 significant digits is plenty
    with atomic_open(path, "wb", force=force) as handle:
        np.savez_compressed(handle, header=np.array(json.dumps(header, sort_keys=True)), **arrays)
    return Path(path)


def load_ground_truth(path: str | os.PathLike[str]) -> GroundTruth:
    """Read a file written by :func:`save_ground_truth`."""
    try:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            arrays = {name: data[name] for name in _TRUTH_ARRAYS}
    except (OSError, ValueError, KeyError) as exc:
        raise InputFileError(path, f"not a mocaptk ground-truth file ({exc})") from None
    if header.get("format") != GROUND_TRUTH_FORMAT:
        raise InputFileError(path, "not a mocaptk ground-truth file (format field)")
    return GroundTruth(
        labels=tuple(header["labels"]), regions=tuple(header["regions"]),
        sides=tuple(header["sides"]), blendshape_names=tuple(header["blendshape_names"]),
        rate=float(header["rate"]),
        takes=[Take(t["name"], t["start"], t["end"], t.get("region")) for t in header["takes"]],
        info=header["info"],
        **{name: np.asarray(arrays[name], dtype=np.int64 if name in ("vertices", "triangles")
                            else np.float64) for name in _TRUTH_ARRAYS},
    )


def write_regions_file(truth: GroundTruth, path: str | os.PathLike[str], *,
                       force: bool = True) -> Path:
    """JSON ``{"region": [labels...]}``."""
    return write_json(path, truth.regions_dict(), force=force)


def write_takes_file(takes: list[Take], path: str | os.PathLike[str], *,
                     force: bool = True) -> Path:
    """JSON ``{"takes": [{"name", "region", "start", "end"}]}`` (0-based, end exclusive)."""
    return write_json(path, {"takes": [t.as_dict() for t in takes]}, force=force)
