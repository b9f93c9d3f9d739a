"""Clustering: facial regions, per-region correlation, threshold clustering, layout methods."""

from .baselines import farthest_point_layout, kmeans_layout, random_layout  # noqa: E402
from .evaluation import (  # noqa: E402
    baseline_layouts, compare_layouts, error_summary, evaluate_layout, fit_reconstruction, heldout_errors,
    holdout_splits, reconstruct, reconstruction_errors,
)
from .neutral import max_displacement, neutral_pose  # noqa: E402

__all__: list[str] = [
    "baseline_layouts", "compare_layouts", "error_summary", "evaluate_layout", "farthest_point_layout",
    "fit_reconstruction", "heldout_errors", "holdout_splits", "kmeans_layout", "max_displacement",
    "neutral_pose", "random_layout", "reconstruct", "reconstruction_errors",
]
