"""The layout data type and its file, ``layout.json`` (see docs/layout-format.md)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mocaptk.errors import InputFileError
from mocaptk.jsonio import read_json, write_json

FORMAT = "mocaptk.layout"
VERSION = 1


@dataclass(frozen=True)
class Cluster:
    """One layout marker and its influence region.

    ``representative``: label (input label, or a new label for a mirrored marker);
    ``members``: labels of the influence region, representative first;
    ``member_correlation``: consolidated correlation of each member with the representative (≤ 3);
    ``position``: neutral position, mm; ``side``: ``"L"``, ``"R"`` or ``"C"`` (midline);
    ``mirrored_from``: label of the marker this one mirrors, else None.
    """

    representative: str
    region: str
    members: tuple[str, ...]
    member_correlation: dict[str, float]
    position: tuple[float, float, float]
    side: str
    mirrored_from: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"representative": self.representative, "region": self.region,
                "members": list(self.members), "member_correlation": dict(self.member_correlation),
                "position": list(self.position), "side": self.side, "mirrored_from": self.mirrored_from}


@dataclass(frozen=True)
class RegionResult:
    """Per-region figures: input ``markers``, mean off-diagonal correlation, threshold, sampled frames."""

    name: str
    markers: tuple[str, ...]
    mean_correlation: float
    threshold: float
    samples: int
    representatives: tuple[str, ...]

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "markers": list(self.markers),
                "mean_correlation": self.mean_correlation, "threshold": self.threshold,
                "samples": self.samples, "representatives": list(self.representatives)}


@dataclass(frozen=True)
class Layout:
    """A marker layout: source, parameters, regions, clusters; ``extra`` holds further top-level keys."""

    source: dict[str, Any]
    parameters: dict[str, Any]
    regions: tuple[RegionResult, ...]
    clusters: tuple[Cluster, ...]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def labels(self) -> list[str]:
        """Layout marker labels (representatives, mirrored ones included), in cluster order."""
        return [c.representative for c in self.clusters]

    def as_dict(self) -> dict[str, Any]:
        out = dict(self.extra)
        out.update({"format": FORMAT, "version": VERSION, "units": "mm", "source": self.source,
                    "parameters": self.parameters, "regions": [r.as_dict() for r in self.regions],
                    "clusters": [c.as_dict() for c in self.clusters], "layout": self.labels})
        return out


def write_layout(layout: Layout, path: str | os.PathLike[str], *, force: bool = True) -> Path:
    """Write ``layout.json`` deterministically (sorted keys, rounded floats), atomically."""
    return write_json(path, layout.as_dict(), force=force)


def read_layout(path: str | os.PathLike[str]) -> Layout:
    """Read a ``layout.json`` written by :func:`write_layout`."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputFileError(path, f"not a {FORMAT} file")
    if data.get("version") != VERSION:
        raise InputFileError(path, f"unsupported layout version {data.get('version')!r} (expected {VERSION})")
    try:
        clusters = tuple(
            Cluster(c["representative"], c["region"], tuple(c["members"]),
                    {k: float(v) for k, v in c["member_correlation"].items()},
                    tuple(float(x) for x in c["position"]), c["side"], c.get("mirrored_from"))
            for c in data["clusters"])
        regions = tuple(
            RegionResult(r["name"], tuple(r["markers"]), _num(r["mean_correlation"]), _num(r["threshold"]),
                         int(r.get("samples", 0)), tuple(r.get("representatives", ())))
            for r in data["regions"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputFileError(path, f"malformed layout ({type(exc).__name__}: {exc})") from None
    known = {"format", "version", "units", "source", "parameters", "regions", "clusters", "layout"}
    extra = {k: v for k, v in data.items() if k not in known}
    return Layout(dict(data["source"]), dict(data["parameters"]), regions, clusters, extra)


def measured_indices(layout: Layout, labels: Sequence[str], *, layout_path: str | os.PathLike[str] | None,
                     session_name: str) -> list[int]:
    """Indices into ``labels`` (a session's) of the layout's measured markers, in cluster order;
    InputFileError naming the layout file when some are not in the session ``session_name``."""
    index = {label: i for i, label in enumerate(labels)}
    measured = [c.representative for c in layout.clusters if c.mirrored_from is None]
    unknown = [label for label in measured if label not in index]
    if unknown:
        raise InputFileError(layout_path, f"{len(unknown)} layout markers are not in {session_name}: "
                             + ", ".join(unknown[:5]))
    return [index[label] for label in measured]


def _num(value: Any) -> float:
    return float("nan") if value is None else float(value)
