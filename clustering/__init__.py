"""Clustering: facial regions, per-region correlation, threshold clustering, layout methods."""

from .baselines import farthest_point_layout, kmeans_layout, random_layout  # noqa: E402
from .evaluation import (  # noqa: E402
    baseline_layouts, compare_layouts, error_summary, evaluate_layout, fit_reconstruction, heldout_errors,
    holdout_splits, reconstruct, reconstruction_errors,
)
from .correlation import Correlation, consolidated_correlation, mean_off_diagonal  # noqa: E402
from .layout import Cluster, Layout, RegionResult, read_layout, write_layout  # noqa: E402
from .neutral import max_displacement, neutral_pose  # noqa: E402
from .pipeline import ClusterOptions, ClusterResult, cluster_session, load_session, stabilize  # noqa: E402
from .regions import (  # noqa: E402
    FACIAL_REGIONS, default_regions, face_frame, geometric_regions, read_regions, regions_from_prefixes,
)
from .symmetry import (  # noqa: E402
    SagittalPlane, estimate_sagittal_plane, fit_sagittal_plane, is_half_capture, mirror_clusters, mirror_label,
    side_tag,
)
from .takes import read_takes, region_segments, sample_frames  # noqa: E402
from .threshold import RegionClusters, cluster_region, reassign, threshold_clusters  # noqa: E402
from .methods import LayoutProblem, LayoutResult, layout_problem, method_names, select_layout  # noqa: E402

__all__: list[str] = [
    "baseline_layouts", "compare_layouts", "error_summary", "evaluate_layout", "farthest_point_layout",
    "fit_reconstruction", "heldout_errors", "holdout_splits", "kmeans_layout", "max_displacement",
    "neutral_pose", "random_layout", "reconstruct", "reconstruction_errors",
    "Cluster", "ClusterOptions", "ClusterResult", "Correlation", "FACIAL_REGIONS", "Layout", "RegionClusters",
    "RegionResult", "SagittalPlane", "cluster_region", "cluster_session", "consolidated_correlation",
    "default_regions", "estimate_sagittal_plane", "face_frame", "fit_sagittal_plane", "geometric_regions",
    "is_half_capture", "load_session", "mean_off_diagonal", "mirror_clusters", "mirror_label", "read_layout",
    "read_regions", "read_takes", "reassign", "region_segments", "regions_from_prefixes", "sample_frames",
    "side_tag", "stabilize", "threshold_clusters", "write_layout",
    "LayoutProblem", "LayoutResult", "layout_problem", "method_names", "select_layout",
]
