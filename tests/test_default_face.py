"""The default face (issue 30) as ``solve``'s mesh on the bundled half-face sample: the whole
face, lips closed at rest and parted at the widest jaw, lids closed at the true full blink."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SAMPLES


@pytest.fixture(scope="module")
def solved():
    """The sample's layout (factor 1.1), the solver trained on its noise-free session, the face
    mesh map and the mesh over the held-out performance (F, V, 3) mm."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver
    from mocaptk.retarget.solve_outputs import face_mesh

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    solver = train_solver(layout, session, {"path": "sample", "sha256": None})
    mesh = face_mesh(solver, layout)
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    dense = np.concatenate([c.positions for c in solve_chunks(solver, layout_frames(solver, perf, "p"))])
    return layout, solver, mesh, mesh.apply(dense)


def test_solve_mesh_is_the_whole_face_with_uvs(solved):
    """Half-face sample, whole face: both halves mirror images (mm), the UVs ICT-FaceKit's."""
    from mocaptk.retarget.default_face import template_openings

    layout, _, mesh, _ = solved
    # the skin, then its eyeballs and mouth interior (2,864 vertices, tests/test_face_parts.py)
    assert mesh is not None and mesh.mirror is not None and mesh.vertices.shape == (9409 + 2864, 3)
    skin = mesh.vertices[:9409]
    plane = layout.extra["sagittal_plane"]
    normal, point = np.asarray(plane["normal"]), np.asarray(plane["point"])
    side = (skin - point) @ normal
    assert side.min() < -80 and side.max() > 80  # ear to ear, the captured half is one side
    image = skin - 2 * side[:, None] * normal
    assert np.abs(image[template_openings()[2]] - skin).max() < 1e-6
    assert mesh.uv.shape == (9409 + 2864, 2) and 0 <= mesh.uv.min() and mesh.uv.max() <= 1


