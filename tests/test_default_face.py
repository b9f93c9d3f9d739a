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
    assert mesh is not None and mesh.mirror is not None and mesh.vertices.shape == (9409, 3)
    plane = layout.extra["sagittal_plane"]
    normal, point = np.asarray(plane["normal"]), np.asarray(plane["point"])
    side = (mesh.vertices - point) @ normal
    assert side.min() < -80 and side.max() > 80  # ear to ear, the captured half is one side
    image = mesh.vertices - 2 * side[:, None] * normal
    assert np.abs(image[template_openings()[2]] - mesh.vertices).max() < 1e-6
    assert mesh.uv.shape == (9409, 2) and 0 <= mesh.uv.min() and mesh.uv.max() <= 1


def test_solve_mesh_closes_lips_and_lids(solved):
    """Mouth seam at rest <= 5 % of the widest opening (measured 0.02 %), lids at the true full
    blink <= 20 % of their rest aperture (measured 11 %), open when there is no blink, and both
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
