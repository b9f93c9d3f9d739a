"""Sessions of the test bed: an identity, a marker set, a ROM and a held-out performance.

Positions are the ICT face (generic neutral + identity + expression deltas, linear as ICT's own
model) at the marker vertices, head-relative (no head motion) unless :func:`head_motion` is
applied. The capture gets sensor noise (Gaussian, ``noise_mm`` per coordinate) and short gaps;
the truth is noise-free and gap-free.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from mocaptk.acquisition.c3d_write import write_c3d
from mocaptk.trajectories import Take, Trajectories

from .ict import IctFace
from .markers import headband, place_markers
from .protocol import performance_weights, rom_weights

RATE = 60.0
TRUTH_FORMAT, TRUTH_VERSION = "testbed.truth", 1


@dataclass(frozen=True)
class Actor:
    """An ICT identity: coefficients of the identity shapes, and the dense marker set on it."""

    identity: np.ndarray  # (I,)
    rest: np.ndarray  # (V, 3) mm, the identity's neutral face
    vertices: np.ndarray  # (M,) marker vertices
    labels: tuple[str, ...]
    rigid: np.ndarray  # (R, 3) mm headband markers (R = 0: none)
    rigid_labels: tuple[str, ...]


def make_actor(face: IctFace, *, identity_seed: int, count: int, half: bool, marker_seed: int,
               rigid: bool = False, like: Actor | None = None) -> Actor:
    """An identity (coefficients ~ N(0, 1.2²) on ICT's identity shapes) and its marker set, or
    ``like``'s marker set (same vertices and labels: another actor wearing the same layout, for
    cross-actor tests)."""
    coeffs = np.random.default_rng([identity_seed, 5]).normal(0.0, 1.2, size=len(face.identities))
    rest = face.neutral + np.einsum("i,ivc->vc", coeffs, face.identities)
    if like is None:
        vertices, labels = place_markers(face, rest, count=count, half=half, seed=marker_seed)
    else:
        vertices, labels = like.vertices, list(like.labels)
    band = headband(face, rest) if rigid else np.zeros((0, 3))
    sides = np.where(band[:, 0] > 0, "L", "R")  # the actor's left is +x
    return Actor(coeffs, rest, vertices, tuple(labels), band, tuple(f"hb{i}_{s}" for i, s in enumerate(sides)))


def truth_positions(face: IctFace, actor: Actor, weights: np.ndarray) -> np.ndarray:
    """(F, M + R, 3) mm noise-free head-relative marker positions for expression ``weights`` (F, E)."""
    deltas = face.expressions[:, actor.vertices].astype(np.float64)  # (E, M, 3)
    skin = actor.rest[actor.vertices][None] + np.einsum("fe,emc->fmc", weights, deltas)
    band = np.broadcast_to(actor.rigid, (len(weights), *actor.rigid.shape))
    return np.concatenate([skin, band], axis=1)


def capture(truth: np.ndarray, *, noise_mm: float, gap_rate: float, seed: int) -> np.ndarray:
    """Sensor noise (N(0, noise_mm²) per coordinate) and gaps (runs of 1–12 frames starting at
    ``gap_rate`` of the points) on ``truth`` (F, M, 3)."""
    rng = np.random.default_rng([seed, 404])
    out = truth + rng.normal(0.0, noise_mm, truth.shape)
    starts = np.argwhere(rng.random(truth.shape[:2]) < gap_rate)
    for frame, marker in starts:
        out[frame:frame + int(rng.integers(1, 13)), marker] = np.nan
    return out


def head_motion(n_frames: int, *, max_deg: float, max_mm: float, seed: int, rate: float = RATE,
                pivot: np.ndarray = np.array([0.0, -80.0, -40.0])) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random head poses: rotations (F, 3, 3) about ``pivot`` (mm, near the neck) up to
    ``max_deg`` and translations (F, 3) up to ``max_mm`` (per axis, low-passed noise ~0.5 Hz)."""
    rng = np.random.default_rng([seed, 808])

    def wander(scale: float) -> np.ndarray:
        x = gaussian_filter1d(rng.normal(size=(n_frames + 200, 3)), sigma=0.35 * rate, axis=0)[100:-100]
        return scale * x / np.abs(x).max(axis=0)

    rot = Rotation.from_rotvec(np.deg2rad(wander(max_deg))).as_matrix()
    shift = wander(max_mm)
    return rot, shift + pivot - np.einsum("fij,j->fi", rot, pivot)


