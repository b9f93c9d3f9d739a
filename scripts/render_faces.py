"""Render the faces of issue 30 for docs/renders/: the default rig, solve's mesh, and rigs on the
MediaPipe canonical face and the ICT-FaceKit head given with ``--mesh``, each at rest, at the
widest jaw opening, the strongest smile and the fullest blink of the sample performance, front
and three-quarter (one PNG per face: 2 rows x 4 poses).

The poses are found on the default rig's own animation (largest mouth opening, largest mouth
width, smallest eye aperture) and used for every face. Usage (from the repository root, with
../shared/data or $MOCAPTK_SHARED_DATA):

    python scripts/render_faces.py [out folder, default docs/renders] [--mesh-only | --default-only]

``--mesh-only``: the ``--mesh`` faces only (the poses still come from the default rig);
``--default-only``: the default rig and solve's mesh only. Each triangle is drawn in its
material's colour and opacity (:mod:`~mocaptk.retarget.face_materials`, as the exported files
carry them): the default face's eyeballs, teeth and mouth socket, a user head's teeth, eyeballs
and gums, and its lash cards and eye shells dark and translucent (drawn opaque they hid the lids
and stood out past the brow). Each view is framed to fit the skin in all four poses.
"""

from __future__ import annotations

import os
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_c3d"
VIEWS = {"front": (0.0, 0.0, 1.0), "three-quarter": (0.62, 0.05, 0.78)}
POSES = ("rest", "widest jaw", "strongest smile", "full blink")
WINDOW = (480, 560)
VIEW_ANGLE_DEG = 22.0


def cells_of(faces: np.ndarray) -> np.ndarray:
    """pyvista's cell array of triangles ``faces`` (T, 3)."""
    return np.hstack([np.full((len(faces), 1), 3), faces]).ravel()


def main(argv: list[str]) -> None:
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import build_rig
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver
    from mocaptk.retarget.solve_outputs import face_mesh

    mesh_only, default_only = "--mesh-only" in argv, "--default-only" in argv
    argv = [a for a in argv if a not in ("--mesh-only", "--default-only")]
    out = Path(argv[0]) if argv else REPO / "docs" / "renders"
    out.mkdir(parents=True, exist_ok=True)
    truth = load_ground_truth(SAMPLE / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    perf = read_trajectories(SAMPLE / "dense_halfface_performance.c3d", strip_prefixes=True)
    build = build_rig(layout, session, check=False)
    frames = pose_frames(build, skinned(build, perf))
    print("frames (rest, jaw, smile, blink):", frames)
    if not mesh_only:
        render(skinned(build, perf, frames), build.rig.faces, out / "default_rig.png",
               "default rig (rig.fbx / rig.glb)", materials=build.rig.materials)
        solver = train_solver(layout, session, {"path": "sample", "sha256": None})
        mesh = face_mesh(solver, layout)
        dense = np.concatenate([c.positions for c in solve_chunks(
            solver, layout_frames(solver, perf, "performance")[frames[1:]])])
        poses = np.concatenate([mesh.vertices[None], mesh.apply(dense)])
        render(poses @ build.cloud.rotation.T, mesh.faces, out / "solve_mesh.png",
               "solve's mesh (mesh.usd / mesh.glb)", materials=mesh.materials)
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, title in ([] if default_only else user_meshes(Path(tmp))):
            user = build_rig(layout, session, mesh=load_mesh(path), check=False)
            render(skinned(user, perf, frames), user.rig.faces, out / f"{name}.png", title,
                   materials=user.rig.materials)


def user_meshes(tmp: Path) -> list[tuple[str, Path, str]]:
    """(name, path, title) of the ``--mesh`` faces from ../shared/data: the MediaPipe canonical
    face and the ICT-FaceKit head (extracted into ``tmp``)."""
    shared = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data"))
    tarball = shared / "face_mesh" / "ict_facekit" / "ict_facekit_FaceXModel_subset.tar.xz"
    with tarfile.open(tarball) as tar:
        member = tar.extractfile("ICT-FaceKit/FaceXModel/generic_neutral_mesh.obj")
        (tmp / "head.obj").write_bytes(member.read())
    return [("mediapipe", shared / "face_mesh" / "mediapipe" / "canonical_face_model.obj",
             "--mesh MediaPipe canonical face"),
            ("ict_head", tmp / "head.obj", "--mesh ICT-FaceKit head")]


def skinned(build, capture, frames=None) -> np.ndarray:
    """The rig's mesh (F, V, 3) mm over ``capture`` (head-relative), or at ``frames`` (0: rest)."""
    from mocaptk.retarget.animate import skin_vertices
    from mocaptk.retarget.build import Capture, bake_capture

    rig = build.rig
    animation = bake_capture(build, Capture("performance", capture))
    joints = animation.translations[:, 1:] + rig.joint_positions[0]
    if frames is not None:
        joints = np.concatenate([rig.joint_positions[None, 1:], joints[frames[1:]]])
    disp = np.concatenate([np.zeros((len(joints), 1, 3)), joints - rig.joint_positions[1:]], axis=1)
    return skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)


