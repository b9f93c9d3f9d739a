"""Sagittal plane, side tags and mirroring of a half-face layout to the other side."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mocaptk.acquisition.orientation import (Orientation, infer_orientation, label_pairs, marker_motion,
                                             mirror_label, side_tag)
from mocaptk.errors import OptionError

from .layout import Cluster
from .neutral import max_displacement
from .regions import face_frame

#: Markers closer than this to the sagittal plane count as midline when labels carry no side tag.
MIDLINE_TOLERANCE_MM = 3.0


def is_half_capture(labels: Sequence[str]) -> bool:
    """True when side tags show one half of the face plus midline markers (L or R, not both, and C)."""
    tags = {side_tag(label) for label in labels}
    return "C" in tags and (("L" in tags) != ("R" in tags))


@dataclass(frozen=True)
class SagittalPlane:
    """Plane through ``point`` (3,) mm with unit ``normal`` (3,) pointing to the subject's left (+lateral)."""

    point: np.ndarray
    normal: np.ndarray

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of ``points`` (..., 3); positive on the normal's side."""
        return (np.asarray(points) - self.point) @ self.normal

    def mirror(self, points: np.ndarray) -> np.ndarray:
        """Reflection of ``points`` (..., 3) mm across the plane."""
        pts = np.asarray(points, dtype=np.float64)
        return pts - 2.0 * self.signed_distance(pts)[..., None] * self.normal

    def side(self, points: np.ndarray, *, tolerance: float = MIDLINE_TOLERANCE_MM) -> list[str]:
        """``"L"``/``"R"``/``"C"`` per point: C within ``tolerance`` mm of the plane."""
        d = self.signed_distance(points)
        return ["C" if abs(x) <= tolerance else ("L" if x > 0 else "R") for x in np.atleast_1d(d)]


def fit_sagittal_plane(midline: np.ndarray, lateral_hint: np.ndarray) -> SagittalPlane:
    """Best-fit plane through midline markers.

    Parameters
    ----------
    midline : (K, 3) mm
        Neutral positions of midline markers (K >= 3, not all on one line).
    lateral_hint : (3,)
        Direction toward the subject's left (e.g. the face frame's lateral axis); orients the
        normal and replaces the fit when the midline markers are (nearly) collinear.
    """
    pts = np.asarray(midline, dtype=np.float64)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if pts.shape[0] < 2:
        raise OptionError("mirroring needs at least 2 midline markers with a neutral position")
    centre = pts.mean(axis=0)
    hint = np.asarray(lateral_hint, dtype=np.float64) / np.linalg.norm(lateral_hint)
    _, s, vt = np.linalg.svd(pts - centre, full_matrices=False)
    if pts.shape[0] >= 3 and s[1] > 0.1 * s[0]:
        normal = vt[2]
    else:  # collinear midline: the plane contains the line and is as close to ⟂ hint as possible
        line = vt[0]
        normal = hint - (hint @ line) * line
    normal = normal / np.linalg.norm(normal)
    if normal @ hint < 0:
        normal = -normal
    return SagittalPlane(centre, normal)


def mirror_clusters(clusters: Sequence[Cluster], plane: SagittalPlane, existing_labels: Sequence[str],
                    midline: set[str]) -> list[Cluster]:
    """Mirror images of the non-midline clusters.

    Each mirrored cluster gets the mirrored representative label and position, the opposite side
    tag, ``mirrored_from`` = the original label, and the mirrored labels of its non-midline
    members (markers in ``midline`` stay only in the original cluster).
    """
    taken = set(existing_labels)
    out = []
    for cluster in clusters:
        if cluster.side == "C":
            continue
        new_label = mirror_label(cluster.representative)
        if new_label in taken:
            raise OptionError(f"cannot mirror {cluster.representative!r}: {new_label!r} already exists "
                              "(the capture is not a half face; use --no-mirror)")
        members = [m for m in cluster.members if m not in midline or m == cluster.representative]
        mirrored = [mirror_label(m) for m in members]
        out.append(Cluster(
            representative=new_label, region=cluster.region, members=tuple(mirrored),
            member_correlation={mirror_label(m): cluster.member_correlation[m] for m in members},
            position=tuple(float(x) for x in plane.mirror(np.array(cluster.position))),
            side="R" if cluster.side == "L" else "L", mirrored_from=cluster.representative))
    return out


