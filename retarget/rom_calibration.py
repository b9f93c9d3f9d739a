"""Actor calibration from the dense range-of-motion session (after Ribera et al. 2017).

The character's shapes read at the actor's markers (:meth:`Correspondence.shape_basis`) say how
the *character* moves there; the actor's face moves differently (other proportions, other
coupling between shapes, other extremes). Following Ribera, Zell, Lewis, Noh and Botsch
(*Facial retargeting with automatic range of motion alignment*, TOG 36(4), 2017), the actor's
own shapes are learned from the range of motion (ROM) — here the dense session, region by
region — with the character's expression space as the prior:

1. **Weights from the current shapes**: every ROM frame (at most :data:`MAX_FRAMES`, evenly
   spread) is solved with the bounded sparse solve (:mod:`.weight_solve`, no smoothness).
2. **Shapes from the weights**: per marker, ridge regression of its displacement from the
   actor's neutral on the frames' weights, pulled towards the character's shape there with
   strength ``prior`` (relative to the mean weight energy): ``B_m = (WᵀW + μI)⁻¹(WᵀΔ_m + μB0_m)``.
   This learns the actor's extremes and coupling; the prior keeps shapes the ROM hardly
   uses (or that markers barely see) at the character's.
3. Repeat :data:`ROUNDS` times.
4. **Range** (``reach``): each shape's ROM extreme (the :data:`RANGE_PERCENTILE`-th percentile
   of its ROM weights, in the character's units) is aligned with the rig's range.

   - ``reach=None`` (default): a shape the actor drives past 1 is stretched so its extreme is 1
     (nothing saturates); none is shrunk, since a ROM need not reach every shape's end. The
     character's amplitude stays the anchor: right when the character moves as much as the actor.
   - ``reach=q`` (Ribera et al.'s alignment, ``q = 1``): the ROM performs every shape to ``q`` of
     its range (a full range-of-motion protocol: 1), so every shape the ROM performs (extreme ≥
     :data:`MIN_PERFORMED`) is scaled so that its extreme is exactly ``q``: the actor's widest jaw
     is the character's widest jaw whatever their amplitudes. Shapes the ROM barely performs
     keep the default rule. Where the ROM reaches less than ``q`` of a shape, its weights come out
     too high by ``q`` / reached.

The neutral maps to all weights 0 by construction: displacements are taken from the actor's
neutral (:func:`mocaptk.clustering.neutral.neutral_pose` of the session).

**Unseen sides** (:func:`side_ties`): when the markers barely see one shape of a left/right pair
(a half-face session sees the right-side shapes through the midline only), that shape follows
its mirror twin: both take one weight.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .weight_solve import DEFAULT_L1, solve_weights

__all__ = ["Calibration", "calibrate", "rom_frames", "rom_weights", "side_ties"]

#: ROM frames used (evenly spread).
MAX_FRAMES = 2000
#: Alternations of weights and shapes.
ROUNDS = 4
#: Default strength of the pull towards the character's shapes.
DEFAULT_PRIOR = 1.0
#: Percentile of a shape's ROM weights taken as its extreme.
RANGE_PERCENTILE = 99.5
#: With ``reach``: a shape whose ROM extreme is below this (character units) counts as not
#: performed by the ROM and is not shrunk.
MIN_PERFORMED = 0.2
#: A side shape seen with less than this fraction of its twin's energy follows the twin.
TIE_ENERGY_RATIO = 0.25


@dataclass(frozen=True, eq=False)
class Calibration:
    """``basis`` (S, M, 3) mm the actor's shapes at every dense marker; ``neutral`` (M, 3) mm;
    ``ties`` (S,) the index of the solved variable each shape takes its weight from (itself
    unless it follows a mirror twin); ``rom_extreme`` (S,) the shapes' ROM extremes (before the
    alignment) and ``stretch`` (S,) the factor the shapes were scaled by (≥ 1 without ``reach``)."""

    basis: np.ndarray
    neutral: np.ndarray
    ties: np.ndarray
    rom_extreme: np.ndarray
    stretch: np.ndarray

    def tied_basis(self, rows: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """The basis of the solved variables at markers ``rows``: (U, m, 3), and the variable
        index (S,) each shape reads its weight from."""
        variables, inverse = np.unique(self.ties, return_inverse=True)
        basis = np.zeros((len(variables), *self.basis[:, rows].shape[1:]))
        np.add.at(basis, inverse, self.basis[:, rows])
        return basis, inverse


def side_ties(names: Sequence[str], prior: np.ndarray) -> np.ndarray:
    """(S,) for each shape the shape whose weight it takes: a side shape whose energy in
    ``prior`` (S, M, 3) is below :data:`TIE_ENERGY_RATIO` of its mirror twin's follows the twin."""
    energy = np.sum(prior ** 2, axis=(1, 2))
    index = {n: i for i, n in enumerate(names)}
    ties = np.arange(len(names))
    for i, name in enumerate(names):
        twin = index.get(_mirror(name))
        if twin is not None and energy[i] < TIE_ENERGY_RATIO * energy[twin]:
            ties[i] = twin
    return ties


