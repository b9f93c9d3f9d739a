"""``mocaptk triangulate RIG OBS.npz OUT``: labelled 2-D detections of a rig -> 3-D markers.

``OBS.npz`` (numpy ``.npz``) holds ``points2d`` ``(cameras, frames, markers, 2)`` float px with
NaN where a camera does not see a marker, and optionally ``labels`` ``(markers,)`` str,
``rate`` (Hz) and ``camera_names`` ``(cameras,)`` str (then matched to the rig's cameras by
name, in any order). ``RIG`` is a mocaptk rig JSON or a Qualisys ``.qca.txt``.
"""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet


@app.command()
def triangulate(
    rig_path: Path = typer.Argument(..., metavar="RIG",
                                    help="Camera rig: mocaptk rig .json or Qualisys .qca.txt."),
    observations_path: Path = typer.Argument(
        ..., metavar="OBS.npz",
        help="2-D detections: points2d (C,F,M,2) px, NaN unseen; optional labels, rate, "
             "camera_names."),
    target: Path = typer.Argument(..., metavar="OUT",
                                  help="Output marker file: .c3d, .csv (Nexus style) or .trc."),
    min_views: int = typer.Option(2, "--min-views",
                                  help="Views that must agree for a 3-D point (>= 2)."),
    threshold: float = typer.Option(4.0, "--threshold", metavar="PX",
                                    help="Reprojection error (px) above which a view is an "
                                         "outlier and is left out."),
    force: bool = typer.Option(False, "--force", help="Overwrite OUT if it exists."),
    quiet: Quiet = False,
) -> None:
    """Triangulate labelled 2-D detections into marker trajectories (outlier-robust)."""
    import numpy as np
    from rich.console import Console

    from mocaptk.acquisition.cameras import load_rig
    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.acquisition.triangulate import compile_notice
    from mocaptk.acquisition.triangulate import triangulate as triangulate_rig
    from mocaptk.atomic import check_writable
    from mocaptk.errors import OptionError

    if min_views < 2:
        raise OptionError(f"--min-views must be >= 2, got {min_views}")
    if not threshold > 0:
        raise OptionError(f"--threshold must be > 0 px, got {threshold}")
    fmt = output_format(target)
    check_writable(target, force=force)
    rig = load_rig(rig_path)
    points2d, labels, rate = read_observations(observations_path, rig.names)
    console = Console(stderr=True, quiet=quiet)
    with console.status("triangulating..."), compile_notice(
            lambda message: console.print(f"mocaptk: {message}", highlight=False, soft_wrap=True)):
        traj = triangulate_rig(rig, points2d, labels=labels, rate=rate, min_views=min_views,
                               outlier_threshold_px=threshold)
    write_trajectories(traj, target, fmt=fmt, force=force)
    solved = np.isfinite(traj.residuals)
    median = float(np.median(traj.residuals[solved])) if solved.any() else float("nan")
    typer.echo(f"wrote {target} ({fmt}: {traj.n_markers} markers, {traj.n_frames} frames, "
               f"{traj.rate:g} Hz); {solved.mean():.1%} of points triangulated, "
               f"median reprojection error {median:.2f} px")


def read_observations(path: Path, camera_names: list[str]):
    """Read an observations ``.npz``; returns ``(points2d in rig camera order, labels, rate)``."""
    import zipfile

    import numpy as np

    from mocaptk.errors import InputFileError

    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputFileError(path, f"cannot read observations .npz ({exc})") from None
    if "points2d" not in arrays:
        raise InputFileError(path, "no 'points2d' array (cameras, frames, markers, 2)")
    points2d = np.asarray(arrays["points2d"], dtype=np.float64)
    if points2d.ndim != 4 or points2d.shape[-1] != 2:
        raise InputFileError(path, f"points2d must have shape (cameras, frames, markers, 2), "
                                   f"got {points2d.shape}")
    if points2d.shape[0] != len(camera_names):
        raise InputFileError(path, f"points2d has {points2d.shape[0]} cameras, the rig has "
                                   f"{len(camera_names)}")
    if "camera_names" in arrays:
        names = [str(n) for n in arrays["camera_names"].ravel()]
        if sorted(names) != sorted(camera_names):
            raise InputFileError(path, f"camera names {names} do not match the rig's "
                                       f"{camera_names}")
        points2d = points2d[[names.index(name) for name in camera_names]]
    labels = None
    if "labels" in arrays:
        labels = [str(label) for label in arrays["labels"].ravel()]
        if len(labels) != points2d.shape[2] or len(set(labels)) != len(labels):
            raise InputFileError(path, f"labels must be {points2d.shape[2]} unique names")
    rate = float(arrays["rate"]) if "rate" in arrays else None
    if rate is not None and not rate > 0:
        raise InputFileError(path, f"rate must be > 0 Hz, got {rate}")
    return points2d, labels, rate
