"""Clustering: facial regions, per-region correlation, threshold clustering, layout methods."""

__all__: list[str] = []
