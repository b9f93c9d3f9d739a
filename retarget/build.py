"""Layout + session (+ mesh) -> skinned :class:`~mocaptk.retarget.rig.Rig`, and the files for it.

:func:`build_rig` is the pure pipeline (arrays in, rig and report out); :func:`write_rig_outputs`
adds the files (``rig.json``/``rig.fbx``/``rig.glb``, ``guide.pdf`` and its PNG views) and is
the one function ``mocaptk rig`` and ``mocaptk cluster`` call.

Frames. The rig is Y up, face looking down +Z (mm). The session's face frame (forward = the
side the face bulges towards, :func:`~mocaptk.surface_mesh.front_direction`; lateral = the
layout's sagittal plane normal, towards the subject's left; up completes it) is snapped to the nearest signed axis permutation when every axis is within
25° of one (so an already Y-up session is left exactly as is), else used as the rotation.

Half-face captures. A layout mirrored to the other side (clusters with ``mirrored_from``)
refers to markers the session does not have: their dense markers are the session's mirrored
across the layout's sagittal plane, and they move like their mirror images (symmetric motion).
The skinning check reports the error on the captured markers only.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from mocaptk.background import beside
from mocaptk.clustering.layout import Cluster, Layout
from mocaptk.clustering.neutral import max_displacement, neutral_pose
from mocaptk.clustering.regions import face_frame
from mocaptk.clustering.symmetry import SagittalPlane, mirror_label, side_tag
from mocaptk.errors import OptionError
from mocaptk.geometry import vector_lengths
from mocaptk.surface_mesh import (SurfaceMesh, cut_openings, front_direction, marker_spacing,
                                  marker_surface_mesh, mesh_quality)
from mocaptk.trajectories import Trajectories

from .align import Alignment, SurfaceProximity, align_mesh_to_markers
from .animate import SkinningError, distance_error, skin_vertices, skinning_error
from .bake import RigAnimation, bake_animation, concatenate_animations, head_pose_between
from .default_face import (CORNER_JOINTS_MM, CORNER_LEFT_OUT_FADE_MM, CORNER_PIN_FADE_MM,
                           EYE_CORNER_MM, MOUTH_CORNER_MM, DefaultFace, default_face)
from .face_materials import mesh_materials
from .face_parts import socket_rows, template_parts
from .eye_openings import cut_eye_openings, template_eye_loops
from .face_template import FittedTemplate, fit_template
from .face_weights import face_anchors, face_rows
from .guide import GuideMarker, guide_markers, write_guide_pdf
from .influence import anchor_vertices, distinct_vertices, edge_graph, main_influence_regions
from .lid_joints import LidJoints, lid_joints
from .mesh_openings import CORNERS, OpenedMesh, fill_sockets, open_mesh, parts_follow, weighted_faces
from .mesh_parts import head_jaw_rows, nose_height, part_weights
from .mesh_space import animation_in_space, inverse, rig_in_space
from .rig import Rig
from .rig_hierarchy import RigHierarchy, fit_jaw_pivot, hierarchical_animation, jaw_members, rig_hierarchy
from .weights import (blend_corners, cap_weights, corner_joints, masked_support, mirror_maps,
                      region_masks, shape_by_regions, symmetric_weights, thin_shell_weights)

__all__ = ["Capture", "DenseCloud", "RigBuild", "RigOptions", "bake_capture", "build_rig",
           "check_surface", "file_hierarchy",
           "dense_cloud", "ground_truth_error", "guide_reference",
           "guide_rows", "influence_members", "marker_driven_error", "mesh_ground_truth_error",
           "rig_frame_rotation", "with_check", "write_rig_outputs"]

#: Marker label (and name stem) of the default face's upper-lid joints: ``upperLid_L``/``_R``.
LID_JOINT = "upperLid"
#: Largest angle (degrees) between a face-frame axis and a coordinate axis for snapping.
SNAP_DEGREES = 25.0
FORMATS = ("json", "fbx", "glb")
#: Default region falloff in dense marker spacings (docs/rig-weights.md has the measurements).
FALLOFF_SPACINGS = 3.0


#: The default mesh's border turns inwards by at most this (degrees) at a marker: deeper notches
#: are filled (a zigzag top of the forehead; sample: 44 -> 14 degrees on the rig's top border).
RIM_NOTCH_DEG = 30.0
#: A user mesh's skin this close (mm) to a mouth corner is capped continuously
#: (:func:`~mocaptk.retarget.weights.cap_weights`): the ICT-FaceKit head's uncut lips swapped
#: their 4th joint between neighbours 6 mm below the corners (sample: 4 triangles folded -> 0;
#: largest stretch 2.50x -> 2.68x there; MediaPipe 1.86x -> 1.90x).
MESH_CORNER_CONTINUOUS_MM = 8.0


@dataclass(frozen=True)
class RigOptions:
    """Options of :func:`build_rig`.

    ``max_influences`` per vertex (4 or 8 usual); ``falloff_mm``: how far (geodesic mm) a joint's
    influence extends past its region's border (``None``: :data:`FALLOFF_SPACINGS` x the dense
    marker spacing; 0: hard borders; see :mod:`~mocaptk.retarget.weights`);
    ``pure_thin_shell``: skip the region shaping (on the sample: equal RMSE at the dense markers,
    lower over a whole face mesh — see docs/rig-weights.md);
    ``subdivisions``: midpoint subdivisions of the marker surface mesh;
    ``ks``/``kb``: thin-shell stretching/bending stiffness;
    ``surface``: the mesh without ``--mesh``: ``"face"`` (the ICT-FaceKit face fitted to the
    markers, :mod:`~mocaptk.retarget.default_face`; the marker surface where it does not fit)
    or ``"markers"`` (the surface through the dense markers);
    ``face_parts``: the default face with its eyeballs and mouth interior
    (:mod:`~mocaptk.retarget.face_parts`; False: the skin alone).
    """

    max_influences: int = 4
    min_weight: float = 1e-3
    falloff_mm: float | None = None
    pure_thin_shell: bool = False
    subdivisions: int = 1
    ks: float = 1.0
    kb: float = 10.0
    surface: str = "face"
    face_parts: bool = True


#: What ``RigOptions.surface`` (and ``solve --surface``) chooses from.
SURFACES = ("face", "markers")


def check_surface(surface: str) -> str:
    """``surface`` if it is one of :data:`SURFACES`, else OptionError."""
    if surface not in SURFACES:
        raise OptionError(f"unknown --surface {surface!r} (choose from {', '.join(SURFACES)})")
    return surface


@dataclass(frozen=True, eq=False)
class DenseCloud:
    """Every dense marker the rig knows, in the rig frame.

    ``labels`` (N,); ``trajectories`` (F, N, 3) mm; ``neutral`` (N, 3) mm; ``captured`` (N,)
    bool - False for markers mirrored from the other side; ``rotation`` (3, 3) session -> rig.
    """

    labels: tuple[str, ...]
    trajectories: np.ndarray
    neutral: np.ndarray
    captured: np.ndarray
    rotation: np.ndarray

    @cached_property
    def _lookup(self) -> dict[str, int]:  # built once: a 10,000-marker cloud is asked per cluster
        return {label: i for i, label in enumerate(self.labels)}

    def index(self, labels: Sequence[str]) -> np.ndarray:
        lookup = self._lookup
        missing = [label for label in labels if label not in lookup]
        if missing:
            raise OptionError(f"layout markers not found in the session: {', '.join(missing[:6])}"
                              + (" ..." if len(missing) > 6 else ""))
        return np.array([lookup[label] for label in labels], dtype=np.int64)


@dataclass(frozen=True, eq=False)
class RigBuild:
    """A rig and how it was made: per-vertex region (cluster index, -1 none), dense-marker
    vertices, alignment of a user mesh, the skinning check, a JSON-ready report, and the
    default face's lid joints."""

    rig: Rig
    layout: Layout
    cloud: DenseCloud
    regions: np.ndarray
    dense_vertices: np.ndarray
    joint_vertices: np.ndarray
    alignment: Alignment | None
    check: SkinningError
    report: dict[str, Any] = field(default_factory=dict)
    lids: LidJoints | None = None

    @property
    def marker_joints(self) -> slice:
        """The rig joints of the layout's markers (after the root; lid joints follow them)."""
        return slice(1, 1 + len(self.layout.clusters))

    def joint_displacements(self, displacement: np.ndarray) -> np.ndarray:
        """Displacements (F, J - 1, 3) mm of every joint but the root from the layout joints'
        (F, L, 3) mm: the lid joints' are derived from them."""
        if self.lids is None:
            return displacement
        return np.concatenate([displacement, self.lids.displacements(displacement)], axis=1)


