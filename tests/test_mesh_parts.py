"""The separate parts of a user's ``--mesh`` (issue 30) on the ICT-FaceKit head (56 pieces: the
skin, teeth, gums and tongue, eyeballs, lashes): each moves with what it belongs to."""

from __future__ import annotations

import tarfile
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path

SAMPLES = Path(__file__).resolve().parents[1] / "sample_c3d"


def test_ict_head_parts_move_with_the_head_the_jaw_or_the_lids(tmp_path):
    """The skin is the largest piece and keeps its weights; every tooth and eyeball takes one
    row (upper teeth and eyeballs the head's, lower teeth the jaw's); lashes and the eyes' wet
    rims take their nearest skin vertex's row; gums and tongue blend from head to jaw."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from mocaptk.retarget.influence import edge_graph
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.mesh_parts import part_weights, skin_faces
    from mocaptk.surface_mesh import boundary_edges

    archive = shared_path("face_mesh", "ict_facekit", "ict_facekit_FaceXModel_subset.tar.xz")
    with tarfile.open(archive) as tar:
        (tmp_path / "head.obj").write_bytes(
            tar.extractfile("ICT-FaceKit/FaceXModel/generic_neutral_mesh.obj").read())
    mesh = load_mesh(tmp_path / "head.obj")
    vertices = mesh.vertices * 10.0  # cm -> mm, as the alignment scales it
    skin = skin_faces(mesh.faces)
    assert skin.sum() == 28068  # the face and the back of the head
    faces = np.concatenate([mesh.faces[skin], mesh.faces[~skin]])
    rng = np.random.default_rng(0)
    weights = rng.random((len(vertices), 6))
    weights /= weights.sum(axis=1, keepdims=True)
    head, jaw = np.eye(6)[0], np.eye(6)[1]
    on = np.unique(faces[:skin.sum()])
    nose_y = vertices[on[np.argmax(vertices[on, 2])], 1]
    got = part_weights(weights, vertices, faces, int(skin.sum()), head=head, jaw=jaw,
                       mouth_y=-31.0, nose_y=nose_y)  # the head's lip line, mm
    np.testing.assert_array_equal(got[on], weights[on])
    _, part = connected_components(edge_graph(vertices, mesh.faces), directed=False)
    kinds = {"head": 0, "jaw": 0, "skin": 0, "blend": 0}
    nearest = on[cKDTree(vertices[on]).query(vertices)[1]]
    for p in np.unique(part[np.unique(mesh.faces[~skin])]):
        members = np.flatnonzero(part == p)
        closed = not len(boundary_edges(mesh.faces[np.isin(mesh.faces[:, 0], members)]))
        rows = got[members]
        if closed:
            kind = "head" if vertices[members, 1].mean() > -31.0 else "jaw"
            np.testing.assert_array_equal(rows, np.tile(head if kind == "head" else jaw, (len(members), 1)))
        elif vertices[members, 1].mean() > nose_y:
            kind = "skin"
            np.testing.assert_array_equal(rows, weights[nearest[members]])
        else:  # the gums and tongue: head's at the top, jaw's at the bottom
            kind = "blend"
            top, bottom = members[np.argmax(vertices[members, 1])], members[np.argmin(vertices[members, 1])]
            np.testing.assert_allclose(got[[top, bottom]], [head, jaw], atol=1e-12)
        kinds[kind] += 1
    # 16 upper teeth + 4 eyeball pieces, 16 lower teeth, 2 x 6 lashes + 2 x 3 eye pieces, the gums
    assert kinds == {"head": 20, "jaw": 16, "skin": 18, "blend": 1}


@pytest.mark.slow
@pytest.mark.parametrize("fallback", [True, False], ids=["fallback markers", "no fallback markers"])
def test_solve_moves_a_meshs_parts_as_the_rig_does(tmp_path, fallback):
    """``solve --mesh`` (:func:`~mocaptk.retarget.solve_outputs.user_mesh`) on the MediaPipe face
    with an upper and a lower tooth and an eyeball added (closed pieces): over the held-out
    performance each stays rigid, the lower tooth drops with the jaw's markers at the widest
    opening, the upper one and the eyeball move with the head's marker (before, the pieces took
    the thin-shell weights of a piece no marker is pinned to, and stayed where they were). A
    solver without fallback pose markers (a layout with no 3 of them apart) takes the layout
    marker that spreads least instead (:func:`~mocaptk.retarget.solve_outputs.parts_head`;
    before, the parts were skipped and stayed where they were)."""
    from dataclasses import replace

    import trimesh

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver
    from mocaptk.retarget.solve_outputs import parts_head, user_mesh

    face = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    ball = trimesh.creation.icosphere(subdivisions=1)
    vertices, faces = [face.vertices], [face.faces]
    pieces = {"upper": ((0.0, -3.7, 4.6), 0.25), "lower": ((0.0, -4.9, 4.6), 0.25),
              "eye": ((-3.18, 2.6, 2.7), 1.0)}  # cm, as the MediaPipe face
    where = {}
    for name, (centre, radius) in pieces.items():
        start = sum(len(v) for v in vertices)
        where[name] = np.arange(start, start + len(ball.vertices))
        vertices.append(np.asarray(ball.vertices) * radius + centre)
        faces.append(np.asarray(ball.faces) + start)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.concatenate(vertices)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.concatenate(faces)]
    (tmp_path / "parts.obj").write_text("\n".join(lines) + "\n")

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    solver = train_solver(layout, session, {"path": "sample", "sha256": None})
    if not fallback:
        solver = replace(solver, fallback_labels=(), fallback_reference=None)
    head_label = parts_head(solver)
    if fallback:
        assert head_label == solver.fallback_labels[0]
    else:  # the least-spreading layout marker moves little in the session (a brow's: 2.8 mm)
        column = session.positions[:, session.index([head_label])[0]]
        moved = np.nanmax(np.linalg.norm(column - solver.model.neutral[solver.labels.index(head_label)], axis=1))
        assert head_label in solver.layout_labels and moved < 5.0
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    dense = np.concatenate([c.positions for c in solve_chunks(solver, layout_frames(solver, perf, "p"))])
    mesh, info = user_mesh(tmp_path / "parts.obj", solver.model.neutral, layout=layout,
                           labels=solver.labels, head=head_label)
    # the skin's removed vertices (the eyes' insides) come before the pieces' (lip copies after)
    offset = -len(info["eye_openings"]["vertices_removed"])
    posed = mesh.apply(dense)
    head = solver.labels.index(head_label)
    chin = [i for i, label in enumerate(solver.labels) if label.startswith("CHIN")]
    drop = solver.model.neutral[chin, 1] - dense[:, chin, 1]  # session frame: Y up, head-relative
    jaw = int(np.argmax(drop.mean(axis=1)))
    for name, (_, radius) in pieces.items():
        index = where[name] + offset
        move = posed[:, index] - mesh.vertices[index]
        # rigid: every vertex moved alike (a translation, as the rig's joints)
        assert np.abs(move - move[:, :1]).max() < 1e-3
        shift = move[jaw, 0]
        if name == "lower":
            # the jaw's lowest markers' drop: 20.0 mm (the chin's markers 2.7-24.5 mm)
            assert np.median(drop[jaw]) < -shift[1] <= drop[jaw].max() and -shift[1] > 10.0
        else:  # with the head's marker, the layout marker that moves least (a brow's: 2.9 mm)
            np.testing.assert_allclose(move[:, 0], dense[:, head] - solver.model.neutral[head], atol=1e-3)
