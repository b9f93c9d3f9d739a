"""How well a capture's layout markers agree with each other: ghosts found, consistency measured.

A Gaussian model of the layout markers in the head frame (mean ``μ`` (3L,), covariance ``Σ``
(3L, 3L) from the training session, regularised) predicts each marker from the others. For a
frame whose present markers are ``P``, with ``Λ = Σ_PP⁻¹``, the leave-one-out residual of marker
``j`` (its position minus the conditional mean given the other present markers) is
``r_j = Λ_jj⁻¹ (Λ (x_P − μ_P))_j``: one inverse per presence pattern gives every marker's
leave-one-out residual at once.

- **Ghosts** (a wrong 2-D match triangulated, a spike, a swap) contradict the others: a marker
  whose residual departs from its own median over the capture by more than
  ``max(floor_mm, k × its robust spread)`` is dropped (worst first, its frame re-tested without
  it) and treated as lost. Measuring the departure from the capture's own median and spread
  makes the test indifferent to what is steady in a capture: another actor's face shape, or
  expressions the range of motion did not cover, raise every frame alike.
- **Consistency** (mm, per frame): the RMS leave-one-out residual of the markers kept. On the
  training session it is ``Screen.training_mm``; a capture far above it is not explained by the
  model (another face, another scale, markers placed elsewhere), whatever its expected error says.
- **The solve's error, measured** (:func:`stabilization_residuals`): the layout's stabilization
  markers outside its face markers are in the capture but not solved from; where the head pose was
  not fitted to them frame by frame, the distance between where the solve puts them and where the
  capture has them is its error on markers it did not see (the ghost test above drops a capture's
  stray points first).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mocaptk.clustering.reconstruction_models import DEFAULT_RIDGE, check_frames
from mocaptk.errors import OptionError

__all__ = ["LayoutGaussian", "Screen", "outlier_threshold", "screen_frames", "stabilization_residuals"]

#: Measurement noise added to the covariance's diagonal (mm, per coordinate): a capture is noisier
#: than the session's mean shape, and the floor keeps ``Σ`` invertible for rigid-moving pairs.
NOISE_MM = 0.2
#: A layout marker is an outlier when its leave-one-out residual departs from its median over the
#: capture by more than ``max(OUTLIER_FLOOR_MM, OUTLIER_SPREADS × its median departure)`` (a
#: 3-D Gaussian's departure passes 3.2 × its median once in 10,000 frames; real residuals have
#: heavier tails).
OUTLIER_FLOOR_MM = 5.0
OUTLIER_SPREADS = 5.0
#: At most this share of a frame's layout markers is dropped as outliers (the rest must carry it).
MAX_DROPPED_SHARE = 0.34
#: Frames the per-marker median and spread are measured on (evenly spaced over the capture).
STATS_FRAMES = 8192


@dataclass(frozen=True)
class LayoutGaussian:
    """Mean ``mean`` (3L,) mm and regularised covariance ``cov`` (3L, 3L) mm² of the layout markers
    (x, y, z per marker) in the head frame."""

    mean: np.ndarray
    cov: np.ndarray

    @classmethod
    def fit(cls, layout_frames: np.ndarray, *, ridge: float = DEFAULT_RIDGE,
            noise_mm: float = NOISE_MM) -> LayoutGaussian:
        """From training frames ``layout_frames`` (F, L, 3) mm (frames with a gap are skipped)."""
        flat = np.asarray(layout_frames, dtype=np.float64).reshape(len(layout_frames), -1)
        data = flat[np.isfinite(flat).all(axis=1)]
        if len(data) < 2:
            raise OptionError("the session needs at least 2 frames with every layout marker seen "
                              "(the layout markers' consistency is learnt from them)")
        mean = data.mean(axis=0)
        cov = np.cov(data, rowvar=False, bias=True)
        cov[np.diag_indices_from(cov)] += ridge * float(np.trace(cov)) / cov.shape[0] + noise_mm ** 2
        return cls(mean, cov)

    @property
    def n_markers(self) -> int:
        return self.mean.size // 3

    def arrays(self) -> dict[str, np.ndarray]:
        return {"mean": self.mean, "cov": self.cov}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> LayoutGaussian:
        return cls(np.asarray(arrays["mean"], dtype=np.float64), np.asarray(arrays["cov"], dtype=np.float64))

    def loo_residuals(self, x: np.ndarray) -> np.ndarray:
        """Leave-one-out residuals (F, L, 3) mm of layout frames ``x`` (F, L, 3) (NaN = lost: its
        residual is NaN, and it takes no part in the others' predictions)."""
        x = np.asarray(x, dtype=np.float64)
        n_frames, n_layout = x.shape[:2]
        out = np.full(x.shape, np.nan)
        present = np.isfinite(x).all(axis=2)
        y = np.where(present[..., None], x - self.mean.reshape(-1, 3), 0.0).reshape(n_frames, -1, 1)
        for rows, z, diag in self._conditioned(present, y, blocks=True):
            diag = np.where(present[rows][..., None, None], diag, np.eye(3))  # lost: 0 after the Schur step
            r = np.linalg.solve(diag, z.reshape(rows.size, n_layout, 3, 1))[..., 0]
            out[rows] = np.where(present[rows][..., None], r, np.nan)
        return out

    def solve_present(self, present: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``Σ_PP⁻¹ v_P`` per frame: ``present`` (F, L) bool, ``v`` (F, 3L, c) (rows of lost
        markers ignored); rows of lost markers in the result are 0 where at least 2 are present."""
        out = np.zeros(v.shape)
        v = np.where(np.repeat(present, 3, axis=1)[..., None], v, 0.0)
        for rows, z, _ in self._conditioned(present, v, blocks=False):
            out[rows] = np.where(np.repeat(present[rows], 3, axis=1)[..., None], z, 0.0)
        return out

    def _conditioned(self, present: np.ndarray, v: np.ndarray, *, blocks: bool):
        """Per group of frames with as many lost markers: ``(rows, Σ_PP⁻¹ v_P, diagonal 3x3 blocks
        of Σ_PP⁻¹ or None)``, frames with fewer than 2 present markers skipped.

        One precision matrix ``Λ = Σ⁻¹`` serves every frame: the lost markers ``M`` are
        conditioned out by a Schur complement, ``Σ_PP⁻¹ = Λ_PP − Λ_PM Λ_MM⁻¹ Λ_MP``, a system
        of the lost markers' size per frame (batched over frames with as many lost markers)."""
        n_layout = present.shape[1]
        lam = self._precision()
        g = np.einsum("ab,fbc->fac", lam, v)  # Λ v; its rows at lost markers are Λ_MP v_P
        lost_count = n_layout - present.sum(axis=1)
        for k in np.unique(lost_count):
            rows = np.flatnonzero((lost_count == k) & (present.sum(axis=1) >= 2))
            if not rows.size:
                continue
            diag = np.broadcast_to(lam.reshape(n_layout, 3, n_layout, 3)[np.arange(n_layout), :,
                                                                           np.arange(n_layout), :],
                                   (rows.size, n_layout, 3, 3)) if blocks else None
            z = g[rows]
            if k:
                lost = np.argsort(present[rows], axis=1, kind="stable")[:, :k]  # lost markers first
                cols = (3 * lost[..., None] + np.arange(3)).reshape(rows.size, 3 * k)
                lam_am = lam[:, cols].transpose(1, 0, 2)  # (n, 3L, 3k) Λ_·M
                lam_mm = np.take_along_axis(lam_am, cols[:, :, None], axis=1)  # (n, 3k, 3k)
                rhs = [np.take_along_axis(z, cols[..., None], axis=1)]
                if blocks:
                    rhs.append(lam_am.transpose(0, 2, 1))
                solved = np.linalg.solve(lam_mm, np.concatenate(rhs, axis=2))
                c = z.shape[2]
                z = z - np.einsum("nak,nkc->nac", lam_am, solved[..., :c])
                if blocks:
                    s = solved[..., c:].reshape(rows.size, 3 * k, n_layout, 3)  # Λ_MM⁻¹ Λ_M·
                    diag = diag - np.einsum("nlak,nklb->nlab",
                                            lam_am.reshape(rows.size, n_layout, 3, 3 * k), s)
            yield rows, z, diag

    def _precision(self) -> np.ndarray:
        cached = self.__dict__.get("_lam")
        if cached is None:
            cached = np.linalg.inv(self.cov)
            cached = (cached + cached.T) / 2
            object.__setattr__(self, "_lam", cached)
        return cached


@dataclass(frozen=True)
class Screen:
    """The outlier test of one capture: per layout marker its median leave-one-out residual
    ``median`` (L, 3) mm and the departure ``threshold_mm`` (L,) beyond which it is an outlier;
    ``training_mm`` the consistency (RMS leave-one-out residual) on the training session."""

    median: np.ndarray
    threshold_mm: np.ndarray
    training_mm: float


def training_consistency(gauss: LayoutGaussian, layout_frames: np.ndarray) -> float:
    """The RMS leave-one-out residual (mm) on training frames ``layout_frames`` (F, L, 3)."""
    return _rms(gauss.loo_residuals(check_frames(np.asarray(layout_frames, dtype=np.float64))))


def capture_screen(gauss: LayoutGaussian, x: np.ndarray, *, training_mm: float,
                   floor_mm: float = OUTLIER_FLOOR_MM, spreads: float = OUTLIER_SPREADS) -> Screen:
    """The outlier test for capture frames ``x`` (F, L, 3) mm in the head frame, measured on at most
    :data:`STATS_FRAMES` of them: a marker's median residual and its median departure from it
    (ghosts are too rare to move either)."""
    step = max(1, -(-len(x) // STATS_FRAMES))
    median, threshold = outlier_threshold(gauss.loo_residuals(x[::step]), floor_mm=floor_mm, spreads=spreads)
    return Screen(median, threshold, float(training_mm))


def outlier_threshold(r: np.ndarray, *, floor_mm: float = OUTLIER_FLOOR_MM,
                      spreads: float = OUTLIER_SPREADS) -> tuple[np.ndarray, np.ndarray]:
    """Per marker of residuals ``r`` (F, L, 3) mm (NaN: absent): its median residual (L, 3) and the
    departure from it (L,) mm beyond which a residual is an outlier, ``max(floor_mm, spreads × its
    median departure)``; a marker never present gets median 0 and the floor."""
    seen = np.isfinite(r).all(axis=2).any(axis=0)
    median = np.zeros(r.shape[1:])
    median[seen] = np.nanmedian(r[:, seen], axis=0)
    typical = np.zeros(r.shape[1])
    typical[seen] = np.nanmedian(np.linalg.norm(r[:, seen] - median[seen], axis=2), axis=0)
    return median, np.maximum(floor_mm, spreads * typical)


def screen_frames(gauss: LayoutGaussian, screen: Screen, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outliers of layout frames ``x`` (f, L, 3) mm (head frame), dropped worst first.

    Returns ``flagged`` (f, L) bool (markers present in ``x`` found contradicted by the others) and
    ``consistency_mm`` (f,): the RMS leave-one-out residual of the markers kept (NaN with fewer
    than 2 markers).
    """
    x = np.array(x, dtype=np.float64)
    flagged = np.zeros(x.shape[:2], dtype=bool)
    present = np.isfinite(x).all(axis=2)
    budget = np.floor(MAX_DROPPED_SHARE * present.sum(axis=1)).astype(int)
    residual = gauss.loo_residuals(x)
    todo = np.arange(len(x))
    while todo.size:
        score = np.linalg.norm(residual[todo] - screen.median, axis=2) / screen.threshold_mm
        score = np.where(np.isfinite(score), score, 0.0)
        worst = score.argmax(axis=1)
        drop = (score[np.arange(todo.size), worst] > 1.0) & (flagged[todo].sum(axis=1) < budget[todo])
        todo, worst = todo[drop], worst[drop]
        if not todo.size:
            break
        flagged[todo, worst] = True
        x[todo, worst] = np.nan
        residual[todo] = gauss.loo_residuals(x[todo])
    sq = np.sum(residual ** 2, axis=2)
    count = np.isfinite(sq).sum(axis=1)
    total = np.where(np.isfinite(sq), sq, 0.0).sum(axis=1)
    consistency = np.where(count >= 2, np.sqrt(total / np.maximum(count, 1)), np.nan)
    return flagged, consistency


def stabilization_residuals(solved: np.ndarray, captured: np.ndarray, *, floor_mm: float = OUTLIER_FLOOR_MM,
                            spreads: float = OUTLIER_SPREADS) -> np.ndarray:
    """Distances (F, R) mm between markers the solve reconstructed, ``solved`` (F, R, 3), and the
    capture's own points of them, ``captured`` (F, R, 3), in the same frame. NaN where either is
    missing, or where the residual departs from the marker's median residual over the capture by
    more than :func:`outlier_threshold` (a ghost or a swap in the capture, not the solve's error:
    the layout markers' outlier test)."""
    r = np.asarray(solved, dtype=np.float64) - np.asarray(captured, dtype=np.float64)
    median, threshold = outlier_threshold(r, floor_mm=floor_mm, spreads=spreads)
    return np.where(np.linalg.norm(r - median, axis=2) > threshold, np.nan, np.linalg.norm(r, axis=2))


def _rms(r: np.ndarray) -> float:
    sq = np.sum(r ** 2, axis=-1)
    sq = sq[np.isfinite(sq)]
    return float(np.sqrt(sq.mean())) if sq.size else float("nan")
