"""Openings cut on a user's ``--mesh`` (issue 30): the MediaPipe canonical face has its lips
joined and its eyes covered; cut along the lip line, the lips stay closed at rest and part when
the jaw opens; its eyes opened, their lids close when the actor blinks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

SAMPLES = Path(__file__).resolve().parents[1] / "sample_c3d"


def test_split_along_opens_a_path_between_its_ends():
    """A 6 x 2 grid of squares cut along its middle row between two inner vertices: the path's
    inner vertices get copies taken by the triangles below, its ends stay joined, and the cut is
    a second boundary loop (a slit), not a split of the mesh."""
    from mocaptk.retarget.eye_openings import boundary_loops
    from mocaptk.retarget.mesh_openings import split_along

    x, y = np.meshgrid(np.arange(7.0), np.arange(3.0))
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    squares = [(r * 7 + c, r * 7 + c + 1, (r + 1) * 7 + c + 1, (r + 1) * 7 + c)
               for r in range(2) for c in range(6)]
    faces = np.array([(a, b, c) for a, b, c, _ in squares] + [(a, c, d) for a, _, c, d in squares])
    cut = split_along(vertices, faces, np.array([8, 9, 10, 11, 12]), up=np.array([0.0, 1.0, 0.0]))
    inner, copies = [9, 10, 11], [21, 22, 23]
    np.testing.assert_array_equal(cut.vertices[21:], vertices[inner])
    low = vertices[faces].mean(axis=1)[:, 1] < 1.0
    assert not np.isin(cut.faces[low], inner).any() and np.isin(cut.faces[low], copies).any()
    assert not np.isin(cut.faces[~low], copies).any()
    assert sorted(len(loop) for loop in boundary_loops(cut.faces)) == [8, 16]
    np.testing.assert_array_equal(cut.corners, [8, 12])
    np.testing.assert_array_equal(cut.edges, [[8, 9], [9, 10], [10, 11], [11, 12]])


@pytest.mark.slow
def test_mediapipe_face_gets_a_mouth_that_parts_and_eyes_that_blink():
    """On the sample performance (1,200 held-out frames): the mouth is closed at rest, open at
    the widest jaw frame, the largest edge stretch stays under 2x (3.05x before the cut), and
    each eye's aperture at the fullest blink is under 20 % of rest."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.animate import skin_vertices
    from mocaptk.retarget.build import Capture, bake_capture, build_rig, jaw_open_frame
    from mocaptk.retarget.default_face import loop_area
    from mocaptk.retarget.eye_openings import eye_loops
    from mocaptk.retarget.mesh_io import load_mesh

    mesh = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    build = build_rig(layout, session, mesh=mesh, check=False)
    rig = build.rig
    cut = np.array(build.report["mesh"]["opening_edges_cut"])  # vertices of the given mesh
    removed = build.report["mesh"]["eye_openings"]["vertices_removed"]  # the eyes' insides
    assert len(cut) >= 6 and len(rig.vertices) == len(mesh.vertices) + len(cut) - 1 - len(removed)
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    animation = bake_capture(build, Capture("performance", perf))
    joints = animation.translations[:, 1:] + rig.joint_positions[0]
    disp = np.concatenate([np.zeros((len(joints), 1, 3)), joints - rig.joint_positions[1:]], axis=1)
    posed = skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)
    path = np.append(cut[:, 0], cut[-1, 1])
    copies = np.arange(len(mesh.vertices), len(mesh.vertices) + len(path) - 2)
    loop = np.concatenate([path, copies[::-1]])
    loop = loop - np.searchsorted(removed, loop)  # the rig's own vertex numbers
    jaw = jaw_open_frame(build, animation)
    rest, widest = loop_area(rig.vertices[loop]), loop_area(posed[jaw, loop])
    assert rest < 1.0 and widest > 300.0  # mm²: sample 0 and 767
    edges = np.unique(np.sort(rig.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    length = np.linalg.norm(rig.vertices[edges[:, 0]] - rig.vertices[edges[:, 1]], axis=1)
    stretch = np.linalg.norm(posed[:, edges[:, 0]] - posed[:, edges[:, 1]], axis=2) / length
    assert stretch.max() < 2.0  # sample 1.86x (3.05x with the lips joined)
    # the covered eyes are opened along the mesh's own edges and get lids that blink
    assert rig.joint_names[-2:] == ("upperLid_R", "upperLid_L")
    eyes = eye_loops(rig.vertices, rig.faces)
    assert len(eyes) == 2 and build.report["mesh"]["eye_openings"]["openings"] == 2
    for loop in eyes:
        rest = loop_area(rig.vertices[loop])
        assert rest > 100.0  # mm²: sample 111 (192 when the holes ran one ring outside the lid margin)
        assert loop_area(posed[:, loop]).min() < 0.2 * rest  # sample 19 %


def test_eyes_open_at_the_lid_margin_and_corner_landmarks_steer_the_cuts():
    """MediaPipe on the sample's neutral (:func:`open_mesh`, as rig and solve call it): the eyes
    open at MediaPipe's own lid contour, none of its vertices removed (the template's rims ran
    one ring outside it on the outer halves); a mouth corner given as a landmark ends the lip
    cut, and moving it moves the cut; given eye corners end both rims of each eye."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.align import align_mesh_to_markers
    from mocaptk.retarget.default_face import loop_area, template_openings
    from mocaptk.retarget.face_template import fit_template
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.mesh_openings import open_mesh
    from mocaptk.surface_mesh import marker_spacing

    mesh = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    neutral = load_ground_truth(SAMPLES / "dense_halfface_truth.npz").marker_neutral
    template = fit_template(neutral, spacing=marker_spacing(neutral))
    placed = align_mesh_to_markers(mesh.vertices, mesh.faces, neutral).transform.apply(mesh.vertices)
    plain = open_mesh(placed, mesh.faces, template)
    assert plain.eye_report["vertices_removed"] == []
    contours = ({33, 7, 163, 144, 145, 153, 154, 155, 246, 161, 160, 159, 158, 157, 173},
                {382, 381, 380, 374, 373, 390, 249, 263, 384, 385, 386, 387, 388, 466})
    _, eyes, _ = template_openings()
    for lid, contour, (upper, lower) in zip(plain.lids, contours, eyes):
        rims = np.concatenate([lid.upper, lid.lower[::-1][1:-1]])
        assert contour <= set(plain.source[rims].tolist())  # all but MediaPipe's inner corner
        rim = np.concatenate([upper, lower[::-1][1:-1]])
        print(f"eye opening {loop_area(plain.vertices[rims]):.0f} mm², the template's "
              f"{loop_area(template.vertices[rim]):.0f} mm²")
    assert plain.lip_cut.path[0] == 78  # the inner lip's corner
    for corner in (61, 62):  # the outer corner, then the next vertex along the inner lip
        cut = open_mesh(placed, mesh.faces, template, corners={"mouth_R": corner, "mouth_L": 291}).lip_cut
        assert cut.path[0] == corner and cut.path[-1] == 291
    given = {"eye_R_outer": 33, "eye_R_inner": 133, "eye_L_inner": 362, "eye_L_outer": 263}
    steered = open_mesh(placed, mesh.faces, template, corners=given)
    for lid, ends in zip(steered.lids, ((33, 133), (362, 263))):
        assert steered.source[lid.upper[[0, -1]]].tolist() == list(ends)
        assert steered.source[lid.lower[[0, -1]]].tolist() == list(ends)