def estimate_sagittal_plane(labels: Sequence[str], neutral: np.ndarray, displacement: np.ndarray, *,
                            half: bool, left: np.ndarray | None = None) -> SagittalPlane:
    """Sagittal plane of a neutral pose ``(M, 3)`` mm.

    Through the ``_C``-tagged midline markers when there are at least 2 (normal toward the ``_L``
    markers, away from the ``_R`` ones); else, for a full face with at least 2 mirror pairs named by
    the labels (:func:`label_pairs`), the plane bisecting them; otherwise normal = the face
    frame's lateral axis (:func:`face_frame`) through the median lateral position (full face) or,
    for a half face (``half``), through the medial edge: the lateral extreme nearer to the most
    forward marker (the nose tip lies on the midline). The normal points to the actor's left by
    the geometry whatever the labels say: ``left`` (3,), default
    :func:`~mocaptk.acquisition.orientation.infer_orientation`'s with ``displacement`` as motion.
    """
    plane = _sagittal_plane(labels, neutral, displacement, half=half)
    if left is None:
        left = infer_orientation(labels, neutral, displacement).frame[0]
    if plane.normal @ left < 0:
        return SagittalPlane(plane.point, -plane.normal)
    return plane


def _sagittal_plane(labels: Sequence[str], neutral: np.ndarray, displacement: np.ndarray, *,
                    half: bool) -> SagittalPlane:
    """:func:`estimate_sagittal_plane` with the normal towards the labels' left."""
    valid = np.isfinite(neutral).all(axis=1)
    frame = face_frame(neutral[valid], displacement[valid])
    tags = np.array([side_tag(label) or "" for label in labels])
    tagged = (tags == "C") & valid
    if tagged.sum() >= 2:
        hint = frame[0]
        left, right = (tags == "L") & valid, (tags == "R") & valid
        if left.any() or right.any():  # side tags say where the subject's left is
            centre = neutral[tagged].mean(axis=0)
            hint = (neutral[left] - centre).sum(axis=0) - (neutral[right] - centre).sum(axis=0)
        return fit_sagittal_plane(neutral[tagged], hint)
    pairs = [(i, j) for i, j in label_pairs(labels) if valid[i] and valid[j]]
    if len(pairs) >= 2 and not half:  # named mirror pairs: the plane bisects them, normal toward L
        left, right = neutral[[i for i, _ in pairs]], neutral[[j for _, j in pairs]]
        normal = (left - right).sum(axis=0)
        if np.linalg.norm(normal) > 0:
            return SagittalPlane((left + right).mean(axis=0) / 2, normal / np.linalg.norm(normal))
    pts = neutral[valid]
    lateral = pts @ frame[0]
    if half:
        tip = lateral[np.argmax(pts @ frame[2])]
        edge = lateral.min() if abs(tip - lateral.min()) < abs(tip - lateral.max()) else lateral.max()
        offset = edge
    else:
        offset = float(np.median(lateral))
    return SagittalPlane(frame[0] * offset, frame[0])


def marker_sides(labels: Sequence[str], positions: np.ndarray, plane: SagittalPlane, *,
                 trust_labels: bool = True) -> list[str]:
    """Side of each marker: its label tag when present (and ``trust_labels``: they agree with the
    geometry), else its side of ``plane``."""
    geometric = plane.side(positions)
    if not trust_labels:
        return geometric
    return [side_tag(label) or geo for label, geo in zip(labels, geometric)]


@dataclass(frozen=True)
class FaceSides:
    """A face's orientation (from its shape and motion), its sagittal plane and every marker's
    side (``"L"``, ``"R"`` or ``"C"``)."""

    orientation: Orientation
    plane: SagittalPlane
    sides: tuple[str, ...]


def face_sides(labels: Sequence[str], positions: np.ndarray, neutral: np.ndarray, *,
               half: bool | None = None, displacement: np.ndarray | None = None) -> FaceSides:
    """The sides of a session's markers as ``cluster`` takes them: ``positions`` (F, M, 3) mm with
    NaN gaps, ``neutral`` (M, 3) mm; ``half``: a half face (default: :func:`is_half_capture`);
    ``displacement``: (M,) each marker's largest displacement, mm, when the caller has it."""
    orientation = infer_orientation(labels, neutral, marker_motion(positions, neutral))
    if displacement is None:
        displacement = max_displacement(positions, neutral)
    plane = estimate_sagittal_plane(labels, neutral, displacement,
                                    half=is_half_capture(labels) if half is None else half,
                                    left=orientation.frame[0])
    sides = marker_sides(labels, neutral, plane, trust_labels=orientation.labels != "contradict")
    return FaceSides(orientation, plane, tuple(sides))


def plane_frame(plane: SagittalPlane, frame: np.ndarray) -> np.ndarray:
    """Face frame (rows lateral, up, forward) with lateral = the plane's normal (for front views)."""
    lateral = plane.normal
    up = frame[1] - (frame[1] @ lateral) * lateral
    up /= np.linalg.norm(up)
    return np.array([lateral, up, np.cross(lateral, up)])
