"""``rig --keep-mesh-space`` (issue 30): the rig files in the given mesh's own coordinates, the
motion scaled to it, on the MediaPipe canonical face (in cm: the fit scales it 9.6x)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_path
from test_retarget_rig import sample  # noqa: F401 (the sample's session and layout: a fixture)
from test_rig_hierarchy import hierarchy_skinned

SAMPLES = Path(__file__).resolve().parents[1] / "sample_c3d"


@pytest.mark.slow
def test_the_mesh_space_rig_deforms_as_the_fitted_one_mapped_back(sample):
    """The head/jaw rig moved into the mesh's space: its mesh is the file's, and at every 50th
    frame of the held-out performance its skinned mesh is the marker-frame one mapped back by
    the fit's inverse (< 1e-9 mm; sample 7e-15), jaw rotations included."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.retarget.build import Capture, bake_capture, build_rig, file_hierarchy
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.mesh_space import animation_in_space, inverse, rig_in_space
    from mocaptk.retarget.rig_hierarchy import hierarchical_animation

    _, session, layout, _ = sample
    mesh = load_mesh(shared_path("face_mesh", "mediapipe", "canonical_face_model.obj"))
    build = build_rig(layout, session, mesh=mesh, check=False)
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    hierarchy = file_hierarchy(build)
    keyed = hierarchical_animation(hierarchy, bake_capture(build, Capture("performance", perf)))
    back = inverse(build.alignment.transform)
    assert back.scale == pytest.approx(1 / 9.64, rel=0.02)  # the head is kept at its own size
    rig, animation = rig_in_space(hierarchy.rig, back), animation_in_space(keyed, back)
    own = np.delete(mesh.vertices, build.report["mesh"]["eye_openings"]["vertices_removed"], axis=0)
    np.testing.assert_allclose(rig.vertices[:len(own)], own, atol=1e-9)  # the eyes' insides cut
    frames = np.arange(0, keyed.frame_count, 50)
    fitted = hierarchy_skinned(hierarchy.rig, keyed, frames)
    kept = hierarchy_skinned(rig, animation, frames)
    assert np.abs(back.apply(fitted) - kept).max() < 1e-9
    motion = np.abs(kept - kept[:1]).max()
    assert motion > 0.1  # cm: the jaw still opens, scaled to the mesh


@pytest.mark.slow
def test_cli_rig_keep_mesh_space_writes_the_mesh_where_it_is(sample, tmp_path, run_cli):
    from mocaptk.clustering.layout import write_layout
    from mocaptk.retarget.export_json import read_rig_json
    from mocaptk.retarget.mesh_io import load_mesh

    _, _, layout, _ = sample
    write_layout(layout, tmp_path / "layout.json")
    path = shared_path("face_mesh", "mediapipe", "canonical_face_model.obj")
    result = run_cli("rig", tmp_path / "layout.json", "--session",
                     SAMPLES / "dense_halfface_performance.c3d", "--out", tmp_path / "o",
                     "--no-stabilize", "--formats", "json", "--mesh", path, "--keep-mesh-space")
    assert result.exit_code == 0, result.stderr
    rig = read_rig_json(tmp_path / "o" / "rig.json")
    mesh = load_mesh(path)
    report = json.loads((tmp_path / "o" / "rig_report.json").read_text())
    own = np.delete(mesh.vertices, report["mesh"]["eye_openings"]["vertices_removed"], axis=0)
    np.testing.assert_allclose(rig.vertices[:len(own)], own, atol=1e-6)
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    joints = rig.joint_positions[3:3 + len(layout.clusters)]  # after face_root, head, jaw
    assert ((joints > low - 1.0) & (joints < high + 1.0)).all()  # on the mesh (cm)
    assert report["mesh_space"]["kept"] and report["mesh_space"]["motion_scale"] < 0.2
