"""Skin quality of the issue-30 faces over the sample's held-out performance (1,200 frames):
the most triangles facing backward against the rest pose in one frame, and the largest edge
stretch (and its 99.9th percentile over the edges), for the default rig and rigs on the
MediaPipe canonical face and the ICT-FaceKit head given with ``--mesh``: on the face surface
(the skin, the mesh's largest part), and apart on its other parts (teeth, eyeballs, lashes).
The ``--mesh`` faces also as ``solve --mesh`` moves them, skin and parts apart. For the
``--mesh`` faces also the mouth opening seen from the front at rest and at the widest
jaw (:func:`visible_opening`) and each eye's aperture at the fullest blink (the area inside its
lid rims, of rest). Usage (repository root, with ../shared/data or $MOCAPTK_SHARED_DATA):

    python benchmarks/bench_face_quality.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
#: Seen from the front, skin this far (mm) behind the lip line at rest is inside the mouth.
DEPTH_MM = 3.0
#: The front view's pixel (mm).
PIXEL_MM = 0.25


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


def visible_opening(points: np.ndarray, rest: np.ndarray, faces: np.ndarray, skin: np.ndarray,
                    curve: np.ndarray) -> float:
    """The mouth's opening (mm²) seen from the front (orthographic along -Z, rig frame) in the
    pose ``points`` (V, 3) mm: in a box around the lip mid-curve ``curve`` (K, 3) mm, the pixels
    whose front-most surface is nothing, a part other than the skin (``skin`` (T,) bool; teeth,
    tongue) or skin that lay :data:`DEPTH_MM` behind the lip line at ``rest`` (the mouth
    socket), in the regions the lips enclose (not touching the box's border). A mesh's own
    mouth socket (the ICT-FaceKit head) counts as open, as a hole does."""
    from scipy import ndimage

    order = np.argsort(curve[:, 0])
    cx, cy, cz = curve[order].T
    x0, y0 = cx.min() - 6.0, cy.min() - 40.0  # the jaw drops the lower lip ~30 mm
    gx = np.arange(x0, cx.max() + 6.0, PIXEL_MM) + PIXEL_MM / 2
    gy = np.arange(y0, cy.max() + 6.0, PIXEL_MM) + PIXEL_MM / 2
    depth = np.full((len(gy), len(gx)), -np.inf)
    inside = np.ones((len(gy), len(gx)), bool)
    centre = rest[faces].mean(axis=1)
    deep = ~skin | (centre[:, 2] < np.interp(centre[:, 0], cx, cz) - DEPTH_MM)
    corners = points[faces]
    low, high = corners[..., :2].min(axis=1), corners[..., :2].max(axis=1)
    for t in np.flatnonzero((high[:, 0] > gx[0]) & (low[:, 0] < gx[-1]) & (high[:, 1] > gy[0])
                            & (low[:, 1] < gy[-1])):
        (i0, i1), (j0, j1) = np.searchsorted(gx, [low[t, 0], high[t, 0]]), np.searchsorted(gy, [low[t, 1], high[t, 1]])
        a, b, c = corners[t]
        det = (b[1] - c[1]) * (a[0] - c[0]) + (c[0] - b[0]) * (a[1] - c[1])
        if i1 <= i0 or j1 <= j0 or abs(det) < 1e-12:
            continue
        x, y = np.meshgrid(gx[i0:i1] - c[0], gy[j0:j1] - c[1])
        u = ((b[1] - c[1]) * x + (c[0] - b[0]) * y) / det
        v = ((c[1] - a[1]) * x + (a[0] - c[0]) * y) / det
        z = u * a[2] + v * b[2] + (1.0 - u - v) * c[2]
        front = (u >= 0) & (v >= 0) & (u + v <= 1) & (z > depth[j0:j1, i0:i1])
        depth[j0:j1, i0:i1][front] = z[front]
        inside[j0:j1, i0:i1][front] = deep[t]
    label, _ = ndimage.label(inside)
    border = np.unique(np.concatenate([label[0], label[-1], label[:, 0], label[:, -1]]))
    return float(((label > 0) & ~np.isin(label, border)).sum() * PIXEL_MM ** 2)


def openings(build, mesh, posed: np.ndarray, perf) -> str:
    """The ``--mesh`` face's mouth opening at rest and at the widest jaw, and its eyes' aperture
    at the fullest blink, as a line; the lid rims are the ones ``rig`` made
    (:func:`~mocaptk.retarget.mesh_openings.open_mesh` again, on the same fit)."""
    from mocaptk.retarget.build import Capture, bake_capture, jaw_open_frame
    from mocaptk.retarget.default_face import loop_area
    from mocaptk.retarget.face_template import fit_template
    from mocaptk.retarget.mesh_openings import lip_midcurve, open_mesh
    from mocaptk.retarget.mesh_parts import skin_faces
    from mocaptk.surface_mesh import marker_spacing

    rig = build.rig
    template = fit_template(build.cloud.neutral, spacing=marker_spacing(build.cloud.neutral))
    opened = open_mesh(build.alignment.transform.apply(mesh.vertices), mesh.faces, template)
    jaw = jaw_open_frame(build, bake_capture(build, Capture("performance", perf)))
    skin, curve = skin_faces(rig.faces), lip_midcurve(template)
    rest, wide = (visible_opening(p, rig.vertices, rig.faces, skin, curve) for p in (rig.vertices, posed[jaw]))
    eyes = []
    for lid in opened.lids:
        loop = np.concatenate([lid.upper, lid.lower[::-1][1:-1]])
        eyes.append(f"{100 * loop_area(posed[:, loop]).min() / loop_area(rig.vertices[loop]):.1f} %")
    return (f"mouth seen from the front {rest:.1f} mm² at rest, {wide:.1f} mm² at the widest jaw "
            f"(frame {jaw}): {100 * rest / wide:.1f} %; eyes at the fullest blink "
            + ", ".join(eyes) + " of rest")


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
            mesh = None if path is None else load_mesh(path)
            build = build_rig(layout, session, mesh=mesh, check=False)
            posed, faces = skinned(build, perf), build.rig.faces
            skin = skin_faces(faces)
            for part, chosen in (("", skin), (" (its other parts)", ~skin)):
                if chosen.any():
                    back, worst, p999 = quality(posed, build.rig.vertices, faces[chosen])
                    print(f"{name}{part}: most backward triangles in a frame {back}, max edge "
                          f"stretch {worst:.2f}x (99.9th percentile {p999:.2f}x)")
            if mesh is not None:
                print(f"{name}: {openings(build, mesh, posed, perf)}")
        solve_meshes(layout, session, perf, user_meshes(Path(tmp)))


def solve_meshes(layout, session, perf, meshes) -> None:
    """The same measures of ``solve --mesh`` (:func:`~mocaptk.retarget.solve_outputs.user_mesh`,
    parts moving as the rig's) over the solved performance, for each (name, path, title)."""
    from mocaptk.retarget.mesh_parts import skin_faces
    from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver
    from mocaptk.retarget.solve_outputs import user_mesh

    solver = train_solver(layout, session, {"path": "sample", "sha256": None})
    dense = np.concatenate([c.positions for c in solve_chunks(solver, layout_frames(solver, perf, "p"))])
    for _, path, title in meshes:
        mesh, _ = user_mesh(path, solver.model.neutral, layout=layout, labels=solver.labels,
                            head=(solver.fallback_labels or (None,))[0])
        posed = mesh.apply(dense)
        skin = skin_faces(mesh.faces)
        for part, chosen in (("", skin), (" (its other parts)", ~skin)):
            if chosen.any():
                back, worst, p999 = quality(posed, mesh.vertices, mesh.faces[chosen])
                print(f"solve {title}{part}: most backward triangles in a frame {back}, max edge "
                      f"stretch {worst:.2f}x (99.9th percentile {p999:.2f}x)")


if __name__ == "__main__":
    main()
