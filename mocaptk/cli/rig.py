"""``mocaptk rig``: layout + session (+ character mesh) -> rig.json/.fbx/.glb and the marker guide."""

from __future__ import annotations

from pathlib import Path

import typer

from mocaptk.errors import InputFileError, OptionError, warn

from .app import app
from .options import Quiet, Rate, Units, recorded_reading


def parse_formats(text: str) -> tuple[str, ...]:
    """``"json,fbx"`` -> ``("json", "fbx")``; empty text = no rig files (guide only)."""
    return tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))


def read_landmarks(path: Path) -> dict[str, int]:
    """Landmarks file: JSON ``{"MARKER_LABEL": vertex_index, ...}`` (>= 3 pairs); the keys of
    :data:`~mocaptk.retarget.mesh_openings.CORNERS` name the mesh's mouth and eye corners."""
    from mocaptk.jsonio import read_json
    from mocaptk.retarget.mesh_openings import CORNERS

    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(v, int) and v >= 0 for v in data.values()):
        raise InputFileError(path, "expected {\"marker label\": vertex index, ...}")
    if len([k for k in data if k not in CORNERS]) in (1, 2) or not data:  # corners alone: ICP
        raise InputFileError(path, "need at least 3 marker/vertex pairs")
    return {str(k): int(v) for k, v in data.items()}


def rig_options(max_influences: int, falloff: float | None, pure_thin_shell: bool,
                subdivisions: int, surface: str = "face", face_parts: bool = True):
    """Validated :class:`~mocaptk.retarget.build.RigOptions` from command-line values."""
    from mocaptk.retarget.build import RigOptions

    if max_influences < 1 or max_influences > 8:
        raise OptionError(f"--max-influences must be 1..8, got {max_influences}")
    if falloff is not None and falloff < 0:
        raise OptionError(f"--falloff must be >= 0 mm, got {falloff}")
    if subdivisions < 0 or subdivisions > 3:
        raise OptionError(f"--subdivisions must be 0..3, got {subdivisions}")
    return RigOptions(max_influences=max_influences, falloff_mm=falloff,
                      pure_thin_shell=pure_thin_shell, subdivisions=subdivisions, surface=surface,
                      face_parts=face_parts)


def animation_captures(layout, session, relative, performances, *, no_stabilize: bool = False,
                       rate: float | None = None, units: str | None = None):
    """The captures ``rig``/``cluster`` bake: the session itself (``session`` as read,
    ``relative`` as the layout was computed on it) and each ``--animate`` file (read with ``rate``
    / ``units``, else as the layout's session for a file of its kind), stabilized on the layout's
    rigid set when the layout's session was (the bake ignores markers other than the layout's;
    the dense ones give the held-out skinning check)."""
    from mocaptk.clustering.pipeline import load_session, rigid_reference, stabilize
    from mocaptk.retarget.build import Capture
    from mocaptk.clustering.layout import layout_rigid_set

    stabilized = bool(layout.parameters.get("stabilized")) and not no_stabilize
    rigid = None if no_stabilize else layout_rigid_set(layout)
    # the performances land in the session's head frame, the rig's (whether or not the session moved)
    reference = rigid_reference(relative, rigid) if rigid else None
    captures = [Capture(Path(str(session.metadata.get("source") or "session")).stem, relative,
                        session if stabilized else None)]
    for path in performances:
        perf_rate, perf_units = recorded_reading(layout, path, rate=rate, units=units)
        perf, _ = load_session(path, rate=perf_rate, units=perf_units)
        present = set(perf.labels)
        missing = [c.representative for c in layout.clusters
                   if c.representative not in present and c.mirrored_from not in present]
        if missing:
            raise InputFileError(path, f"lacks {len(missing)} layout markers: "
                                       f"{', '.join(missing[:5])}")
        steady = stabilize(perf, rigid=rigid, reference=reference)[0] if rigid else perf
        captures.append(Capture(path.stem, steady, perf if rigid else None))
    return captures