@dataclass(frozen=True, eq=False)
class Capture:
    """A capture to bake onto a rig: ``relative`` head-relative (stabilized like the layout's
    session; session frame), ``raw`` the same capture as recorded (None: no head motion, e.g. a
    head-mounted capture), ``name`` its clip name (file stem)."""

    name: str
    relative: Trajectories
    raw: Trajectories | None = None


def bake_capture(build: RigBuild, capture: Capture) -> RigAnimation:
    """The motion of ``capture``'s layout markers baked onto the build's rig (gaps filled and
    reported, head pose on the root; see :mod:`~mocaptk.retarget.bake`).

    A mirrored layout marker missing from the capture moves as the mirror image of its source
    (like the rig's own session). Markers other than the layout's are ignored.

    Raises
    ------
    OptionError
        The capture lacks layout markers.
    """
    relative = capture.relative
    lookup = {label: i for i, label in enumerate(relative.labels)}
    own, mirrored, missing = [], [], []
    for c in build.layout.clusters:
        if c.representative in lookup:
            own.append(lookup[c.representative])
            mirrored.append(False)
        elif c.mirrored_from in lookup:
            own.append(lookup[c.mirrored_from])
            mirrored.append(True)
        else:
            missing.append(c.representative)
    if missing:
        raise OptionError(f"{capture.name}: lacks {len(missing)} layout markers: "
                          + ", ".join(missing[:6]) + (" ..." if len(missing) > 6 else ""))
    positions = np.take(relative.positions, own, axis=1)  # x[:, own]'s values, ~2.5x faster
    flip = np.flatnonzero(mirrored)
    if len(flip):
        positions[:, flip] = _sagittal_plane(build.layout).mirror(np.take(positions, flip, axis=1))
    rotation = build.cloud.rotation
    head_rot = head_trans = None
    if capture.raw is not None:
        raw = capture.raw.select(list(relative.labels)).positions
        pose_rot, pose_trans = head_pose_between(raw, relative.positions)
        head_rot = np.einsum("ij,fjk,lk->fil", rotation, pose_rot, rotation)  # Q R Q^T
        head_trans = pose_trans @ rotation.T
    bind = build.rig.joint_positions[1:]
    positions = bind + build.joint_displacements(positions @ rotation.T - bind[:positions.shape[1]])
    return bake_animation(build.rig, positions, rate=relative.rate,
                          head_rotations=head_rot, head_translations=head_trans,
                          takes=relative.takes, name=capture.name, first_frame=relative.first_frame)


def file_hierarchy(build: RigBuild) -> RigHierarchy:
    """The joint hierarchy written to the rig files (:mod:`~mocaptk.retarget.rig_hierarchy`): the
    jaw's joints and its pivot fitted on the session's own motion, the layout's stabilization
    markers (layout.json ``stabilization``) as locators under the head."""
    rig, layout, cloud = build.rig, build.layout, build.cloud
    clusters = len(layout.clusters)
    bind = rig.joint_positions[build.marker_joints]
    lower = np.zeros(rig.joint_count - 1, bool)  # the lid joints ride the head
    lower[:clusters] = jaw_members([c.region for c in layout.clusters], bind)
    plane = layout.extra.get("sagittal_plane")
    midline = (float((cloud.rotation @ np.asarray(plane["point"], float))[0])
               if isinstance(plane, dict) else float(np.mean(bind[:, 0])))
    reps = cloud.index([c.representative for c in layout.clusters])
    jaw = np.flatnonzero(lower[:clusters])
    pivot = fit_jaw_pivot(bind[jaw], np.take(cloud.trajectories, reps[jaw], axis=1),
                          midline_x=midline)
    stabilization = layout.extra.get("stabilization") or {}
    reference = stabilization.get("reference")
    locators = [(label, side_tag(label) or "C", np.asarray(position, float) @ cloud.rotation.T)
                for label, position in zip(stabilization.get("rigid_labels") or (),
                                           () if reference is None else reference)]
    return rig_hierarchy(rig, lower=lower, pivot=pivot, stabilization=locators)


def jaw_open_frame(build: RigBuild, animation: RigAnimation, *, start: int = 0) -> int:
    """Frame (>= ``start``) of ``animation`` where the jaw is open widest: the chin-region joints
    (else the lowest third of the joints) lowest below their bind positions, head-relative."""
    bind = build.rig.joint_positions[1:]
    regions = np.array(build.rig.joint_regions[1:])
    chosen = regions == "chin"
    if not chosen.any():
        chosen = bind[:, 1] <= np.percentile(bind[:, 1], 33)
    local = animation.translations[start:, 1:][:, chosen] + build.rig.joint_positions[0]
    drop = (bind[chosen, 1] - local[..., 1]).mean(axis=1)
    return int(start + np.argmax(drop))


def held_out_check(build: RigBuild, capture: Capture) -> dict[str, Any] | None:
    """The marker-driven skinning check on another capture of the same dense markers (a
    held-out performance): overall, per region and its worst case; None when the capture lacks
    the session's dense markers (a production capture with the layout only)."""
    try:
        cloud = dense_cloud(build.layout, capture.relative, rotation=build.cloud.rotation)
        missing = set(build.cloud.labels) - set(cloud.labels)
    except OptionError:
        return None
    if missing:
        return None
    check, by_region = skinning_check(build, cloud)
    return {"capture": capture.name, **check.as_dict(), **by_region}


