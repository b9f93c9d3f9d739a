"""Marker-driven skinning check: move the mesh with the layout markers, compare with the truth.

Translation-only linear blend skinning (the joints never rotate): a vertex moves by the
weighted sum of its joints' displacements, ``v'(t) = v + Σ_j w_j (p_j(t) − p_j(0))``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["SkinningError", "distance_error", "skin_vertices", "skinning_error"]


def skin_vertices(rest: np.ndarray, weight_index: np.ndarray, weight_value: np.ndarray,
                  joint_displacement: np.ndarray) -> np.ndarray:
    """Skinned vertex positions (F, V, 3) mm.

    Parameters
    ----------
    rest : (V, 3) mm
    weight_index, weight_value : (V, k)
        Joint indices and weights (rows sum to 1).
    joint_displacement : (F, J, 3) mm
        Each joint's offset from its bind position per frame (NaN not allowed).
    """
    disp = np.asarray(joint_displacement, dtype=float)
    n_frames, n_joints, _ = disp.shape
    n_vertices, k = np.shape(weight_index)
    skin = sp.csr_matrix((np.ravel(weight_value), (np.repeat(np.arange(n_vertices), k),
                                                   np.ravel(weight_index))),
                         shape=(n_vertices, n_joints))
    moved = skin @ disp.transpose(1, 0, 2).reshape(n_joints, -1)  # (V, F*3)
    moved = moved.reshape(n_vertices, n_frames, 3).transpose(1, 0, 2)
    return np.asarray(rest, dtype=float)[None] + moved


@dataclass(frozen=True)
class SkinningError:
    """Distance between skinned and true vertex positions, mm, over valid (frame, vertex) pairs."""

    rmse_mm: float
    p95_mm: float
    max_mm: float
    frames: int
    vertices: int

    def as_dict(self) -> dict[str, float | int]:
        return {"rmse_mm": self.rmse_mm, "p95_mm": self.p95_mm, "max_mm": self.max_mm,
                "frames": self.frames, "vertices": self.vertices}


def skinning_error(predicted: np.ndarray, truth: np.ndarray) -> SkinningError:
    """RMSE (sqrt of the mean squared 3-D distance), 95th percentile and max, NaN-aware.

    ``predicted`` and ``truth`` (F, V, 3) mm; pairs with NaN in either are left out.
    """
    return distance_error(np.linalg.norm(np.asarray(predicted) - np.asarray(truth), axis=2))


def distance_error(dist: np.ndarray) -> SkinningError:
    """:func:`skinning_error` of the distances ``dist`` (F, V) mm between predicted and true
    positions (NaN: left out)."""
    ok = np.isfinite(dist)
    if not ok.any():
        return SkinningError(float("nan"), float("nan"), float("nan"), 0, 0)
    d = dist[ok]
    return SkinningError(float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95)),
                         float(d.max()), int(ok.any(axis=1).sum()), int(ok.any(axis=0).sum()))
