"""Rig building on the bundled synthetic sample: weights, exactness, marker-driven RMSE, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SAMPLES


@pytest.fixture(scope="module")
def sample():
    """The sample's noise-free session (ground truth), its layout at factor 1.1, and the rig."""
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import build_rig

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    return truth, session, layout, build_rig(layout, session)


@pytest.fixture(scope="module")
def markers(sample):
    """The rig on the marker surface (``surface="markers"``) of the sample's session."""
    from mocaptk.retarget.build import RigOptions, build_rig

    truth, session, layout, _ = sample
    return truth, session, layout, build_rig(layout, session, options=RigOptions(surface="markers"))


def test_rig_weights_partition_unity_capped_and_exact_at_markers(sample, markers):
    _, _, layout, build = sample
    rig = build.rig
    # a joint per layout marker, then the default face's two upper-lid joints
    assert rig.joint_count == len(layout.clusters) + 3
    assert rig.joint_names[-2:] == ("upperLid_R", "upperLid_L")
    assert rig.max_influences == 4
    np.testing.assert_allclose(rig.weight_value.sum(axis=1), 1.0, atol=1e-12)
    assert np.all((rig.weight_value > 0).sum(axis=1) >= 1)
    assert np.all((rig.weight_value == 0) | (rig.weight_value >= 1e-3))
    # at its marker's vertex a joint has weight exactly 1, but where the lid moves it (EYE_08,
    # under the brow: 0.32 on its lid, the part of the template's blink its marker does not show)
    # and within MOUTH_CORNER_MM of a mouth corner (70 % of the corner's blend: a lip marker
    # there held exactly stretched the closed seam's skin 2.08x at the widest jaw)
    from mocaptk.retarget.default_face import MOUTH_CORNER_MM, template_openings

    (upper, _), _, _ = template_openings()
    corner = np.linalg.norm(rig.vertices[build.joint_vertices][:, None]
                            - rig.vertices[[upper[0], upper[-1]]], axis=2).min(axis=1) < MOUTH_CORNER_MM
    lids = rig.dense_weights()[:, -2:]
    for j, v in enumerate(build.joint_vertices):
        if not lids[v].any() and not corner[j]:
            assert rig.weight_index[v, 0] == j + 1 and rig.weight_value[v, 0] == 1.0
        elif corner[j]:  # its own joint still leads
            assert rig.weight_index[v, 0] == j + 1 and 0.5 < rig.weight_value[v, 0] < 1.0
    assert (lids[build.joint_vertices] > 0).any(axis=1).sum() == 2
    assert 0 < corner.sum() < 0.2 * len(corner), corner.sum()  # the sample: 12 of 69
    # joints sit at their markers' neutral positions, under one root; their vertices are on the
    # fitted face, moved by the lips' closing (the sample's lips are 11 mm apart at rest)
    np.testing.assert_allclose(rig.joint_positions[build.marker_joints],
                               build.cloud.neutral[build.cloud.index(layout.labels)], atol=1e-9)
    assert np.linalg.norm(rig.joint_positions[build.marker_joints]
                          - rig.vertices[build.joint_vertices], axis=1).max() < 5.5
    assert list(rig.joint_parents) == [-1] + [0] * (rig.joint_count - 1)
    # every captured dense marker has a vertex with a region
    assert np.all(build.regions[build.dense_vertices] >= 0)
    assert build.report["mesh"]["kind"] == "face"
    # on the marker surface every joint is its marker's vertex, exact
    rig = markers[3].rig
    assert rig.joint_count == len(layout.clusters) + 1
    for j, v in enumerate(markers[3].joint_vertices):
        assert rig.weight_index[v, 0] == j + 1 and rig.weight_value[v, 0] == 1.0
    np.testing.assert_allclose(rig.joint_positions[1:], rig.vertices[markers[3].joint_vertices],
                               atol=1e-9)
    assert markers[3].report["mesh"]["kind"] == "marker surface"


