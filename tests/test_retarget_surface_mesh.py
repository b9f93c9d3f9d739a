"""The marker surface mesh: a clean, outward-facing, manifold disk through the dense markers."""

from __future__ import annotations

import numpy as np
import pytest

from mocaptk.surface_mesh import (EDGE_BLOCK_FRAMES, cut_openings, edge_lengths, face_normals,
                                  marker_spacing, marker_surface_mesh, mesh_edges, mesh_quality,
                                  nanpercentile_rows, vertex_normals)


def face_cap(*, spacing: float = 10.0, half: bool = False, seed: int = 0) -> np.ndarray:
    """Jittered markers ~``spacing`` mm apart on an ellipsoidal face cap looking down +Z (mm)."""
    rng = np.random.default_rng(seed)
    az, el = np.meshgrid(np.arange(-75, 76, 7.0), np.arange(-55, 61, 7.0))
    az = np.radians(az + rng.uniform(-1.5, 1.5, az.shape)).ravel()
    el = np.radians(el + rng.uniform(-1.5, 1.5, el.shape)).ravel()
    pts = np.column_stack([75 * np.sin(az) * np.cos(el), 100 * np.sin(el),
                           90 * np.cos(az) * np.cos(el)])
    pts[:, 2] += 25 * np.exp(-(pts[:, 0] ** 2 + (pts[:, 1] + 5) ** 2) / 400)  # a nose
    if half:
        pts = pts[pts[:, 0] > -3]
    return pts * spacing / 10.0


@pytest.mark.parametrize("half", [False, True])
def test_surface_mesh_is_clean_manifold_disk_facing_front(half):
    pts = face_cap(half=half)
    vertices, faces = marker_surface_mesh(pts)
    np.testing.assert_array_equal(vertices, pts)  # vertex i = marker i
    q = mesh_quality(vertices, faces)
    assert q.non_manifold_edges == 0 and q.non_manifold_vertices == 0
    assert q.boundary_loops == 1
    assert q.unreferenced_vertices == 0
    assert q.min_angle_deg > 12.0  # no slivers
    assert q.max_edge_mm < 2.5 * marker_spacing(pts) + 1e-9 or q.max_edge_mm < 3.0 * q.median_edge_mm
    # consistent orientation: every interior edge is used once in each direction
    half_edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(half_edges, axis=0)) == len(half_edges)
    # outward = towards the viewer (+Z) on the front of the face
    front = np.abs(pts[:, 0]) < 30
    assert np.all(vertex_normals(vertices, faces)[front, 2] > 0.3)
    assert face_normals(vertices, faces).sum(axis=0)[2] > 0


def test_surface_mesh_orientation_follows_the_face_not_the_axes():
    pts = face_cap()
    rot = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # face now looks down -Y
    vertices, faces = marker_surface_mesh(pts @ rot.T)
    assert face_normals(vertices, faces).sum(axis=0)[1] < 0
    # same connectivity as unrotated (the chart does not depend on the axes)
    _, faces0 = marker_surface_mesh(pts)
    e0, _ = mesh_edges(faces0)
    e1, _ = mesh_edges(faces)
    assert len(e0) == len(e1) and np.array_equal(e0, e1)


def test_surface_mesh_flat_grid_and_determinism():
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.arange(15.0), np.arange(12.0)), -1).reshape(-1, 2) * 10
    pts = np.column_stack([g + rng.normal(0, 1.0, g.shape), np.zeros(len(g))])
    v1, f1 = marker_surface_mesh(pts)
    v2, f2 = marker_surface_mesh(pts.copy())
    np.testing.assert_array_equal(f1, f2)
    q = mesh_quality(v1, f1)
    assert q.boundary_loops == 1 and q.non_manifold_vertices == 0 and q.unreferenced_vertices == 0
    assert face_normals(v1, f1)[:, 2].min() > 0.99  # flat cloud: tie broken towards +Z


def test_surface_mesh_on_real_face_landmarks(shared_data):
    import trimesh

    from conftest import shared_path
    obj = shared_path("face_mesh", "mediapipe", "canonical_face_model.obj")
    pts = np.asarray(trimesh.load(obj, process=False).vertices) * 10.0  # cm -> mm
    vertices, faces = marker_surface_mesh(pts)
    q = mesh_quality(vertices, faces)
    assert q.non_manifold_edges == 0 and q.non_manifold_vertices == 0 and q.boundary_loops == 1
    assert q.min_angle_deg > 8.0
    assert face_normals(vertices, faces).sum(axis=0)[2] > 0


@pytest.mark.parametrize("bad", [np.full((5, 3), np.nan), np.zeros((2, 3)),
                                 np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3.0]]),
                                 np.zeros((4, 3))])
def test_surface_mesh_rejects_degenerate_clouds(bad):
    with pytest.raises(ValueError):
        marker_surface_mesh(bad)


@pytest.mark.parametrize("name", ["dense_halfface.c3d", "dense_halfface_performance.c3d"])
def test_surface_mesh_keeps_every_marker_of_the_bundled_sample(name):
    """The peeled border once dropped the marker under the nose (NOSE_12_L) off the surface."""
    from conftest import SAMPLES

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.clustering.neutral import neutral_pose

    points = neutral_pose(read_trajectories(SAMPLES / name).positions)
    q = mesh_quality(*marker_surface_mesh(points))
    assert q.unreferenced_vertices == 0
    assert q.non_manifold_edges == 0 and q.non_manifold_vertices == 0 and q.boundary_loops == 1


