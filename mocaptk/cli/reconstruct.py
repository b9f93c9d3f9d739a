"""``mocaptk reconstruct RIG DETECTIONS --out raw.c3d``: unlabelled blobs -> unlabelled 3-D
trajectory fragments ``*1``, ``*2``, ... (epipolar matching, see docs/optics.md)."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet


@app.command()
def reconstruct(
    rig_path: Path = typer.Argument(..., metavar="RIG", help="Camera rig: mocaptk rig .json or Qualisys .qca.txt."),
    detections_path: Path = typer.Argument(..., metavar="DETECTIONS", help="Blobs from mocaptk detect (.npz)."),
    out: Path = typer.Option(..., "--out", metavar="OUT", help="Output: .c3d, .csv or .trc."),
    tolerance: float = typer.Option(1.0, "--tolerance", metavar="PX",
                                    help="Epipolar / reprojection distance for a match (px)."),
    link: float = typer.Option(4.0, "--link", metavar="MM", help="Largest frame-to-frame step of a fragment."),
    rate: float = typer.Option(None, "--rate", help="Frame rate in Hz (default: the detections', the rig's, 60)."),
    force: bool = typer.Option(False, "--force", help="Overwrite OUT."),
    quiet: Quiet = False,
) -> None:
    """Match unlabelled blobs across cameras, triangulate, link into fragments."""
    import numpy as np

    from mocaptk.acquisition.cameras import load_rig
    from mocaptk.acquisition.correspondence import reconstruct as reconstruct_points
    from mocaptk.acquisition.detections_file import load_detections
    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.atomic import check_writable
    from mocaptk.errors import InputFileError, OptionError
    from mocaptk.trajectories import Trajectories

    if not tolerance > 0 or not link > 0 or (rate is not None and not rate > 0):
        raise OptionError("--tolerance, --link and --rate must be > 0")
    fmt = output_format(out)
    check_writable(out, force=force)
    rig = load_rig(rig_path)
    detections = load_detections(detections_path)
    names = detections.camera_names
    if len(names) != len(rig):
        raise InputFileError(detections_path, f"{len(names)} cameras, the rig {rig_path.name} has {len(rig)}")
    if sorted(names) != sorted(rig.names):
        order = list(range(len(rig)))  # unnamed folders (cam1, cam2...): camera order
    else:
        order = [names.index(name) for name in rig.names]
    result = reconstruct_points(rig, detections.points2d[order], tolerance_px=tolerance, link_mm=link)
    positions = result.trajectories_array()
    frame_rate = rate or detections.rate or rig.rate or 60.0
    traj = Trajectories(positions=positions, labels=[f"*{i + 1}" for i in range(positions.shape[1])],
                        rate=frame_rate)
    write_trajectories(traj, out, fmt=fmt, force=force)
    lengths = result.fragment_lengths()
    n_points = int(np.isfinite(result.points[..., 0]).sum())
    if not quiet and len(lengths):
        typer.echo(f"{n_points} points in {positions.shape[0]} frames ({n_points / max(positions.shape[0], 1):.1f} "
                   f"per frame); fragment length median {np.median(lengths):.0f}, "
                   f"p10 {np.percentile(lengths, 10):.0f}, max {lengths.max()} frames")
    typer.echo(f"wrote {out} ({fmt}: {positions.shape[1]} unlabelled fragments, {positions.shape[0]} frames, "
               f"{frame_rate:g} Hz)")