def rig_frame_rotation(neutral: np.ndarray, displacement: np.ndarray, *,
                       lateral: np.ndarray | None = None) -> np.ndarray:
    """Rotation (3, 3) from session coordinates to the rig frame (X left, Y up, Z forward).

    ``lateral``: the subject's left (e.g. the layout's sagittal plane normal); without it the
    clustering stage's face frame guesses it (less reliable on full, wide faces).
    """
    ok = np.isfinite(neutral).all(axis=1) & np.isfinite(displacement)
    forward = front_direction(neutral[ok])
    if lateral is None:
        lateral = face_frame(neutral[ok], displacement[ok])[0]
    lateral = np.asarray(lateral, dtype=float)
    lateral = lateral - (lateral @ forward) * forward
    lateral /= np.linalg.norm(lateral)
    frame = np.array([lateral, np.cross(forward, lateral), forward])  # rows: X, Y, Z
    snapped = np.zeros((3, 3))
    for row, axis in enumerate(frame):
        k = int(np.argmax(np.abs(axis)))
        if np.degrees(np.arccos(min(1.0, abs(axis[k])))) > SNAP_DEGREES:
            return frame
        snapped[row, k] = np.sign(axis[k])
    if abs(np.linalg.det(snapped) - 1.0) > 1e-9:
        return frame
    return snapped


#: Frames per block of :func:`dense_cloud` (a few MB of temporaries at a few hundred markers).
CLOUD_BLOCK_FRAMES = 1024


def dense_cloud(layout: Layout, session: Trajectories, *, rotation: np.ndarray | None = None,
                neutral: np.ndarray | None = None, frames: slice | None = None) -> DenseCloud:
    """The session's markers (+ mirrored ones the layout needs), rotated into the rig frame.

    ``rotation`` (3, 3) session -> rig; default: :func:`rig_frame_rotation` of the session.
    ``neutral`` (markers, 3) mm: the session's :func:`neutral_pose` when the caller has it (one
    pass over the frames less). ``frames``: the frames the cloud keeps (default all; the rotation
    is still the one of all frames). Markers never seen are left out.
    """
    positions = np.asarray(session.positions, dtype=float)
    neutral = neutral_pose(positions) if neutral is None else np.asarray(neutral, dtype=float)
    seen = np.isfinite(neutral).all(axis=1)
    labels = [label for label, ok in zip(session.labels, seen) if ok]
    own = np.flatnonzero(seen)
    neutral = neutral[seen]
    captured = np.ones(len(labels), bool)
    mirrored = [c for c in layout.clusters if c.mirrored_from is not None]
    src = np.zeros(0, dtype=np.int64)
    if mirrored:
        plane = _sagittal_plane(layout)
        lookup = {label: i for i, label in enumerate(labels)}
        sources = {mirror_label(label): i for label, i in lookup.items()}
        # the whole mirrored half, also side markers that joined a midline cluster: a symmetric mesh
        wanted = ({m for c in mirrored for m in c.members}
                  | {mirror_label(label) for label in labels if side_tag(label) in ("L", "R")}
                  ) - set(lookup)
        unknown = sorted(m for m in wanted if m not in sources)
        if unknown:
            raise OptionError("mirrored layout markers have no source marker in the session: "
                              + ", ".join(unknown[:6]))
        new = sorted(wanted)
        src = np.array([sources[m] for m in new], dtype=np.int64)
        neutral = np.concatenate([neutral, plane.mirror(neutral[src])])
        labels += new
        captured = np.concatenate([captured, np.zeros(len(new), bool)])
    def filled(block: np.ndarray) -> np.ndarray:  # (b, markers, 3) -> (b, cloud markers, 3)
        out = np.empty((block.shape[0], len(labels), 3))
        # np.take: the same values as x[:, index], ~4x faster (one copy per (frame, marker) row)
        out[:, :own.size] = np.take(block, own, axis=1)
        if src.size:
            out[:, own.size:] = plane.mirror(np.take(out, src, axis=1))
        return out

    kept = positions if frames is None else positions[frames]
    # block by block: no whole-session temporaries (gathers, mirror, concatenation)
    cloud = np.empty((kept.shape[0], len(labels), 3))
    for start in range(0, kept.shape[0], CLOUD_BLOCK_FRAMES):
        cloud[start:start + CLOUD_BLOCK_FRAMES] = filled(kept[start:start + CLOUD_BLOCK_FRAMES])
    if rotation is None:
        plane_dict = layout.extra.get("sagittal_plane")
        lateral = np.asarray(plane_dict["normal"], float) if isinstance(plane_dict, dict) else None
        if lateral is not None:  # the displacement only guesses the lateral axis (always finite)
            displacement = np.zeros(len(labels))
        elif frames is None:
            displacement = max_displacement(cloud, neutral)
        else:  # over all frames: the largest of each block's (the same maximum)
            displacement = np.zeros(len(labels))
            for start in range(0, positions.shape[0], CLOUD_BLOCK_FRAMES):
                block = filled(positions[start:start + CLOUD_BLOCK_FRAMES])
                np.maximum(displacement, max_displacement(block, neutral), out=displacement)
        rotation = rig_frame_rotation(neutral, displacement, lateral=lateral)
    for start in range(0, cloud.shape[0], CLOUD_BLOCK_FRAMES):  # each frame's product as before
        block = cloud[start:start + CLOUD_BLOCK_FRAMES]
        block[...] = block @ rotation.T
    return DenseCloud(tuple(labels), cloud, neutral @ rotation.T, captured, rotation)