def test_marker_driven_rmse_on_held_out_performance(sample):
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.build import ground_truth_error

    _, _, _, build = sample
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    truth = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    err = ground_truth_error(build, perf, truth.positions, truth.labels)
    # measured 0.88 mm on the 139-marker sample (docs/rig-weights.md); markers carry ~0.3 mm noise
    assert err.rmse_mm < 1.2 and err.p95_mm < 2.5
    assert err.vertices == int(build.cloud.captured.sum())
    # a rigid rig (every vertex follows its nearest joint) is clearly worse: weights matter
    # (measured 1.22x the RMSE on the 139-marker sample, > 1.3x on the earlier 127-marker one)
    rigid = build.rig.weight_value.copy()
    rigid[:, 0], rigid[:, 1:] = 1.0, 0.0
    from mocaptk.retarget.build import RigBuild

    blunt = RigBuild(build.rig.__class__(**{**_rig_fields(build.rig), "weight_value": rigid}),
                     build.layout, build.cloud, build.regions, build.dense_vertices,
                     build.joint_vertices, None, build.check, lids=build.lids)
    assert ground_truth_error(blunt, perf, truth.positions, truth.labels).rmse_mm > 1.15 * err.rmse_mm


def test_held_out_mouth_error_by_region_and_its_worst_case(sample):
    """The held-out performance per region: the mouth (the lips cut apart) at most 1.5x the mean
    of the other regions (issue 11; measured 0.60x here, 1.19x from the observed session in
    docs/rig-weights.md), and the largest error named by marker, region and frame."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.retarget.build import Capture, held_out_check

    _, _, _, build = sample
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    held = held_out_check(build, Capture("performance", perf))
    rmse = {region: r["rmse_mm"] for region, r in held["regions"].items()}
    assert set(rmse) == {"cheek", "chin", "eye", "forehead_brow", "mouth", "nose"}
    others = np.mean([v for region, v in rmse.items() if region != "mouth"])
    assert rmse["mouth"] <= 1.5 * others, rmse
    worst = held["max"]
    assert worst["error_mm"] == max(r["max_mm"] for r in held["regions"].values())
    region_of = {m: c.region for c in build.layout.clusters for m in c.members}
    assert worst["region"] == region_of[worst["marker"]] and 0 <= worst["frame"] < perf.n_frames
    assert worst["layout_distance_mm"] > 0  # not a layout marker: those are exact


def _rig_fields(rig):
    return {name: getattr(rig, name) for name in (
        "vertices", "faces", "joint_names", "joint_parents", "joint_positions", "joint_sides",
        "joint_regions", "joint_markers", "weight_index", "weight_value")}


def test_eight_influences_and_pure_thin_shell(sample):
    from mocaptk.retarget.build import RigOptions, build_rig

    _, session, layout, build4 = sample
    build8 = build_rig(layout, session, options=RigOptions(max_influences=8, pure_thin_shell=True,
                                                            subdivisions=0, surface="markers"))
    assert build8.rig.max_influences == 8
    assert (build8.rig.weight_value > 0).sum(axis=1).max() > 4
    assert build8.rig.vertex_count == len(build8.cloud.labels)  # no subdivision
    assert build8.check.rmse_mm < 1.0 and build4.check.rmse_mm < 1.0


def test_cli_rig_writes_rig_and_guide(sample, tmp_path, run_cli):
    from mocaptk.clustering.layout import write_layout
    from mocaptk.retarget.export_json import read_rig_json

    _, _, layout, _ = sample
    write_layout(layout, tmp_path / "layout.json")
    session = SAMPLES / "dense_halfface_performance.c3d"
    out = tmp_path / "rig"
    result = run_cli("rig", tmp_path / "layout.json", "--session", session, "--out", out,
                     "--no-stabilize", "--formats", "json,glb")
    assert result.exit_code == 0, result.stderr
    assert "marker-driven skinning check: RMSE" in result.stdout
    for name in ("rig.json", "rig.glb", "guide.pdf", "guide_front.png", "guide_profile.png",
                 "rig_report.json"):
        assert (out / name).stat().st_size > 0
    assert not (out / "rig.fbx").exists()
    rig = read_rig_json(out / "rig.json")
    rigid = (layout.extra.get("stabilization") or {}).get("rigid_labels") or []
    # face_root, head, jaw, the layout's joints, the two lids, one locator per stabilization marker
    assert rig.joint_count == 3 + len(layout.clusters) + 2 + len(rigid)
    # the face (its UVs kept), then its eyeballs, teeth and mouth socket (2,864 vertices)
    assert rig.texcoords is not None and rig.vertex_count == 9409 + 2864
    report = json.loads((out / "rig_report.json").read_text())
    assert report["skinning_check"]["rmse_mm"] < 1.5
    # existing outputs are refused without --force, in one line
    again = run_cli("rig", tmp_path / "layout.json", "--session", session, "--out", out,
                    "--no-stabilize", "--formats", "json")
    assert again.exit_code == 2 and again.stderr.count("\n") == 1
    assert "already exists" in again.stderr


@pytest.mark.parametrize("args, message", [
    (["--formats", "json,obj"], "unknown rig format"),
    (["--max-influences", "0"], "--max-influences"),
    (["--mesh", "nothere.obj"], "mesh file not found"),
    (["--falloff", "-1"], "--falloff"),
    (["--surface", "bogus"], "unknown --surface 'bogus' (choose from face, markers)"),
    (["--keep-mesh-space"], "--keep-mesh-space needs --mesh"),
])
def test_cli_rig_bad_input_is_one_line_exit_2(sample, tmp_path, run_cli, args, message):
    from mocaptk.clustering.layout import write_layout

    _, _, layout, _ = sample
    write_layout(layout, tmp_path / "layout.json")
    result = run_cli("rig", tmp_path / "layout.json", "--session",
                     SAMPLES / "dense_halfface_performance.c3d", "--out", tmp_path / "o",
                     "--no-stabilize", *args)
    assert result.exit_code == 2
    assert result.stderr.startswith("mocaptk: error:") and message in result.stderr
    assert result.stderr.count("\n") == 1


def test_cli_rig_bad_landmarks_file(sample, tmp_path, run_cli):
    from mocaptk.clustering.layout import write_layout

    _, _, layout, _ = sample
    write_layout(layout, tmp_path / "layout.json")
    for content, message in (('{"NOSE_01_C": 5}', "at least 3"), ("[1, 2", "invalid JSON"),
                             ('{"a": -1, "b": 2, "c": 3}', "vertex index")):
        (tmp_path / "lm.json").write_text(content)
        result = run_cli("rig", tmp_path / "layout.json", "--session",
                         SAMPLES / "dense_halfface_performance.c3d", "--landmarks",
                         tmp_path / "lm.json", "--out", tmp_path / "o", "--no-stabilize")
        assert result.exit_code == 2 and message in result.stderr and "lm.json" in result.stderr


def test_cli_rig_missing_layout(tmp_path, run_cli):
    result = run_cli("rig", tmp_path / "none.json", "--session", tmp_path / "none.c3d")
    assert result.exit_code == 2 and "none.json" in result.stderr


def test_rig_on_the_ict_face_mesh_against_true_vertices(sample, tmp_path):
    """--mesh with the ICT-FaceKit face: aligned to the markers, skinned, checked on all vertices."""
    import trimesh

    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.errors import InputFileError
    from mocaptk.retarget.build import build_rig, mesh_ground_truth_error
    from mocaptk.retarget.mesh_io import load_mesh

    try:
        model = load_face_model()
    except InputFileError as exc:
        pytest.skip(str(exc))
    truth, session, layout, _ = sample
    count = model.face_vertex_count
    neutral = model.identity_mesh(truth.identity_coefficients)[:count]
    trimesh.Trimesh(neutral * 0.01, model.face_triangles, process=False).export(tmp_path / "f.obj")
    build = build_rig(layout, session, mesh=load_mesh(tmp_path / "f.obj"))  # a mesh in dm
    assert build.alignment.rms_mm < 0.1 and build.alignment.transform.scale == pytest.approx(100, rel=1e-3)
    assert build.rig.vertex_count == count
    frames = slice(0, None, 20)
    moved = neutral[None] + np.tensordot(truth.weights[frames].astype(float),
                                         model.blendshapes[:, :count], axes=1)
    err = mesh_ground_truth_error(build, _every(session, 20), moved)
    # measured 1.1-1.9 mm over the whole face region (it extends past the markers: ears, lids)
    assert err.rmse_mm < 2.0 and err.vertices == count


def test_rig_on_the_ict_facekit_head_obj(sample, tmp_path):
    """--mesh with the whole ICT-FaceKit head OBJ (26,719 vertices, UV seams, 12 materials):
    read as the file's vertices (a seam does not split the skin into pieces), no trimesh
    warnings, and the rig follows the markers as on the default mesh."""
    import tarfile
    import warnings

    from scipy.sparse.csgraph import connected_components

    from conftest import shared_path
    from mocaptk.retarget.build import build_rig
    from mocaptk.retarget.influence import edge_graph
    from mocaptk.retarget.mesh_io import load_mesh

    archive = shared_path("face_mesh", "ict_facekit", "ict_facekit_FaceXModel_subset.tar.xz")
    member = "ICT-FaceKit/FaceXModel/generic_neutral_mesh.obj"
    with tarfile.open(archive) as tar:
        (tmp_path / "head.obj").write_bytes(tar.extractfile(member).read())
    _, session, layout, default = sample
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        mesh = load_mesh(tmp_path / "head.obj")
        build = build_rig(layout, session, mesh=mesh)
    positions = sum(1 for line in open(tmp_path / "head.obj") if line.startswith("v "))
    assert build.rig.vertex_count == positions == 26719
    # the skin, eyes, teeth, gums... 56 parts (was one per triangle), the skin in one piece
    count, part = connected_components(edge_graph(mesh.vertices, mesh.faces), directed=False)
    assert count < 100 and np.bincount(part).max() > 10_000
    assert build.alignment.rms_mm < 0.5
    assert build.check.rmse_mm < default.check.rmse_mm + 0.1
    # its skin never folds over the held-out performance: its uncut lips swapped their 4th joint
    # between neighbours 6 mm below the mouth corners (4 triangles folded; capped continuously
    # there now)
    from pathlib import Path

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.retarget.animate import skin_vertices
    from mocaptk.retarget.build import Capture, bake_capture
    from mocaptk.retarget.mesh_parts import skin_faces

    rig = build.rig
    perf = read_trajectories(Path(__file__).resolve().parents[1] / "sample_c3d"
                             / "dense_halfface_performance.c3d", strip_prefixes=True)
    joints = bake_capture(build, Capture("performance", perf)).translations[:, 1:] + rig.joint_positions[0]
    faces = rig.faces[skin_faces(rig.faces)]

    def normals(p):
        return np.cross(p[..., faces[:, 1], :] - p[..., faces[:, 0], :], p[..., faces[:, 2], :] - p[..., faces[:, 0], :])

    rest = normals(rig.vertices)
    # its lids close in a blink: no weight crosses the eye sockets (across them the lower lids
    # followed the markers under the brow down and the lids closed to 30 % of the aperture)
    from mocaptk.retarget.default_face import loop_area
    from mocaptk.retarget.face_template import fit_template
    from mocaptk.retarget.mesh_openings import open_mesh
    from mocaptk.retarget.mesh_parts import nose_height, parts
    from mocaptk.surface_mesh import marker_spacing

    opened = open_mesh(build.alignment.transform.apply(mesh.vertices), mesh.faces,
                       fit_template(build.cloud.neutral, spacing=marker_spacing(build.cloud.neutral)))
    assert len(opened.lids) == 2 and len(opened.sockets) > 0
    eyes = [np.concatenate([lid.upper, lid.lower[::-1][1:-1]]) for lid in opened.lids]
    aperture = [np.inf, np.inf]
    pieces = parts(rig.vertices, rig.faces, opened.skin,
                   nose_y=nose_height(rig.vertices, rig.faces, opened.skin))
    around_eyes = [members for members, kind in pieces if kind == "lid"]
    for start in range(0, len(joints), 100):  # bounded memory: 100 frames of 26,719 vertices
        moved = joints[start:start + 100] - rig.joint_positions[1:]
        disp = np.concatenate([np.zeros((len(moved), 1, 3)), moved], axis=1)
        posed = skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)
        assert not (np.einsum("ftk,tk->ft", normals(posed), rest) < 0).any()
        aperture = [min(a, loop_area(posed[:, eye]).min() / loop_area(rig.vertices[eye]))
                    for a, eye in zip(aperture, eyes)]
        # the pieces around the eyes: a lash card moves as its lid's margin, a shell over the
        # eye rigidly (following the nearest skin, its halves tore apart in a blink: 8.4x)
        for members in around_eyes:
            shift = posed[:, members] - rig.vertices[members]
            span = np.linalg.norm(shift - shift[:, :1], axis=2).max()
            assert span < 1e-6 or np.ptp(shift[..., 1], axis=1).max() < 5.0
    assert max(aperture) < 0.2  # sample 17.5 % of rest (29.6 % across the sockets)


def test_obj_reader_fans_polygons_and_counts_negative_indices(tmp_path):
    from mocaptk.errors import InputFileError
    from mocaptk.retarget.mesh_io import load_mesh

    path = tmp_path / "quad.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\n"
                    "g a\nusemtl m\nf 1/1 2/2 3/1 4/2\nf -4//1 -2//1 -1//1\n")
    mesh = load_mesh(path)
    assert mesh.vertices.shape == (4, 3)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [0, 2, 3]])
    path.write_text("v 0 0 0\nv 1 0 0\nf 1 2 3\n")
    with pytest.raises(InputFileError, match="missing vertex"):
        load_mesh(path)


def _every(session, step):
    return session.replace(positions=session.positions[::step], metadata={})


def test_marker_surface_separates_the_lips(markers):
    """The marker surface is cut where the motion opens it: no triangle spans the lip line, the
    mouth is its own boundary loop, and no vertex of the upper lip shares an edge with the lower."""
    from mocaptk.surface_mesh import mesh_edges

    _, _, _, build = markers
    mesh = build.report["mesh"]
    cut = {tuple(sorted(pair)) for pair in mesh["opening_edges_cut"]}
    assert ("MOUTH_05_C", "MOUTH_12_C") in cut and len(cut) >= 6
    assert all(a.startswith("MOUTH") and b.startswith("MOUTH") for a, b in cut)
    assert mesh["eye_openings"]["openings"] == 2  # the bundled ICT-FaceKit face: every machine
    assert mesh["boundary_loops"] == 4  # the face's border, the mouth and the two eyes
    labels = build.cloud.labels
    vertex = {label: int(build.dense_vertices[i]) for i, label in enumerate(labels)}
    edges = {tuple(sorted(e)) for e in mesh_edges(build.rig.faces)[0].tolist()}
    assert not any(tuple(sorted((vertex[a], vertex[b]))) in edges for a, b in cut)


def test_bundled_eye_template_is_the_ict_facekit_face():
    """The packaged face region is ICT-FaceKit's neutral face region, vertex for vertex, so the
    eye cut does not depend on the data folder beside the repo."""
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.errors import InputFileError
    from mocaptk.retarget.eye_openings import eye_loops
    from mocaptk.retarget.face_template import template_face

    face, triangles = template_face()
    assert len(eye_loops(face, triangles)) == 2
    try:
        model = load_face_model()
    except InputFileError as exc:
        pytest.skip(str(exc))
    np.testing.assert_array_equal(face, model.neutral[:model.face_vertex_count])
    np.testing.assert_array_equal(triangles, model.face_triangles)


def _true_face(truth) -> tuple[np.ndarray, np.ndarray]:
    """The ICT-FaceKit face region the sample was made from: vertices (V, 3) mm, triangles (T, 3);
    skips without ICT-FaceKit (../shared/data)."""
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.errors import InputFileError

    try:
        model = load_face_model()
    except InputFileError as exc:
        pytest.skip(str(exc))
    return (model.identity_mesh(truth.identity_coefficients)[:model.face_vertex_count],
            model.face_triangles)


def test_marker_surface_opens_the_eyes(markers):
    """No triangle of the marker surface spans an eye of the ICT-FaceKit face the sample was
    made from; the cut is mirror-symmetric and every marker stays on the surface."""
    from mocaptk.retarget.eye_openings import eye_loops
    from mocaptk.surface_mesh import boundary_edges

    truth, _, _, build = markers
    face, triangles = _true_face(truth)
    loops = eye_loops(face, triangles)
    assert len(loops) == 2 and build.report["mesh"]["eye_openings"]["openings"] == 2
    assert build.report["weights"]["mirror_symmetric"]
    faces, vertices = build.rig.faces, build.rig.vertices
    centroids = vertices[faces].mean(axis=1)
    for loop in loops:  # the true eye opening, seen from the front (the eyes look down +Z)
        rim = face[loop]
        inner = (np.abs(centroids[:, 0] - rim[:, 0].mean()) < 0.3 * np.ptp(rim[:, 0])) & \
                (np.abs(centroids[:, 1] - rim[:, 1].mean()) < 0.3 * np.ptp(rim[:, 1]))
        assert not inner.any()
        # the opening is a hole in the surface: boundary vertices ring it
        ring = vertices[np.unique(boundary_edges(faces))]
        near = np.linalg.norm(ring[:, :2] - rim[:, :2].mean(axis=0), axis=1)
        assert (near < np.ptp(rim[:, 0])).sum() >= 6
    assert len(np.unique(faces)) == build.rig.vertex_count


def test_mirrored_guide_rows_replace_their_sources_midline_markers_too(sample):
    from mocaptk.clustering.symmetry import mirror_label
    from mocaptk.retarget.build import guide_rows

    *_, build = sample
    rows = {row.label: row for row in guide_rows(build) if row.number}  # stabilization rows: 0
    mirrored = [c for c in build.layout.clusters if c.mirrored_from]
    with_midline = 0
    for c in mirrored:
        source = rows[c.mirrored_from]
        assert rows[c.representative].replaces == tuple(
            m if m.endswith("_C") else mirror_label(m) for m in source.replaces)
        with_midline += any(m.endswith("_C") for m in source.replaces)
    assert with_midline >= 1  # the layout file keeps those in the source cluster only


def test_mirrored_clusters_influence_their_sources_midline_markers(sample):
    """A mirrored cluster's influence region holds its source's midline members (NOSE_20_R,
    MOUTH_10_R, MOUTH_06_R lacked them): both twins' region masks are 1 there."""
    from mocaptk.clustering.symmetry import mirror_label
    from mocaptk.retarget.build import FALLOFF_SPACINGS, influence_members
    from mocaptk.retarget.influence import edge_graph
    from mocaptk.retarget.weights import region_masks

    *_, build = sample
    clusters = build.layout.clusters
    members = influence_members(clusters)
    index = {c.representative: i for i, c in enumerate(clusters)}
    vertex = dict(zip(build.cloud.labels, build.dense_vertices.tolist()))
    graph = edge_graph(build.rig.vertices, build.rig.faces)
    masks = region_masks(graph, build.regions, len(clusters),
                         falloff_mm=FALLOFF_SPACINGS * build.report["marker_spacing_mm"],
                         members=[[vertex[m] for m in ms] for ms in members])
    shared = 0
    for i, c in enumerate(clusters):
        if c.mirrored_from is None:
            continue
        source = index[c.mirrored_from]
        assert members[i] == tuple(m if m.endswith("_C") else mirror_label(m)
                                   for m in clusters[source].members)
        midline = [m for m in clusters[source].members if m.endswith("_C")]
        assert set(midline) <= set(members[i]) and not set(midline) & set(c.members)
        for m in midline:
            assert masks[vertex[m], i] == masks[vertex[m], source] == 1.0
        shared += len(midline)
    assert shared >= 3  # NOSE_20_R, MOUTH_10_R, MOUTH_06_R's sources hold midline markers


