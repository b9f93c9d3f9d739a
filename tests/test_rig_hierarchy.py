"""retarget/rig_hierarchy.py: the jaw's pivot and rotation, and a hierarchy that deforms the mesh
exactly as the flat rig does (the sample's rig driven by its held-out performance)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mocaptk.retarget.rig_hierarchy import fit_jaw_pivot, jaw_rotations


def _opening(pivot, bind, angles):
    rot = Rotation.from_euler("x", np.asarray(angles)[:, None]).as_matrix()
    return np.einsum("fij,nj->fni", rot, bind - pivot) + pivot, rot


def test_a_hinge_gives_back_its_pivot_and_angles():
    rng = np.random.default_rng(0)
    bind = rng.normal([0.0, -60.0, 100.0], [25.0, 8.0, 6.0], (20, 3))
    pivot = np.array([0.0, -5.0, 20.0])
    angles = np.radians(np.linspace(0.0, 25.0, 50))
    frames, rot = _opening(pivot, bind, angles)
    frames += rng.normal(0.0, 0.2, frames.shape)  # marker noise
    fit = fit_jaw_pivot(bind, frames, midline_x=0.0)
    assert fit.method == "fitted" and np.linalg.norm(fit.position - pivot) < 3.0
    got = jaw_rotations(bind, frames, fit.position)
    error = Rotation.from_matrix(np.einsum("fji,fjk->fik", rot, got)).magnitude()
    assert np.degrees(error).max() < 0.5


def test_no_opening_or_a_pivot_in_front_of_the_chin_gives_the_default():
    bind = np.array([[0.0, -70.0, 100.0], [20.0, -60.0, 95.0], [-20.0, -60.0, 95.0],
                     [0.0, -50.0, 105.0]])
    still = fit_jaw_pivot(bind, np.repeat(bind[None], 10, axis=0), midline_x=0.0)
    assert still.method == "default" and still.position[2] < bind[:, 2].max() - 20.0
    ahead, _ = _opening(np.array([0.0, -40.0, 180.0]), bind, np.radians(np.linspace(0, 20, 30)))
    assert fit_jaw_pivot(bind, ahead, midline_x=0.0).method == "default"


@pytest.mark.slow
def hierarchy_skinned(rig, animation, frames: np.ndarray) -> np.ndarray:
    """``rig``'s mesh (n, V, 3) mm at ``frames`` of ``animation``, linear blend skinning over the
    joints' world rotations and positions (identity bind rotations)."""
    rotations, positions = animation.world_transforms(frames)
    out = np.zeros((len(frames), rig.vertex_count, 3))
    for k in range(rig.max_influences):
        j, w = rig.weight_index[:, k], rig.weight_value[:, k]
        out += w[None, :, None] * (np.einsum("fvij,vj->fvi", rotations[:, j],
                                             rig.vertices - rig.joint_positions[j])
                                   + positions[:, j])
    return out


def test_the_hierarchy_deforms_the_mesh_as_the_flat_rig():
    """On the sample's rig and held-out performance (1,200 frames): the same skinned mesh
    (< 1e-6 mm) at every 50th frame, and the jaw opens."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import Capture, bake_capture, build_rig, file_hierarchy
    from mocaptk.retarget.rig_hierarchy import hierarchical_animation

    from conftest import SAMPLES

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    build = build_rig(layout, session, check=False)
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    flat = bake_capture(build, Capture("performance", perf))
    hierarchy = file_hierarchy(build)
    keyed = hierarchical_animation(hierarchy, flat)
    frames = np.arange(0, flat.frame_count, 50)

    gap = np.abs(hierarchy_skinned(build.rig, flat, frames)
                 - hierarchy_skinned(hierarchy.rig, keyed, frames)).max()
    print(f"hierarchy vs flat rig: skinned mesh differs by at most {gap:.2g} mm")
    assert gap < 1e-6
    jaw = np.degrees(Rotation.from_quat(keyed.rotations[:, keyed.rotated.index(2)]).magnitude())
    print(f"jaw rotation: median {np.median(jaw):.2f} deg, max {jaw.max():.1f} deg")
    assert jaw.max() > 10.0 and np.median(jaw) < 5.0
