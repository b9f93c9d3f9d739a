"""The layout data type and its file, ``layout.json`` (see docs/layout-format.md)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.acquisition.orientation import mirror_label
from mocaptk.errors import InputFileError, shorten
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
    """Read a ``layout.json`` written by :func:`write_layout`; every field's type is checked, so a
    hand-edited or damaged file is an :class:`InputFileError` naming the field, not a crash later."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise InputFileError(path, f"not a {FORMAT} file")
    if data.get("version") != VERSION:
        raise InputFileError(path, f"unsupported layout version {data.get('version')!r} (expected {VERSION})")
    try:
        clusters = tuple(_cluster(c, f"clusters[{i}]") for i, c in enumerate(_list(data, "clusters")))
        regions = tuple(_region(r, f"regions[{i}]") for i, r in enumerate(_list(data, "regions")))
        source, parameters = (_field(data, key, dict, "an object") for key in ("source", "parameters"))
        _check_reading(source)
        _check_source(source)
        _check_parameters(parameters)
        _check_extras(data)
    except _Malformed as exc:
        raise InputFileError(path, f"malformed layout: {exc}") from None
    if not clusters:
        raise InputFileError(path, "malformed layout: no clusters")
    labels = [c.representative for c in clusters]
    if len(set(labels)) != len(labels):
        twice = sorted({label for label in labels if labels.count(label) > 1})
        raise InputFileError(path, "malformed layout: a layout marker named twice: " + ", ".join(twice[:5]))
    known = {"format", "version", "units", "source", "parameters", "regions", "clusters", "layout"}
    extra = {k: v for k, v in data.items() if k not in known}
    return Layout(dict(source), dict(parameters), regions, clusters, extra)


class _Malformed(ValueError):
    """A field of layout.json of the wrong type (message: where, and what it must be)."""