def test_mirrored_layout_gives_mirrored_weights_and_names(sample):
    """Mirrored vertices with L/R joints swapped carry the same weights (< 1e-6; before: up to
    0.27), and every joint's flip_name (swap the trailing _L/_R) is a joint of the rig."""
    from mocaptk.retarget.build import _sagittal_plane
    from mocaptk.retarget.default_face import template_openings

    _, _, _, build = sample
    rig = build.rig
    assert build.report["weights"]["mirror_symmetric"]
    plane = _sagittal_plane(build.layout)
    normal, point = build.cloud.rotation @ plane.normal, build.cloud.rotation @ plane.point
    mirror = template_openings()[2]  # ICT-FaceKit's own pairs (the lips' seam has twins)
    skin = rig.vertices[:len(mirror)]  # the skin; its eyeballs and mouth interior after it
    image = skin - 2 * ((skin - point) @ normal)[:, None] * normal
    assert np.abs(skin[mirror] - image).max() < 1e-9
    flip = {"L": "R", "R": "L", "C": "C"}
    names = list(rig.joint_names)
    assert all(n[:-1] + flip[n[-1]] in names for n in names[1:])
    swap = [0] + [names.index(n[:-1] + flip[n[-1]]) for n in names[1:]]
    weights = rig.dense_weights()[:len(mirror)]
    assert np.abs(weights - weights[mirror][:, swap]).max() < 1e-6