def _weight_mirror(layout: Layout, cloud: DenseCloud, vertices: np.ndarray,
                   spacing: float, *, vertex: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertex mirror (V,), joint mirror (J,) over the clusters) for a mirrored layout on a
    mirror-symmetric mesh (every vertex's image within 5 % of the marker spacing; ``vertex``:
    the mesh's own vertex mirror when it has one), else None."""
    clusters = layout.clusters
    if vertex is None:
        vertex = _vertex_mirror(layout, cloud, vertices, spacing)
    if vertex is None:
        return None
    by_label = {c.representative: i for i, c in enumerate(clusters)}
    joints = np.arange(len(clusters))
    for i, c in enumerate(clusters):
        if c.mirrored_from in by_label:
            joints[i], joints[by_label[c.mirrored_from]] = by_label[c.mirrored_from], i
    return vertex, joints


def _vertex_mirror(layout: Layout, cloud: DenseCloud, vertices: np.ndarray,
                   spacing: float) -> np.ndarray | None:
    """Each vertex's mirror vertex (V,) for a mirrored layout on a mirror-symmetric mesh, else None."""
    if not any(c.mirrored_from for c in layout.clusters):
        return None
    plane = _sagittal_plane(layout)
    return mirror_maps(vertices, cloud.rotation @ plane.point, cloud.rotation @ plane.normal,
                       tolerance_mm=0.05 * spacing)


#: A dense marker follows the jaw when its drop is at least this fraction of the jaw markers'
#: (least squares over the session; sample: lower lip 1.2-1.9, upper lip 0.1-0.4).
JAW_FOLLOWING = 0.7


def _follows_jaw(layout: Layout, cloud: DenseCloud, members: list[np.ndarray]) -> np.ndarray:
    """Which dense markers (N,) bool drop with the jaw: their downward motion (rig Y) against the
    mean drop of the jaw joints' influence members (:func:`~.rig_hierarchy.jaw_members`), least
    squares over the session, at least :data:`JAW_FOLLOWING`."""
    bind = cloud.neutral[cloud.index([c.representative for c in layout.clusters])]
    jaw = jaw_members([c.region for c in layout.clusters], bind)
    sources = np.concatenate([members[j] for j in np.flatnonzero(jaw)])
    along, power = np.zeros(len(cloud.labels)), 0.0
    for start in range(0, cloud.trajectories.shape[0], CLOUD_BLOCK_FRAMES):  # no (F, N) copy
        drop = np.nan_to_num(cloud.neutral[None, :, 1]
                             - cloud.trajectories[start:start + CLOUD_BLOCK_FRAMES, :, 1])
        signal = drop[:, sources].mean(axis=1)
        along += drop.T @ signal
        power += float(signal @ signal)
    return along >= JAW_FOLLOWING * max(power, 1e-12)


def _rig_plane(layout: Layout, cloud: DenseCloud) -> tuple[np.ndarray, np.ndarray] | None:
    """The sagittal plane ``(point, normal)`` in the rig frame for a mirrored layout, else None."""
    if not any(c.mirrored_from for c in layout.clusters):
        return None
    plane = _sagittal_plane(layout)
    return cloud.rotation @ plane.point, cloud.rotation @ plane.normal


def _sagittal_plane(layout: Layout) -> SagittalPlane:
    plane = layout.extra.get("sagittal_plane")
    try:
        return SagittalPlane(np.asarray(plane["point"], float), np.asarray(plane["normal"], float))
    except (TypeError, KeyError, ValueError):
        raise OptionError("the layout has mirrored markers but no sagittal_plane; "
                          "re-run mocaptk cluster") from None


def build_rig(layout: Layout, session: Trajectories, *, mesh: SurfaceMesh | None = None,
              landmarks: dict[str, int] | None = None, options: RigOptions = RigOptions(),
              progress: Callable[[str], None] | None = None,
              neutral: np.ndarray | None = None, check: bool = True) -> RigBuild:
    """Skinned rig of ``layout`` on ``mesh`` (default: the dense marker surface).

    ``session`` must be the (stabilized) session the layout was computed on; ``neutral`` its
    neutral pose (markers, 3) mm when the caller has it. ``landmarks`` maps marker labels to
    vertex indices of ``mesh`` for its alignment. ``check=False`` leaves the skinning check out
    (NaN; :func:`with_check` adds it later, e.g. computed beside other work).
    """
    say = progress or (lambda _: None)
    cloud = dense_cloud(layout, session, neutral=neutral)
    reps = [c.representative for c in layout.clusters]
    rep_idx = cloud.index(reps)
    members = [cloud.index(m) for m in influence_members(layout.clusters)]
    spacing = marker_spacing(cloud.neutral)
    alignment = None
    cut = np.zeros((0, 2), dtype=np.int64)  # marker pairs across an opening (default mesh)
    eye_cut = None  # eye apertures cut from the fitted face template (default mesh)
    chart_kind = None  # what the default mesh was triangulated in
    texcoords = None
    check_surface(options.surface)
    face = None
    lip_cut = None  # the lip line cut on a user's mesh
    mesh_lid_set = ()  # the eyes' lids found on a user's mesh
    mouth_corners = None  # vertices where the mouth's rims meet (default face, cut user mesh)
    opened = None  # a user's mesh with its openings
    if mesh is None and options.surface == "face":
        say("fitting the face")
        face = default_face(cloud.neutral, spacing=spacing, plane=_rig_plane(layout, cloud),
                            parts=options.face_parts)
    if face is not None:
        vertices, faces, texcoords = face.vertices, face.faces, face.uv
        mouth_corners = np.array([face.upper_lip[0], face.upper_lip[-1]])
        dense_vertices, _ = face_anchors(face, cloud.neutral, _follows_jaw(layout, cloud, members))
        dense_vertices[rep_idx] = distinct_vertices(face.fitted, cloud.neutral[rep_idx],
                                                    dense_vertices[rep_idx])
        mesh_kind = "face"
    elif mesh is None:
        say("triangulating the marker surface")
        # coincident markers (a duplicated label, a mislabel) share one vertex
        unique, first, dense_vertices = np.unique(cloud.neutral, axis=0, return_index=True,
                                                  return_inverse=True)
        order = np.argsort(first)  # keep the markers' order for the vertices
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        template = fit_template(unique[order], spacing=spacing)
        vertex_mirror = _vertex_mirror(layout, cloud, unique[order], spacing)  # chart and eye cut
        chart = None if template is None else template.chart(unique[order], mirror=vertex_mirror)
        vertices, faces = marker_surface_mesh(unique[order], chart=chart,
                                              max_notch_deg=RIM_NOTCH_DEG)
        chart_kind = "sphere" if chart is None else "ICT-FaceKit face fitted to the markers"
        firsts = first[order]
        faces, cut = cut_openings(faces, cloud.trajectories, cloud.neutral[firsts], columns=firsts)
        cut = firsts[cut]
        say("opening the eyes")
        eyes = template_eye_loops(template) if template is not None else []
        if eyes:
            before = len(faces)
            faces = cut_eye_openings(vertices, faces, eyes, depth_mm=2.0 * spacing,
                                     vertex_mirror=vertex_mirror)
            eye_cut = {"method": "ICT-FaceKit face fitted to the markers",
                       "openings": len(eyes), "triangles_removed": before - len(faces)}
        vertices, faces = _subdivide(vertices, faces, options.subdivisions)
        dense_vertices = rank[np.ravel(dense_vertices)].astype(np.int64)
        mesh_kind = "marker surface"
    else:
        say("aligning the mesh")
        pairs = None
        corners = {k: v for k, v in (landmarks or {}).items() if k in CORNERS}
        markers = {k: v for k, v in (landmarks or {}).items() if k not in CORNERS}
        if markers:
            pairs = {int(cloud.index([label])[0]): int(v) for label, v in markers.items()}
        alignment = align_mesh_to_markers(mesh.vertices, mesh.faces, cloud.neutral,
                                          landmarks=pairs)
        say("cutting the mouth and eye openings")
        template = fit_template(cloud.neutral, spacing=spacing)
        opened = open_mesh(alignment.transform.apply(mesh.vertices), mesh.faces, template,
                           corners=corners)
        vertices, faces, mouth_corners = opened.vertices, opened.faces, opened.mouth_corners
        lip_cut, mesh_lid_set, eye_cut = opened.lip_cut, opened.lids, opened.eye_report
        skin = faces[:opened.skin]  # markers sit on the skin, not on a lash or a tooth
        dense_vertices, _ = anchor_vertices(vertices, skin, cloud.neutral,
                                            proximity=SurfaceProximity(vertices, skin))
        # a coarse mesh can put two layout markers on one vertex: give each its own
        dense_vertices[rep_idx] = distinct_vertices(vertices, cloud.neutral[rep_idx],
                                                    dense_vertices[rep_idx])
        mesh_kind = "user mesh"
    joint_vertices = dense_vertices[rep_idx]
    say("computing weights")
    solved_on = faces if opened is None else weighted_faces(opened)  # not across eye sockets
    graph = edge_graph(vertices, solved_on)
    regions = main_influence_regions(graph, [dense_vertices[m] for m in members])
    weights = thin_shell_weights(vertices, solved_on, joint_vertices, graph=graph, ks=options.ks,
                                 kb=options.kb)
    falloff = FALLOFF_SPACINGS * spacing if options.falloff_mm is None else float(options.falloff_mm)
    support = None  # masked thin-shell weight: small beyond the markers (ears, neck)
    if not options.pure_thin_shell:
        member_vertices = [dense_vertices[m] for m in members]
        masks = region_masks(graph, regions, len(reps), falloff_mm=falloff, members=member_vertices)
        support = masked_support(weights, masks)
        weights = shape_by_regions(weights, masks)
    if opened is not None:  # the eye sockets between their rims
        weights = fill_sockets(weights, opened)
    if face is not None:  # as solve's mesh: the face's weights continued beyond the markers
        weights = face_rows(weights, face, pinned=joint_vertices, support=support)
    elif mouth_corners is not None:
        weights = blend_corners(weights, vertices, mouth_corners, reach_mm=MOUTH_CORNER_MM,
                                pinned=joint_vertices)
    if mouth_corners is not None:  # around the mouth corners, one set of joints: no step where
        # they change (a --mesh too: the ICT-FaceKit head below its corners 2.68x -> 2.50x)
        weights = corner_joints(weights, vertices, mouth_corners, inner_mm=CORNER_JOINTS_MM[0],
                                outer_mm=CORNER_JOINTS_MM[1], count=options.max_influences,
                                pinned=joint_vertices, pin_fade_mm=CORNER_PIN_FADE_MM,
                                others_fade_mm=CORNER_LEFT_OUT_FADE_MM)
    # (V, J, 3) differences squared in place: one such temporary, not three (V 37,149 x J 458 at 10k)
    nearest = np.argmin(vector_lengths(vertices[:, None] - vertices[joint_vertices][None]), axis=1)
    mirror = _weight_mirror(layout, cloud, vertices, spacing,
                            vertex=None if face is None else face.mirror)
    joint_positions = cloud.neutral[rep_idx]
    labels, sides = list(reps), [c.side for c in layout.clusters]
    regions_of = [c.region for c in layout.clusters]
    lids = None
    lid_rows = False  # the lids' vertices are capped continuously (their edges are tiny)
    eye_lids = face.lids if face is not None else mesh_lid_set
    if eye_lids and options.max_influences > 1:
        lids, weights = lid_joints(vertices, eye_lids, weights, joint_vertices=joint_vertices,
                                   displacement=cloud.trajectories[:, rep_idx]
                                   - cloud.neutral[rep_idx])
        joint_positions = np.vstack([joint_positions, lids.positions])
        labels += [LID_JOINT] * len(eye_lids)
        sides += ["R", "L"] if len(eye_lids) == 2 else ["C"] * len(eye_lids)
        regions_of += ["eye"] * len(eye_lids)
        lid_rows = weights[:, len(reps):].any(axis=1)
        corners = [c for lid in eye_lids for c in (lid.upper[0], lid.upper[-1])]
        weights = blend_corners(weights, vertices, corners, pinned=joint_vertices,
                                reach_mm=EYE_CORNER_MM if opened is None else opened.eye_corner_mm)
        if mirror is not None:  # the right eye's lid is the left's mirror image
            n = len(reps)
            lid_mirror = np.arange(n, n + len(eye_lids))[::-1 if len(eye_lids) == 2 else 1]
            mirror = (mirror[0], np.concatenate([mirror[1], lid_mirror]))
    if opened is not None:  # teeth, eyeballs, lashes: with the head, the jaw or the lids
        weights = _part_weights(weights, opened, layout, cloud, rep_idx, template, options, spacing)
    if face is not None and face.parts is not None:  # the default face's eyeballs and mouth
        (vertices, faces, texcoords, weights, nearest, lid_rows,
         mirror) = _with_face_parts(face, weights, nearest, lid_rows, mirror,
                                    _face_part_rows(weights, layout, cloud, rep_idx, options),
                                    joint_positions)
        regions = np.concatenate([regions, np.full(len(vertices) - len(regions), -1)])  # no joint's
    if mirror is not None:
        weights = symmetric_weights(weights, *mirror)
        nearest = np.where(mirror[0] < np.arange(len(nearest)), mirror[1][nearest[mirror[0]]],
                           nearest)
    if opened is not None and mouth_corners is not None:
        from scipy.spatial import cKDTree

        near = cKDTree(vertices[mouth_corners]).query(vertices)[0] < MESH_CORNER_CONTINUOUS_MM
        lid_rows = np.asarray(lid_rows, bool) | (near & np.isin(np.arange(len(vertices)),
                                                                 faces[:opened.skin]))
    index, value = cap_weights(weights, max_influences=options.max_influences,
                               min_weight=options.min_weight, fallback=nearest, mirror=mirror,
                               continuous=lid_rows)
    rig = Rig.from_markers(vertices, faces, marker_labels=labels, marker_positions=joint_positions,
                           marker_sides=sides, marker_regions=regions_of,
                           weight_index=index, weight_value=value, texcoords=texcoords,
                           materials=_materials(face, opened, vertices, faces))
    quality = mesh_quality(vertices, faces)
    report = {
        "mesh": {"kind": mesh_kind, "vertices": len(vertices), "triangles": len(faces),
                 "min_angle_deg": quality.min_angle_deg, "boundary_loops": quality.boundary_loops,
                 "subdivisions": options.subdivisions if mesh_kind == "marker surface" else 0,
                 "chart": chart_kind,
                 "opening_edges_cut": ([[cloud.labels[a], cloud.labels[b]] for a, b in cut]
                                       if lip_cut is None else lip_cut.edges.tolist()),
                 "eye_openings": eye_cut},
        "alignment": None if alignment is None else {
            "method": alignment.method, "scale": alignment.transform.scale,
            "rms_residual_mm": alignment.rms_mm, "max_residual_mm": alignment.max_mm},
        "weights": {"method": "thin-shell" if options.pure_thin_shell else
                    "thin-shell shaped by influence regions",
                    "falloff_mm": None if options.pure_thin_shell else falloff,
                    "ks": options.ks, "kb": options.kb, "max_influences": options.max_influences,
                    "mirror_symmetric": mirror is not None,
                    "min_weight": options.min_weight},
        "joints": len(reps), "dense_markers": int(cloud.captured.sum()),
        "mirrored_dense_markers": int((~cloud.captured).sum()),
        "marker_spacing_mm": spacing,
        "frame_rotation": cloud.rotation,
        "skinning_check": None,  # its place in rig_report.json; filled by with_check
    }
    build = RigBuild(rig, layout, cloud, regions, dense_vertices, joint_vertices, alignment,
                     SkinningError(float("nan"), float("nan"), float("nan"), 0, 0), report, lids)
    if not check:
        return build
    say("checking by animation")
    return with_check(build, *skinning_check(build))


def _part_weights(weights: np.ndarray, opened: OpenedMesh, layout: Layout, cloud: DenseCloud,
                  rep_idx: np.ndarray, template: FittedTemplate | None, options: RigOptions,
                  spacing: float) -> np.ndarray:
    """A user mesh's skin beyond the markers and its parts other than the skin
    (:func:`~mocaptk.retarget.mesh_openings.parts_follow`): the head's row is the layout joint
    that moves least in the session (:func:`_least_moving`), the jaw's the (up to
    ``max_influences``) lowest jaw joints."""
    return parts_follow(weights, opened, cloud.neutral, head=_least_moving(cloud, rep_idx),
                        regions=[c.region for c in layout.clusters], positions=cloud.neutral[rep_idx],
                        jaw_count=options.max_influences, spacing=spacing, template=template)


def _least_moving(cloud: DenseCloud, rep_idx: np.ndarray) -> int:
    """The layout joint (index into ``rep_idx``) that moves least in the session: the parts' head."""
    bind = cloud.neutral[rep_idx]
    moved = np.nanmax(np.linalg.norm(cloud.trajectories[:, rep_idx] - bind, axis=2), axis=0)
    return int(np.argmin(np.nan_to_num(moved, nan=np.inf)))


def _face_part_rows(weights: np.ndarray, layout: Layout, cloud: DenseCloud, rep_idx: np.ndarray,
                    options: RigOptions) -> tuple[np.ndarray, np.ndarray]:
    """The default face's parts' head and jaw rows (J,) over the columns of ``weights`` (the
    layout's joints, then the lids', which get nothing), as a user mesh's parts get them
    (:func:`~mocaptk.retarget.mesh_parts.head_jaw_rows`)."""
    head, jaw = head_jaw_rows(_least_moving(cloud, rep_idx), [c.region for c in layout.clusters],
                              cloud.neutral[rep_idx], count=options.max_influences)
    extra = np.zeros(weights.shape[1] - len(rep_idx))
    return np.concatenate([head, extra]), np.concatenate([jaw, extra])


def _with_face_parts(face: DefaultFace, weights: np.ndarray, nearest: np.ndarray, lid_rows: Any,
                     mirror: tuple[np.ndarray, np.ndarray] | None,
                     rows: tuple[np.ndarray, np.ndarray], joint_positions: np.ndarray) -> tuple:
    """The default face's mesh with its eyeballs and mouth interior after its skin
    (:mod:`~mocaptk.retarget.face_parts`): ``(vertices, faces, texcoords, weights, nearest,
    lid_rows, mirror)`` each extended over the parts' vertices. They move as a user mesh's
    parts (:func:`~mocaptk.retarget.mesh_parts.part_weights`, ``rows`` the head's and the
    jaw's), the socket with the lips where it meets them (:func:`~mocaptk.retarget.face_parts.socket_rows`)."""
    parts, count = face.parts, len(face.vertices)
    vertices = np.vstack([face.vertices, parts.vertices])
    faces = np.vstack([face.faces, parts.faces + count])
    weights = np.vstack([weights, np.zeros((len(parts.vertices), weights.shape[1]))])
    weights = part_weights(weights, vertices, faces, len(face.faces), head=rows[0], jaw=rows[1],
                           mouth_y=float(face.vertices[face.upper_lip, 1].mean()),
                           nose_y=nose_height(vertices, faces, len(face.faces)))
    weights = socket_rows(weights, parts, count)
    near = np.argmin(np.linalg.norm(parts.vertices[:, None] - joint_positions[None], axis=2), axis=1)
    # the socket is blended from several rows: capped continuously; its lip vertices as their lip
    continuous = np.concatenate([np.broadcast_to(lid_rows, count), template_parts()[4] < 0])
    on = np.flatnonzero(parts.attach >= 0)
    continuous[count + on] = continuous[parts.attach[on]]
    nearest = np.concatenate([nearest, near])
    nearest[count + on] = nearest[parts.attach[on]]
    if mirror is not None and parts.mirror is not None:
        mirror = (np.concatenate([mirror[0], count + parts.mirror]), mirror[1])
    return (vertices, faces, np.vstack([face.uv, np.full((len(parts.vertices), 2), 0.5)]), weights,
            nearest, continuous, mirror)


def _materials(face: DefaultFace | None, opened: OpenedMesh | None, vertices: np.ndarray,
               faces: np.ndarray) -> np.ndarray | None:
    """Each triangle's material (:mod:`~mocaptk.retarget.face_materials`): the default face's
    skin and parts' own, a user mesh's by its parts' kinds; None (all skin) otherwise."""
    if face is not None and face.parts is not None:
        return np.concatenate([np.zeros(len(face.faces), np.int64), face.parts.material])
    if opened is not None:
        return mesh_materials(vertices, faces, opened.skin)
    return None


def with_check(build: RigBuild, check: SkinningError, by_region: dict[str, Any]) -> RigBuild:
    """``build`` with the :func:`skinning_check` result ``(check, by_region)`` in its ``check``
    and report (the report's other keys as they are now, in their order)."""
    report = {**build.report, "skinning_check": {**check.as_dict(), **by_region}}
    return replace(build, check=check, report=report)


def marker_driven_error(build: RigBuild, cloud: DenseCloud | None = None, *,
                        truth: np.ndarray | None = None) -> SkinningError:
    """Drive the rig with its markers' trajectories; error at the captured dense markers (mm).

    ``cloud``: the markers that drive the rig (default: the build's own session, else e.g. a
    held-out performance, see :func:`ground_truth_error`); displacements are taken from the
    bind (neutral) pose of the build. ``truth`` (F, N_captured, 3) mm, rig frame, replaces the
    compared positions (default: the cloud's own captured markers). Frames where a layout
    marker is missing are skipped. A dense marker's prediction is its bind position moved by
    its vertex's skinned displacement.
    """
    return distance_error(_marker_distances(build, cloud, truth)[0])


def skinning_check(build: RigBuild, cloud: DenseCloud | None = None
                   ) -> tuple[SkinningError, dict[str, Any]]:
    """The marker-driven check of :func:`marker_driven_error`, overall and per region with its
    worst case, from one skinning pass over the frames.

    Returns the overall :class:`SkinningError` and
    ``{"regions": {region: {"rmse_mm", "max_mm", "markers"}}, "worst_markers": [...]`` (the 5 dense
    markers with the largest RMSE: label, region, rmse, max, frame of the max)
    ``, "max": {"marker", "region", "frame", "error_mm", "layout_distance_mm"}}``: where the
    largest error happens, and how far that marker is from the nearest layout marker.
    """
    cloud = build.cloud if cloud is None else cloud
    dist, labels, frames = _marker_distances(build, cloud, None)  # (F_used, N)
    # a marker's own region (as cluster's table counts it), not that of the layout marker it follows
    region_of = {m: c.region for c in build.layout.clusters for m in c.members}
    region_of.update({m: r.name for r in build.layout.regions for m in r.markers})
    names = [region_of.get(label, "") for label in labels]
    regions = {}
    for region in sorted(set(names)):
        cols = [i for i, n in enumerate(names) if n == region]
        d = dist[:, cols]
        ok = np.isfinite(d)
        if ok.any():
            regions[region or "none"] = {"rmse_mm": float(np.sqrt(np.mean(d[ok] ** 2))),
                                         "max_mm": float(d[ok].max()), "markers": len(cols)}
    with np.errstate(invalid="ignore"):
        per_marker = np.sqrt(np.nanmean(dist ** 2, axis=0))
    filled = np.where(np.isfinite(dist), dist, -1.0)
    worst = []
    for i in np.argsort(-np.nan_to_num(per_marker, nan=-1.0))[:5]:
        row = int(np.argmax(filled[:, i]))
        worst.append({"marker": labels[i], "region": names[i], "rmse_mm": float(per_marker[i]),
                      "max_mm": float(filled[row, i]), "frame": int(frames[row])})
    row, col = np.unravel_index(int(np.argmax(filled)), filled.shape)
    layout_positions = build.cloud.neutral[build.cloud.index(build.layout.labels)]
    marker_neutral = build.cloud.neutral[build.cloud.index([labels[col]])][0]
    summary = {"regions": regions, "worst_markers": worst,
               "max": {"marker": labels[col], "region": names[col], "frame": int(frames[row]),
                       "error_mm": float(filled[row, col]),
                       "layout_distance_mm": float(np.linalg.norm(layout_positions - marker_neutral,
                                                                  axis=1).min())}}
    return distance_error(dist), summary


#: Frames per block of :func:`_marker_distances` (its skinned and true positions stay a few MB).
CHECK_BLOCK_FRAMES = 1024


def _marker_distances(build: RigBuild, cloud: DenseCloud | None, truth: np.ndarray | None
                      ) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Distances (F_used, N) mm between the skinned (predicted) and true positions of the
    captured dense markers, their labels (N,) and the frames used (F_used,) (frames with every
    layout marker seen); block by block of frames, no (F, N, 3) temporaries."""
    cloud = build.cloud if cloud is None else cloud
    rig = build.rig
    captured = np.flatnonzero(cloud.captured)
    labels = [cloud.labels[i] for i in captured]
    bind_joints = build.cloud.neutral[build.cloud.index(build.layout.labels)]
    bind_dense = build.cloud.index(labels)
    joint_columns = cloud.index(build.layout.labels)
    rows = build.dense_vertices[bind_dense]
    rest = np.asarray(rig.vertices)[rows]
    offset = build.cloud.neutral[bind_dense] - rest
    weight_index, weight_value = rig.weight_index[rows], rig.weight_value[rows]
    distances, used = [], []
    for start in range(0, cloud.trajectories.shape[0], CHECK_BLOCK_FRAMES):
        block = cloud.trajectories[start:start + CHECK_BLOCK_FRAMES]
        # np.take, not x[:, index] / x[mask]: the same values, 2-4x faster gathers
        joints = np.take(block, joint_columns, axis=1)
        joints -= bind_joints
        frames = np.flatnonzero(np.isfinite(joints).all(axis=(1, 2)))
        disp = np.zeros((frames.size, rig.joint_count, 3))
        disp[:, 1:] = build.joint_displacements(np.take(joints, frames, axis=0))  # 0: the root
        predicted = skin_vertices(rest, weight_index, weight_value, disp)
        predicted += offset[None]
        target = (np.take(block, captured, axis=1) if truth is None
                  else np.asarray(truth)[start:start + len(block)])
        predicted -= np.take(target, frames, axis=0)
        distances.append(vector_lengths(predicted))
        used.append(start + frames)
    return (np.concatenate(distances) if distances else np.zeros((0, len(labels))), labels,
            np.concatenate(used) if used else np.zeros(0, dtype=np.int64))


def ground_truth_error(build: RigBuild, session: Trajectories, truth_positions: np.ndarray,
                       truth_labels: Sequence[str]) -> SkinningError:
    """Skinning error of ``session``'s layout markers driving the rig, against noise-free
    ``truth_positions`` (F, M, 3) mm (session frame) of the dense markers ``truth_labels``."""
    cloud = dense_cloud(build.layout, session, rotation=build.cloud.rotation)
    lookup = {label: i for i, label in enumerate(truth_labels)}
    captured = [cloud.labels[i] for i in np.flatnonzero(cloud.captured)]
    missing = [label for label in captured if label not in lookup]
    if missing:
        raise OptionError(f"ground truth lacks markers: {', '.join(missing[:6])}")
    truth = np.asarray(truth_positions, float)[:, [lookup[label] for label in captured]]
    return marker_driven_error(build, cloud, truth=truth @ build.cloud.rotation.T)


def mesh_ground_truth_error(build: RigBuild, session: Trajectories,
                            truth_vertices: np.ndarray) -> SkinningError:
    """Skinning error over every mesh vertex against true vertex positions.

    ``truth_vertices`` (F, V, 3) mm in the session frame, vertex i = rig mesh vertex i (e.g. the
    ICT-FaceKit face deformed by the synthetic session's blendshape weights, with the rig built
    on that face via ``--mesh``); the rig is driven by ``session``'s layout markers.
    """
    cloud = dense_cloud(build.layout, session, rotation=build.cloud.rotation)
    rig = build.rig
    bind = build.cloud.neutral[build.cloud.index(build.layout.labels)]
    joints = cloud.trajectories[:, cloud.index(build.layout.labels)] - bind
    usable = np.isfinite(joints).all(axis=(1, 2))
    disp = np.zeros((int(usable.sum()), rig.joint_count, 3))
    disp[:, 1:] = build.joint_displacements(joints[usable])
    predicted = skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)
    truth = np.asarray(truth_vertices, float)[usable] @ build.cloud.rotation.T
    if truth.shape != predicted.shape:
        raise OptionError(f"truth has {truth.shape[1]} vertices, the rig mesh {rig.vertex_count}")
    return skinning_error(predicted, truth)


def _subdivide(vertices: np.ndarray, faces: np.ndarray, times: int) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint subdivision ``times`` times; the original vertices keep their indices."""
    import trimesh.remesh

    for _ in range(max(0, times)):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64)