def test_solve_mesh_closes_lips_and_lids(solved):
    """Mouth seam at rest <= 5 % of the widest opening (measured 1.3 %), lids at the true full
    blink <= 20 % of their rest aperture (measured 9 %), open when there is no blink, and both
    halves move: the mirrored half's lower lip drops at the widest jaw as the captured one's."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.default_face import loop_area, template_openings

    _, _, mesh, frames = solved
    (upper, lower), eyes, mirror = template_openings()
    mouth = np.concatenate([upper, lower[::-1][1:-1]])
    area = loop_area(frames[:, mouth])
    widest = int(np.nanargmax(area))
    assert loop_area(mesh.vertices[mouth]) <= 0.05 * area[widest] and area[widest] > 400
    drop = (frames[widest, lower] - mesh.vertices[lower])[:, 1]
    twin = (frames[widest, mirror[lower]] - mesh.vertices[mirror[lower]])[:, 1]
    assert drop.min() < -5 and np.abs(drop - twin).max() < 1e-3
    truth = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    names = list(truth.blendshape_names)
    for (top, bottom), blink in zip(eyes, ("eyeBlink_R", "eyeBlink_L")):
        loop = np.concatenate([top, bottom[::-1][1:-1]])
        aperture = loop_area(frames[:, loop]) / loop_area(mesh.vertices[loop])
        weight = truth.weights[:, names.index(blink)]
        assert aperture[int(np.argmax(weight))] <= 0.2
        assert np.percentile(aperture[weight < 0.05], 5) > 0.8


def test_solve_mesh_neither_folds_nor_tears_at_the_mouth(solved):
    """No triangle of solve's face faces backward against its rest in any frame of the held-out
    performance (was 2: the template's slivers inside the mouth corners), and within 20 mm of a
    mouth corner the largest stretch is 1.94x (was 2.35x, at a lip marker's vertex blended
    towards the corner, then 2.04x; now the markers' own vertices take 70 % of the corner
    blend, as the rig's: face_weights.face_rows). Elsewhere it is 1.95x at most (was 2.27x at
    the upper lids' crease in a blink: the lids now close with the rig's 12 mm field, the blink
    still sensed with 8 mm)."""
    from mocaptk.retarget.default_face import template_openings

    _, _, mesh, frames = solved
    faces = mesh.faces[mesh.materials == 0]  # the skin (its parts: tests/test_face_parts.py)
    rest = mesh.vertices

    def normals(points):
        return np.cross(points[..., faces[:, 1], :] - points[..., faces[:, 0], :],
                        points[..., faces[:, 2], :] - points[..., faces[:, 0], :])

    assert (np.einsum("ftk,tk->ft", normals(frames), normals(rest)) < 0).sum() == 0
    (upper, _), _, _ = template_openings()
    corners = rest[[upper[0], upper[-1]]]
    near = np.linalg.norm(rest[faces].mean(axis=1)[:, None] - corners, axis=2).min(axis=1) < 20
    edges = np.unique(np.sort(faces[near][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    stretch = np.linalg.norm(frames[:, edges[:, 0]] - frames[:, edges[:, 1]], axis=2) / length
    assert np.nanmax(stretch) <= 2.0, np.nanmax(stretch)
    edges = np.unique(np.sort(faces[~near][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    stretch = np.linalg.norm(frames[:, edges[:, 0]] - frames[:, edges[:, 1]], axis=2) / length
    assert np.nanmax(stretch) <= 2.0, np.nanmax(stretch)


def test_template_slivers_are_flipped():
    """The ICT-FaceKit template's two 2.6° slivers inside the mouth corners are flipped with
    their neighbours: every triangle's smallest angle >= 5°, the same vertices, triangle count
    and openings, every triangle still facing the way its original did."""
    import igl

    from mocaptk.retarget.default_face import _template, flip_slivers, triangle_angles
    from mocaptk.retarget.face_template import template_face

    vertices, original = template_face()
    faces = _template()[1]
    assert triangle_angles(vertices[original]).min() < 3.0
    assert triangle_angles(vertices[faces]).min() >= 5.0
    changed = np.flatnonzero((faces != original).any(axis=1))
    assert len(changed) == 4 and faces.shape == original.shape
    assert sorted(map(len, igl.boundary_loop_all(faces))) == sorted(map(len, igl.boundary_loop_all(original)))
    before = np.cross(*(vertices[original[changed, k]] - vertices[original[changed, 0]] for k in (1, 2)))
    after = np.cross(*(vertices[faces[changed, k]] - vertices[faces[changed, 0]] for k in (1, 2)))
    assert (np.einsum("tk,tk->t", before, after) > 0).all()
    assert np.array_equal(flip_slivers(vertices, faces), faces)  # nothing left to flip


def test_lip_anchors_put_each_marker_on_its_own_lip():
    """A marker that follows the jaw but was anchored on the upper lip's inner roll moves to the
    nearest lower-lip vertex (and one that does not, to the upper lip); the sample's own anchors
    need no move (build_rig: 0 moved; a synthetic actor's 3: 5.46x -> 3.58x)."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.default_face import default_face, lip_anchors
    from mocaptk.surface_mesh import marker_spacing

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    points = truth.marker_neutral
    face = default_face(points, spacing=marker_spacing(points))
    upper, lower = face.upper_lip, face.lower_lip
    middle = len(upper) // 2
    # two markers just off the lips' inner rims, each anchored on the other lip
    probe = face.fitted[[lower[len(lower) // 2], upper[middle]]] + [[0, -1.0, 1.0], [0, 1.0, 1.0]]
    wrong = np.array([upper[middle], lower[len(lower) // 2]])
    moved = lip_anchors(face, wrong, probe, np.array([True, False]))
    assert moved[0] != wrong[0] and moved[1] != wrong[1]
    assert np.linalg.norm(face.fitted[moved[0]] - face.fitted[lower[len(lower) // 2]]) < 3.0
    assert np.linalg.norm(face.fitted[moved[1]] - face.fitted[upper[middle]]) < 3.0
    right = lip_anchors(face, moved, probe, np.array([True, False]))
    assert np.array_equal(right, moved)  # already on their own lips: kept


def test_solve_finds_the_lip_markers_that_follow_the_jaw(solved):
    """solve's default face puts each lip marker on its own lip as the rig's does; without the
    session's motion it asks the solver which dense markers drop with the jaw (the layout
    Gaussian's pose for a 5 mm jaw drop, through the model). On the sample: only markers the
    session itself shows dropping with the jaw (the rig's rule), most of them (16 of 21 seen),
    the lower lip's middle among them and no upper-lip or nose marker."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.build import _follows_jaw, dense_cloud, influence_members
    from mocaptk.retarget.solve_outputs import jaw_following

    layout, solver, _, _ = solved
    follows = jaw_following(solver, layout, lateral=np.asarray(layout.extra["sagittal_plane"]["normal"]))
    cloud = dense_cloud(layout, load_ground_truth(SAMPLES / "dense_halfface_truth.npz").trajectories())
    session = _follows_jaw(layout, cloud, [cloud.index(m) for m in influence_members(layout.clusters)])
    ours = {label for label, f in zip(solver.labels, follows) if f}
    theirs = {label for label, f, seen in zip(cloud.labels, session, cloud.captured) if f and seen}
    assert ours <= theirs and len(ours) >= 0.75 * len(theirs), (ours, theirs)
    assert {"MOUTH_12_C", "MOUTH_15_C"} <= ours
    assert not any(label.startswith(("NOSE", "CHEEK", "EYE", "FOREHEAD")) for label in ours)


def test_solve_mesh_has_eyeballs_and_a_mouth_behind_the_skin(solved):
    """solve's face carries the default face's eyeballs, teeth and socket (their own materials):
    along the face's view no eyeball or tooth vertex is in front of the skin at rest, at the
    widest jaw or at either full blink (measured: 0.45 mm behind at least over the performance),
    the socket's lip vertices move with the lips, the lower teeth with the jaw (20 mm down)."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.geometry import similarity_transform
    from mocaptk.retarget.default_face import loop_area, template_openings
    from mocaptk.retarget.face_parts import in_front, template_parts
    from mocaptk.retarget.face_template import template_face

    _, _, mesh, frames = solved
    _, _, _, attach, group = template_parts()
    count = 9409
    assert np.bincount(mesh.materials).tolist()[1:] == np.bincount(template_parts()[2]).tolist()[1:]
    skin = mesh.faces[mesh.materials == 0]
    view = similarity_transform(template_face()[0], mesh.vertices[:count]).rotation[:, 2]
    (upper, lower), _, _ = template_openings()
    widest = int(np.nanargmax(loop_area(frames[:, np.concatenate([upper, lower[::-1][1:-1]])])))
    truth = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    names = list(truth.blendshape_names)
    blinks = [int(np.argmax(truth.weights[:, names.index(b)])) for b in ("eyeBlink_R", "eyeBlink_L")]
    for points in [mesh.vertices] + [frames[f].astype(float) for f in [widest, *blinks]]:
        for g in range(4):
            depth = in_front(points[count:][group == g], points[:count], skin, view=view)
            assert depth.max() < -0.3, (g, depth.max())
    on = attach >= 0
    np.testing.assert_allclose(frames[:, count:][:, on], frames[:, attach[on]], atol=1e-4)
    drop = (frames[widest, count:][group == 3] - mesh.vertices[count:][group == 3]) @ np.cross(
        view, np.cross((0.0, 1.0, 0.0), view))  # along the face's up
    assert drop.max() < -15.0
