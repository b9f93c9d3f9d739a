"""The separate parts of a user's ``--mesh`` (issue 30) on the ICT-FaceKit head (56 pieces: the
skin, teeth, gums and tongue, eyeballs, lashes): each moves with what it belongs to."""

from __future__ import annotations

import tarfile

import numpy as np

from conftest import shared_path


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