def pose_frames(build, posed: np.ndarray) -> list[int]:
    """[rest, widest jaw, strongest smile, fullest blink] frames of the default face animation
    (rest: a placeholder 0, rendered from the bind pose)."""
    from mocaptk.retarget.default_face import loop_area, template_openings

    (upper, lower), eyes, _ = template_openings()
    mouth = loop_area(posed[:, np.concatenate([upper, lower[::-1][1:-1]])])
    width = np.linalg.norm(posed[:, upper[0]] - posed[:, upper[-1]], axis=1)
    eye = sum(loop_area(posed[:, np.concatenate([t, b[::-1][1:-1]])]) for t, b in eyes)
    closed = mouth < np.percentile(mouth, 50)  # a smile, not a wide-open mouth
    return [0, int(np.argmax(mouth)), int(np.argmax(np.where(closed, width, -np.inf))),
            int(np.argmin(eye))]




def camera_distance(points: np.ndarray, centre: np.ndarray, direction: np.ndarray) -> float:
    """How far (mm) from ``centre`` along the unit ``direction`` the camera fits ``points``
    (V, 3) mm in the window with a 6 % margin on each side (both its width and its height)."""
    back = -direction / np.linalg.norm(direction)
    right = np.cross(back, (0.0, 1.0, 0.0))
    right /= np.linalg.norm(right)
    up = np.cross(right, back)
    rel = points - centre
    tan_y = np.tan(np.radians(VIEW_ANGLE_DEG) / 2.0) / 1.06
    tan_x = tan_y * WINDOW[0] / WINDOW[1]
    toward = rel @ -back  # how much nearer the camera than the centre
    return float(np.max(np.maximum(np.abs(rel @ right) / tan_x, np.abs(rel @ up) / tan_y) + toward))


def render(poses: np.ndarray, faces: np.ndarray, path: Path, title: str, *,
           materials: np.ndarray | None = None) -> None:
    """A 2 x 4 grid (views x poses) of ``poses`` (4, V, 3) mm, rig frame, into ``path``;
    ``materials`` (T,) each triangle's, drawn in its colour and opacity (default: all skin)."""
    import matplotlib.pyplot as plt
    import pyvista as pv

    from mocaptk.retarget.face_materials import LOOKS, MATERIALS

    pv.OFF_SCREEN = True
    kinds = np.zeros(len(faces), int) if materials is None else np.asarray(materials)
    looks = [(k, *LOOKS[name]) for k, name in enumerate(MATERIALS)]
    skin = faces[kinds == 0]
    centre = poses[0][np.unique(skin)].mean(axis=0)
    fig, axes = plt.subplots(2, 4, figsize=(12, 7.6))
    for row, (view, direction) in enumerate(VIEWS.items()):
        direction = np.array(direction) / np.linalg.norm(direction)
        distance = camera_distance(poses[:, np.unique(skin)].reshape(-1, 3), centre, direction)
        for col, (pose, points) in enumerate(zip(POSES, poses)):
            plotter = pv.Plotter(off_screen=True, window_size=WINDOW)
            plotter.set_background("white")
            plotter.enable_depth_peeling()  # the translucent pieces in depth order
            for kind, colour, opacity in looks:
                if (kinds == kind).any():
                    plotter.add_mesh(pv.PolyData(np.asarray(points, float), cells_of(faces[kinds == kind])),
                                     color=colour, opacity=opacity, smooth_shading=True, specular=0.2)
            plotter.camera_position = [tuple(centre + distance * direction), tuple(centre),
                                       (0.0, 1.0, 0.0)]
            plotter.camera.view_angle = VIEW_ANGLE_DEG
            axes[row, col].imshow(plotter.screenshot(return_img=True))
            plotter.close()
            axes[row, col].set_axis_off()
            if row == 0:
                axes[row, col].set_title(pose)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    print("wrote", path)


if __name__ == "__main__":
    main(sys.argv[1:])