def _faces_against(vertices, faces, surface, surface_faces):
    """Dot (T,) of each triangle's normal with the true surface normal nearest its centroid."""
    from scipy.spatial import cKDTree

    from mocaptk.surface_mesh import face_normals, vertex_normals

    _, nearest = cKDTree(surface).query(vertices[faces].mean(axis=1))
    return np.einsum("ij,ij->i", face_normals(vertices, faces),
                     vertex_normals(surface, surface_faces)[nearest])


def test_marker_surface_does_not_fold_at_the_nostrils(markers):
    """Triangulated in the fitted ICT-FaceKit face's chart, the marker surface follows the true
    skin around the nose (the sphere chart folded it: 46 of the 1,816 triangles face into the
    head there, the worst at 162 degrees from the skin), and a mirrored layout gets a
    mirror-symmetric mesh."""
    from mocaptk.retarget.build import _subdivide, _vertex_mirror
    from mocaptk.surface_mesh import marker_spacing, marker_surface_mesh

    truth, _, layout, build = markers
    face, triangles = _true_face(truth)
    assert build.report["mesh"]["chart"] == "ICT-FaceKit face fitted to the markers"
    rig = build.rig
    dots = _faces_against(rig.vertices, rig.faces, face, triangles)
    sphere = _faces_against(*_subdivide(*marker_surface_mesh(build.cloud.neutral),
                                        build.report["mesh"]["subdivisions"]),
                            face, triangles)
    assert (dots < 0).sum() <= 12 and dots.min() > -0.5  # 10, the worst 103 degrees
    assert (sphere < 0).sum() >= 40 and sphere.min() < -0.9
    mirror = _vertex_mirror(layout, build.cloud, rig.vertices, marker_spacing(build.cloud.neutral))
    mesh = {tuple(sorted(f)) for f in rig.faces.tolist()}
    assert {tuple(sorted(mirror[f].tolist())) for f in rig.faces} == mesh