def influence_members(clusters: Sequence[Cluster]) -> list[tuple[str, ...]]:
    """Each cluster's dense markers as the rig uses them: a mirrored cluster has the mirror
    images of all its source's members, the midline ones too (the layout file keeps a midline
    marker in its source cluster only, so the twins' regions and weights would differ)."""
    source = {c.representative: c for c in clusters}
    return [tuple(mirror_label(m) if side_tag(m) in ("L", "R") else m
                  for m in source[c.mirrored_from].members)
            if c.mirrored_from in source else c.members for c in clusters]


#: A nose tip lies between these fractions of the face's height (rig frame: lowest marker 0, highest 1).
NOSE_HEIGHT = (0.35, 0.8)


def guide_reference(neutral: np.ndarray) -> tuple[np.ndarray, str]:
    """The guide's reference point (3,) mm and its name, from the dense neutral ``(M, 3)`` mm in
    the rig frame: the most forward marker, the "nose tip" when it lies at a nose's height
    (:data:`NOSE_HEIGHT`; the sample: 0.48), else the "front marker" (blenderFace has no nose
    marker: its most forward one is on the upper lip, at 0.24)."""
    tip = neutral[int(np.argmax(neutral[:, 2]))]
    height = (tip[1] - neutral[:, 1].min()) / max(float(np.ptp(neutral[:, 1])), 1e-9)
    return tip, ("nose tip" if NOSE_HEIGHT[0] <= height <= NOSE_HEIGHT[1] else "front marker")