def test_bowtie_repair_when_earlier_fans_took_every_triangle_of_a_vertex():
    """Vertex 5 joins two small fans, one of vertex 0 and one of vertex 1: repairing 0 and 1 drops
    both of its triangles (10,000 markers 2 mm apart raised 'argmax of an empty sequence')."""
    from mocaptk.surface_mesh import _repair_bowties

    fans = [[0, 10, 11], [0, 11, 12], [0, 12, 13], [1, 20, 21], [1, 21, 22], [1, 22, 23]]
    faces = np.array(fans + [[0, 5, 6], [1, 5, 7]])
    np.testing.assert_array_equal(_repair_bowties(faces, 24), fans)


def test_surface_mesh_border_has_no_zigzag_notches():
    """The peel left notches along the border (a zigzag top of the forehead): on the sample
    (median of the first 60 frames) the border turned inwards by up to 54 degrees (CHIN_10_L;
    44 at FOREHEAD_BROW_07_L); the notches are filled, every turn is within 30 degrees."""
    from conftest import SAMPLES

    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.retarget.build import RIM_NOTCH_DEG
    from mocaptk.surface_mesh import border_turns

    session = read_c3d(SAMPLES / "dense_halfface.c3d")
    points = np.nanmedian(session.positions[:60], axis=0)
    vertices, faces = marker_surface_mesh(points, max_notch_deg=RIM_NOTCH_DEG)
    _, turn = border_turns(vertices, faces)
    assert turn.min() >= -RIM_NOTCH_DEG - 1e-9
    q = mesh_quality(vertices, faces)
    assert q.boundary_loops == 1 and q.non_manifold_edges == 0 and q.min_angle_deg > 15.0
    _, old = border_turns(*marker_surface_mesh(points))
    assert old.min() < -40.0  # without the fill (the layouts' and solve's mesh)


def test_edge_lengths_are_numpy_norms_across_blocks_and_gaps():
    """Frame by frame the values of np.linalg.norm of the edge vectors, bit for bit (the blocks'
    layout must not change the sums), NaN where an end is missing, over a partial last block."""
    pts = face_cap()
    _, faces = marker_surface_mesh(pts)
    edges, _ = mesh_edges(faces)
    rng = np.random.default_rng(3)
    frames = 3 * EDGE_BLOCK_FRAMES + 5
    traj = pts[None] + rng.normal(scale=2.0, size=(frames, len(pts), 3))
    traj[rng.random((frames, len(pts))) < 0.05] = np.nan
    expected = np.linalg.norm(traj[:, edges[:, 0]] - traj[:, edges[:, 1]], axis=2)
    got = edge_lengths(traj, edges)
    assert got.shape == (frames, len(edges)) and np.isnan(got).any()
    np.testing.assert_array_equal(got, expected)


def test_cut_openings_measures_a_long_session_on_evenly_spaced_frames():
    """The stretch is the 99th percentile over every k-th frame of a session longer than
    ``max_frames``: an edge that opens only in the frames left out is kept, and it is cut when
    every frame is measured."""
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.arange(8.0), np.arange(6.0)), -1).reshape(-1, 2) * 10
    pts = np.column_stack([g + rng.normal(0, 1.0, g.shape), np.zeros(len(g))])
    _, faces = marker_surface_mesh(pts)
    frames = 400
    traj = np.repeat(pts[None], frames, axis=0)
    a, b = mesh_edges(faces)[0][len(faces) // 2]
    traj[1::2, b] += 3.0 * (pts[b] - pts[a])  # the edge (a, b) stretched 4x in every odd frame
    kept, cut = cut_openings(faces, traj, pts, max_frames=frames // 2)  # every 2nd frame: 0, 2, ...
    assert len(cut) == 0 and len(kept) == len(faces)
    _, cut = cut_openings(faces, traj, pts, max_frames=frames)
    assert [int(a), int(b)] in cut.tolist()


@pytest.mark.parametrize("q", [99, 95, 50, 100])
def test_nanpercentile_rows_is_numpys_bit_for_bit(q):
    """The values of np.nanpercentile(axis=1) for rows with NaN gaps of every size (none, one
    value left, all NaN), ties, zeros and inf; the input is consumed."""
    rng = np.random.default_rng(q)
    values = rng.gamma(2.0, 3.0, size=(40, 1500))
    values[rng.random(values.shape) < rng.random((40, 1))] = np.nan  # 0..100 % gaps per row
    values[1] = np.round(values[1])  # ties
    values[2, 5:] = np.nan  # five values
    values[3, 1:] = np.nan  # one value
    values[4] = np.nan  # never seen
    values[5, :700] = 0.0
    values[6, ::97] = np.inf  # inf among the top ranks
    values[7, :] = np.inf
    with np.errstate(invalid="ignore"), pytest.warns(RuntimeWarning):  # numpy: all-NaN row
        expected = np.nanpercentile(values, q, axis=1)
    got = nanpercentile_rows(values.copy(), q)
    np.testing.assert_array_equal(got, expected)
    assert np.isnan(got[4]) and np.isnan(got[6]) == np.isnan(expected[6])