def test_render_labels_do_not_overlap(sample, tmp_path):
    """The rig renders' marker numbers (40R and 41R overlapped) are placed clear of every other
    label and dot; a label moved away gets a leader line."""
    from mocaptk.retarget.build import guide_rows
    from mocaptk.retarget.renders import _draw_markers

    *_, build = sample
    joints = np.asarray(build.rig.joint_positions)[build.marker_joints]
    width, height = 1050, 1200  # the front view: x right, y up, framed on the markers like it
    half = 1.2 * max(np.ptp(joints[:, 1]) / 2, np.ptp(joints[:, 0]) / 2 * height / width) + 8.0
    scale = height / (2 * half)  # pixels per mm, as render_view's parallel camera
    pixels = np.column_stack([width / 2 + scale * (joints[:, 0] - joints[:, 0].mean()),
                              height / 2 - scale * (joints[:, 1] - joints[:, 1].mean())])
    names = [row.name for row in guide_rows(build)]
    regions = [c.region for c in build.layout.clusters]
    # and a crowd like the c3d session's 40R / 41R: markers 8 px from three of them
    pixels = np.vstack([pixels, pixels[:3] + [6.0, 5.0]])
    names, regions = names + ["40R", "41R", "99L"], regions + regions[:3]
    image = np.full((height, width, 3), 255, np.uint8)
    boxes = _draw_markers(image, pixels, np.ones(len(pixels), bool), regions, names,
                          tmp_path / "f.png", force=True)
    assert (tmp_path / "f.png").stat().st_size > 10_000
    assert np.isfinite(boxes).all()
    for k, box in enumerate(boxes):
        others = np.delete(boxes, k, axis=0)
        overlap = ((box[0] < others[:, 2]) & (others[:, 0] < box[2])
                   & (box[1] < others[:, 3]) & (others[:, 1] < box[3]))
        assert not overlap.any(), names[k]
        dots = np.delete(pixels, k, axis=0)  # 7 pt dots: radius ~5 px
        near = np.clip(dots, box[:2], box[2:])
        assert np.linalg.norm(near - dots, axis=1).min() >= 4.5, names[k]


