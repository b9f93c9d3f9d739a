"""The animated mesh of ``mocaptk solve``: a sparse linear map from dense markers to mesh vertices.

The default face (:meth:`MeshMap.face`: the ICT-FaceKit face fitted to the dense neutral, lips
closed with a seam, lids that close on a blink, the whole face for a half-face session); the
marker surface through the dense neutral (vertices = dense markers), optionally
midpoint-subdivided; a given mesh following the markers by thin-shell weights; or a map learned
from training frames of the mesh itself.

Half-face sessions: the map's extra columns are the seen dense markers reflected across the
sagittal plane (:class:`Mirror`), so the uncaptured half moves as the mirror image. Blinks: the
lid's full-blink shape is added in proportion to the blink its sensor markers show
(:class:`Blink`), less what the linear map already makes of those markers' motion, so a pure
blink gives exactly the lid's shape.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from mocaptk.acquisition.stabilize import in_head_frame
from mocaptk.clustering.neutral import neutral_pose
from mocaptk.clustering.reconstruction_models import DEFAULT_RIDGE, batched_ridge
from mocaptk.errors import OptionError
from mocaptk.surface_mesh import marker_surface_mesh

from .align import Alignment, SurfaceProximity, align_mesh_to_markers
from .face_template import FittedTemplate
from .influence import anchor_vertices
from .mesh_openings import OpenedMesh

__all__ = ["Blink", "MeshMap", "Mirror"]

#: Dense markers each vertex of a learned mesh map is regressed from (:meth:`MeshMap.learned`).
MESH_NEIGHBOURS = 8
#: A dense marker farther than this from a user's aligned mesh is not pinned to it (mm).
ANCHOR_REACH_MM = 5.0


@dataclass(frozen=True, eq=False)
class Mirror:
    """Extra dense columns: the markers ``source`` (K,) reflected across the plane through
    ``point`` (3,) mm with unit ``normal`` (3,) (head-relative session frame)."""

    source: np.ndarray
    point: np.ndarray
    normal: np.ndarray

    def extend(self, dense: np.ndarray) -> np.ndarray:
        """``dense`` (f, M, 3) mm with the reflected columns appended: (f, M + K, 3)."""
        image = np.take(dense, self.source, axis=1)
        image = image - 2.0 * ((image - self.point) @ self.normal)[..., None] * self.normal
        return np.concatenate([dense, image], axis=1)


@dataclass(frozen=True, eq=False)
class Blink:
    """One eye: ``sensors`` (S,) dense columns, their ``rest`` (S, 3) mm and ``full`` (S, 3) mm
    displacement at a full blink, and ``shape`` (V, 3) mm added to the mesh at a full blink."""

    sensors: np.ndarray
    rest: np.ndarray
    full: np.ndarray
    shape: np.ndarray

    def amount(self, dense: np.ndarray) -> np.ndarray:
        """The blink (f,) in [0, 1]: the least-squares fraction of ``full`` the sensors show."""
        moved = np.nan_to_num(np.take(dense, self.sensors, axis=1) - self.rest)
        return np.clip(np.einsum("fsk,sk->f", moved, self.full) / float(np.sum(self.full ** 2)),
                       0.0, 1.0)


@dataclass(frozen=True)
class MeshMap:
    """The animated mesh: ``vertices`` (V, 3) mm neutral, ``faces`` (T, 3), ``matrix`` the linear
    map and ``offset`` (V, 3) mm: vertex positions = matrix @ dense markers + offset (unseen dense
    markers have no column weight); ``uv`` (V, 2) texture coordinates when the mesh has them,
    ``mirror`` the reflected columns of a half-face session, ``blinks`` the lids' shapes,
    ``materials`` (T,) each triangle's (:mod:`~mocaptk.retarget.face_materials`; None: all skin). ``matrix`` is (V, M) dense float32 when x, y and z share the
    weights (one GEMM per chunk: ~15x a sparse product of the same map), else (3V, 3M) sparse on
    the flattened coordinates (x, y, z per point)."""

    vertices: np.ndarray
    faces: np.ndarray
    matrix: np.ndarray | sp.csr_matrix
    offset: np.ndarray | None = None
    uv: np.ndarray | None = None
    mirror: Mirror | None = None
    blinks: tuple[Blink, ...] = ()
    materials: np.ndarray | None = None

    @classmethod
    def face(cls, neutral: np.ndarray, *, plane: tuple[np.ndarray, np.ndarray] | None = None,
             mirrored: bool = False, jaw_following: np.ndarray | None = None, head: int | None = None,
             regions: Sequence[str] | None = None) -> MeshMap | None:
        """The default face (:mod:`~mocaptk.retarget.default_face`) fitted to the dense neutral
        ``neutral`` (M, 3) mm (NaN = unseen; head-relative session frame), following the dense
        markers pinned to it (:meth:`anchored`) with the rig's fixes
        (:mod:`~mocaptk.retarget.face_weights`: ``jaw_following`` (M,) bool puts each lip marker
        on its own lip), or None where the template does not fit.

        ``plane`` ``(point, unit normal)``: the sagittal plane (the subject's left); with
        ``mirrored`` (a half-face session) the face is completed by the markers' mirror images.
        With ``head`` (the dense marker that moves least) and ``regions`` (M,) (each dense
        marker's) the face has its eyeballs and mouth interior, moving as the rig's
        (:meth:`_with_face_parts`); else the skin alone.
        """
        from mocaptk.surface_mesh import marker_spacing

        from .build import FALLOFF_SPACINGS, rig_frame_rotation
        from .default_face import LID_REACH_MM, SOLVE_LID_REACH_MM, default_face
        from .face_weights import face_anchors, face_rows
        from .influence import edge_graph, main_influence_regions
        from .weights import masked_support, region_masks

        neutral = np.asarray(neutral, dtype=np.float64)
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        mirror = None
        if mirrored:
            if plane is None:
                raise OptionError("a mirrored layout needs its sagittal_plane; re-run mocaptk cluster")
            normal = np.asarray(plane[1], float) / np.linalg.norm(plane[1])
            mirror = Mirror(seen, np.asarray(plane[0], float), normal)
        columns = neutral if mirror is None else mirror.extend(neutral[None])[0]
        used = seen if mirror is None else np.concatenate([seen, len(neutral) + np.arange(seen.size)])
        rotation = rig_frame_rotation(neutral[seen], np.zeros(seen.size),
                                      lateral=None if plane is None else plane[1])
        points = columns[used] @ rotation.T  # the rig frame: Y up, facing +Z
        rig_plane = None if mirror is None else (rotation @ mirror.point, rotation @ mirror.normal)
        spacing = marker_spacing(points)
        with_parts = head is not None and regions is not None and bool(np.isfinite(neutral[head]).all())
        face = default_face(points, spacing=spacing, plane=rig_plane, lid_reach_mm=LID_REACH_MM,
                            sense_reach_mm=SOLVE_LID_REACH_MM, parts=with_parts)
        if face is None:
            return None
        follows = None if jaw_following is None else np.asarray(jaw_following, bool)[used % len(neutral)]
        nearest, dist = face_anchors(face, points, follows)
        anchors = np.full(len(columns), -1, dtype=np.intp)
        close = dist <= ANCHOR_REACH_MM
        anchors[used[close]] = nearest[close]
        vertices = face.vertices @ rotation  # back to the session frame
        mesh = cls.anchored(vertices, face.faces, anchors, columns)
        pinned = np.flatnonzero(anchors >= 0)
        graph = edge_graph(face.vertices, face.faces)
        masks = region_masks(graph, main_influence_regions(graph, [[v] for v in anchors[pinned]]),
                             pinned.size, falloff_mm=FALLOFF_SPACINGS * spacing)
        matrix = face_rows(np.asarray(mesh.matrix, dtype=np.float64), face, pinned=anchors[pinned],
                           support=masked_support(np.asarray(mesh.matrix)[:, pinned], masks))
        mesh = replace(mesh, matrix=matrix)._with_openings(face.vertices, None, face.lids, anchors,
                                                           columns, rotation)
        mesh = replace(mesh, uv=face.uv, mirror=mirror)
        if face.parts is not None:
            own = [regions[m] for m in (seen if mirror is None else np.concatenate([seen, seen]))]
            mesh = mesh._with_face_parts(face, rotation, columns, used, int(head), own, points)
        return mesh

    def _with_face_parts(self, face, rotation: np.ndarray, columns: np.ndarray, used: np.ndarray,
                         head: int, regions: Sequence[str], points: np.ndarray) -> MeshMap:
        """This map of the default ``face`` with its eyeballs and mouth interior's rows after the
        skin's, as the rig weights them (:func:`~mocaptk.retarget.mesh_parts.part_weights`, the
        socket's lip vertices with their lips, :func:`~mocaptk.retarget.face_parts.socket_rows`):
        ``rotation`` session -> rig, ``columns`` (C, 3) mm as :meth:`anchored`, ``used`` (U,)
        the columns placed, ``points`` (U, 3) mm them in the rig frame, ``regions`` (U,) theirs,
        ``head`` the column that moves least."""
        from .build import RigOptions
        from .face_parts import socket_rows
        from .mesh_parts import head_jaw_rows, nose_height, part_weights

        parts, count = face.parts, len(face.vertices)
        head_row, jaw_row = head_jaw_rows(int(np.flatnonzero(used == head)[0]), regions, points,
                                          count=RigOptions().max_influences)  # as the rig's jaw row
        wide = np.zeros((2, self.matrix.shape[1]))
        wide[:, used] = head_row, jaw_row
        vertices = np.vstack([face.vertices, parts.vertices])
        faces = np.vstack([face.faces, parts.faces + count])
        matrix = np.vstack([np.asarray(self.matrix, dtype=np.float64),
                            np.zeros((len(parts.vertices), self.matrix.shape[1]))])
        matrix = part_weights(matrix, vertices, faces, len(face.faces), head=wide[0], jaw=wide[1],
                              mouth_y=float(face.vertices[face.upper_lip, 1].mean()),
                              nose_y=nose_height(vertices, faces, len(face.faces)))
        matrix = socket_rows(matrix, parts, count)
        placed = vertices @ rotation  # the session frame
        blinks = tuple(replace(b, shape=np.vstack([b.shape, np.zeros((len(parts.vertices), 3))]))
                       for b in self.blinks)
        return replace(self, vertices=placed, faces=faces, matrix=matrix.astype(np.float32),
                       offset=placed - matrix @ np.nan_to_num(columns), blinks=blinks,
                       uv=np.vstack([self.uv, np.full((len(parts.vertices), 2), 0.5)]),
                       materials=np.concatenate([np.zeros(len(face.faces), np.int64), parts.material]))

    def _with_openings(self, rig_vertices: np.ndarray, mouth: np.ndarray | None, lids: tuple,
                       anchors: np.ndarray, columns: np.ndarray, rotation: np.ndarray, *,
                       eye_corner_mm: float | None = None) -> MeshMap:
        """This map with its openings' corners blended and its lids' blinks (the default face, a
        user's opened mesh): ``rig_vertices`` (V, 3) mm its vertices in the rig frame
        (``rotation`` session -> rig), ``mouth`` (2,) the mouth's corner vertices (None: no
        mouth cut), ``lids`` the eyes' :class:`~mocaptk.retarget.default_face.Lid` (their corners
        blended within ``eye_corner_mm``, default the default face's), ``anchors`` (M,) and
        ``columns`` (M, 3) mm as :meth:`anchored` (the default face's mouth:
        :func:`~mocaptk.retarget.face_weights.face_rows`)."""
        from .default_face import EYE_CORNER_MM, MOUTH_CORNER_MM
        from .lid_joints import SENSOR_MIN_MM
        from .weights import blend_corners

        # the openings part like lenses, not cracks whose tips fold (as the rig's weights)
        matrix = self.matrix
        for corners, reach in (([] if mouth is None else list(mouth), MOUTH_CORNER_MM),
                               ([c for lid in lids for c in (lid.upper[0], lid.upper[-1])],
                                EYE_CORNER_MM if eye_corner_mm is None else eye_corner_mm)):
            if corners:
                matrix = blend_corners(matrix, rig_vertices, corners, reach_mm=reach,
                                       pinned=anchors[anchors >= 0])
        matrix = np.asarray(matrix).astype(np.float32)
        mesh = replace(self, matrix=matrix,
                       offset=self.vertices - matrix.astype(np.float64) @ np.nan_to_num(columns))
        blinks = []
        for lid in lids:
            shape = lid.blink @ rotation
            sensed = shape if lid.sensed is None else lid.sensed @ rotation
            full = np.where((anchors >= 0)[:, None], sensed[np.maximum(anchors, 0)], 0.0)
            sensors = np.flatnonzero(np.linalg.norm(full, axis=1) > SENSOR_MIN_MM)  # as the rig
            if sensors.size:
                made = mesh.matrix @ full  # what the map already makes of the sensors' blink
                blinks.append(Blink(sensors, columns[sensors], full[sensors], shape - made))
        return replace(mesh, blinks=tuple(blinks))

    @classmethod
    def marker_surface(cls, neutral: np.ndarray, *, subdivisions: int = 0) -> MeshMap:
        """The marker surface through the dense neutral ``neutral`` (M, 3) mm (NaN = unseen),
        midpoint-subdivided ``subdivisions`` times (each splits a triangle into 4)."""
        if subdivisions < 0 or subdivisions > 4:
            raise OptionError(f"--subdivisions must be 0..4, got {subdivisions}")
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        _, faces = marker_surface_mesh(neutral[seen])
        faces = np.asarray(faces, dtype=np.int64)
        matrix = sp.csr_matrix((np.ones(seen.size), (np.arange(seen.size), seen)),
                               shape=(seen.size, neutral.shape[0]))
        for _ in range(subdivisions):
            matrix, faces = _midpoint_subdivide(matrix, faces)
        return cls(matrix @ np.nan_to_num(neutral), faces, _per_axis(matrix))

    @classmethod
    def anchored(cls, vertices: np.ndarray, faces: np.ndarray, anchors: np.ndarray,
                 neutral: np.ndarray, *, min_weight: float = 1e-4) -> MeshMap:
        """A given mesh ``vertices`` (V, 3) mm, ``faces`` (T, 3) following the dense markers pinned
        at vertices ``anchors`` (M,) (-1: not pinned; neutral ``neutral`` (M, 3) mm) by
        thin-shell interpolation (Le et al.'s ``W = Â⁻¹B̂``). A vertex several markers are
        pinned to moves by their mean displacement (a coarse mesh); weights below
        ``min_weight`` are dropped (sparse, fast)."""
        from mocaptk.clustering.reconstruction_models import KB, KS, TIKHONOV
        from mocaptk.thin_shell import interpolation_weights, thin_shell_operator

        anchors = np.asarray(anchors, dtype=np.intp)
        pinned = np.flatnonzero(anchors >= 0)
        if pinned.size == 0:
            raise OptionError("no dense marker is pinned to the mesh")
        held, slot = np.unique(anchors[pinned], return_inverse=True)
        share = np.bincount(slot)
        mean = sp.csr_matrix((1.0 / share[slot], (slot, pinned)), shape=(held.size, len(anchors)))
        op = thin_shell_operator(vertices, faces, ks=KS, kb=KB)
        op = op + TIKHONOV * float(np.abs(op.diagonal()).mean()) * sp.identity(op.shape[0])
        weights = interpolation_weights(op, held)
        weights[np.abs(weights) < min_weight] = 0.0
        matrix = sp.csr_matrix(sp.csr_matrix(weights) @ mean)
        offset = (np.asarray(vertices, dtype=np.float64)
                  - matrix @ np.nan_to_num(np.asarray(neutral, dtype=np.float64)))
        return cls(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                   _per_axis(matrix), offset)

    @classmethod
    def fitted(cls, vertices: np.ndarray, faces: np.ndarray, neutral: np.ndarray, *,
               reach_mm: float = ANCHOR_REACH_MM, lateral: np.ndarray | None = None,
               corners: Mapping[str, int] | None = None,
               landmarks: Mapping[int, int] | None = None, head: int | None = None,
               regions: Sequence[str] | None = None
               ) -> tuple[MeshMap, Alignment, int, OpenedMesh]:
        """A user's mesh ``vertices`` (V, 3) (any unit, Y up, facing +Z), ``faces`` (T, 3) aligned
        onto the dense neutral ``neutral`` (M, 3) mm (NaN = unseen) by ICP with scale and opened
        (:func:`~mocaptk.retarget.mesh_openings.open_mesh`, ``corners`` its corner landmarks) as
        ``mocaptk rig --mesh`` does (in the rig frame, ``lateral`` the subject's left if known);
        each seen dense marker is pinned at the skin vertex nearest to its closest surface point
        unless it is more than ``reach_mm`` from the surface (beyond the mesh's border), then
        :meth:`anchored`, its openings' corners blended and its lids blinking. Returns the map,
        the alignment, how many markers were pinned and the opened mesh (rig frame).
        ``landmarks`` {dense marker: vertex} start the alignment (``rig --landmarks``). With
        ``head`` (the dense marker that moves least) and ``regions`` (M,) (each dense marker's),
        the mesh's parts other than its skin move as the rig's (:meth:`_with_parts`)."""
        from mocaptk.surface_mesh import marker_spacing

        from .build import rig_frame_rotation
        from .face_materials import mesh_materials
        from .face_template import fit_template
        from .mesh_openings import fill_sockets, open_mesh, weighted_faces

        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        row = {int(m): i for i, m in enumerate(seen)}
        if landmarks and any(m not in row for m in landmarks):
            raise OptionError("--landmarks names a dense marker the session never saw")
        alignment = align_mesh_to_markers(vertices, faces, neutral[seen], landmarks=None if not landmarks
                                          else {row[m]: v for m, v in landmarks.items()})
        rotation = rig_frame_rotation(neutral[seen], np.zeros(seen.size), lateral=lateral)
        points = neutral[seen] @ rotation.T  # the rig frame, where the template fits
        template = fit_template(points, spacing=marker_spacing(points))
        opened = open_mesh(alignment.transform.apply(vertices) @ rotation.T, faces, template,
                           corners=corners)
        placed = opened.vertices @ rotation
        skin = opened.faces[:opened.skin]  # markers sit on the skin, not on a lash or a tooth
        nearest, dist = anchor_vertices(placed, skin, neutral[seen],
                                        proximity=SurfaceProximity(placed, skin))
        anchors = np.full(len(neutral), -1, dtype=np.intp)
        close = dist <= reach_mm
        anchors[seen[close]] = nearest[close]
        mesh = cls.anchored(placed, weighted_faces(opened), anchors, neutral)  # not across sockets
        mesh = replace(mesh, faces=opened.faces,
                       matrix=fill_sockets(mesh.matrix, opened).astype(np.float32))
        mesh = mesh._with_openings(opened.vertices, opened.mouth_corners, opened.lids, anchors,
                                   neutral, rotation, eye_corner_mm=opened.eye_corner_mm)
        if head is not None and regions is not None:
            mesh = mesh._with_parts(opened, points, seen, head, [regions[m] for m in seen],
                                    template, neutral)
        mesh = replace(mesh, materials=mesh_materials(opened.vertices, opened.faces, opened.skin))
        return mesh, alignment, int(close.sum()), opened

    def _with_parts(self, opened: OpenedMesh, points: np.ndarray, seen: np.ndarray, head: int,
                    regions: Sequence[str], template: FittedTemplate | None,
                    columns: np.ndarray) -> MeshMap:
        """This map of a user's ``opened`` mesh with its parts' rows (and their share of the lids'
        blinks) set as the rig sets its weights (:func:`~mocaptk.retarget.mesh_openings.parts_follow`):
        ``points`` (S, 3) mm the ``seen`` dense markers in the rig frame, ``head`` the dense
        marker that moves least, ``regions`` (S,) theirs, ``columns`` (M, 3) mm as :meth:`anchored`."""
        from mocaptk.surface_mesh import marker_spacing

        from .build import RigOptions
        from .mesh_openings import parts_follow

        m = self.matrix.shape[1]
        row = np.flatnonzero(seen == head)
        if not row.size:
            return self
        matrix = np.asarray(self.matrix, dtype=np.float64)
        # each lid's own blink shape (V, 3) goes along as 3 more columns: a lash takes its lid's
        lids = [b.shape + matrix[:, b.sensors] @ b.full for b in self.blinks]
        rows = parts_follow(np.concatenate([matrix] + lids, axis=1), opened, points, head=int(row[0]),
                            regions=regions, positions=points, columns=seen,
                            jaw_count=RigOptions().max_influences,  # the rig's default jaw row
                            spacing=marker_spacing(points), template=template)
        matrix = rows[:, :m]
        blinks = tuple(replace(b, shape=rows[:, m + 3 * i:m + 3 * i + 3] - matrix[:, b.sensors] @ b.full)
                       for i, b in enumerate(self.blinks))
        return replace(self, matrix=matrix.astype(np.float32), blinks=blinks,
                       offset=self.vertices - matrix @ np.nan_to_num(columns))

    @classmethod
    def learned(cls, vertices: np.ndarray, faces: np.ndarray, markers: np.ndarray,
                positions: np.ndarray, *, neighbours: int = MESH_NEIGHBOURS,
                ridge: float = DEFAULT_RIDGE, block: int = 256) -> MeshMap:
        """A mesh seen moving with the dense markers: per vertex, ridge regression of its position
        from the 3 coordinates of its ``neighbours`` nearest dense markers (neutral pose).

        ``vertices`` (V, 3) mm the neutral mesh, ``faces`` (T, 3); ``markers`` (F, M, 3) mm
        training frames of the dense markers (NaN gaps; the frames without any gap are used, as
        the ridge models do) and ``positions`` (F, V, 3) mm the mesh in those frames (a synthetic
        session's ground truth, or registered scans). Unlike :meth:`anchored` it learns how
        vertices beyond the markers move (the neck with the jaw, the inner lips).
        """
        n_verts, n_markers = len(vertices), markers.shape[1]
        neutral = neutral_pose(markers)
        seen = np.flatnonzero(np.isfinite(neutral).all(axis=1))
        rows = np.isfinite(markers[:, seen]).all(axis=(1, 2)) & np.isfinite(positions).all(axis=(1, 2))
        k = min(int(neighbours), seen.size)
        if rows.sum() < 2 * 3 * k or k < 1:
            raise OptionError(f"a learned mesh map needs at least {2 * 3 * k} training frames "
                              f"without gaps, got {int(rows.sum())}")
        x = markers[rows].reshape(int(rows.sum()), -1)
        x_mean = x.mean(axis=0)
        x -= x_mean
        near = seen[cKDTree(neutral[seen]).query(vertices, k=k)[1].reshape(n_verts, k)]
        cols = (3 * near[..., None] + np.arange(3)).reshape(n_verts, 3 * k)  # (V, 3k)
        coef = np.empty((n_verts, 3 * k, 3))
        offset = np.empty((n_verts, 3))
        for start in range(0, n_verts, block):  # bounded memory: (frames, block, 3k) at a time
            part = slice(start, start + block)
            xs = x[:, cols[part]].transpose(1, 0, 2)  # (b, F, 3k)
            ys = np.asarray(positions[rows, part], dtype=np.float64).transpose(1, 0, 2)  # (b, F, 3)
            y_mean = ys.mean(axis=1)
            coef[part] = batched_ridge(xs.transpose(0, 2, 1) @ xs,
                                       xs.transpose(0, 2, 1) @ (ys - y_mean[:, None]), ridge)
            offset[part] = y_mean - np.einsum("bk,bkc->bc", x_mean[cols[part]], coef[part])
        matrix = sp.csr_matrix((coef.transpose(0, 2, 1).ravel().astype(np.float32),
                                (np.repeat(np.arange(3 * n_verts), 3 * k),
                                 np.repeat(cols, 3, axis=0).ravel())),
                               shape=(3 * n_verts, 3 * n_markers))
        return cls(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64),
                   matrix, offset)

    def apply(self, dense: np.ndarray,
              poses: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Vertex positions (f, V, 3) float32 mm from dense markers (f, M, 3) (unsolved frames NaN).

        ``poses`` ``(R (f, 3, 3), t (f, 3))``: the head pose of each frame (dense = R y + t for
        head-relative y) when the map has head-relative parts (mirror images, blinks): those
        are taken head-relative and the result put back."""
        solved = np.isfinite(dense).all(axis=2).any(axis=1)
        if poses is not None and (self.mirror is not None or self.blinks):
            rot, trans = poses
            relative = in_head_frame(dense, rot, trans)
            verts = self.apply(relative)
            verts = np.einsum("fij,fvj->fvi", rot, verts) + trans[:, None]
            verts[~solved] = np.nan
            return verts.astype(np.float32)
        full_dense = dense if self.mirror is None else self.mirror.extend(dense)
        verts = self._linear(full_dense)
        for blink in self.blinks:
            verts += (blink.amount(full_dense)[:, None, None] * blink.shape).astype(np.float32)
        verts[~solved] = np.nan
        return verts

    def _linear(self, dense: np.ndarray) -> np.ndarray:
        f, m, _ = dense.shape
        x = np.nan_to_num(dense).astype(np.float32)  # unseen: weight 0
        if isinstance(self.matrix, np.ndarray):
            verts = (x.transpose(0, 2, 1).reshape(3 * f, m) @ self.matrix.T).reshape(f, 3, -1)
            verts = verts.transpose(0, 2, 1)
        else:
            verts = np.asarray(self.matrix @ x.reshape(f, 3 * m).T).T.reshape(f, -1, 3)
        return verts + (0.0 if self.offset is None else self.offset.astype(np.float32))


def _per_axis(matrix: sp.spmatrix) -> np.ndarray:
    """A (V, M) map applied to x, y and z alike, as a dense float32 array."""
    return np.asarray(matrix.toarray(), dtype=np.float32)


def _midpoint_subdivide(matrix: sp.csr_matrix, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """One midpoint subdivision of a mesh given as rows of a linear map: each edge gets its
    midpoint row (the mean of its ends), each triangle becomes 4 (orientation kept)."""
    n = matrix.shape[0]
    corners = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1)  # (T, 3, 2)
    edges, inverse = np.unique(np.sort(corners.reshape(-1, 2), axis=1), axis=0, return_inverse=True)
    mid = n + inverse.reshape(-1, 3)  # midpoint of edge ab, bc, ca per face
    half = sp.csr_matrix((np.full(2 * len(edges), 0.5),
                          (np.repeat(np.arange(len(edges)), 2), edges.ravel())), shape=(len(edges), n))
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack(t, axis=1) for t in
                                ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return sp.csr_matrix(sp.vstack([matrix, half @ matrix])), new_faces