@app.command()
def rig(
    layout: Path = typer.Argument(..., metavar="LAYOUT", help="layout.json written by mocaptk cluster."),
    session: Path = typer.Option(..., "--session", help="The dense session the layout was made "
                                 "from (its neutral pose places the mesh and the joints)."),
    mesh: Path = typer.Option(None, "--mesh", help="Character face mesh (OBJ, PLY, glTF/GLB, STL, "
                              "OFF; Y up, facing +Z, any unit). Default: --surface."),
    surface: str = typer.Option("face", "--surface", help="The mesh without --mesh: face (the "
                                "ICT-FaceKit face fitted to the actor: closed lips, blinking lids, "
                                "the whole face) or markers (a surface through the dense markers)."),
    no_face_parts: bool = typer.Option(False, "--no-face-parts", help="The default face's skin "
                                       "alone, without its eyeballs, teeth and mouth socket."),
    landmarks: Path = typer.Option(None, "--landmarks", help="JSON {marker label: mesh vertex "
                                   "index} (>= 3) to start the mesh alignment (default: ICP); keys "
                                   "mouth_R, mouth_L, eye_R_outer, eye_R_inner, eye_L_inner, "
                                   "eye_L_outer name the mesh's corners the openings end on."),
    keep_mesh_space: bool = typer.Option(False, "--keep-mesh-space", help="Write the rig in the "
                                         "--mesh file's own coordinates (read as mm), the motion "
                                         "scaled to it (default: the mesh fitted to the actor)."),
    max_influences: int = typer.Option(4, "--max-influences", help="Joints per vertex (1-8; 4 "
                                       "suits game engines; 8 changes little, see docs)."),
    formats: str = typer.Option("json,fbx,glb", "--formats", help="Comma-separated rig files to "
                                "write: json, fbx, glb."),
    falloff: float = typer.Option(None, "--falloff", help="How far (mm along the skin) a joint's "
                                  "influence reaches past its cluster's border (default: 3 x "
                                  "the dense marker spacing)."),
    pure_thin_shell: bool = typer.Option(False, "--pure-thin-shell", help="Do not shape the "
                                         "thin-shell weights by the influence regions."),
    subdivisions: int = typer.Option(1, "--subdivisions", help="Subdivide the marker surface "
                                     "(--surface markers) this many times (0-3)."),
    animate: list[Path] = typer.Option(None, "--animate", help="A performance (C3D/CSV/TRC with "
                                       "the layout's labels; other markers are ignored) to bake "
                                       "onto the rig after the session's own motion; repeatable."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: the layout's folder)."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Do not remove rigid head "
                                      "motion even if the layout was made on stabilized data."),
    rate: Rate = None,  # default: as the layout's session was read (layout.json's source.reading)
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Overwrite existing rig/guide files."),
    quiet: Quiet = False,
) -> None:
    """Build a skinned face rig and a printable marker guide from a layout."""
    from rich.console import Console

    from mocaptk.atomic import claim_output
    from mocaptk.clustering.layout import check_members, read_layout
    from mocaptk.clustering.pipeline import load_session, stabilize
    from mocaptk.retarget.build import write_rig_outputs
    from mocaptk.clustering.layout import layout_rigid_set

    options = rig_options(max_influences, falloff, pure_thin_shell, subdivisions, surface,
                          not no_face_parts)
    chosen = parse_formats(formats)
    # refused (read-only, exists) and locked before any work; rig_report.json: written by every run
    claim_output((out or layout.parent) / "rig_report.json", force=force)
    lay = read_layout(layout)
    session_rate, session_units = recorded_reading(lay, session, rate=rate, units=units)
    traj, source = load_session(session, rate=session_rate, units=session_units)
    check_members(lay, traj.labels, layout_path=layout, session_name=session.name)
    raw = traj
    expected = lay.source.get("sha256")
    if expected and expected != source["sha256"]:
        warn(f"{session} is not the file the layout was computed from (sha256 differs)")
    if lay.parameters.get("stabilized") and not no_stabilize:
        traj, _ = stabilize(traj, rigid=layout_rigid_set(lay))
    pairs = read_landmarks(landmarks) if landmarks else None
    captures = animation_captures(lay, raw, traj, animate or [], no_stabilize=no_stabilize,
                                  rate=rate, units=units)
    console = Console(stderr=True, quiet=quiet)
    with console.status("building the rig") as status:
        build, written = write_rig_outputs(
            lay, traj, out or layout.parent, mesh_path=mesh, landmarks=pairs, options=options,
            formats=chosen, title=f"{layout.name} + {session.name}", force=force,
            captures=captures, progress=lambda text: status.update(text),
            keep_mesh_space=keep_mesh_space)
    if not quiet:
        check = build.check
        typer.echo(f"rig: {build.rig.joint_count - 1} joints under {build.rig.joint_names[0]}, "
                   f"{build.rig.vertex_count} vertices ({build.report['mesh']['kind']}), "
                   f"max {options.max_influences} influences")
        if build.alignment is not None:
            typer.echo(f"mesh alignment ({build.alignment.method}): residual RMS "
                       f"{build.alignment.rms_mm:.2f} mm, max {build.alignment.max_mm:.2f} mm")
        typer.echo(f"marker-driven skinning check: RMSE {check.rmse_mm:.2f} mm, 95th percentile "
                   f"{check.p95_mm:.2f} mm ({check.vertices} dense markers, {check.frames} frames)")
        typer.echo(check_summary(build.report))
        if "animation" in build.report:
            typer.echo(animation_summary(build.report["animation"]))
        for path in written.values():
            typer.echo(f"wrote {path}")