def _mirror(name: str) -> str:
    """``mouthSmileLeft`` ↔ ``mouthSmileRight``, ``smile_L`` ↔ ``smile_R``."""
    swap = {"Left": "Right", "Right": "Left", "_L": "_R", "_R": "_L", "left": "right",
            "right": "left", ".L": ".R", ".R": ".L"}
    match = re.search(r"(Left|Right|left|right|_L|_R|\.L|\.R)$", name)
    return name[:match.start()] + swap[match.group(1)] if match else name


def calibrate(rom: np.ndarray, neutral: np.ndarray, prior: np.ndarray, ties: np.ndarray, *,
              strength: float = DEFAULT_PRIOR, l1: float = DEFAULT_L1,
              rounds: int = ROUNDS, reach: float | None = None) -> Calibration:
    """Learn the actor's shapes from the ROM ``rom`` (F, M, 3) mm (head-relative, NaN gaps).

    ``neutral`` (M, 3) mm the actor's neutral; ``prior`` (S, M, 3) mm the character's shapes
    at the markers in the actor's frame; ``ties`` from :func:`side_ties`; ``reach`` in (0, 1]
    the fraction of each shape's range the ROM performs (None: keep the character's amplitude).
    """
    delta = rom_frames(rom, neutral)
    basis = np.array(prior, dtype=np.float64)
    calibration = Calibration(basis, neutral, np.asarray(ties), np.ones(len(prior)), np.ones(len(prior)))
    for _ in range(rounds):
        weights = rom_weights(calibration, delta, l1)
        basis = _refit(weights, delta, prior, strength)
        calibration = Calibration(basis, neutral, calibration.ties, calibration.rom_extreme,
                                  calibration.stretch)
    weights = rom_weights(calibration, delta, l1)
    extreme = np.percentile(weights, RANGE_PERCENTILE, axis=0) if len(weights) else np.zeros(len(prior))
    stretch = np.maximum(extreme, 1.0)
    if reach is not None:  # the actor's extreme is the rig's reach
        stretch = np.where(extreme >= MIN_PERFORMED, extreme / reach, stretch)
    return Calibration(basis * stretch[:, None, None], neutral, calibration.ties, extreme, stretch)


def rom_frames(rom: np.ndarray, neutral: np.ndarray) -> np.ndarray:
    """The ROM frames a calibration learns from, (F', M, 3) mm from ``neutral``: at most
    :data:`MAX_FRAMES` of ``rom`` (F, M, 3), evenly spread."""
    step = max(1, int(np.ceil(len(rom) / MAX_FRAMES)))
    return np.asarray(rom[::step], dtype=np.float64) - neutral


def rom_weights(calibration: Calibration, delta: np.ndarray, l1: float) -> np.ndarray:
    """Each ROM frame's weights (F, S) with the current shapes (unbounded above: the extremes
    must show before the range step)."""
    basis, inverse = calibration.tied_basis()
    solved = solve_weights(basis, delta, l1=l1, smooth=0.0, upper=np.inf)
    return solved.weights[:, inverse]


def _refit(weights: np.ndarray, delta: np.ndarray, prior: np.ndarray, strength: float) -> np.ndarray:
    """Per marker, its displacement regressed on the weights with a pull to ``prior``: (S, M, 3)."""
    n_shapes, n_markers = prior.shape[:2]
    mu = strength * max(float(np.mean(np.sum(weights ** 2, axis=0))), 1e-12)
    seen = np.isfinite(delta).all(axis=2)  # (F, M)
    basis = np.empty_like(prior)
    eye = mu * np.eye(n_shapes)
    for m in range(n_markers):
        rows = seen[:, m]
        w = weights[rows]
        basis[:, m] = np.linalg.solve(w.T @ w + eye, w.T @ delta[rows, m] + mu * prior[:, m])
    return basis