def guide_rows(build: RigBuild) -> list[GuideMarker]:
    """Guide table rows of a built rig (numbers = layout order); a mirrored marker replaces its
    :func:`influence_members`."""
    clusters = build.layout.clusters
    members = influence_members(clusters)
    nose, _ = guide_reference(build.cloud.neutral)
    stabilization = build.layout.extra.get("stabilization") or {}
    reference = stabilization.get("reference")
    heads = [(label, side_tag(label) or "C", np.asarray(pos, float)) for label, pos in
             zip(stabilization.get("rigid_labels") or (), () if reference is None else reference)]
    return guide_markers([c.representative for c in clusters], [c.region for c in clusters],
                         [c.side for c in clusters],
                         np.asarray(build.rig.joint_positions)[build.marker_joints],
                         members, nose, mirrored_from=[c.mirrored_from for c in clusters],
                         stabilization=heads)


def write_rig_outputs(layout: Layout, session: Trajectories, out_dir: str | os.PathLike[str], *,
                      mesh_path: str | os.PathLike[str] | None = None,
                      landmarks: dict[str, int] | None = None,
                      options: RigOptions = RigOptions(), formats: Sequence[str] = FORMATS,
                      title: str = "", force: bool = False, captures: Sequence[Capture] = (),
                      progress: Callable[[str], None] | None = None,
                      neutral: np.ndarray | None = None,
                      keep_mesh_space: bool = False) -> tuple[RigBuild, dict[str, Path]]:
    """Build the rig and write ``rig.json``/``rig.fbx``/``rig.glb`` (as ``formats`` asks),
    ``guide.pdf``, ``guide_front.png``, ``guide_profile.png`` and ``rig_report.json`` into
    ``out_dir``. Existing files are refused unless ``force``.

    ``captures`` are baked onto the rig one after the other (their takes become clips) and
    keyed into every rig file (rig.json: ``rig_animation.npz``); the report's ``animation``
    lists the takes and every filled gap. ``neutral``: the session's neutral pose, if known.
    ``keep_mesh_space``: the rig files in ``mesh_path``'s own coordinates (read as mm), the
    motion scaled to it (:mod:`~mocaptk.retarget.mesh_space`); the guide stays on the actor."""
    from mocaptk.atomic import check_writable

    from .export_fbx import write_rig_fbx
    from .export_glb import write_rig_glb
    from .export_json import write_rig_json
    from .mesh_io import load_mesh

    if keep_mesh_space and mesh_path is None:
        raise OptionError("--keep-mesh-space needs --mesh (the default face has no space of its own)")
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        raise OptionError(f"unknown rig format(s) {', '.join(unknown)} (choose from json, fbx, glb)")
    out = Path(out_dir)
    names = {f: out / f"rig.{f}" for f in formats}
    if captures and "json" in formats:
        names["animation"] = out / "rig_animation.npz"
    names.update(guide=out / "guide.pdf", front=out / "guide_front.png",
                 profile=out / "guide_profile.png", report=out / "rig_report.json")
    if captures:
        names.update({f"render_{pose}_{view}": out / "renders" / f"{pose}_{view}.png"
                      for pose in ("rest", "jaw_open") for view in ("front", "profile")})
    for target in names.values():
        check_writable(target, force=force)
    mesh = load_mesh(mesh_path) if mesh_path is not None else None
    build = build_rig(layout, session, mesh=mesh, landmarks=landmarks, options=options,
                      progress=progress, neutral=neutral, check=False)
    say = progress or (lambda _: None)
    animation = None
    say("checking by animation" + (" and baking the animation" if captures else ""))
    # the check in a second process while the animation is baked: the same numbers, less waiting
    with beside(lambda: skinning_check(build), what="the skinning check") as checked:
        if captures:
            animation = concatenate_animations([bake_capture(build, c) for c in captures])
            build.report["animation"] = animation.report()
            held_out = [held_out_check(build, c) for c in captures[1:]]
            build.report["held_out"] = [h for h in held_out if h is not None]
    build = with_check(build, *checked.value)
    hierarchy = file_hierarchy(build)
    build.report["hierarchy"] = hierarchy.report()
    keyed = None if animation is None else hierarchical_animation(hierarchy, animation)
    if keep_mesh_space and build.alignment is not None:  # the given mesh's own size and place
        back = inverse(build.alignment.transform)
        hierarchy = replace(hierarchy, rig=rig_in_space(hierarchy.rig, back))
        keyed = None if keyed is None else animation_in_space(keyed, back)
        build.report["mesh_space"] = {"kept": True, "motion_scale": back.scale}
    writers = {"json": write_rig_json, "fbx": write_rig_fbx, "glb": write_rig_glb}

    def write_rig_files() -> None:
        for fmt in formats:
            writers[fmt](hierarchy.rig, names[fmt], animation=keyed, force=True)

    say(f"writing {', '.join(f'rig.{fmt}' for fmt in formats)} and rendering the guide")
    with beside(write_rig_files if formats else None, what="the rig files"):  # a process each
        _write_guide(build, names, animation, captures, options=options, title=title, say=say)
    return build, names


