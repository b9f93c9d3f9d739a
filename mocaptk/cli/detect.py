"""``mocaptk detect IMAGES... --out detections.npz``: unlabelled marker centres per camera and frame.

IMAGES is one folder of images (or one video) per camera, in camera order, or a single folder
whose sub-folders are the cameras (as ``mocaptk synth --images`` writes them). A merged blob
(two markers in one) is written as two flagged centres on its major axis. Beside the output it
writes ``<stem>_overlay.png``: each camera's first frame with its blobs circled.
"""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet


@app.command()
def detect(
    images: list[Path] = typer.Argument(..., metavar="IMAGES",
                                        help="A folder / video per camera, or one folder of camera folders."),
    out: Path = typer.Option(..., "--out", metavar="DETECTIONS.npz", help="Output detections."),
    min_area: int = typer.Option(6, "--min-area", metavar="PX", help="Smallest blob kept (px)."),
    max_area: int = typer.Option(2000, "--max-area", metavar="PX", help="Largest blob kept (px)."),
    step: int = typer.Option(1, "--step", help="Use every STEP-th frame of a video."),
    rate: float = typer.Option(None, "--rate", help="Frame rate in Hz (stored for reconstruct)."),
    force: bool = typer.Option(False, "--force", help="Overwrite outputs."),
    quiet: Quiet = False,
) -> None:
    """Find marker blobs (sub-pixel centres, size filters, merged flag) in every image."""
    import cv2
    import numpy as np

    from mocaptk.acquisition.detect_images import detect_sources
    from mocaptk.acquisition.calibration_figure import mosaic
    from mocaptk.acquisition.detections_file import pack, save_detections
    from mocaptk.acquisition.image_sequences import ImageSource, camera_sources
    from mocaptk.atomic import check_writable, write_bytes
    from mocaptk.errors import InputFileError, OptionError

    if min_area < 1 or max_area < min_area or step < 1:
        raise OptionError("--min-area must be >= 1, --max-area >= --min-area, --step >= 1")
    if rate is not None and not rate > 0:
        raise OptionError(f"--rate must be > 0 Hz, got {rate}")
    overlay = out.with_name(f"{out.stem}_overlay.png")
    for path in (out, overlay):
        check_writable(path, force=force)
    sources = [ImageSource(path, step=step) for path in camera_sources(images)]
    found, firsts = detect_sources(sources, min_area=min_area, max_area=max_area)
    per_image, panels = [], []
    for source, row, first in zip(sources, found, firsts):
        if per_image and len(row) != len(per_image[0]):
            raise InputFileError(source.path, f"{len(row)} frames, the first camera has "
                                              f"{len(per_image[0])}: cameras must have one image per frame")
        per_image.append([(blobs.centres, blobs.merged, blobs.area) for blobs in row])
        if first is not None:
            panels.append(_overlay(first, row[0], source.path.name))
    detections = pack(per_image, [s.path.name for s in sources], rate)
    save_detections(detections, out, force=force)
    write_bytes(overlay, cv2.imencode(".png", mosaic(panels, legend="green: marker blob   orange: "
                                                            "half of a merged blob (split in two)"))[1].tobytes(),
                force=force)
    counts = np.isfinite(detections.points2d[..., 0]).sum(axis=2)
    if not quiet:
        for name, row, merged in zip(detections.camera_names, counts, detections.merged.sum(axis=2)):
            typer.echo(f"{name}: {row.mean():.1f} blobs per frame ({merged.sum()} merged)")
    typer.echo(f"wrote {out} ({len(sources)} cameras, {counts.shape[1]} frames) and {overlay}")


def _overlay(image, blobs, title: str):
    """First-frame panel: blobs circled (green; merged orange), zoomed to the blobs."""
    import cv2
    import numpy as np

    from mocaptk.acquisition.calibration_figure import PANEL_HEIGHT

    colour = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    for (x, y), merged, area in zip(blobs.centres, blobs.merged, blobs.area):
        radius = int(np.sqrt(area / np.pi)) + 4
        cv2.circle(colour, (int(round(x)), int(round(y))), radius,
                   (0, 140, 255) if merged else (0, 220, 0), 1, cv2.LINE_AA)
    if len(blobs.centres):  # the box around the blobs, 40 px margin
        x0, y0 = np.maximum(np.floor(blobs.centres.min(axis=0)).astype(int) - 40, 0)
        x1, y1 = np.ceil(blobs.centres.max(axis=0)).astype(int) + 41
        colour = colour[y0:y1, x0:x1]
    scale = PANEL_HEIGHT / colour.shape[0]
    colour = cv2.resize(colour, None, fx=scale, fy=scale,
                        interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    cv2.putText(colour, f"{title}: {len(blobs.centres)} blobs", (10, 28), cv2.FONT_HERSHEY_SIMPLEX,
                0.7, (255, 255, 255), 2, cv2.LINE_AA)
    return colour