def _field(obj: dict, key: str, kind: type, what: str, where: str = "") -> Any:
    """``obj[key]`` if it is a ``kind`` (dict, list or str), else _Malformed naming it."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        raise _Malformed(f"{name} is missing")
    if not isinstance(obj[key], kind):
        raise _Malformed(f"{name} must be {what}")
    return obj[key]


def _list(obj: Any, key: str, where: str = "") -> list:
    return _field(obj, key, list, "a list", where)


def _labels(obj: Any, key: str, where: str) -> tuple[str, ...]:
    values = _list(obj, key, where)
    if not all(isinstance(v, str) for v in values):
        raise _Malformed(f"{where}.{key} must be a list of marker labels")
    return tuple(values)


def _number(value: Any, name: str, *, null_ok: bool = False) -> float:
    """A JSON number; with ``null_ok``, null is NaN (as the writer stores a NaN statistic)."""
    if value is None and null_ok:
        return float("nan")
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Malformed(f"{name} must be a number")
    return float(value)


def _cluster(c: Any, where: str) -> Cluster:
    if not isinstance(c, dict):
        raise _Malformed(f"{where} must be an object")
    correlation = _field(c, "member_correlation", dict, "an object", where)
    position = _list(c, "position", where)
    if len(position) != 3:
        raise _Malformed(f"{where}.position must be 3 numbers (mm)")
    side = _field(c, "side", str, "a string", where)
    if side not in ("L", "R", "C"):
        raise _Malformed(f"{where}.side must be L, R or C")
    mirrored_from = c.get("mirrored_from")
    if mirrored_from is not None and not isinstance(mirrored_from, str):
        raise _Malformed(f"{where}.mirrored_from must be a marker label or null")
    return Cluster(_field(c, "representative", str, "a marker label", where),
                   _field(c, "region", str, "a region name", where), _labels(c, "members", where),
                   {str(k): _number(v, f"{where}.member_correlation.{k}") for k, v in correlation.items()},
                   tuple(_number(x, f"{where}.position") for x in position), side, mirrored_from)


def _check_reading(source: dict) -> None:
    """``source.reading`` (how cluster read the session; evaluate, solve and rig read it alike):
    rate null or > 0 Hz, units null or text, first_frame a whole number."""
    if source.get("reading") is None:
        return
    reading = _field(source, "reading", dict, "an object", "source")
    rate = reading.get("rate")
    if rate is not None and not _number(rate, "source.reading.rate") > 0:
        raise _Malformed("source.reading.rate must be null or a positive number of Hz")
    if reading.get("units") is not None and not isinstance(reading["units"], str):
        raise _Malformed("source.reading.units must be null or text (mm, cm, m, in or mm per file unit)")
    first = reading.get("first_frame", 0)
    if isinstance(first, bool) or not isinstance(first, int):
        raise _Malformed("source.reading.first_frame must be a whole number")


def _check_source(source: dict) -> None:
    """``source.path`` (the session's file name, looked up by solve / rig) and ``source.sha256``."""
    path = source.get("path")
    if path is not None:
        if not isinstance(path, str) or not path or "\0" in path:
            raise _Malformed("source.path must be a file name")
        if len(os.fsencode(path)) > 4096 or any(len(os.fsencode(part)) > 255 for part in Path(path).parts):
            raise _Malformed("source.path is too long for a file name")
    if source.get("sha256") is not None and not isinstance(source["sha256"], str):
        raise _Malformed("source.sha256 must be a text")


#: Types of the parameters that commands read back from a layout (others are only shown).
_PARAMETERS = {"stabilized": (bool, "true or false"), "mirror": (bool, "true or false"),
               "method": (str, "a text"), "factor": ((int, float), "a number")}


def _check_parameters(parameters: dict) -> None:
    for key, (kind, what) in _PARAMETERS.items():
        value = parameters.get(key)
        if value is not None and (not isinstance(value, kind) or (kind != bool and isinstance(value, bool))):
            raise _Malformed(f"parameters.{key} must be {what}")


#: Largest coordinate (mm) of a sagittal-plane point, and the range of its normal's length: the
#: writer stores a unit normal near the face; beyond these, products over- or underflow.
_PLANE_REACH_MM = 1e6
_NORMAL_LENGTH = (1e-6, 1e6)


def _check_extras(data: dict) -> None:
    """The optional top-level keys that rig, plan, evaluate and the report read back."""
    if data.get("sagittal_plane") is not None:
        plane = _field(data, "sagittal_plane", dict, "an object")
        for key in ("point", "normal"):
            values = _list(plane, key, "sagittal_plane")
            if len(values) != 3 or not np.all(np.isfinite([_number(v, f"sagittal_plane.{key}") for v in values])):
                raise _Malformed(f"sagittal_plane.{key} must be 3 finite numbers")
        if not any(plane["normal"]):
            raise _Malformed("sagittal_plane.normal must not be zero")
        if max(abs(v) for v in plane["point"]) > _PLANE_REACH_MM:
            raise _Malformed(f"sagittal_plane.point is more than {_PLANE_REACH_MM:g} mm away")
        if not _NORMAL_LENGTH[0] <= math.hypot(*plane["normal"]) <= _NORMAL_LENGTH[1]:
            raise _Malformed("sagittal_plane.normal must be a direction (length about 1, not zero)")
    if data.get("orientation") is not None:
        orientation = _field(data, "orientation", dict, "an object")
        rows = _list(orientation, "frame", "orientation")
        if len(rows) != 3 or not all(isinstance(r, list) and len(r) == 3 for r in rows) or not np.all(
                np.isfinite([_number(x, "orientation.frame") for r in rows for x in r])):
            raise _Malformed("orientation.frame must be 3 rows of 3 finite numbers")
        if orientation.get("labels") not in ("agree", "contradict", "decided", "none"):
            raise _Malformed("orientation.labels must be agree, contradict, decided or none")
    if data.get("stabilization") is not None:
        stabilization = _field(data, "stabilization", dict, "an object")
        if stabilization.get("rigid_labels") is not None:
            rigid = _labels(stabilization, "rigid_labels", "stabilization")
            if stabilization.get("reference") is not None:
                reference = _list(stabilization, "reference", "stabilization")
                if len(reference) != len(rigid) or not all(
                        isinstance(p, list) and len(p) == 3
                        and np.all(np.isfinite([_number(v, "stabilization.reference") for v in p]))
                        for p in reference):
                    raise _Malformed("stabilization.reference must hold 3 finite numbers per rigid label")


def _region(r: Any, where: str) -> RegionResult:
    if not isinstance(r, dict):
        raise _Malformed(f"{where} must be an object")
    samples = r.get("samples", 0)
    if isinstance(samples, bool) or not isinstance(samples, int):
        raise _Malformed(f"{where}.samples must be a whole number")
    representatives = _labels(r, "representatives", where) if "representatives" in r else ()
    return RegionResult(_field(r, "name", str, "a region name", where), _labels(r, "markers", where),
                        _number(_field(r, "mean_correlation", object, "", where), f"{where}.mean_correlation",
                                null_ok=True),
                        _number(_field(r, "threshold", object, "", where), f"{where}.threshold", null_ok=True),
                        samples, representatives)


def layout_rigid_set(layout: Layout) -> tuple[str, ...] | None:
    """The layout's stabilization markers: its session's rigid head set, recorded whether or not
    the session itself needed stabilizing (None: none recorded)."""
    labels = (layout.extra.get("stabilization") or {}).get("rigid_labels")
    return tuple(labels) if labels else None


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


def check_members(layout: Layout, labels: Sequence[str], *, layout_path: str | os.PathLike[str] | None,
                  session_name: str) -> None:
    """InputFileError naming the layout file when a cluster member is neither a marker of the
    session ``session_name`` (``labels``) nor the mirror image of one (a half-face layout's twin),
    or a stabilization marker is not one of the session's."""
    known = set(labels)
    unknown = list(dict.fromkeys(m for c in layout.clusters for m in (c.representative, *c.members)
                                 if m not in known and mirror_label(m) not in known))
    if unknown:
        raise InputFileError(layout_path, f"{len(unknown)} layout members are not markers of {session_name} "
                             "(nor mirror twins of them): " + ", ".join(shorten(m, 40) for m in unknown[:5]))
    rigid = [m for m in layout_rigid_set(layout) or () if m not in known]
    if rigid:
        raise InputFileError(layout_path, f"{len(rigid)} stabilization markers are not markers of "
                             f"{session_name}: " + ", ".join(shorten(m, 40) for m in rigid[:5]))
