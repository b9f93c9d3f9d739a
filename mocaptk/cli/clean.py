"""``mocaptk clean IN OUT``: head stabilization, gap filling and low-pass filtering of a marker file."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet, Rate, Rigid, Units, rigid_labels


def layout_head_frame(path: Path):
    """A layout's stabilization markers and their positions (K, 3) mm in its session's head frame."""
    import numpy as np

    from mocaptk.clustering.layout import read_layout
    from mocaptk.errors import InputFileError

    stabilization = read_layout(path).extra.get("stabilization") or {}
    labels, positions = stabilization.get("rigid_labels"), stabilization.get("reference")
    if not labels or positions is None:
        raise InputFileError(path, "records no stabilization markers with their reference positions "
                             "(made by an older mocaptk: run cluster again)")
    return tuple(labels), np.asarray(positions, dtype=np.float64)


@app.command()
def clean(
    source: Path = typer.Argument(..., metavar="SOURCE", help="Input marker file (C3D, Vicon CSV, TRC, column CSV, .npz)."),
    target: Path = typer.Argument(..., metavar="TARGET", help="Output file: .c3d, .csv (Nexus style) or .trc."),
    stabilize: bool = typer.Option(True, "--stabilize/--no-stabilize",
                                   help="Remove rigid head motion (positions become head-relative)."),
    rigid: Rigid = None,
    reference: Path = typer.Option(None, "--reference", metavar="LAYOUT", help="Stabilize into the "
                                   "head frame of this layout.json's session, on its stabilization "
                                   "markers (so the result lines up with the session and its layout)."),
    pose_cutoff: float = typer.Option(12.0, "--pose-cutoff", metavar="HZ",
                                      help="Fit the head pose to the rigid markers low-passed at this "
                                           "cut-off (their noise stays out of the pose; the output is not "
                                           "filtered); 0: fit the raw markers."),
    fill_max_gap: int = typer.Option(10, "--fill-max-gap", min=0,
                                     help="Longest gap (frames) filled by spline interpolation, and longest "
                                          "leading/trailing gap filled at all; longer interior gaps are filled "
                                          "from correlated neighbours. 0: no gap filling."),
    lowpass_hz: float = typer.Option(None, "--lowpass", help="Zero-phase Butterworth low-pass cut-off (Hz); "
                                                            "default: no filtering."),
    report: Path = typer.Option(None, "--report", help="Also write a JSON report (rigid set, pose residuals, "
                                                      "every gap and how it was filled)."),
    force: bool = typer.Option(False, "--force", help="Overwrite OUT (and the report) if they exist."),
    units: Units = None,
    rate: Rate = None,
    quiet: Quiet = False,
) -> None:
    """Clean a session: stabilize the head, fill gaps, low-pass filter (in that order), write OUT."""
    import numpy as np

    echo = (lambda text: None) if quiet else typer.echo

    from mocaptk.acquisition.filtering import check_cutoff, lowpass
    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.acquisition.gapfill import fill_gaps
    from mocaptk.acquisition.stabilize import stabilize_head
    from mocaptk.atomic import claim_output
    from mocaptk.errors import InputFileError, OptionError
    from mocaptk.jsonio import write_json
    from .info import read_marker_file

    fmt = output_format(target)
    if rigid and not stabilize:
        raise OptionError("--rigid needs --stabilize")
    if reference is not None and (rigid or not stabilize):
        raise OptionError("--reference stabilizes on the layout's own markers: it goes with neither "
                          "--rigid nor --no-stabilize")
    head = None if reference is None else layout_head_frame(reference)
    claim_output(target, force=force)
    if report is not None:
        claim_output(report, force=force)
    traj = read_marker_file(source, units=units, rate=rate)
    if lowpass_hz is not None:
        check_cutoff(lowpass_hz, rate=traj.rate)  # fail before the slower steps
    if not pose_cutoff >= 0:  # NaN too
        raise OptionError(f"--pose-cutoff must be >= 0 Hz, got {pose_cutoff:g}")
    doc: dict = {"format": "mocaptk-clean-report", "version": 1, "source": str(source)}
    before = 100 * traj.gap_stats().total_missing_fraction
    if stabilize:
        if head is not None:
            missing = [label for label in head[0] if label not in set(traj.labels)]
            if missing:
                raise InputFileError(source, f"lacks the stabilization markers of {reference.name}: "
                                     f"{', '.join(missing[:5])}")
        result = stabilize_head(traj, rigid_labels=head[0] if head else rigid_labels(rigid),
                                reference=head[1] if head else None, pose_cutoff_hz=pose_cutoff or None)
        traj = result.trajectories
        fitted = np.isfinite(result.rms_residual_mm)
        no_pose = int(np.isnan(result.rotations[:, 0, 0]).sum())
        bridged = int((~fitted).sum()) - no_pose
        median_rms = float(np.median(result.rms_residual_mm[fitted])) if fitted.any() else float("nan")
        echo(f"stabilized on {', '.join(result.rigid_labels)} (reference frame {result.reference_frame}): "
                   f"median rigid-fit RMS {median_rms:.3f} mm, {bridged} frames with an interpolated head pose, "
                   f"{no_pose} frames without one")
        doc["stabilization"] = {"rigid_labels": list(result.rigid_labels), "reference_frame": result.reference_frame,
                                "pose_cutoff_hz": pose_cutoff or None,
                                "median_rms_residual_mm": median_rms, "frames_interpolated_pose": bridged,
                                "frames_without_pose": no_pose}
    if fill_max_gap > 0:
        traj, fill_report = fill_gaps(traj, max_gap=fill_max_gap)
        echo(f"gap filling: {fill_report.summary()}")
        doc["gap_filling"] = {"max_gap": fill_max_gap, **fill_report.as_dict()}
    if lowpass_hz is not None:
        traj = lowpass(traj, cutoff_hz=lowpass_hz)
        echo(f"low-pass: Butterworth order 4, zero phase, {lowpass_hz:g} Hz")
        doc["lowpass_hz"] = lowpass_hz
    after = 100 * traj.gap_stats().total_missing_fraction
    doc["missing_percent"] = {"before": before, "after": after}
    write_trajectories(traj, target, fmt=fmt, force=force)
    if report is not None:
        write_json(report, doc, force=force)
    echo(f"wrote {target}: {traj.n_markers} markers, {traj.n_frames} frames, "
               f"missing {before:.2f} % -> {after:.2f} %")
