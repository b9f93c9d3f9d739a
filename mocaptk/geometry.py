"""Shared geometry: similarity transforms (rotation, translation, uniform scale) between point sets;
lengths of many 3-vectors; bounding boxes; the smoothstep blend."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import OptionError

__all__ = ["Similarity", "bounds", "similarity_transform", "smoothstep", "vector_lengths"]


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation`` (rotation (3, 3) proper, translation (3,) mm)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (..., 3)."""
        return self.scale * np.asarray(points, dtype=float) @ self.rotation.T + self.translation

    def then(self, other: Similarity) -> Similarity:
        """The transform applying ``self`` first, then ``other``."""
        return Similarity(other.scale * self.scale, other.rotation @ self.rotation,
                          other.scale * other.rotation @ self.translation + other.translation)


def similarity_transform(source: np.ndarray, target: np.ndarray, *,
                         with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping ``source`` (N, 3) onto ``target`` (N, 3) (Umeyama 1991).

    Needs N >= 3 points not all on a line.
    """
    src = np.asarray(source, dtype=float)
    dst = np.asarray(target, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise OptionError(f"need matching (N >= 3, 3) point sets, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, sing, vt = np.linalg.svd(b.T @ a / len(src))
    if sing[1] <= 1e-12 * max(sing[0], 1e-300):
        raise OptionError("the corresponding points are collinear; alignment is undefined")
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ fix @ vt
    var = float(np.sum(a ** 2) / len(src))
    scale = float(np.trace(np.diag(sing) @ fix) / var) if with_scale else 1.0
    return Similarity(scale, rotation, mu_d - scale * rotation @ mu_s)


def smoothstep(x: np.ndarray) -> np.ndarray:
    """``3x² - 2x³`` of ``x`` clipped to [0, 1]: a 0 -> 1 blend with no kink where it starts or
    ends (the weights' fades and masks)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def vector_lengths(vectors: np.ndarray, *, axis: int = -1) -> np.ndarray:
    """Euclidean lengths of the 3-vectors along ``axis`` of a float array (that axis removed):
    the values of ``np.linalg.norm(vectors, axis=axis)`` (same sum order), without its
    temporaries. ``vectors`` is overwritten (squared in place)."""
    squares = np.moveaxis(vectors, axis, 0)
    squares *= squares
    out = np.add(squares[0], squares[1])
    out += squares[2]
    return np.sqrt(out, out=out)


def bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(low, high)`` ``(3,)``: per-axis minimum and maximum of ``points (..., 3)``, in their
    dtype. One strided pass per axis: numpy reduces an ``(N, 3)`` array over axis 0
    ~7x slower (an inner loop of 3 per row)."""
    flat = points.reshape(-1, 3)
    return (np.array([flat[:, k].min() for k in range(3)], points.dtype),
            np.array([flat[:, k].max() for k in range(3)], points.dtype))