def check_summary(report: dict) -> str:
    """The skinning check per region on the session and on every held-out capture of a rig
    report (``RigBuild.report``), each with its largest error."""
    lines = [region_summary(report["skinning_check"], "the session")]
    for held in report.get("held_out", []):
        lines.append(f"held-out {held['capture']}: RMSE {held['rmse_mm']:.2f} mm, max "
                     f"{held['max_mm']:.2f} mm")
        lines.append(region_summary(held, held["capture"]))
    return "\n".join(lines)


def region_summary(check: dict, what: str) -> str:
    """Per-region RMSE lines and where the largest error is (which marker, which frame)."""
    regions = check["regions"]
    lines = [f"  {region:<16} RMSE {r['rmse_mm']:.2f} mm, max {r['max_mm']:.2f} mm "
             f"({r['markers']} marker{'' if r['markers'] == 1 else 's'})" for region, r in regions.items()]
    others = [r["rmse_mm"] for name, r in regions.items() if name != "mouth"]
    if "mouth" in regions and sum(others) > 0:  # the weak region of a face rig (issue 11)
        lines.append(f"  mouth / mean of the other regions: "
                     f"{regions['mouth']['rmse_mm'] * len(others) / sum(others):.2f}x")
    worst = check["max"]
    lines.append(f"  largest error on {what}: {worst['error_mm']:.1f} mm at {worst['marker']} "
                 f"({worst['region']}), frame {worst['frame']}; "
                 f"{worst['layout_distance_mm']:.1f} mm from the nearest layout marker")
    return "\n".join(lines)


def animation_summary(report: dict) -> str:
    """One line: clips, frames, rate and how many marker-frames were filled."""
    takes = report["takes"]
    return (f"animation: {len(takes)} clips, {report['frames']} frames at {report['rate_hz']:g} Hz; "
            f"{report['filled_marker_frames']} marker-frames gap-filled before keying "
            f"({len(report['gaps'])} gaps, listed in rig_report.json)")


def cluster_rig_outputs(result, folder: Path, *, mesh: Path | None, max_influences: int,
                        formats: str, quiet: bool, session=None, animate=()):
    """What ``mocaptk cluster`` adds to its output folder: rig files + guide (``formats`` may be
    ``none`` to skip both). ``result`` is the clustering pipeline's ``ClusterResult``.
    Returns the :class:`~mocaptk.retarget.build.RigBuild` (None when skipped)."""
    from rich.console import Console

    from mocaptk.retarget.build import write_rig_outputs

    chosen = parse_formats(formats)
    if chosen == ("none",):
        return None
    from mocaptk.clustering.layout import read_layout

    # the layout as written (rounded), so `mocaptk rig` on layout.json builds the same rig
    layout = read_layout(folder / "layout.json")
    captures = animation_captures(layout, session or result.trajectories, result.trajectories,
                                  animate)
    console = Console(stderr=True, quiet=quiet)
    with console.status("building the rig") as status:
        build, _ = write_rig_outputs(
            layout, result.trajectories, folder, mesh_path=mesh,
            options=rig_options(max_influences, None, False, 1), formats=chosen,
            title=f"{layout.source.get('path', '')} factor {layout.parameters.get('factor')}",
            force=True, captures=captures, progress=lambda text: status.update(text),
            neutral=result.neutral)
    return build
