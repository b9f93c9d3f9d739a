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
    python benchmarks/bench_face_quality.py --default
    python benchmarks/bench_face_quality.py --actor LAYOUT.json SESSION.c3d [CAPTURE.c3d]

``--default``: the default face only, the rig and ``solve``'s mesh side by side (folds, stretch
overall and within 20 mm of a mouth corner, the mouth's seam at rest of its widest opening,
the lids' aperture at the true full blink, and the error per region: the rig's held-out
marker-driven RMSE, the solve mesh's at its dense markers' vertices against the noise-free
truth). ``--actor``: the default rig of another actor's layout and session (as ``mocaptk rig``
reads them), skinned over ``CAPTURE`` (default: the session itself), folds and stretch
(docs/default-face.md has the command lines of the actors measured).
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


def stretch_near_mouth(posed: np.ndarray, rest: np.ndarray, faces: np.ndarray) -> str:
    """``quality`` overall and within 20 mm of a mouth corner (the default face's), as text."""
    from mocaptk.retarget.default_face import template_openings

    (upper, _), _, _ = template_openings()
    near = np.linalg.norm(rest[faces].mean(axis=1)[:, None] - rest[[upper[0], upper[-1]]],
                          axis=2).min(axis=1) < 20.0
    back, worst, p999 = quality(posed, rest, faces)
    return (f"most backward triangles in a frame {back}, max edge stretch {worst:.3f}x (99.9th "
            f"percentile {p999:.3f}x), within 20 mm of a mouth corner "
            f"{quality(posed, rest, faces[near])[1]:.3f}x")


def default_face() -> None:
    """The default face's rig and solve's mesh on the sample performance (``--default``)."""
    from render_faces import SAMPLE, skinned

    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.build import Capture, bake_capture, build_rig, held_out_check, jaw_open_frame
    from mocaptk.retarget.default_face import loop_area, template_openings
    from mocaptk.retarget.solve import layout_frames, solve_chunks, train_solver
    from mocaptk.retarget.solve_outputs import face_mesh

    truth = load_ground_truth(SAMPLE / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    perf = read_trajectories(SAMPLE / "dense_halfface_performance.c3d", strip_prefixes=True)
    held = load_ground_truth(SAMPLE / "dense_halfface_performance_truth.npz")
    names = list(held.blendshape_names)
    (upper, lower), eyes, _ = template_openings()
    mouth = np.concatenate([upper, lower[::-1][1:-1]])

    def openings(posed: np.ndarray, rest: np.ndarray, widest: int) -> str:
        apertures = []
        for (top, bottom), blink in zip(eyes, ("eyeBlink_R", "eyeBlink_L")):
            loop = np.concatenate([top, bottom[::-1][1:-1]])
            full = int(np.argmax(held.weights[:, names.index(blink)]))
            apertures.append(100 * loop_area(posed[full, loop]) / loop_area(rest[loop]))
        return (f"mouth at rest {100 * loop_area(rest[mouth]) / loop_area(posed[widest, mouth]):.2f} "
                f"% of the widest (frame {widest}); eyes at the true full blink "
                + ", ".join(f"{a:.1f} %" for a in apertures) + " of rest")

    def regions(errors: dict[str, float]) -> str:
        others = np.mean([v for k, v in errors.items() if k != "mouth"])
        return (", ".join(f"{k} {v:.3f}" for k, v in sorted(errors.items()))
                + f" mm; mouth / the others' mean {errors['mouth'] / others:.2f}")

    build = build_rig(layout, session, check=False)
    rig = build.rig
    posed = skinned(build, perf)
    widest = jaw_open_frame(build, bake_capture(build, Capture("performance", perf)))
    print(f"default rig: {stretch_near_mouth(posed, rig.vertices, rig.faces)}")
    print(f"default rig: {openings(posed, rig.vertices, widest)}")
    check = held_out_check(build, Capture("performance", perf))["regions"]
    print(f"default rig: held-out RMSE {regions({k: v['rmse_mm'] for k, v in check.items()})}")

    solver = train_solver(layout, session, {"path": "sample", "sha256": None})
    mesh = face_mesh(solver, layout)
    dense = np.concatenate([c.positions for c in solve_chunks(solver, layout_frames(solver, perf, "p"))])
    frames = mesh.apply(dense)
    print(f"solve's mesh: {stretch_near_mouth(frames, mesh.vertices, mesh.faces)}")
    print(f"solve's mesh: {openings(frames, mesh.vertices, int(np.nanargmax(loop_area(frames[:, mouth]))))}")
    true = held.trajectories()
    seen = np.flatnonzero(np.isfinite(solver.model.neutral).all(axis=1))
    vertex = np.argmax(np.asarray(mesh.matrix)[:, seen], axis=0)  # each marker's own vertex
    moved = frames[:, vertex] + (solver.model.neutral[seen] - mesh.vertices[vertex])
    error = np.linalg.norm(moved - true.positions[:, true.index([solver.labels[i] for i in seen])], axis=2)
    region_of = {m: c.region for c in layout.clusters for m in c.members}
    by_region = np.array([region_of.get(solver.labels[i], "none") for i in seen])
    print("solve's mesh: RMSE at its markers' vertices against the truth " + regions(
        {r: float(np.sqrt(np.nanmean(error[:, by_region == r] ** 2))) for r in np.unique(by_region)}))


def actor(layout_path: Path, session_path: Path, capture_path: Path | None) -> None:
    """The default rig of another actor (``--actor``): folds and stretch over its capture."""
    from mocaptk.cli.rig import animation_captures
    from mocaptk.clustering.layout import layout_rigid_set, read_layout
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.retarget.build import build_rig
    from render_faces import skinned

    layout = read_layout(layout_path)
    raw, _ = load_session(session_path)
    session = stabilize(raw, rigid=layout_rigid_set(layout))[0] if layout.parameters.get("stabilized") else raw
    captures = animation_captures(layout, raw, session, [capture_path] if capture_path else [])
    build = build_rig(layout, session, check=False)
    posed = skinned(build, captures[-1].relative)
    print(f"{layout_path} ({len(layout.clusters)} joints, {build.rig.vertex_count} vertices) over "
          f"{captures[-1].name} ({len(posed)} frames): "
          f"{stretch_near_mouth(posed, build.rig.vertices, build.rig.faces)}")


def main() -> None:
    if "--default" in sys.argv:
        return default_face()
    if "--actor" in sys.argv:
        paths = [Path(p) for p in sys.argv[sys.argv.index("--actor") + 1:]]
        return actor(paths[0], paths[1], paths[2] if len(paths) > 2 else None)

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
