"""``mocaptk rig``: layout + session (+ character mesh) -> rig.json/.fbx/.glb and the marker guide."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from ..errors import InputFileError, OptionError
from .app import app
from .options import Quiet


def parse_formats(text: str) -> tuple[str, ...]:
    """``"json,fbx"`` -> ``("json", "fbx")``; empty text = no rig files (guide only)."""
    return tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))


def read_landmarks(path: Path) -> dict[str, int]:
    """Landmarks file: JSON ``{"MARKER_LABEL": vertex_index, ...}`` (>= 3 pairs)."""
    from ..jsonio import read_json

    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(v, int) and v >= 0 for v in data.values()):
        raise InputFileError(path, "expected {\"marker label\": vertex index, ...}")
    if len(data) < 3:
        raise InputFileError(path, "need at least 3 marker/vertex pairs")
    return {str(k): int(v) for k, v in data.items()}


def rig_options(max_influences: int, falloff: float | None, pure_thin_shell: bool,
                subdivisions: int):
    """Validated :class:`~mocaptk.retarget.build.RigOptions` from command-line values."""
    from ..retarget.build import RigOptions

    if max_influences < 1 or max_influences > 8:
        raise OptionError(f"--max-influences must be 1..8, got {max_influences}")
    if falloff is not None and falloff < 0:
        raise OptionError(f"--falloff must be >= 0 mm, got {falloff}")
    if subdivisions < 0 or subdivisions > 3:
        raise OptionError(f"--subdivisions must be 0..3, got {subdivisions}")
    return RigOptions(max_influences=max_influences, falloff_mm=falloff,
                      pure_thin_shell=pure_thin_shell, subdivisions=subdivisions)


@app.command()
def rig(
    layout: Path = typer.Argument(..., help="layout.json written by mocaptk cluster."),
    session: Path = typer.Option(..., "--session", help="The dense session the layout was made "
                                 "from (its neutral pose places the mesh and the joints)."),
    mesh: Path = typer.Option(None, "--mesh", help="Character face mesh (OBJ, PLY, glTF/GLB, STL, "
                              "OFF; Y up, facing +Z, any unit). Default: a surface through the "
                              "dense markers."),
    landmarks: Path = typer.Option(None, "--landmarks", help="JSON {marker label: mesh vertex "
                                   "index} (>= 3) to start the mesh alignment (default: ICP)."),
    max_influences: int = typer.Option(4, "--max-influences", help="Joints per vertex (1-8; 4 "
                                       "suits game engines; 8 changes little, see docs)."),
    formats: str = typer.Option("json,fbx,glb", "--formats", help="Comma-separated rig files to "
                                "write: json, fbx, glb."),
    falloff: float = typer.Option(None, "--falloff", help="How far (mm along the skin) a joint's "
                                  "influence reaches past its cluster's border (default: 3 x "
                                  "the dense marker spacing)."),
    pure_thin_shell: bool = typer.Option(False, "--pure-thin-shell", help="Do not shape the "
                                         "thin-shell weights by the influence regions."),
    subdivisions: int = typer.Option(1, "--subdivisions", help="Subdivide the default marker "
                                     "surface this many times (0-3)."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: the layout's folder)."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Do not remove rigid head "
                                      "motion even if the layout was made on stabilized data."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing rig/guide files."),
    quiet: Quiet = False,
) -> None:
    """Build a skinned face rig and a printable marker guide from a layout."""
    from rich.console import Console

    from ..clustering.layout import read_layout
    from ..clustering.pipeline import load_session, stabilize
    from ..retarget.build import write_rig_outputs
    from .evaluate import layout_rigid_set

    options = rig_options(max_influences, falloff, pure_thin_shell, subdivisions)
    chosen = parse_formats(formats)
    lay = read_layout(layout)
    traj, source = load_session(session)
    expected = lay.source.get("sha256")
    if expected and expected != source["sha256"]:
        print(f"mocaptk: warning: {session} is not the file the layout was computed from "
              "(sha256 differs)", file=sys.stderr)
    if lay.parameters.get("stabilized") and not no_stabilize:
        traj, _ = stabilize(traj, rigid=layout_rigid_set(lay))
    pairs = read_landmarks(landmarks) if landmarks else None
    console = Console(stderr=True, quiet=quiet)
    with console.status("building the rig") as status:
        build, written = write_rig_outputs(
            lay, traj, out or layout.parent, mesh_path=mesh, landmarks=pairs, options=options,
            formats=chosen, title=f"{layout.name} + {session.name}", force=force,
            progress=lambda text: status.update(text))
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
        for path in written.values():
            typer.echo(f"wrote {path}")


def cluster_rig_outputs(result, folder: Path, *, mesh: Path | None, max_influences: int,
                        formats: str, quiet: bool):
    """What ``mocaptk cluster`` adds to its output folder: rig files + guide (``formats`` may be
    ``none`` to skip both). ``result`` is the clustering pipeline's ``ClusterResult``.
    Returns the :class:`~mocaptk.retarget.build.RigBuild` (None when skipped)."""
    from rich.console import Console

    from ..retarget.build import write_rig_outputs

    chosen = parse_formats(formats)
    if chosen == ("none",):
        return None
    console = Console(stderr=True, quiet=quiet)
    with console.status("building the rig") as status:
        build, _ = write_rig_outputs(
            result.layout, result.trajectories, folder, mesh_path=mesh,
            options=rig_options(max_influences, None, False, 1), formats=chosen,
            title=f"{result.layout.source.get('path', '')} factor "
                  f"{result.layout.parameters.get('factor')}",
            force=True, progress=lambda text: status.update(text))
    return build