def apply_pose(positions: np.ndarray, rot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Head-relative (F, M, 3) → world: ``R p + t`` per frame (NaN stays NaN)."""
    return np.einsum("fij,fmj->fmi", rot, positions) + shift[:, None]


@dataclass(frozen=True)
class TestbedSession:
    capture: Trajectories  # noisy, with gaps
    truth: np.ndarray  # (F, M, 3) noise-free
    weights: np.ndarray  # (F, E)


def rom_session(face: IctFace, actor: Actor, *, seed: int, noise_mm: float = 0.2,
                gap_rate: float = 2e-4) -> TestbedSession:
    weights, takes = rom_weights(face.expression_names, rate=RATE, seed=seed)
    truth = truth_positions(face, actor, weights)
    traj = Trajectories(capture(truth, noise_mm=noise_mm, gap_rate=gap_rate, seed=seed),
                        actor.labels + actor.rigid_labels, RATE,
                        metadata={"takes": [Take(n, a, b) for n, a, b in takes]})
    return TestbedSession(traj, truth, weights)


def performance_session(face: IctFace, actor: Actor, *, seed: int, seconds: float = 60.0,
                        noise_mm: float = 0.2, gap_rate: float = 2e-4) -> TestbedSession:
    weights = performance_weights(face.expression_names, rate=RATE, seconds=seconds, seed=seed)
    truth = truth_positions(face, actor, weights)
    traj = Trajectories(capture(truth, noise_mm=noise_mm, gap_rate=gap_rate, seed=seed + 1),
                        actor.labels + actor.rigid_labels, RATE)
    return TestbedSession(traj, truth, weights)


def save_truth(session: TestbedSession, path: str | os.PathLike[str], *, info: dict) -> Path:
    """``.npz``: noise-free ``positions`` (F, M, 3) mm, ``weights`` and a JSON header."""
    header = {"format": TRUTH_FORMAT, "version": TRUTH_VERSION, "labels": list(session.capture.labels),
              "rate": session.capture.rate, **info}
    np.savez_compressed(path, header=np.array(json.dumps(header, sort_keys=True)),
                        positions=session.truth.astype(np.float64), weights=session.weights.astype(np.float32))
    return Path(path)


def load_truth(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict]:
    """(positions (F, M, 3) mm, header) of :func:`save_truth`."""
    with np.load(path, allow_pickle=False) as data:
        return data["positions"], json.loads(str(data["header"]))


def write_set(face: IctFace, folder: str | os.PathLike[str], *, identity_seed: int, count: int,
              half: bool, marker_seed: int, rigid: bool = False, seconds: float = 60.0) -> dict[str, Path]:
    """``rom.c3d`` + ``rom_truth.npz`` and ``performance.c3d`` + ``performance_truth.npz``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    actor = make_actor(face, identity_seed=identity_seed, count=count, half=half, marker_seed=marker_seed,
                       rigid=rigid)
    info = {"identity": [float(c) for c in actor.identity], "vertices": [int(v) for v in actor.vertices],
            "half": half, "identity_seed": identity_seed, "marker_seed": marker_seed}
    out = {}
    for name, session in (("rom", rom_session(face, actor, seed=identity_seed * 100 + 1)),
                          ("performance", performance_session(face, actor, seed=identity_seed * 100 + 2,
                                                              seconds=seconds))):
        out[name] = write_c3d(session.capture, folder / f"{name}.c3d")
        out[f"{name}_truth"] = save_truth(session, folder / f"{name}_truth.npz", info=info)
    return out
