"""Reconstruction models: every dense marker from a layout's markers, behind one interface.

All models work in head-relative coordinates (mm) and take the layout markers of each frame with
NaN for the ones lost; a frame is solved from the markers present in it (never filled first).

Kinds (``MODEL_KINDS``):

- ``ridge``: ridge regression of all marker coordinates from the present layout coordinates
  (the model of ``mocaptk evaluate``), one closed-form model per presence pattern, from the
  training covariance (sufficient statistics: a new pattern costs one small solve), cached.
- ``thin-shell``: Le, Zhu & Deng's ``W = Â⁻¹B̂`` on the marker surface mesh of the neutral pose:
  the dense displacement is the minimal stretching + bending surface through the present layout
  markers' displacements (a lost marker's constraint is dropped: W of the present ones).
- ``pdm-linear`` / ``pdm-biquadratic``: thin-shell + Ma et al. (2008) polynomial displacement
  detail. Per layout marker a 5-D local deformation (3-D offset, 2 in-plane strains from its
  2-ring of layout neighbours), PCA to (d1, d2), interpolated over the mesh with the thin-shell
  weights; per dense marker and axis a (bi)quadratic / linear polynomial in (d1, d2) fitted by
  ridge least squares to the thin-shell residual of the training frames.
- ``ridge-cv`` (default): ``ridge`` whose strength is chosen by leave-one-block-out
  cross-validation on the training frames (``CV_BLOCKS`` contiguous blocks, ``CV_RIDGES``): weak on
  clean, linear faces, strong on noisy real captures; the only kind that holds on every set of the
  test bed (docs/testbed.md).
- ``local-ridge`` (ours): each dense marker by ridge from its ``neighbours`` (4) nearest *present*
  layout markers (neutral pose, Euclidean), from the same training covariance as ``ridge``. A
  global ridge learns cross-region correlations of the training takes (the brow is still while
  the mouth take runs) that a production performance, which mixes regions, does not have; the
  local model cannot (docs/solve.md measures it). A marker whose neighbourhood is lost (its nearest
  present layout marker more than 2x farther than its nearest layout marker) falls back to the
  global ridge.
- ``tapered-ridge`` (ours): ``ridge`` from a covariance localised by marker distance, as
  ensemble Kalman filters do: each 3x3 block of the training covariance is multiplied by the
  Gaspari–Cohn taper (compact support, positive definite in 3-D) of the two markers' neutral
  distance, so far markers stop explaining each other smoothly instead of at a hard neighbour
  count. The taper length is chosen by leave-one-block-out cross-validation on the training
  frames (``CV_BLOCKS`` contiguous blocks: a session records its takes one after another), from
  ``TAPER_RADII`` times the neutral's RMS radius and no taper (= ``ridge``).

Every prediction carries a per-frame expected error (mm): the model's RMS error over the dense
markers on (up to 200) training frames with every layout marker present, plus, per missing layout
marker, the increase measured with that marker alone dropped (added in quadrature; an
approximation for several markers lost at once).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.atomic import write_bytes
from mocaptk.errors import InputFileError, OptionError, quoted, unreadable
from mocaptk.jsonio import dumps, parse_json
from mocaptk.surface_mesh import marker_surface_mesh, mesh_edges
from mocaptk.thin_shell import interpolation_weights, thin_shell_operator

from .neutral import neutral_pose

__all__ = [
    "CvRidgeModel", "DEFAULT_KIND", "DEFAULT_RIDGE", "MODEL_FORMAT", "MODEL_KINDS", "MODEL_VERSION", "FaceModel",
    "Prediction", "ReconstructionModel", "RidgeMoments", "TaperedRidgeModel", "batched_ridge", "check_frames", "fit_model",
    "fit_reconstruction", "gaspari_cohn", "load_model", "model_from_arrays", "row_patterns", "save_model",
]

#: Default ridge strength, relative to the mean diagonal of the input Gram matrix.
DEFAULT_RIDGE = 1e-3
MODEL_KINDS = ("ridge", "ridge-cv", "local-ridge", "tapered-ridge", "thin-shell", "pdm-linear", "pdm-biquadratic")
#: The kind ``mocaptk solve`` uses without ``--model-kind``: the only one never more than 2 % worse
#: than plain ridge on any set of the test bed (docs/testbed.md: an independent generator, our own
#: synth, real blenderFace across takes and subjects).
DEFAULT_KIND = "ridge-cv"
#: Layout markers each dense marker is solved from in ``local-ridge``.
LOCAL_NEIGHBOURS = 4
#: ... unless its nearest present one is this many times farther than its nearest layout marker.
LOCAL_REACH = 2.0
MODEL_FORMAT, MODEL_VERSION = "mocaptk.model", 1
#: ``tapered-ridge``: taper lengths tried (times the neutral's RMS radius; inf = no taper) and
#: the contiguous blocks of training frames each left out once to choose among them.
TAPER_RADII = (0.5, 0.8, 1.2, 1.6, 2.4, 3.2, np.inf)
CV_BLOCKS = 6
#: ``ridge-cv``: relative ridge strengths tried, each scored on the same blocks.
CV_RIDGES = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1)
#: Ridge strength of the detail polynomials, relative to the mean diagonal of their Gram matrix.
DETAIL_RIDGE = 1e-2
#: Training frames used to measure the expected error (evenly subsampled).
CHECK_FRAMES = 200
#: Per-pattern sub-models kept (least recently used dropped first): memory stays bounded.
CACHE_PATTERNS = 2048
#: Thin-shell stiffness (Le et al.'s ks = 1, kb = 10) and the tiny Tikhonov term that keeps marker
#: surface parts without a present marker (isolated outliers) at their neutral position.
KS, KB, TIKHONOV = 1.0, 10.0, 1e-9


def row_patterns(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct rows of a 2-D bool array and, per row, the number of its pattern (fast np.unique)."""
    packed = np.ascontiguousarray(np.packbits(mask, axis=1))
    keys = packed.view(np.dtype((np.void, packed.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return mask[first], inverse.ravel()


def ridge_fit(inputs: np.ndarray, targets: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """Ridge fit ``targets ≈ inputs @ W + b``; inputs finite (F, K), targets may hold NaN (F, T).

    Each target column is fitted on its finite rows (the intercept is not penalised); columns
    sharing a NaN pattern share one Gram matrix. A column with fewer than 2 finite rows gets
    W = 0 and b = its mean (or 0).
    """
    n_frames = inputs.shape[0]
    present = np.isfinite(targets)
    shift = inputs.mean(axis=0)  # centring keeps the normal equations well conditioned
    aug = np.hstack([inputs - shift, np.ones((n_frames, 1))])
    rhs = aug.T @ np.where(present, targets, 0.0)  # (K+1, T): NaN rows contribute nothing
    return _pattern_fits(aug.T @ aug, rhs, aug, present, n_frames, shift, ridge)


def _pattern_fits(full: np.ndarray, rhs: np.ndarray, aug: np.ndarray, present: np.ndarray, n_frames: int,
                  shift: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`ridge_fit` from ``full`` = Σ aᵢaᵢᵀ and ``rhs`` = Σ aᵢyᵢᵀ (NaN targets as 0) over
    ``n_frames`` rows ``aᵢ = [xᵢ − shift, 1]`` (K+1); ``aug`` (G, K+1) and ``present`` (G, T) are
    the rows where targets may be missing (all rows, or only the gap rows when the other
    ``n_frames − G`` rows have every target)."""
    n_in, n_out = full.shape[0] - 1, rhs.shape[1]
    coef = np.zeros((n_in, n_out))
    intercept = np.zeros(n_out)
    if present.shape[0]:
        patterns, inverse = row_patterns(present.T)
    else:  # no row may miss a target (row_patterns of empty rows has no pattern)
        patterns, inverse = np.ones((1, 0), dtype=bool), np.zeros(n_out, dtype=np.intp)
    for p, rows in enumerate(patterns):
        cols = np.flatnonzero(inverse == p)
        n_rows = n_frames - int((~rows).sum())
        if n_rows < 1:
            continue
        if n_rows < 2:
            intercept[cols] = rhs[n_in, cols] / n_rows
            continue
        if n_rows == n_frames:
            gram = full.copy()
        elif n_rows >= n_frames // 2 or aug.shape[0] < n_frames:  # subtract the few missing rows
            missing = aug[~rows]
            gram = full - missing.T @ missing
        else:
            kept = aug[rows]
            gram = kept.T @ kept
        sums = gram[n_in, :n_in]
        centred_trace = float(np.trace(gram[:n_in, :n_in]) - sums @ sums / n_rows)
        lam = ridge * max(centred_trace / n_in, 1e-12)
        gram[np.arange(n_in), np.arange(n_in)] += lam
        solution = np.linalg.solve(gram, rhs[:, cols])
        coef[:, cols] = solution[:n_in]
        intercept[cols] = solution[n_in] - shift @ solution[:n_in]
    return coef, intercept


@dataclass(frozen=True, eq=False)
class RidgeMoments:
    """Training frames ``(F, M, 3)`` mm of :func:`fit_reconstruction` for any layout: the frames
    with every marker present as their mean and centred Gram matrix, the frames with gaps kept.
    A sub-model then costs a pass over the gap frames and a (3L + 1)-sized solve instead of a
    pass over every training frame; the same fit as :func:`ridge_fit` to rounding (errors ~1e-9 mm).
    """

    mean: np.ndarray  # (3M,) mean of the complete frames, mm
    gram: np.ndarray  # (3M, 3M) their centred Gram matrix, mm²
    complete: int  # how many
    gaps: np.ndarray  # (G, 3M) the frames with a gap, mm
    ridge: float

    @classmethod
    def fit(cls, train: np.ndarray, *, ridge: float = DEFAULT_RIDGE) -> RidgeMoments:
        """From training frames ``(F, M, 3)`` mm, NaN gaps."""
        flat = np.asarray(train, dtype=np.float64).reshape(train.shape[0], -1)
        whole = np.isfinite(flat).all(axis=1)
        mean = flat[whole].mean(axis=0) if whole.any() else np.zeros(flat.shape[1])
        centred = flat[whole] - mean
        return cls(mean, centred.T @ centred, int(whole.sum()), flat[~whole], _ridge(ridge))

    def model(self, layout_idx: Sequence[int] | np.ndarray) -> ReconstructionModel:
        """:func:`fit_reconstruction` of the training frames for ``layout_idx``."""
        return ReconstructionModel(None, _layout_indices(layout_idx, self.mean.size // 3), self.ridge,
                                   moments=self)

    def fit_columns(self, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(W (K, 3M), b (3M,)) of :func:`ridge_fit` on the frames where the coordinates ``cols``
        (K,) are present: the complete frames from the moments, the gap frames directly."""
        x_gap = self.gaps[:, cols]
        gap_rows = self.gaps[np.isfinite(x_gap).all(axis=1)]
        n = self.complete + gap_rows.shape[0]
        if n == 0:  # never present together: as ridge_fit of no rows
            return np.zeros((cols.size, self.mean.size)), np.zeros(self.mean.size)
        shift = (self.complete * self.mean[cols] + gap_rows[:, cols].sum(axis=0)) / n
        offset = self.mean[cols] - shift  # the complete frames' mean, from the shift
        full = np.empty((cols.size + 1, cols.size + 1))
        full[:-1, :-1] = self.gram[np.ix_(cols, cols)] + self.complete * np.outer(offset, offset)
        full[-1, :-1] = full[:-1, -1] = self.complete * offset
        full[-1, -1] = self.complete
        rhs = np.empty((cols.size + 1, self.mean.size))
        rhs[:-1] = self.gram[cols] + self.complete * np.outer(offset, self.mean)
        rhs[-1] = self.complete * self.mean
        aug = np.hstack([gap_rows[:, cols] - shift, np.ones((gap_rows.shape[0], 1))])
        present = np.isfinite(gap_rows)
        full += aug.T @ aug
        rhs += aug.T @ np.where(present, gap_rows, 0.0)
        return _pattern_fits(full, rhs, aug, present, n, shift, self.ridge)


def batched_ridge(gram: np.ndarray, cross: np.ndarray, ridge: float) -> np.ndarray:
    """Ridge coefficients (N, K, C) from centred Gram matrices (N, K, K) and cross products
    (N, K, C); the strength is relative to each Gram matrix's mean diagonal (scale-free)."""
    k = gram.shape[1]
    gram = gram.copy()
    lam = ridge * np.maximum(np.einsum("nii->n", gram) / k, 1e-12)
    gram[:, np.arange(k), np.arange(k)] += lam[:, None]
    return np.linalg.solve(gram, cross)


@dataclass
class ReconstructionModel:
    """``evaluate``'s exact ridge: per presence pattern, fitted on the training frames where the
    pattern's layout markers are all present, each target on its own finite rows (keeps the
    training frames; use :func:`fit_model` for a compact, savable model).
    """

    train: np.ndarray | None  # (F, M, 3) mm, NaN gaps (None: from ``moments``)
    layout: np.ndarray  # (L,) intp
    ridge: float = DEFAULT_RIDGE
    _cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)
    moments: RidgeMoments | None = None  # the training frames summarised (RidgeMoments.model)

    def submodel(self, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(W (3K, 3M), b (3M,)) using only the layout markers flagged in ``present`` (L,) bool."""
        key = present.tobytes()
        if key not in self._cache:
            cols = self.layout[present]
            if self.moments is not None:
                self._cache[key] = self.moments.fit_columns((3 * cols[:, None] + np.arange(3)).ravel())
                return self._cache[key]
            x = self.train[:, cols].reshape(self.train.shape[0], -1)
            rows = np.isfinite(x).all(axis=1)
            y = self.train[rows].reshape(int(rows.sum()), -1)
            self._cache[key] = ridge_fit(x[rows], y, self.ridge)
        return self._cache[key]

    def predict_positions(self, layout_positions: np.ndarray) -> np.ndarray:
        """(F, M, 3) mm from the layout markers (F, L, 3) (NaN = lost); present ones copied."""
        n_markers = self.train.shape[1] if self.moments is None else self.moments.mean.size // 3
        return _by_pattern(layout_positions, self.layout, n_markers,
                           lambda pattern, x: _affine(x, *self.submodel(pattern), n_markers))


def fit_reconstruction(train: np.ndarray, layout_idx: Sequence[int] | np.ndarray, *,
                       ridge: float = DEFAULT_RIDGE) -> ReconstructionModel:
    """``evaluate``'s ridge reconstruction of all markers from ``layout_idx``.

    Parameters
    ----------
    train : (frames, markers, 3) float, mm, NaN gaps
    layout_idx : (L,) int
        Indices of the layout markers (columns of ``train``).
    ridge : float
        Ridge strength relative to the mean input variance (scale-free).
    """
    train = np.asarray(train, dtype=np.float64)
    return ReconstructionModel(train, _layout_indices(layout_idx, train.shape[1]), _ridge(ridge))


def _layout_indices(layout_idx: Sequence[int] | np.ndarray, n_markers: int) -> np.ndarray:
    layout = np.unique(np.asarray(layout_idx, dtype=np.intp))
    if layout.size == 0 or layout[0] < 0 or layout[-1] >= n_markers:
        raise OptionError(f"layout indices must be in 0..{n_markers - 1} and not empty")
    return layout


def _ridge(ridge: float) -> float:
    if ridge < 0:
        raise OptionError(f"ridge must be >= 0, got {ridge}")
    return float(ridge)


def _affine(x: np.ndarray, coef: np.ndarray, intercept: np.ndarray, n_markers: int) -> np.ndarray:
    return (x.reshape(len(x), -1) @ coef + intercept).reshape(len(x), n_markers, 3)


def _by_pattern(layout_positions: np.ndarray, layout: np.ndarray, n_markers: int,
                solve: Callable[[np.ndarray, np.ndarray], np.ndarray], *,
                markers: np.ndarray | None = None) -> np.ndarray:
    """Apply ``solve(pattern (L,) bool, present layout markers (f, K, 3)) -> (f, M, 3)`` per
    presence pattern; frames without any layout marker are NaN; present layout markers copied.
    ``markers`` (N,) intp: ``solve`` gives only these dense markers, (f, N, 3), and so does the result."""
    x = np.asarray(layout_positions, dtype=np.float64)
    out = np.full((x.shape[0], n_markers if markers is None else len(markers), 3), np.nan)
    present = np.isfinite(x).all(axis=2)
    patterns, inverse = row_patterns(present)
    for p, pattern in enumerate(patterns):
        if pattern.any():
            frames = np.flatnonzero(inverse == p)
            out[frames] = solve(pattern, x[frames][:, pattern])
    if markers is None:
        out[:, layout] = np.where(present[..., None], x, out[:, layout])
        return out
    for i, j in zip(*np.nonzero(np.asarray(markers)[:, None] == layout[None])):  # measured ones copied
        out[:, i] = np.where(present[:, j, None], x[:, j], out[:, i])
    return out


class _LRU(OrderedDict):
    """A bounded cache: the least recently used entry goes first."""

    def get_or(self, key: bytes, make: Callable[[], Any]) -> Any:
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = self[key] = make()
        if len(self) > CACHE_PATTERNS:
            self.popitem(last=False)
        return value


@dataclass(frozen=True)
class Prediction:
    """Dense markers solved from layout-marker frames.

    ``positions`` (F, M, 3) mm (NaN in frames without any layout marker); ``expected_error_mm``
    (F,) the model's expected RMS error over the dense markers for that frame's missing pattern
    (NaN without any layout marker); ``missing`` (F, L) bool, the layout markers lost per frame.
    """

    positions: np.ndarray
    expected_error_mm: np.ndarray
    missing: np.ndarray


class FaceModel:
    """Base of the reconstruction models: ``predict`` + the expected error per missing pattern.

    Subclasses set ``kind``, ``layout`` (L,) intp, ``n_markers``, ``neutral`` (M, 3) mm, implement
    ``_solve(pattern, x)`` and ``_arrays()``; ``error_base`` (scalar) and ``error_drop`` (L,)
    hold the expected-error table (see the module docstring).
    """

    kind: str
    layout: np.ndarray
    n_markers: int
    neutral: np.ndarray
    error_base: float = float("nan")
    error_drop: np.ndarray

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def _arrays(self) -> dict[str, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def predict_positions(self, layout_positions: np.ndarray) -> np.ndarray:
        """(F, M, 3) mm from the layout markers (F, L, 3), NaN = lost; present ones copied."""
        return _by_pattern(layout_positions, self.layout, self.n_markers, self._solve)

    def predict_markers(self, layout_positions: np.ndarray, markers: Sequence[int] | np.ndarray) -> np.ndarray:
        """``predict_positions(layout_positions)[:, markers]`` (F, N, 3) mm; models that can
        predict a few dense markers for less than all of them override it (the same numbers)."""
        return self.predict_positions(layout_positions)[:, np.asarray(markers, dtype=np.intp)]

    def predict(self, layout_positions: np.ndarray) -> Prediction:
        """Dense markers, expected error and missing flags from layout markers (F, L, 3) mm."""
        x = np.asarray(layout_positions, dtype=np.float64)
        if x.ndim != 3 or x.shape[1:] != (self.layout.size, 3):
            raise OptionError(f"expected layout frames of shape (F, {self.layout.size}, 3), got {x.shape}")
        missing = ~np.isfinite(x).all(axis=2)
        excess = np.maximum(self.error_drop ** 2 - self.error_base ** 2, 0.0)
        error = np.sqrt(self.error_base ** 2 + missing.astype(float) @ excess)
        error[missing.all(axis=1)] = np.nan
        return Prediction(self.predict_positions(x), error, missing)

    def measure_expected_error(self, check: np.ndarray) -> None:
        """Fill the expected-error table from training frames ``check`` (f, M, 3) mm."""
        complete = np.isfinite(check[:, self.layout]).all(axis=(1, 2))
        check = check[complete]
        if check.shape[0] == 0:
            self.error_base, self.error_drop = float("nan"), np.full(self.layout.size, np.nan)
            return
        x = check[:, self.layout]
        self.error_base = _rms(self.predict_positions(x) - check)
        drops = np.empty(self.layout.size)
        for j in range(self.layout.size):
            lost = x.copy()
            lost[:, j] = np.nan
            drops[j] = _rms(self.predict_positions(lost) - check) if self.layout.size > 1 else np.nan
        self.error_drop = drops

    def check_residuals(self, train: np.ndarray) -> np.ndarray:
        """Distances (f, M) mm between each dense marker and its prediction from every layout
        marker, on the training frames the expected error is measured on (:func:`check_frames`
        of ``train`` (F, M, 3) mm with every layout marker present); their RMS is ``error_base``."""
        check = check_frames(np.asarray(train, dtype=np.float64))
        check = check[np.isfinite(check[:, self.layout]).all(axis=(1, 2))]
        return np.linalg.norm(self.predict_positions(check[:, self.layout]) - check, axis=2)

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything :func:`model_from_arrays` needs (saved in ``model.npz``)."""
        return {"layout": self.layout, "neutral": self.neutral,
                "error_base": np.array(self.error_base), "error_drop": self.error_drop,
                **self._arrays()}


def check_frames(train: np.ndarray) -> np.ndarray:
    """The training frames (f, M, 3) the expected error is measured on: ``train`` (F, M, 3)
    evenly subsampled to at most :data:`CHECK_FRAMES`."""
    return train[::-(-train.shape[0] // CHECK_FRAMES)]


def _rms(diff: np.ndarray) -> float:
    sq = np.sum(diff ** 2, axis=-1)
    sq = sq[np.isfinite(sq)]
    return float(np.sqrt(sq.mean())) if sq.size else float("nan")


class RidgeModel(FaceModel):
    """Ridge per presence pattern from the training covariance of the gap-free frames.

    ``mean`` (3M,), ``cov`` (3M, 3M) centred cross-product sums over the training frames without
    any gap (same solution as :func:`ridge_fit` on those frames), ``frames`` their count.
    """

    kind = "ridge"

    def __init__(self, *, layout: np.ndarray, neutral: np.ndarray, mean: np.ndarray,
                 cov: np.ndarray, frames: int, ridge: float) -> None:
        self.layout, self.neutral = layout, neutral
        self.n_markers = neutral.shape[0]
        self.mean, self.cov, self.frames, self.ridge = mean, cov, int(frames), float(ridge)
        self._cache = _LRU()

    @classmethod
    def fit(cls, train: np.ndarray, layout: np.ndarray, *, ridge: float) -> RidgeModel:
        flat = train.reshape(train.shape[0], -1)
        rows = np.isfinite(flat).all(axis=1)
        if rows.sum() < 2:
            raise OptionError("ridge needs at least 2 training frames without gaps")
        data = flat[rows]
        mean = data.mean(axis=0)
        centred = data - mean
        return cls(layout=layout, neutral=neutral_pose(train), mean=mean, cov=centred.T @ centred,
                   frames=int(rows.sum()), ridge=ridge)

    def submodel(self, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(W (3K, 3M), b (3M,)) from the present layout markers ``pattern`` (L,) bool."""
        return self._cache.get_or(b"global" + pattern.tobytes(), lambda: self._pattern_ridge(self.cov, pattern))

    def _pattern_ridge(self, cov: np.ndarray, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cols = (3 * self.layout[pattern][:, None] + np.arange(3)).ravel()
        gram = cov[np.ix_(cols, cols)].copy()
        lam = self.ridge * max(float(np.trace(gram)) / cols.size, 1e-12)
        gram[np.diag_indices_from(gram)] += lam
        coef = np.linalg.solve(gram, cov[cols])
        return coef, self.mean - self.mean[cols] @ coef

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        return _affine(x, *self.submodel(pattern), self.n_markers)

    def predict_markers(self, layout_positions: np.ndarray, markers: Sequence[int] | np.ndarray) -> np.ndarray:
        """Only the columns of ``markers`` of each pattern's ridge: (F, N, 3) mm."""
        markers = np.asarray(markers, dtype=np.intp)
        cols = (3 * markers[:, None] + np.arange(3)).ravel()

        def solve(pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
            coef, offset = self.submodel(pattern)
            return (x.reshape(len(x), -1) @ coef[:, cols] + offset[cols]).reshape(len(x), markers.size, 3)

        return _by_pattern(layout_positions, self.layout, self.n_markers, solve, markers=markers)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {"mean": self.mean, "cov": self.cov, "frames": np.array(self.frames),
                "ridge": np.array(self.ridge)}


def _beyond_reach(neutral: np.ndarray, layout: np.ndarray, pattern: np.ndarray) -> np.ndarray:
    """(M,) bool: dense markers whose nearest present layout marker (``pattern`` (L,) bool) is
    more than ``LOCAL_REACH`` times farther than their nearest layout marker (neutral (M, 3) mm):
    their neighbourhood is lost, a local model has nothing near to read."""
    points = np.nan_to_num(neutral, nan=np.inf)
    dist = np.linalg.norm(points[:, None] - points[layout][None], axis=2)
    return dist[:, pattern].min(axis=1) > LOCAL_REACH * np.maximum(dist.min(axis=1), 1e-9)


class LocalRidgeModel(RidgeModel):
    """Each dense marker by ridge from its ``neighbours`` nearest present layout markers."""

    kind = "local-ridge"

    def __init__(self, *, neighbours: int, **stats: Any) -> None:
        super().__init__(**stats)
        if neighbours < 1:
            raise OptionError(f"neighbours must be >= 1, got {neighbours}")
        self.neighbours = int(neighbours)

    @classmethod
    def fit(cls, train: np.ndarray, layout: np.ndarray, *, ridge: float,
            neighbours: int = LOCAL_NEIGHBOURS) -> LocalRidgeModel:
        stats = RidgeModel.fit(train, layout, ridge=ridge)
        return cls(layout=layout, neutral=stats.neutral, mean=stats.mean, cov=stats.cov,
                   frames=stats.frames, ridge=ridge, neighbours=neighbours)

    def local_models(self, pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per dense marker: its nearest present layout markers (M, k) (positions among the
        present ones), weights (M, 3k, 3), offsets (M, 3) of ``pattern`` (L,) bool, and (M,) bool
        whether its nearest present marker is more than ``LOCAL_REACH`` times farther than its
        nearest layout marker (then the global ridge solves it)."""
        def make() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            present = self.layout[pattern]
            k = min(self.neighbours, present.size)
            neutral = np.nan_to_num(self.neutral, nan=np.inf)
            dist = np.linalg.norm(neutral[:, None] - neutral[present][None], axis=2)
            near = np.argsort(dist, axis=1, kind="stable")[:, :k]  # (M, k)
            cols = (3 * present[near][..., None] + np.arange(3)).reshape(self.n_markers, 3 * k)
            targets = 3 * np.arange(self.n_markers)[:, None] + np.arange(3)  # (M, 3)
            coef = batched_ridge(self.cov[cols[:, :, None], cols[:, None, :]],
                                 self.cov[cols[:, :, None], targets[:, None, :]], self.ridge)
            offset = self.mean[targets] - np.einsum("mk,mkc->mc", self.mean[cols], coef)
            return near, coef, offset, _beyond_reach(self.neutral, self.layout, pattern)
        return self._cache.get_or(pattern.tobytes(), make)

    predict_markers = FaceModel.predict_markers  # its own solve, not the global ridge's columns

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        near, coef, offset, lost = self.local_models(pattern)
        inputs = x[:, near].reshape(len(x), self.n_markers, -1)  # (f, M, 3k)
        out = np.einsum("fmk,mkc->fmc", inputs, coef) + offset
        if lost.any():  # its neighbourhood is gone: the global model reads the whole face
            out[:, lost] = super()._solve(pattern, x)[:, lost]
        return out

    def _arrays(self) -> dict[str, np.ndarray]:
        return {**super()._arrays(), "neighbours": np.array(self.neighbours)}


def gaspari_cohn(distance: np.ndarray, length: float) -> np.ndarray:
    """Gaspari & Cohn's (1999) compactly supported correlation (5th-order piecewise rational) of
    ``distance`` (any shape, mm): 1 at 0, 0 beyond ``2 * length``; ``length`` inf gives 1."""
    z = np.abs(distance) / length
    out = np.zeros_like(z, dtype=np.float64)
    near, far = z <= 1, (z > 1) & (z < 2)
    a, b = z[near], z[far]
    out[near] = -0.25 * a ** 5 + 0.5 * a ** 4 + 0.625 * a ** 3 - 5 / 3 * a ** 2 + 1
    out[far] = b ** 5 / 12 - 0.5 * b ** 4 + 0.625 * b ** 3 + 5 / 3 * b ** 2 - 5 * b + 4 - 2 / (3 * b)
    return out


class TaperedRidgeModel(RidgeModel):
    """``ridge`` on the training covariance ``cov`` tapered by marker distance (``taper_mm``,
    chosen by cross-validation on the training frames; ``cv_rmse_mm`` per tried length). A dense
    marker whose neighbourhood is lost (as in ``local-ridge``) is solved by the untapered ridge:
    the taper has cut the far markers that still carry it (the jaw when the lower lip is gone)."""

    kind = "tapered-ridge"

    def __init__(self, *, taper_mm: float, cv_lengths_mm: np.ndarray, cv_rmse_mm: np.ndarray,
                 **stats: Any) -> None:
        super().__init__(**stats)
        self.taper_mm = float(taper_mm)
        self.cv_lengths_mm, self.cv_rmse_mm = cv_lengths_mm, cv_rmse_mm
        self.tapered = self.cov * self.taper(self.neutral, self.taper_mm)

    predict_markers = FaceModel.predict_markers  # its own solve, not the global ridge's columns

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        coef, offset = self._cache.get_or(b"tapered" + pattern.tobytes(),
                                          lambda: self._pattern_ridge(self.tapered, pattern))
        out = _affine(x, coef, offset, self.n_markers)
        lost = self._cache.get_or(b"reach" + pattern.tobytes(),
                                  lambda: _beyond_reach(self.neutral, self.layout, pattern))
        if lost.any():  # only the lost markers' columns of the untapered ridge
            coef, offset = self.submodel(pattern)
            cols = (3 * np.flatnonzero(lost)[:, None] + np.arange(3)).ravel()
            out[:, lost] = (x.reshape(len(x), -1) @ coef[:, cols] + offset[cols]).reshape(len(x), -1, 3)
        return out

    @staticmethod
    def taper(neutral: np.ndarray, length: float) -> np.ndarray:
        """(3M, 3M) taper of the neutral markers (M, 3) mm at ``length`` mm (per 3x3 block)."""
        points = np.nan_to_num(neutral, nan=0.0)
        distance = np.linalg.norm(points[:, None] - points[None], axis=2)
        return np.kron(gaspari_cohn(distance, length), np.ones((3, 3)))

    @classmethod
    def fit(cls, train: np.ndarray, layout: np.ndarray, *, ridge: float) -> TaperedRidgeModel:
        stats = RidgeModel.fit(train, layout, ridge=ridge)
        seen = stats.neutral[np.isfinite(stats.neutral).all(axis=1)]
        radius = float(np.sqrt(np.mean(np.sum((seen - seen.mean(axis=0)) ** 2, axis=1))))
        lengths = np.array(TAPER_RADII) * radius
        cols = (3 * layout[:, None] + np.arange(3)).ravel()
        scores = _block_cv(train, layout, stats.n_markers,
                           [(cls.taper(stats.neutral, length)[cols], ridge) for length in lengths])
        best = float(lengths[int(np.argmin(scores))])
        return cls(layout=layout, neutral=stats.neutral, mean=stats.mean, cov=stats.cov,
                   frames=stats.frames, ridge=ridge, taper_mm=best, cv_lengths_mm=lengths,
                   cv_rmse_mm=scores)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {**super()._arrays(), "taper_mm": np.array(self.taper_mm),
                "cv_lengths_mm": self.cv_lengths_mm, "cv_rmse_mm": self.cv_rmse_mm}


class CvRidgeModel(RidgeModel):
    """``ridge`` whose strength is chosen by leave-one-block-out cross-validation on the training
    frames (``CV_RIDGES``, the same blocks as the taper's); ``cv_rmse_mm`` per tried strength."""

    kind = "ridge-cv"

    def __init__(self, *, cv_ridges: np.ndarray, cv_rmse_mm: np.ndarray, **stats: Any) -> None:
        super().__init__(**stats)
        self.cv_ridges, self.cv_rmse_mm = np.asarray(cv_ridges, dtype=np.float64), cv_rmse_mm

    @classmethod
    def fit(cls, train: np.ndarray, layout: np.ndarray) -> CvRidgeModel:
        stats = RidgeModel.fit(train, layout, ridge=DEFAULT_RIDGE)
        scores = _block_cv(train, layout, stats.n_markers, [(None, r) for r in CV_RIDGES])
        return cls(layout=layout, neutral=stats.neutral, mean=stats.mean, cov=stats.cov, frames=stats.frames,
                   ridge=CV_RIDGES[int(np.argmin(scores))], cv_ridges=np.array(CV_RIDGES), cv_rmse_mm=scores)

    def _arrays(self) -> dict[str, np.ndarray]:
        return {**super()._arrays(), "cv_ridges": self.cv_ridges, "cv_rmse_mm": self.cv_rmse_mm}


def _block_cv(train: np.ndarray, layout: np.ndarray, n_markers: int,
              settings: Sequence[tuple[np.ndarray | None, float]]) -> np.ndarray:
    """RMSE (mm, every dense marker) per setting (taper rows (3L, 3M) of the layout coordinates
    or None, relative ridge strength) of leaving each of ``CV_BLOCKS`` contiguous blocks of the
    gap-free training frames out (fitted on the rest, every layout marker present)."""
    flat = train.reshape(train.shape[0], -1)
    data = flat[np.isfinite(flat).all(axis=1)]
    bounds = np.linspace(0, len(data), min(CV_BLOCKS, len(data) // 2) + 1).astype(int)
    cols = (3 * layout[:, None] + np.arange(3)).ravel()
    squared = np.zeros(len(settings))
    for start, stop in zip(bounds[:-1], bounds[1:]):
        kept = np.r_[data[:start], data[stop:]]
        mean = kept.mean(axis=0)
        centred = kept - mean
        cross = centred[:, cols].T @ centred  # (3L, 3M): all the ridge solve needs
        held = data[start:stop]
        for i, (taper, ridge) in enumerate(settings):
            tapered = cross if taper is None else cross * taper
            gram = tapered[:, cols]
            lam = ridge * max(float(np.trace(gram)) / cols.size, 1e-12)
            coef = np.linalg.solve(gram + lam * np.eye(cols.size), tapered)
            squared[i] += np.sum(((held[:, cols] - mean[cols]) @ coef + mean - held) ** 2)
    return np.sqrt(squared / (len(data) * n_markers))


class ThinShellModel(FaceModel):
    """``W = Â⁻¹B̂`` on the marker surface mesh (vertices = the dense markers, ``faces`` (T, 3))."""

    kind = "thin-shell"

    def __init__(self, *, layout: np.ndarray, neutral: np.ndarray, faces: np.ndarray) -> None:
        self.layout, self.neutral, self.faces = layout, neutral, faces
        self.n_markers = neutral.shape[0]
        seen = np.isfinite(neutral).all(axis=1)
        self._seen = np.flatnonzero(seen)
        local = np.full(self.n_markers, -1, dtype=np.intp)
        local[self._seen] = np.arange(self._seen.size)
        self._local_layout = local[layout]
        op = thin_shell_operator(neutral[self._seen], local[faces], ks=KS, kb=KB)
        scale = float(np.abs(op.diagonal()).mean()) or 1.0
        self._operator = op + TIKHONOV * scale * _identity(op.shape[0])
        self._cache = _LRU()

    @classmethod
    def fit(cls, train: np.ndarray, layout: np.ndarray) -> ThinShellModel:
        neutral = neutral_pose(train)
        if not np.isfinite(neutral[layout]).all():
            raise OptionError("a layout marker is never seen in the training frames")
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        _, faces = marker_surface_mesh(neutral[seen])
        return cls(layout=layout, neutral=neutral, faces=seen[np.asarray(faces, dtype=np.intp)])

    def weights(self, pattern: np.ndarray) -> np.ndarray:
        """(M_seen, K) thin-shell weights of the present layout markers ``pattern`` (L,) bool."""
        return self._cache.get_or(pattern.tobytes(), lambda: interpolation_weights(
            self._operator, self._local_layout[pattern]))

    def interpolate(self, pattern: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Values (f, K, C) at the present layout markers -> (f, M, C) over the surface (NaN unseen)."""
        out = np.full((values.shape[0], self.n_markers, values.shape[2]), np.nan)
        out[:, self._seen] = np.einsum("mk,fkc->fmc", self.weights(pattern), values)
        return out

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        return self.neutral + self.interpolate(pattern, x - self.neutral[self.layout[pattern]])

    def _arrays(self) -> dict[str, np.ndarray]:
        return {"faces": self.faces}


def _identity(n: int):
    import scipy.sparse as sp

    return sp.identity(n, format="csr")


class LocalDeformation:
    """Ma et al.'s per-marker 5-D local deformation and its PCA to (d1, d2).

    For layout marker j: its offset from neutral (3) and 2 in-plane strains: the 2x2 linear map
    taking its 2-ring neighbours' neutral offsets to their current offsets, both in the marker's
    tangent basis (the 2 main directions of its neutral neighbourhood), minus identity, diagonal.
    ``neighbours[j]`` (layout positions), ``tangents`` (L, 3, 2), ``pca_mean`` (L, 5),
    ``pca_axes`` (L, 5, 2) with the standardisation folded in (d = (f − mean) @ axes); (d1, d2)
    are clipped to their training range (a polynomial must not extrapolate: a marker with lost
    neighbours can get an unusual strain). A strain needs >= 3 present neighbours, else it is 0.
    """

    def __init__(self, *, neutral: np.ndarray, neighbours: list[np.ndarray], tangents: np.ndarray,
                 pca_mean: np.ndarray, pca_axes: np.ndarray, bounds: np.ndarray | None = None) -> None:
        self.neutral, self.neighbours, self.tangents = neutral, neighbours, tangents
        self.pca_mean, self.pca_axes = pca_mean, pca_axes
        self.bounds = bounds  # (2, L, 2) training range of (d1, d2): no polynomial extrapolation

    @classmethod
    def fit(cls, layout_neutral: np.ndarray, train_layout: np.ndarray) -> LocalDeformation:
        neighbours = _two_rings(layout_neutral)
        tangents = np.zeros((len(layout_neutral), 3, 2))
        for j, nb in enumerate(neighbours):
            offsets = layout_neutral[nb] - layout_neutral[j]
            tangents[j] = np.linalg.svd(offsets, full_matrices=False)[2][:2].T
        model = cls(neutral=layout_neutral, neighbours=neighbours, tangents=tangents,
                    pca_mean=np.zeros((len(layout_neutral), 5)),
                    pca_axes=np.tile(np.eye(5)[:, :2], (len(layout_neutral), 1, 1)))
        feats = model.features(train_layout)
        mean = feats.mean(axis=0)
        axes = np.zeros((len(layout_neutral), 5, 2))
        for j in range(len(layout_neutral)):
            scale = np.maximum(feats[:, j].std(axis=0), 1e-9)
            z = (feats[:, j] - mean[j]) / scale
            _, sing, vt = np.linalg.svd(z, full_matrices=False)
            spread = np.maximum(sing[:2] / np.sqrt(max(len(z), 1)), 1e-9)
            axes[j] = (vt[:2] / spread[:, None]).T / scale[:, None]  # unit variance d1, d2
        model.pca_mean, model.pca_axes = mean, axes
        d = model.parameters(train_layout)
        model.bounds = np.stack([d.min(axis=0), d.max(axis=0)])
        return model

    def features(self, x: np.ndarray) -> np.ndarray:
        """(F, L, 5) offsets + strains of layout frames ``x`` (F, L, 3), NaN = lost (a lost
        marker's features are NaN; a marker with < 3 present neighbours gets zero strain)."""
        offsets = x - self.neutral
        strains = np.zeros(x.shape[:2] + (2,))
        present = np.isfinite(x).all(axis=2)
        for j, nb in enumerate(self.neighbours):
            p = (self.neutral[nb] - self.neutral[j]) @ self.tangents[j]  # (K, 2)
            q = np.nan_to_num((x[:, nb] - x[:, j:j + 1]) @ self.tangents[j])  # (F, K, 2)
            w = (present[:, nb] & present[:, j:j + 1]).astype(float)
            gram = np.einsum("fk,ka,kb->fab", w, p, p)
            cross = np.einsum("fk,ka,fkb->fab", w, p, q)
            ok = (w.sum(axis=1) >= 3) & (np.linalg.det(gram) > 1e-9 * np.einsum("faa->f", gram) ** 2)
            if ok.any():
                mapping = np.linalg.solve(gram[ok], cross[ok])  # (f, 2, 2): q ≈ p @ mapping
                strains[ok, j] = np.stack([mapping[:, 0, 0], mapping[:, 1, 1]], axis=1) - 1.0
        return np.concatenate([offsets, strains], axis=2)

    def parameters(self, x: np.ndarray) -> np.ndarray:
        """(F, L, 2) PCA parameters (d1, d2) of layout frames ``x`` (F, L, 3), clipped to the
        training range."""
        d = np.einsum("flc,lcd->fld", self.features(x) - self.pca_mean, self.pca_axes)
        return d if self.bounds is None else np.clip(d, self.bounds[0], self.bounds[1])

    def arrays(self) -> dict[str, np.ndarray]:
        sizes = np.array([len(nb) for nb in self.neighbours])
        return {"pdm_neighbours": np.concatenate(self.neighbours), "pdm_neighbour_counts": sizes,
                "pdm_tangents": self.tangents, "pdm_mean": self.pca_mean, "pdm_axes": self.pca_axes,
                "pdm_bounds": self.bounds}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], layout_neutral: np.ndarray) -> LocalDeformation:
        ends = np.cumsum(arrays["pdm_neighbour_counts"])
        neighbours = np.split(np.asarray(arrays["pdm_neighbours"], dtype=np.intp), ends[:-1])
        return cls(neutral=layout_neutral, neighbours=neighbours, tangents=arrays["pdm_tangents"],
                   pca_mean=arrays["pdm_mean"], pca_axes=arrays["pdm_axes"],
                   bounds=arrays["pdm_bounds"])


def _two_rings(points: np.ndarray) -> list[np.ndarray]:
    """Per point, its neighbours up to 2 edges away on the surface mesh of ``points`` (L, 3)
    (all other points when there are too few for a mesh or a ring has < 2 points)."""
    n = len(points)
    everyone = [np.delete(np.arange(n), j) for j in range(n)]
    if n < 4:
        return everyone
    _, faces = marker_surface_mesh(points)
    edges, _ = mesh_edges(faces)
    adjacency = np.zeros((n, n), bool)
    adjacency[edges[:, 0], edges[:, 1]] = adjacency[edges[:, 1], edges[:, 0]] = True
    two = adjacency | ((adjacency.astype(int) @ adjacency.astype(int)) > 0)
    np.fill_diagonal(two, False)
    return [np.flatnonzero(two[j]) if two[j].sum() >= 2 else everyone[j] for j in range(n)]


def _basis(d: np.ndarray, degree: str) -> np.ndarray:
    """Polynomial terms (..., B) of (d1, d2) (..., 2): Ma et al.'s biquadratic or the linear one."""
    d1, d2 = d[..., 0], d[..., 1]
    one = np.ones_like(d1)
    if degree == "linear":
        return np.stack([d1, d2, one], axis=-1)
    return np.stack([d1 * d1, d2 * d2, d1 * d2, d1, d2, one], axis=-1)


class DetailModel(FaceModel):
    """Thin-shell + per-marker polynomial displacement detail (Ma et al. 2008).

    ``coef`` (M, B, 3) the polynomials; ``bounds`` (2, M, 2) the training range of each dense
    marker's interpolated (d1, d2). A lost layout marker's neighbours interpolate their own PCA
    parameters (other axes) into its area: unclamped, a quadratic took such values to ~50 mm.
    """

    def __init__(self, *, kind: str, surface: ThinShellModel, local: LocalDeformation,
                 coef: np.ndarray, degree: str, bounds: np.ndarray | None = None) -> None:
        self.kind, self.surface, self.local = kind, surface, local
        self.coef, self.degree, self.bounds = coef, degree, bounds
        self.layout, self.neutral, self.n_markers = surface.layout, surface.neutral, surface.n_markers

    @classmethod
    def fit(cls, kind: str, train: np.ndarray, layout: np.ndarray) -> DetailModel:
        surface = ThinShellModel.fit(train, layout)
        residual = train - surface.predict_positions(train[:, layout])
        degree = "linear" if kind == "pdm-linear" else "biquadratic"
        x = train[:, layout]
        rows = np.isfinite(x).all(axis=(1, 2))
        local = LocalDeformation.fit(surface.neutral[layout], x[rows])
        model = cls(kind=kind, surface=surface, local=local,
                    coef=np.zeros((train.shape[1], 6 if degree == "biquadratic" else 3, 3)),
                    degree=degree)
        d = model._vertex_parameters(np.ones(layout.size, bool), x[rows])
        model.bounds = np.stack([np.fmin.reduce(d, axis=0), np.fmax.reduce(d, axis=0)])  # NaN: unseen
        model.coef = _fit_polynomials(_basis(d, degree), residual[rows])
        return model

    def _vertex_parameters(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(f, M, 2) (d1, d2) interpolated over the surface from the present layout markers,
        clipped to each dense marker's training range (no polynomial extrapolation)."""
        full = np.full((x.shape[0], self.layout.size, 3), np.nan)
        full[:, pattern] = x
        d = self.surface.interpolate(pattern, self.local.parameters(full)[:, pattern])
        return d if self.bounds is None else np.clip(d, self.bounds[0], self.bounds[1])

    def _solve(self, pattern: np.ndarray, x: np.ndarray) -> np.ndarray:
        terms = _basis(self._vertex_parameters(pattern, x), self.degree)
        detail = np.nan_to_num(np.einsum("fmb,mbc->fmc", terms, self.coef))
        return self.surface._solve(pattern, x) + detail

    def _arrays(self) -> dict[str, np.ndarray]:
        return {**self.surface._arrays(), **self.local.arrays(), "pdm_coef": self.coef,
                "pdm_vertex_bounds": self.bounds}


def _fit_polynomials(terms: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Per marker ridge least squares ``residual[:, m] ≈ terms[:, m] @ coef[m]``: coef (M, B, 3).

    ``terms`` (F, M, B), ``residual`` (F, M, 3) (NaN rows of a marker left out)."""
    ok = np.isfinite(residual).all(axis=2) & np.isfinite(terms).all(axis=2)  # (F, M)
    t = np.where(ok[..., None], terms, 0.0)
    r = np.where(ok[..., None], residual, 0.0)
    gram = np.einsum("fmb,fmc->mbc", t, t)
    rhs = np.einsum("fmb,fmc->mbc", t, r)
    n_terms = terms.shape[2]
    lam = DETAIL_RIDGE * np.maximum(np.einsum("mbb->m", gram) / n_terms, 1e-12)
    gram[:, np.arange(n_terms), np.arange(n_terms)] += lam[:, None]
    return np.linalg.solve(gram, rhs)


def fit_model(train: np.ndarray, layout_idx: Sequence[int] | np.ndarray, *, kind: str = DEFAULT_KIND,
              ridge: float = DEFAULT_RIDGE, neighbours: int = LOCAL_NEIGHBOURS,
              expected_error: bool = True) -> FaceModel:
    """Fit a reconstruction model of ``kind`` (see ``MODEL_KINDS``) on head-relative training frames.

    Parameters
    ----------
    train : (frames, markers, 3) float, mm, NaN gaps
    layout_idx : (L,) int, the layout markers (columns of ``train``)
    kind : one of ``MODEL_KINDS``
    ridge : ridge strength of the ridge kinds, relative to the mean input variance (``ridge-cv``
        chooses its own)
    neighbours : layout markers each dense marker is solved from (``local-ridge``)
    expected_error : measure the expected-error table (L + 1 extra predictions on training
        frames; held-out scoring does not need it: then the expected error is NaN)
    """
    train = np.asarray(train, dtype=np.float64)
    layout = _layout_indices(layout_idx, train.shape[1])
    ridge = _ridge(ridge)
    if kind == "ridge":
        model: FaceModel = RidgeModel.fit(train, layout, ridge=ridge)
    elif kind == "thin-shell":
        model = ThinShellModel.fit(train, layout)
    elif kind == "local-ridge":
        model = LocalRidgeModel.fit(train, layout, ridge=ridge, neighbours=neighbours)
    elif kind == "tapered-ridge":
        model = TaperedRidgeModel.fit(train, layout, ridge=ridge)
    elif kind == "ridge-cv":
        model = CvRidgeModel.fit(train, layout)
    elif kind in ("pdm-linear", "pdm-biquadratic"):
        model = DetailModel.fit(kind, train, layout)
    else:
        raise OptionError(f"unknown model kind {kind!r} (choose from {', '.join(MODEL_KINDS)})")
    if expected_error:
        model.measure_expected_error(check_frames(train))
    else:
        model.error_base, model.error_drop = float("nan"), np.full(layout.size, np.nan)
    return model


def model_from_arrays(kind: str, arrays: Mapping[str, np.ndarray]) -> FaceModel:
    """Rebuild a model saved by :meth:`FaceModel.arrays` (the inverse of it)."""
    a = {k: np.asarray(v) for k, v in arrays.items()}
    layout, neutral = a["layout"].astype(np.intp), a["neutral"].astype(np.float64)

    stats = {"layout": layout, "neutral": neutral, "mean": a.get("mean"), "cov": a.get("cov"),
             "frames": int(a.get("frames", 0)), "ridge": float(a.get("ridge", 0.0))}
    if kind == "ridge":
        model: FaceModel = RidgeModel(**stats)
    elif kind == "local-ridge":
        model = LocalRidgeModel(**stats, neighbours=int(a["neighbours"]))
    elif kind == "tapered-ridge":
        model = TaperedRidgeModel(**stats, taper_mm=float(a["taper_mm"]),
                                  cv_lengths_mm=a["cv_lengths_mm"], cv_rmse_mm=a["cv_rmse_mm"])
    elif kind == "ridge-cv":
        model = CvRidgeModel(**stats, cv_ridges=a["cv_ridges"], cv_rmse_mm=a["cv_rmse_mm"])
    elif kind in ("thin-shell", "pdm-linear", "pdm-biquadratic"):
        surface = ThinShellModel(layout=layout, neutral=neutral, faces=a["faces"].astype(np.intp))
        if kind == "thin-shell":
            model = surface
        else:
            local = LocalDeformation.from_arrays(a, neutral[layout])
            model = DetailModel(kind=kind, surface=surface, local=local, coef=a["pdm_coef"],
                                degree="linear" if kind == "pdm-linear" else "biquadratic",
                                bounds=a["pdm_vertex_bounds"])
    else:
        raise OptionError(f"unknown model kind {kind!r}")
    model.error_base, model.error_drop = float(a["error_base"]), a["error_drop"]
    return model


def save_model(model: FaceModel, path: str | os.PathLike[str], *, header: Mapping[str, Any],
               extra: Mapping[str, np.ndarray] | None = None, force: bool = True) -> Path:
    """Write ``model`` as ``model.npz`` (deterministic bytes) with a JSON ``header`` entry.

    ``header`` describes the session and layout (labels, session identity); ``format``,
    ``version`` and ``kind`` are added. ``extra``: arrays of the caller's saved beside the
    model's (names must not clash with them; :func:`load_model` returns them apart).
    """
    head = {**header, "format": MODEL_FORMAT, "version": MODEL_VERSION, "kind": model.kind}
    entries = {"header": np.frombuffer(dumps(head).encode(), dtype=np.uint8), **model.arrays(),
               **(extra or {})}
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name in sorted(entries):
            item = io.BytesIO()
            np.lib.format.write_array(item, np.asarray(entries[name], order="C"), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            archive.writestr(info, item.getvalue())
    return write_bytes(path, buffer.getvalue(), force=force)


def load_model(path: str | os.PathLike[str], *, session: Mapping[str, Any] | None = None,
               labelled: bool = False) -> tuple[FaceModel, dict]:
    """Read a model written by :func:`save_model`; returns ``(model, header)``.

    ``session``: the identity the model must have been trained on (``header["session"]`` must
    match it on every key given); raises :class:`InputFileError` otherwise. Every array's shape and
    every header field is checked first: a damaged or hand-made file is an error naming it.
    ``labelled``: the header must name the markers (``labels``, ``layout_labels``, a ``session``),
    as solve's model files do.
    """
    try:  # our own handle: np.load leaves its own open when the archive is damaged
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except OSError as exc:
        raise unreadable(path, exc) from None
    except (ValueError, zipfile.BadZipFile, EOFError, NotImplementedError, RuntimeError):
        raise InputFileError(path, "not a mocaptk model file (.npz)") from None
    if not isinstance(arrays.get("header"), np.ndarray) or arrays["header"].dtype != np.uint8:
        raise InputFileError(path, "not a mocaptk model file (no header)")
    try:
        header = parse_json(bytes(arrays.pop("header")).decode(), path)
    except UnicodeDecodeError:
        raise InputFileError(path, "not a mocaptk model file (no header)") from None
    if not isinstance(header, dict) or header.get("format") != MODEL_FORMAT:
        found = header.get("format") if isinstance(header, dict) else None
        raise InputFileError(path, f"not a mocaptk model file (format {quoted(found)})")
    if header.get("version") != MODEL_VERSION:
        raise InputFileError(path, f"model version {quoted(header.get('version'))} is not supported "
                             f"(this mocaptk reads version {MODEL_VERSION})")
    trained = header.get("session") if isinstance(header.get("session"), dict) else {}
    for key, value in (session or {}).items():
        if trained.get(key) != value:
            raise InputFileError(path, f"the model was trained on another session ({key} "
                                 f"{quoted(trained.get(key))}, expected {quoted(value)})")
    # numbers as float64 (index arrays stay integers): linalg refuses float16, and an int8 cov
    # cannot take the ridge added in place
    arrays = {k: v.astype(np.float64) if v.dtype.kind == "f" or (v.dtype.kind in "iu" and k not in _INDEX_ARRAYS)
              else v for k, v in arrays.items()}
    try:
        _check_model(header, arrays, labelled=labelled)
    except _BadModel as exc:
        raise InputFileError(path, f"malformed model file: {exc}") from None
    try:
        return model_from_arrays(header["kind"], arrays), header
    except (ValueError, IndexError, np.linalg.LinAlgError) as exc:  # e.g. a singular thin-shell
        raise InputFileError(path, f"malformed model file ({type(exc).__name__}: {exc})") from None


class _BadModel(ValueError):
    """A model file's array or header field is not what :func:`save_model` writes."""


#: Arrays every kind of model file holds, and those of each kind (beside layout, neutral, errors).
_KIND_ARRAYS = {"ridge": ("mean", "cov", "frames", "ridge"),
                "local-ridge": ("mean", "cov", "frames", "ridge", "neighbours"),
                "tapered-ridge": ("mean", "cov", "frames", "ridge", "taper_mm", "cv_lengths_mm", "cv_rmse_mm"),
                "ridge-cv": ("mean", "cov", "frames", "ridge", "cv_ridges", "cv_rmse_mm"),
                "thin-shell": ("faces",)}
_PDM_ARRAYS = ("faces", "pdm_neighbours", "pdm_neighbour_counts", "pdm_tangents", "pdm_mean", "pdm_axes",
               "pdm_bounds", "pdm_coef", "pdm_vertex_bounds")
#: Arrays of marker / triangle indices (kept integer when a model file is read).
_INDEX_ARRAYS = ("layout", "faces", "pdm_neighbours", "pdm_neighbour_counts")
#: Largest coordinate (mm) of a stored position: beyond it, squares overflow.
_REACH_MM = 1e6


def _check_model(header: dict, a: Mapping[str, np.ndarray], *, labelled: bool) -> None:
    """Raise :class:`_BadModel` unless ``header`` and arrays ``a`` are a model's, shapes matching."""
    kind = header.get("kind")
    if kind not in MODEL_KINDS:
        raise _BadModel(f"unknown model kind {quoted(kind)} (known: {', '.join(MODEL_KINDS)})")
    names = ("layout", "neutral", "error_base", "error_drop",
             *_KIND_ARRAYS.get(kind, _PDM_ARRAYS))
    missing = [n for n in names if n not in a]
    if missing:
        raise _BadModel(f"no {missing[0]} array")
    for name in names:
        if a[name].dtype.kind not in "iuf":
            raise _BadModel(f"{name} must hold numbers")

    def shape(name: str, *dims: int) -> np.ndarray:
        if a[name].shape != dims:
            raise _BadModel(f"{name} has shape {a[name].shape}, expected {dims}")
        return a[name]

    def finite(name: str, *, low: float = -np.inf, high: float = np.inf, nan: bool = False) -> None:
        v = a[name].astype(np.float64)  # float16 / int8 compared with 1e12 warned of an overflow
        v = v[~np.isnan(v)] if nan else v
        if not (np.isfinite(v).all() and (v >= low).all() and (v <= high).all()):
            raise _BadModel(f"{name} has values out of range")

    def indices(name: str, n: int) -> None:
        if a[name].dtype.kind not in "iu" or a[name].size and (a[name].min() < 0 or a[name].max() >= n):
            raise _BadModel(f"{name} must hold indices 0..{n - 1}")

    neutral = a["neutral"]
    if neutral.ndim != 2 or neutral.shape[1:] != (3,) or not neutral.shape[0]:
        raise _BadModel(f"neutral has shape {neutral.shape}, expected (markers, 3)")
    m = neutral.shape[0]
    finite("neutral", low=-_REACH_MM, high=_REACH_MM, nan=True)
    if a["layout"].ndim != 1 or not a["layout"].size:
        raise _BadModel(f"layout has shape {a['layout'].shape}, expected (layout markers,)")
    n_layout = a["layout"].size
    indices("layout", m)
    if np.unique(a["layout"]).size != n_layout or not np.isfinite(neutral[a["layout"]]).all():
        raise _BadModel("layout must name distinct markers with a neutral position")
    seen = neutral[np.isfinite(neutral).all(axis=1)]
    try:  # every model's mesh (solve's surface, thin-shell) is laid over the neutral markers
        marker_surface_mesh(seen)
    except ValueError as exc:
        raise _BadModel(f"neutral positions give no marker surface ({exc})") from None
    shape("error_base")
    shape("error_drop", n_layout)
    finite("error_base", low=0, high=_REACH_MM, nan=True)
    finite("error_drop", low=0, high=_REACH_MM, nan=True)
    if kind in ("ridge", "local-ridge", "tapered-ridge", "ridge-cv"):
        shape("mean", 3 * m)
        shape("cov", 3 * m, 3 * m)
        for name in ("frames", "ridge"):
            shape(name)
        for name in ("mean", "cov"):
            finite(name, low=-_REACH_MM ** 2, high=_REACH_MM ** 2)
        finite("ridge", low=0, high=1e6)
        finite("frames", low=0)
    if kind == "local-ridge":
        shape("neighbours")
        finite("neighbours", low=1, high=n_layout)
    if kind == "tapered-ridge":
        shape("taper_mm")
        if not a["taper_mm"] > 1e-6:  # inf: no taper (a length the CV may choose)
            raise _BadModel("taper_mm has values out of range")
        for name in ("cv_lengths_mm", "cv_rmse_mm"):
            if a[name].ndim != 1:
                raise _BadModel(f"{name} must be a list of numbers")
    if kind == "ridge-cv":
        for name in ("cv_ridges", "cv_rmse_mm"):
            if a[name].ndim != 1:
                raise _BadModel(f"{name} must be a list of numbers")
    if "faces" in names:
        if a["faces"].ndim != 2 or a["faces"].shape[1:] != (3,) or not a["faces"].size:
            raise _BadModel(f"faces has shape {a['faces'].shape}, expected (triangles, 3)")
        indices("faces", m)
        if not np.isfinite(neutral[a["faces"]]).all():
            raise _BadModel("faces must join markers with a neutral position")
    if kind in ("pdm-linear", "pdm-biquadratic"):
        counts = a["pdm_neighbour_counts"]
        shape("pdm_neighbour_counts", n_layout)
        indices("pdm_neighbour_counts", n_layout)
        if a["pdm_neighbours"].ndim != 1 or a["pdm_neighbours"].size != counts.sum():
            raise _BadModel("pdm_neighbours must list pdm_neighbour_counts neighbours per layout marker")
        indices("pdm_neighbours", n_layout)
        shape("pdm_tangents", n_layout, 3, 2)
        shape("pdm_mean", n_layout, 5)
        shape("pdm_axes", n_layout, 5, 2)
        shape("pdm_bounds", 2, n_layout, 2)
        shape("pdm_coef", m, 3 if kind == "pdm-linear" else 6, 3)
        shape("pdm_vertex_bounds", 2, m, 2)
        for name in ("pdm_tangents", "pdm_mean", "pdm_axes", "pdm_coef"):
            finite(name, low=-_REACH_MM, high=_REACH_MM)
    _check_header(header, m, n_layout, labelled=labelled)


def _check_header(header: dict, m: int, n_layout: int, *, labelled: bool) -> None:
    """The header's labels (dense ``m``, layout ``n_layout``; required if ``labelled``), rigid set
    and session identity."""
    if not labelled and not any(k in header for k in ("labels", "layout_labels", "rigid_labels")):
        return
    def labels(key: str, n: int | None) -> list[str]:
        value = header.get(key)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise _BadModel(f"header {key} must be a list of marker labels")
        if n is not None and len(value) != n:
            raise _BadModel(f"header {key} lists {len(value)} markers, the arrays {n}")
        if len(set(value)) != len(value):
            raise _BadModel(f"header {key} names a marker twice")
        return value

    dense = set(labels("labels", m))
    if not set(labels("layout_labels", n_layout)) <= dense:
        raise _BadModel("header layout_labels must be among its labels")
    if labelled and not isinstance(header.get("session"), dict):
        raise _BadModel("header session must be an object")
    rigid = labels("rigid_labels", None) if header.get("rigid_labels") is not None else []
    if not set(rigid) <= dense:
        raise _BadModel("header rigid_labels must be among its labels")
    reference = header.get("rigid_reference")
    if reference is not None:
        try:
            ref = np.asarray(reference, dtype=np.float64)
        except (TypeError, ValueError):
            raise _BadModel("header rigid_reference must be rows of 3 numbers") from None
        if ref.shape != (len(rigid), 3) or not (np.abs(ref) <= _REACH_MM).all():
            raise _BadModel("header rigid_reference must be one row of 3 finite numbers per rigid label")