def test_default_face_closes_its_lips_and_eyes_on_the_performance(sample, markers):
    """The default face on the held-out performance (issue 30): lips closed at rest (seam area
    <= 5 % of the widest opening; measured 0.02 %), open at the widest jaw, the lids closed at
    the true full blink (aperture <= 20 % of rest; measured 8.8 %) and the blink sensed from the
    eye-region markers following the true one (r = 0.98); per region the marker-driven error is
    within 5 % of the marker surface's (mouth 0.26 vs 0.29 mm, nose 0.43 vs 0.42 mm) and the
    mouth's at most 1.5x the others'."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.retarget.build import Capture, held_out_check, jaw_open_frame
    from mocaptk.retarget.default_face import loop_area, template_openings

    _, _, _, build = sample
    rig = build.rig
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    truth = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    animation, posed = _performance_skin(build, perf)
    (upper, lower), eyes, _ = template_openings()
    mouth = loop_area(posed[:, np.concatenate([upper, lower[::-1][1:-1]])])
    rest = loop_area(rig.vertices[np.concatenate([upper, lower[::-1][1:-1]])])
    widest = jaw_open_frame(build, animation)
    assert rest <= 0.05 * mouth[widest] and mouth[widest] > 400  # mm²
    names = list(truth.blendshape_names)
    for (top, bottom), blink in zip(eyes, ("eyeBlink_R", "eyeBlink_L")):
        loop = np.concatenate([top, bottom[::-1][1:-1]])
        aperture = loop_area(posed[:, loop]) / loop_area(rig.vertices[loop])
        weight = truth.weights[:, names.index(blink)]
        assert aperture[int(np.argmax(weight))] <= 0.2
        assert np.corrcoef(weight, 1 - aperture)[0, 1] > 0.95
        assert np.percentile(aperture[weight < 0.05], 5) > 0.8  # open when not blinking
    held = {region: r["rmse_mm"] for region, r in
            held_out_check(build, Capture("performance", perf))["regions"].items()}
    before = {region: r["rmse_mm"] for region, r in
              held_out_check(markers[3], Capture("performance", perf))["regions"].items()}
    assert all(held[r] <= 1.05 * before[r] for r in before), (held, before)
    assert held["mouth"] <= 1.5 * np.mean([v for r, v in held.items() if r != "mouth"])
    assert rig.uv().min() >= 0 and rig.uv().max() <= 1 and rig.texcoords is not None


def _performance_skin(build, capture):
    """The rig's animation of ``capture`` and its skinned mesh (F, V, 3) mm, rig frame."""
    from mocaptk.retarget.animate import skin_vertices
    from mocaptk.retarget.build import Capture, bake_capture

    rig = build.rig
    animation = bake_capture(build, Capture("performance", capture))
    joints = animation.translations[:, 1:] + rig.joint_positions[0]
    disp = np.concatenate([np.zeros((len(joints), 1, 3)), joints - rig.joint_positions[1:]], axis=1)
    return animation, skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)


