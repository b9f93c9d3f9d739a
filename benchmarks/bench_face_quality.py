"""Skin quality of the issue-30 faces over the sample's held-out performance (1,200 frames):
the most triangles facing backward against the rest pose in one frame, and the largest edge
stretch (and its 99.9th percentile over the edges), for the default rig and rigs on the
MediaPipe canonical face and the ICT-FaceKit head given with ``--mesh``: on the face surface
(the skin, the mesh's largest part), and apart on its other parts (teeth, eyeballs, lashes). Usage (repository
root, with ../shared/data or $MOCAPTK_SHARED_DATA):

    python benchmarks/bench_face_quality.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))


def quality(posed: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> tuple[int, float, float]:
    """(most backward triangles in a frame, max edge stretch, its 99.9th percentile over edges)
    of ``posed`` (F, V, 3) against ``rest`` (V, 3)."""
    edges = np.unique(np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    stretch = (np.linalg.norm(posed[:, edges[:, 0]] - posed[:, edges[:, 1]], axis=2) / length).max(axis=0)

    def normals(p: np.ndarray) -> np.ndarray:
        return np.cross(p[..., faces[:, 1], :] - p[..., faces[:, 0], :],
                        p[..., faces[:, 2], :] - p[..., faces[:, 0], :])

    backward = np.einsum("ftk,tk->ft", normals(posed), normals(rest)) < 0
    return int(backward.sum(axis=1).max()), float(stretch.max()), float(np.percentile(stretch, 99.9))


def main() -> None:
    from render_faces import SAMPLE, skinned, user_meshes

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import build_rig
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.mesh_parts import skin_faces

    truth = load_ground_truth(SAMPLE / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    perf = read_trajectories(SAMPLE / "dense_halfface_performance.c3d", strip_prefixes=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name, path in [("default rig", None)] + [(title, path) for _, path, title
                                                     in user_meshes(Path(tmp))]:
            build = build_rig(layout, session, mesh=None if path is None else load_mesh(path),
                              check=False)
            posed, faces = skinned(build, perf), build.rig.faces
            skin = skin_faces(faces)
            for part, chosen in (("", skin), (" (its other parts)", ~skin)):
                if chosen.any():
                    back, worst, p999 = quality(posed, build.rig.vertices, faces[chosen])
                    print(f"{name}{part}: most backward triangles in a frame {back}, max edge "
                          f"stretch {worst:.2f}x (99.9th percentile {p999:.2f}x)")


if __name__ == "__main__":
    main()
