"""The default face's eyeballs and mouth interior (issue 30) on the bundled half-face sample: they
exist, stay behind the skin at rest, at the widest jaw, the strongest smile and the full blink of
the held-out performance, the lower teeth follow the jaw and the socket stays on the lips."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SAMPLES


@pytest.fixture(scope="module")
def rigs():
    """The sample's default rig with its parts and without, and the held-out performance skinned
    (F, V, 3) mm, rig frame, with the frames of its widest jaw, strongest smile and full blinks."""
    from mocaptk.acquisition.formats import read_trajectories
    from mocaptk.acquisition.synth_session import load_ground_truth
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.retarget.animate import skin_vertices
    from mocaptk.retarget.build import Capture, RigOptions, bake_capture, build_rig, jaw_open_frame

    truth = load_ground_truth(SAMPLES / "dense_halfface_truth.npz")
    session = truth.trajectories()
    layout = cluster_session(session, options=ClusterOptions(
        factor=1.1, stabilize=False, takes=truth.takes)).layout
    build = build_rig(layout, session, check=False)
    skin_only = build_rig(layout, session, check=False, options=RigOptions(face_parts=False))
    perf = read_trajectories(SAMPLES / "dense_halfface_performance.c3d", strip_prefixes=True)
    weights = load_ground_truth(SAMPLES / "dense_halfface_performance_truth.npz")
    names = list(weights.blendshape_names)
    rig = build.rig
    animation = bake_capture(build, Capture("performance", perf))
    joints = animation.translations[:, 1:] + rig.joint_positions[0]
    disp = np.concatenate([np.zeros((len(joints), 1, 3)), joints - rig.joint_positions[1:]], axis=1)
    posed = skin_vertices(rig.vertices, rig.weight_index, rig.weight_value, disp)
    frames = {"widest jaw": jaw_open_frame(build, animation),
              "strongest smile": int(np.argmax(weights.weights[:, names.index("mouthSmile_L")])),
              "blink R": int(np.argmax(weights.weights[:, names.index("eyeBlink_R")])),
              "blink L": int(np.argmax(weights.weights[:, names.index("eyeBlink_L")]))}
    return build, skin_only, posed, frames


def test_the_default_rig_has_eyeballs_teeth_and_a_socket_and_keeps_its_skin(rigs):
    """Skin first (its 9,409 vertices and weights exactly as without the parts), then 2 eyeballs,
    32 teeth and the mouth socket; ``face_parts=False`` gives the skin alone."""
    from mocaptk.retarget.face_materials import MATERIALS
    from mocaptk.retarget.face_parts import template_parts

    build, skin_only, _, _ = rigs
    rig, skin = build.rig, skin_only.rig
    count = len(skin.vertices)
    _, faces, material, _, group = template_parts()
    assert count == 9409 and len(rig.vertices) == count + len(group)
    np.testing.assert_array_equal(rig.faces[:len(skin.faces)], skin.faces)
    np.testing.assert_array_equal(rig.faces[len(skin.faces):], faces + count)
    np.testing.assert_array_equal(rig.vertices[:count], skin.vertices)
    np.testing.assert_array_equal(rig.weight_index[:count], skin.weight_index)
    np.testing.assert_array_equal(rig.weight_value[:count], skin.weight_value)
    assert [MATERIALS[m] for m in np.unique(material)] == ["sclera", "iris", "teeth", "mouth"]
    assert np.bincount(group + 1).tolist()[1:] == [318, 316, 616, 535]  # eyes R, L, teeth up, down
    # rigid parts: closed pieces, within the face's box
    from mocaptk.surface_mesh import boundary_edges

    assert len(boundary_edges(faces[material < 4])) == 0
    box = rig.vertices[:count].min(axis=0), rig.vertices[:count].max(axis=0)
    assert np.all((rig.vertices[count:] > box[0]) & (rig.vertices[count:] < box[1]))


@pytest.mark.parametrize("pose", ["rest", "widest jaw", "strongest smile", "blink R", "blink L"])
def test_eyeballs_and_teeth_stay_behind_the_skin(rigs, pose):
    """Along the view (+Z) no vertex of an eyeball or a tooth is in front of the skin over it
    (measured: at least 0.37 mm behind over the performance; rest 1.8 mm, widest jaw 1.1 mm,
    eyes at the full blink 1.5 mm; teeth 6.8 mm or more)."""
    from mocaptk.retarget.face_parts import in_front, template_parts

    build, skin_only, posed, frames = rigs
    count, skin = len(skin_only.rig.vertices), skin_only.rig.faces
    points = build.rig.vertices if pose == "rest" else posed[frames[pose]]
    group = template_parts()[4]
    for g in range(4):
        depth = in_front(points[count:][group == g], points[:count], skin)
        assert np.isfinite(depth).sum() > 0.5 * (group == g).sum()  # most are under skin
        assert depth.max() < -0.3, (pose, g, depth.max())


def test_lower_teeth_follow_the_jaw_and_the_socket_the_lips(rigs):
    """Head-relative, the upper teeth and the eyeballs move as one with the head joint; the lower teeth move rigidly
    down with the jaw (20.8 mm at the widest jaw, the lower lip 26.6 mm), staying above the lower
    lip's rim; the socket's lip vertices are the lips' own in every frame."""
    from mocaptk.retarget.face_parts import template_parts

    build, skin_only, posed, frames = rigs
    count = len(skin_only.rig.vertices)
    _, _, _, attach, group = template_parts()
    rest, jaw = build.rig.vertices[count:], posed[frames["widest jaw"]][count:]
    move = jaw - rest
    # eyeballs and upper teeth: one rigid translation, the head joint's (the layout joint that
    # moves least; the sample's is on the brow, 2.2 mm up at the widest jaw)
    still = move[(group >= 0) & (group <= 2)]
    assert np.ptp(still[:, 1:], axis=0).max() < 1e-6 and np.ptp(still[:, 0]) < 0.2 and np.abs(still).max() < 2.5
    lower = move[group == 3]
    # one rigid translation (its mirror halves' rows are each other's image: 0.11 mm apart in X)
    assert np.ptp(lower[:, 1:], axis=0).max() < 1e-6 and np.ptp(lower[:, 0]) < 0.2
    assert lower[0, 1] < -15.0
    face = posed[frames["widest jaw"]][:count]
    from mocaptk.retarget.default_face import template_openings

    (_, lips), _, _ = template_openings()
    assert jaw[group == 3, 1].max() > face[lips[len(lips) // 2], 1] + 5.0  # seen over the lip
    on = attach >= 0
    gap = np.linalg.norm(posed[:, count:][:, on] - posed[:, attach[on]], axis=2)
    assert gap.max() < 1e-9, gap.max()


def test_rig_files_give_the_parts_their_own_materials(rigs, tmp_path):
    """rig.glb: one primitive per material (skin, sclera, iris, teeth, mouth), the Khronos
    validator at 0 errors, warnings and infos; rig.fbx read by ufbx: the same materials, each
    polygon its part's."""
    from readers import installed
    from readers.glb_reader import read_skinned_glb

    from mocaptk.retarget import write_rig_glb
    from mocaptk.retarget.export_fbx import write_rig_fbx

    build, _, _, _ = rigs
    rig = build.rig
    names = ["face_skin", "face_sclera", "face_iris", "face_teeth", "face_mouth"]
    glb = read_skinned_glb(write_rig_glb(rig, tmp_path / "rig.glb")).gltf
    assert [m.name for m in glb.materials] == names
    primitives = glb.meshes[0].primitives
    assert [p.material for p in primitives] == [0, 1, 2, 3, 4]
    counts = [glb.accessors[p.indices].count // 3 for p in primitives]
    assert counts == np.bincount(rig.materials).tolist() and all(m.alphaMode == "OPAQUE" for m in glb.materials)
    issues = installed.run_validator(tmp_path / "rig.glb")["issues"]
    assert (issues["numErrors"], issues["numWarnings"], issues["numInfos"]) == (0, 0, 0), issues["messages"]
    scene = installed.run_ufbx(write_rig_fbx(rig, tmp_path / "rig.fbx"))
    assert scene["materials"] == names
    np.testing.assert_array_equal(scene["face_material"], rig.materials)


def test_a_user_heads_cards_are_translucent(tmp_path):
    """The ICT-FaceKit head given with --mesh: its lash cards and eye-occlusion shells (open pieces
    around the eyes) get the translucent card material (glTF BLEND and double-sided, USD opacity
    0.3), its eyeballs sclera, its teeth teeth and its gums and tongue mouth; usdchecker clean."""
    import tarfile

    from pxr import Usd, UsdGeom, UsdShade, UsdValidation

    from conftest import shared_path
    from mocaptk.retarget.export_glb import _BufferBuilder, face_materials
    from mocaptk.retarget.export_usd import write_mesh_usd
    from mocaptk.retarget.face_materials import MATERIALS, mesh_materials
    from mocaptk.retarget.mesh_io import load_mesh
    from mocaptk.retarget.mesh_parts import skin_faces

    tarball = shared_path("face_mesh", "ict_facekit", "ict_facekit_FaceXModel_subset.tar.xz")
    with tarfile.open(tarball) as tar:
        member = tar.extractfile("ICT-FaceKit/FaceXModel/generic_neutral_mesh.obj")
        (tmp_path / "head.obj").write_bytes(member.read())
    head = load_mesh(tmp_path / "head.obj")
    skin = skin_faces(head.faces)
    faces = np.concatenate([head.faces[skin], head.faces[~skin]])
    materials = mesh_materials(head.vertices, faces, int(skin.sum()))
    used = {MATERIALS[m]: int(n) for m, n in enumerate(np.bincount(materials)) if n}
    # ICT-FaceKit's triangles: eyeballs (sclera and iris) 6,264, teeth 8,696, gums and tongue
    # 5,808; lashes 2,160 + eye-occlusion 512 + wet rims 652 + eye blend 60
    assert used == {"skin": int(skin.sum()), "sclera": 6264, "teeth": 8696, "mouth": 5808,
                    "card": 3384}, used
    looks = face_materials(_BufferBuilder(), sorted({int(m) for m in materials}))["materials"]
    assert [(m.alphaMode, m.doubleSided) for m in looks][-1] == ("BLEND", True)
    assert all(m.alphaMode in (None, "OPAQUE") for m in looks[:-1])
    path = write_mesh_usd(tmp_path / "head.usd", rest=head.vertices, faces=faces, n_frames=1,
                          frames=[head.vertices[None]], rate=30.0, materials=materials)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/face_mesh"))
    subsets = UsdGeom.Subset.GetGeomSubsets(mesh, UsdGeom.Tokens.face, "materialBind")
    assert sorted(s.GetPrim().GetName() for s in subsets) == sorted(used)
    card = next(s for s in subsets if s.GetPrim().GetName() == "card")
    bound, _ = UsdShade.MaterialBindingAPI(card.GetPrim()).ComputeBoundMaterial()
    shader = UsdShade.Shader(stage.GetPrimAtPath(bound.GetPath().AppendChild("surface")))
    assert shader.GetInput("opacity").Get() == pytest.approx(0.3)
    registry = UsdValidation.ValidationRegistry()  # what usdchecker runs
    errors = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators()).Validate(stage)
    assert not errors, [e.GetMessage() for e in errors]