def test_default_face_lids_neither_fold_nor_tear_on_the_performance(sample):
    """Around the eyes (within 15 mm of an opening) no triangle of the default rig faces
    backward against its rest in any frame of the held-out performance and no edge stretches
    past 2x its rest length (issue 30; measured 0 and 1.98x; before: 146 folded triangles at
    the full blink and 4.71x, from lid weights dropped by the capping, a blink counted twice and
    the eye corners' torn weights). Over the whole face no triangle faces backward either (the
    template's two slivers inside the mouth corners are flipped) and the largest stretch is
    1.985x (was 2.62x, then 2.077x below the mouth corners at the widest jaw, now 1.978x there:
    the lip markers' own vertices take 70 % of the corner blend, CORNER_PIN_HOLD). Farther than
    20 mm from them it is 1.99x (was 2.06x behind the ears, where the weights were ratios of
    tiny masked thin-shell weights; now filled harmonically)."""
    from scipy.spatial import cKDTree

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.retarget.default_face import template_openings

    _, _, _, build = sample
    rig = build.rig
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    _, posed = _performance_skin(build, perf)
    _, eyes, _ = template_openings()
    rims = rig.vertices[np.concatenate([np.concatenate(eye) for eye in eyes])]
    skin = rig.faces[rig.materials == 0]  # the eyeballs and mouth interior: tests/test_face_parts.py
    faces = skin[cKDTree(rims).query(rig.vertices[skin].mean(axis=1))[0] < 15.0]
    edges = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)

    def normals(points):
        return np.cross(points[..., faces[:, 1], :] - points[..., faces[:, 0], :],
                        points[..., faces[:, 2], :] - points[..., faces[:, 0], :])

    backward = np.einsum("ftk,tk->ft", normals(posed), normals(rig.vertices)) < 0
    rest = np.linalg.norm(rig.vertices[edges[:, 0]] - rig.vertices[edges[:, 1]], axis=1)
    stretch = np.linalg.norm(posed[:, edges[:, 0]] - posed[:, edges[:, 1]], axis=2) / rest
    assert len(faces) > 2000 and backward.sum(axis=1).max() == 0
    assert stretch.max() <= 2.0, stretch.max()
    faces = skin
    edges = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    assert (np.einsum("ftk,tk->ft", normals(posed), normals(rig.vertices)) < 0).sum() == 0
    rest = np.linalg.norm(rig.vertices[edges[:, 0]] - rig.vertices[edges[:, 1]], axis=1)
    stretch = np.linalg.norm(posed[:, edges[:, 0]] - posed[:, edges[:, 1]], axis=2) / rest
    assert stretch.max() <= 2.0 and np.percentile(stretch.max(axis=0), 99.9) <= 1.95
    (upper, _), _, _ = template_openings()
    middle = rig.vertices[edges].mean(axis=1)
    corners = rig.vertices[[upper[0], upper[-1]]]
    far = np.linalg.norm(middle[:, None] - corners, axis=2).min(axis=1) >= 20
    assert stretch[:, far].max() <= 2.0, stretch[:, far].max()
