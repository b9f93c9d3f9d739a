"""``mocaptk calibrate CAMERA... --out RIG.json``: camera intrinsics (and with ``--synced`` the
rig's extrinsics) from photos or videos of a checkerboard or ChArUco board.

Each CAMERA is a folder of photos or a video file (sampled every ``--step`` frames), in camera
order, or one folder of camera folders (sorted by name). Beside RIG.json it writes ``<stem>_corners.png``: per camera, the view with the largest
error, detected corners against their reprojections.

With ``--synced``, ``--wand WAND.npz --wand-length MM`` adds a wand (two markers a known distance
apart, waved through the volume) to the bundle adjustment: WAND.npz is ``mocaptk detect``'s output
for the wand footage, the same cameras in the same order.
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from .app import app
from .options import Quiet


def parse_corners(text: str) -> tuple[int, int]:
    from mocaptk.errors import OptionError

    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise OptionError(f"--corners must be COLSxROWS inner corners (e.g. 4x7), got {text!r}") from None
    return cols, rows


@app.command()
def calibrate(
    sources: list[Path] = typer.Argument(..., metavar="CAMERA",
                                         help="One folder of photos or one video per camera, in order."),
    out: Path = typer.Option(..., "--out", metavar="RIG.json", help="Output rig JSON."),
    board_kind: str = typer.Option("checkerboard", "--board", metavar="checkerboard|charuco",
                                   help="Calibration target."),
    corners: str = typer.Option("4x7", "--corners", metavar="COLSxROWS",
                                help="Inner corners of the board (ChArUco: squares - 1 each way)."),
    square: float = typer.Option(60.0, "--square", metavar="MM", help="Square side in mm."),
    marker: float = typer.Option(0.0, "--marker", metavar="MM",
                                 help="ArUco marker side in mm (ChArUco; default 0.75 x square)."),
    dictionary: str = typer.Option("DICT_4X4_50", "--dictionary",
                                   help="OpenCV ArUco dictionary of a ChArUco board."),
    step: int = typer.Option(10, "--step", help="Use every STEP-th frame of a video."),
    synced: bool = typer.Option(False, "--synced",
                                help="Photo/frame k of every camera is the same instant: also solve "
                                     "the rig's extrinsics by bundle adjustment (ChArUco)."),
    wand_file: Path = typer.Option(None, "--wand", metavar="WAND.npz",
                                   help="With --synced: `mocaptk detect`'s detections of a waved wand "
                                        "(same cameras, same order), added to the bundle adjustment."),
    wand_length: float = typer.Option(None, "--wand-length", metavar="MM",
                                      help="Distance between the wand's two marker centres, mm."),
    force: bool = typer.Option(False, "--force", help="Overwrite outputs."),
    quiet: Quiet = False,
) -> None:
    """Calibrate cameras from board photos or videos; write a rig JSON and a check picture."""
    import cv2
    import numpy as np

    from mocaptk.acquisition.boards import Board
    from mocaptk.acquisition.calibration import (View, bundle_adjust, calibrate_intrinsics,
                                                 chained_stereo, rig_from_poses)
    from mocaptk.acquisition.calibration_figure import corner_panel, mosaic
    from mocaptk.acquisition.cameras import save_rig
    from mocaptk.acquisition.image_sequences import ImageSource, camera_sources
    from mocaptk.atomic import check_writable, write_bytes
    from mocaptk.errors import InputFileError, OptionError

    if step < 1:
        raise OptionError(f"--step must be >= 1, got {step}")
    if synced and board_kind != "charuco":
        raise OptionError("--synced needs --board charuco: a checkerboard's corners have no ids, so "
                          "two cameras cannot tell which corner is which")
    if (wand_file is None) != (wand_length is None):
        raise OptionError("--wand and --wand-length go together (the wand's detections and its length in mm)")
    if wand_file is not None and not synced:
        raise OptionError("--wand needs --synced: the wand refines the rig's extrinsics")
    if wand_length is not None and not (math.isfinite(wand_length) and wand_length > 0):
        raise OptionError(f"--wand-length must be > 0 mm, got {wand_length:g}")
    try:
        board = Board(board_kind, parse_corners(corners), square,
                      marker=marker or 0.75 * square, dictionary=dictionary)
    except ValueError as exc:
        raise OptionError(str(exc)) from None
    picture = out.with_name(f"{out.stem}_corners.png")
    for path in (out, picture):
        check_writable(path, force=force)
    cameras = [ImageSource(path, step=step) for path in camera_sources(sources)]
    wand_blobs = None
    if wand_file is not None:  # checked before the slow part
        from mocaptk.acquisition.detections_file import load_detections

        wand_blobs = load_detections(wand_file).points2d
        if len(wand_blobs) != len(cameras):
            raise InputFileError(wand_file, f"{len(wand_blobs)} cameras, but {len(cameras)} are calibrated: "
                                            "detect the wand footage of the same cameras, in the same order")

    views, sizes, fits = [], [], []
    for source in cameras:
        found, size = [], None
        for name, image in source.frames():
            size = (image.shape[1], image.shape[0])
            found.append(View(name, *board.detect(image)))
        try:
            fit = calibrate_intrinsics(board, found, size)
        except ValueError as exc:
            raise InputFileError(source.path, f"{exc} ({board.kind} {corners}, {square:g} mm)") from None
        views.append(found)
        sizes.append(size)
        fits.append(fit)
        if not quiet:
            typer.echo(f"{source.path.name}: {len(fit.view_rms)}/{len(found)} views kept, RMS "
                       f"{fit.rms:.3f} px, focal {fit.matrix[0, 0]:.1f} x {fit.matrix[1, 1]:.1f} px")
            unseen = [name for name, reason in fit.dropped.items() if reason == "board not found"]
            if unseen:
                typer.echo(f"  dropped {len(unseen)} view(s), board not found: {', '.join(unseen)}")
            for view_name, reason in fit.dropped.items():
                if reason != "board not found":
                    typer.echo(f"  dropped {view_name}: {reason}")

    names = [source.path.stem for source in cameras]
    report = {name: {"rms_px": fit.rms, "views_kept": len(fit.view_rms),
                     "view_rms_px": fit.view_rms, "dropped": fit.dropped}
              for name, fit in zip(names, fits)}
    intrinsics = [(fit.matrix, fit.distortion) for fit in fits]
    if synced:
        try:
            start = chained_stereo(board, views, fits)
        except ValueError as exc:
            raise OptionError(f"--synced: {exc}") from None
        wand, wand_note, wand_record = None, "", {}
        if wand_blobs is not None:
            from mocaptk.acquisition.wand import LENGTH_TOLERANCE, wand_from_blobs

            board_rig = rig_from_poses(names, intrinsics, start, sizes)
            try:
                wand = wand_from_blobs(wand_blobs, board_rig, wand_length)
            except ValueError as exc:
                raise InputFileError(wand_file, str(exc)) from None
            wand_note = f", wand {wand.n_frames} of {wand_blobs.shape[1]} frames"
            if not quiet:
                seen = np.isfinite(wand.pixels[..., 0, 0]).sum(axis=1)
                typer.echo(f"wand: {wand.n_frames} of {wand_blobs.shape[1]} frames kept (both ends seen by "
                           f">= 2 cameras, length within {LENGTH_TOLERANCE:.0%}); frames per camera: "
                           + ", ".join(f"{name} {n}" for name, n in zip(names, seen)))
            wand_record = {"wand": {"length_mm": wand_length, "frames": int(wand_blobs.shape[1]),
                                    "frames_kept": wand.n_frames}}
        result = bundle_adjust(board, views, fits, start, wand=wand)
        if result.wand_weight is not None:  # the noise that weighed the wand against the board
            wand_note += f"; noise: corners {result.corner_sd_px:.3f} px, wand blobs {result.wand_sd_px:.3f} px"
        poses, intrinsics = result.rig_poses, result.intrinsics
        for name, rms in zip(names, result.camera_rms):
            report[name]["bundle_rms_px"] = rms
        extrinsics = (f"bundle adjustment (RMS {result.initial_rms:.3f} -> {result.final_rms:.3f} px"
                      f"{wand_note})")
    else:
        poses, wand_record = [(np.eye(3), np.zeros(3))] * len(cameras), {}
        extrinsics = "not calibrated (every camera at the origin; use --synced with a ChArUco board)"
    rig = rig_from_poses(names, intrinsics, poses, sizes, name=out.stem,
                         metadata={"calibration": report, "board": board.__dict__,
                                   "extrinsics": extrinsics, **wand_record})

    panels = []
    for source, found, fit in zip(cameras, views, fits):
        worst = max(fit.view_rms, key=fit.view_rms.get)
        view = next(v for v in found if v.name == worst)
        image = next(img for name, img in source.frames() if name == worst)
        rvec, tvec = fit.poses[worst]
        reprojected = cv2.projectPoints(board.object_points()[view.ids], rvec, tvec, fit.matrix,
                                        fit.distortion)[0].reshape(-1, 2)
        panels.append(corner_panel(image, view.pixels, reprojected,
                                   f"{source.path.name}: worst view {worst}\n"
                                   f"{fit.view_rms[worst]:.3f} px (camera {fit.rms:.3f} px)"))
    save_rig(rig, out, force=force)
    write_bytes(picture, cv2.imencode(".png", mosaic(panels))[1].tobytes(), force=force)
    typer.echo(f"wrote {out} ({len(rig)} cameras; extrinsics: {extrinsics}) and {picture}")