def _write_guide(build: RigBuild, names: dict[str, Path], animation: RigAnimation | None,
                 captures: Sequence[Capture], *, options: RigOptions, title: str,
                 say: Callable[[str], None]) -> None:
    """The renders, ``guide.pdf`` and ``rig_report.json`` of :func:`write_rig_outputs`."""
    from mocaptk.atomic import write_bytes
    from mocaptk.jsonio import write_json

    from .renders import render_view

    clusters = build.layout.clusters
    joints = np.asarray(build.rig.joint_positions)[build.marker_joints]
    rows = guide_rows(build)
    numbers = [row.name for row in rows]  # the guide's names (16L / 16R) in every view
    for view in ("front", "profile"):
        render_view(build.rig.vertices, build.rig.faces, build.regions,
                    [c.region for c in clusters], joints, numbers, names[view], view=view)
    if animation is not None:
        say("rendering the rig at rest and with the jaw open")
        frame = jaw_open_frame(build, animation, start=animation.frame_count
                               - captures[-1].relative.n_frames)
        build.report["renders"] = {"jaw_open_frame": frame,
                                   "jaw_open_take": next(t.name for t in animation.takes
                                                         if t.start <= frame < t.end)}
        posed_joints = animation.translations[frame, 1:] + build.rig.joint_positions[0]
        posed = skin_vertices(build.rig.vertices, build.rig.weight_index, build.rig.weight_value,
                              np.vstack([np.zeros(3), posed_joints
                                         - build.rig.joint_positions[1:]])[None])[0]
        posed_joints = posed_joints[:len(clusters)]
        for view in ("front", "profile"):  # at rest: the guide's view, the same picture
            write_bytes(names[f"render_rest_{view}"], names[view].read_bytes(), force=True)
            render_view(posed, build.rig.faces, build.regions, [c.region for c in clusters],
                        posed_joints, numbers, names[f"render_jaw_open_{view}"], view=view)
    check = build.check
    notes = [f"{len(clusters)} markers; mesh: {build.report['mesh']['kind']} "
             f"({build.rig.vertex_count} vertices); weights: {build.report['weights']['method']}, "
             f"max {options.max_influences} influences",
             f"marker-driven skinning check on the session: RMSE {check.rmse_mm:.2f} mm, "
             f"95th percentile {check.p95_mm:.2f} mm over {check.vertices} dense markers"]
    if build.alignment is not None:
        notes.append(f"mesh alignment ({build.alignment.method}): residual RMS "
                     f"{build.alignment.rms_mm:.2f} mm, max {build.alignment.max_mm:.2f} mm")
    write_guide_pdf(names["guide"], rows, front_png=names["front"],
                    profile_png=names["profile"], outline=build.cloud.neutral,
                    title=title or "mocaptk marker placement guide", notes=notes,
                    landmark=guide_reference(build.cloud.neutral)[1], force=True)
    write_json(names["report"], {"format": "mocaptk.rig_report", "version": 1, **build.report},
               force=True)
