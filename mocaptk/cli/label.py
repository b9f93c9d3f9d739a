"""``mocaptk label CAPTURE --template T --out LABELLED``: give an unlabelled capture the template's
labels (or ``--check`` / ``--fix`` the labels of a labelled one); see docs/label.md."""

from __future__ import annotations

from pathlib import Path

import typer

from .app import app
from .options import Quiet, Rate, Units

def read_input(path: Path, *, units: str | None, rate: float | None):
    """A marker file, ``--units``/``--rate`` applied only where the format takes them."""
    from mocaptk.acquisition.formats import detect_format, read_trajectories

    fmt = detect_format(path)
    text = fmt not in ("c3d", "npz")
    return read_trajectories(path, fmt=fmt, units=units if text else None,
                             rate=rate if fmt == "generic_csv" else None)


def _check_text_options(units: str | None, rate: float | None, paths: list[Path]) -> None:
    """``--units``/``--rate`` must apply to at least one input: never silently ignored."""
    from mocaptk.acquisition.formats import detect_format
    from mocaptk.errors import OptionError

    formats = [detect_format(p) for p in paths if p.suffix.lower() != ".json"]
    if units is not None and all(f in ("c3d", "npz") for f in formats):
        raise OptionError("--units applies to text inputs only; CAPTURE and the template declare their units")
    if rate is not None and "generic_csv" not in formats:
        raise OptionError("--rate applies to column CSV inputs only; CAPTURE and the template store their rate")


def load_template(path: Path, *, units: str | None, rate: float | None):
    """The labelling template of a labelled session, or of a ``layout.json`` (its markers, from its
    session, found as solve finds it)."""
    from mocaptk.acquisition.labelling import is_unnamed
    from mocaptk.acquisition.labelling.template import build_template
    from mocaptk.errors import InputFileError

    layout = layout_path = None
    if path.suffix.lower() == ".json":
        from mocaptk.clustering.layout import read_layout

        from .options import recorded_reading
        from .options import session_path

        layout, layout_path = read_layout(path), path
        path = session_path(layout_path, layout.source, None)  # where solve finds it
        rate, units = recorded_reading(layout, path, rate=rate, units=units)  # read as cluster read it
    traj = read_input(path, units=units, rate=rate)
    if all(is_unnamed(label) for label in traj.labels):
        raise InputFileError(path, "the template has no marker labels (unlabelled points only): label it "
                                   "first, or give a labelled session")
    return layout_template(layout, traj, layout_path=layout_path) if layout else build_template(traj)


def layout_template(layout, session, *, layout_path: Path):
    """The template of a layout: its markers and stabilization markers, from its ``session``
    (mirrored twins of a half-face layout are not in the session: left out)."""
    from mocaptk.acquisition.labelling.template import build_template
    from mocaptk.clustering.layout import layout_rigid_set
    from mocaptk.errors import InputFileError

    wanted = dict.fromkeys([*layout.labels, *(layout_rigid_set(layout) or ())])
    present = [m for m in wanted if m in set(session.labels)]
    if len(present) < 4:
        raise InputFileError(layout_path, f"only {len(present)} of the layout's markers are in its session")
    return build_template(session.select(present))


def label_for_layout(layout, layout_path: Path, capture, *, session=None, given: Path | None = None):
    """``--label`` of solve and retarget: ``(capture labelled with the layout's template, summary
    line)``. ``session``: the layout's session when the caller has read it, else it is read here
    (``given`` or where layout.json records it). The capture's column names are ignored."""
    from mocaptk.acquisition.labelling import capture as lc
    from mocaptk.acquisition.labelling.report import label_report, summary_line
    from mocaptk.clustering.pipeline import load_session

    from .options import recorded_reading
    from .options import session_path

    if session is None:
        path = session_path(layout_path, layout.source, given)
        rate, units = recorded_reading(layout, path, rate=None, units=None)
        session, _ = load_session(str(path), rate=rate, units=units)
    template = layout_template(layout, session, layout_path=layout_path)
    result = lc.label_capture(template, capture)
    lc.check_match(capture, result)
    line = summary_line(label_report(template, result, first_frame=capture.first_frame))
    return lc.labelled_trajectories(template, capture, result, keep_unlabelled=False), line


@app.command()
def label(
    capture: Path = typer.Argument(..., metavar="CAPTURE", help="Unlabelled capture (fragments or per-frame clouds), or a "
                                             "labelled one with --check."),
    template: Path = typer.Option(..., "--template", "-t", metavar="T",
                                  help="Labelled session of the same face and markers (C3D, CSV, TRC), "
                                       "or a layout.json (its markers, from its session, found as solve finds it)."),
    out: Path = typer.Option(None, "--out", "-o", metavar="LABELLED",
                             help="Output capture: .c3d, .csv or .trc (needed unless --check alone)."),
    report: Path = typer.Option(None, "--report", metavar="JSON",
                                help="Report path (default: label_report.json beside --out)."),
    mode: str = typer.Option("auto", "--mode", metavar="auto|fragments|clouds",
                             help="Input kind: trajectory fragments, untracked per-frame clouds, or "
                                  "detected."),
    drop_unlabelled: bool = typer.Option(False, "--drop-unlabelled",
                                         help="Drop the points left unlabelled instead of keeping them "
                                              "as *N columns."),
    check: bool = typer.Option(False, "--check", help="CAPTURE is labelled: list label swaps and wrong "
                                                      "labels against the template."),
    fix: bool = typer.Option(False, "--fix", help="With --check: write the corrected capture to --out."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing outputs."),
    units: Units = None,
    rate: Rate = None,
    quiet: Quiet = False,
) -> None:
    """Label an unlabelled capture with a template session's marker names (or check its labels)."""
    from rich.console import Console

    from mocaptk.acquisition.formats import output_format, write_trajectories
    from mocaptk.acquisition.labelling import capture as lc
    from mocaptk.acquisition.labelling.report import label_report, summary_line
    from mocaptk.atomic import claim_output
    from mocaptk.errors import OptionError
    from mocaptk.jsonio import write_json

    if mode not in ("auto", "fragments", "clouds"):
        raise OptionError(f"--mode must be auto, fragments or clouds, got {mode!r}")
    if fix and not check:
        raise OptionError("--fix needs --check")
    if out is None and not (check and not fix):
        raise OptionError("--out is needed (unless --check alone)")
    if out is not None:
        output_format(out)
        claim_output(out, force=force)
    if report is None and out is not None:
        report = out.parent / "label_report.json"
    if report is not None:
        claim_output(report, force=force)
    _check_text_options(units, rate, [capture, template])
    console = Console(stderr=True, quiet=quiet)
    with console.status("reading the template and building its motion model"):
        tpl = load_template(template, units=units, rate=rate)
        raw = read_input(capture, units=units, rate=rate)
        lc.check_scale(tpl, raw)
    # the labeller's kernel compiles on its first use in an installation (~20 CPU-s), then is cached
    labelling = console.status("labelling (the first run of an installation compiles the labeller)")
    if check:
        with labelling:
            runs, found = lc.check_labels(tpl, raw)
        for run in runs:
            typer.echo(f"{run.label}: frames {raw.first_frame + run.start}–{raw.first_frame + run.end - 1} "
                       f"are {run.found}" + (" (swapped)" if run.swap else ""))
        if fix:
            write_trajectories(lc.fix_labels(tpl, raw, runs), out, force=force)
        if report is not None:
            write_json(report, {"format": "mocaptk.label-check", "version": 1, "frames": raw.n_frames,
                                "mislabels": [{"label": r.label, "found": r.found, "swap": r.swap,
                                               "start": raw.first_frame + r.start,
                                               "end": raw.first_frame + r.end - 1} for r in runs]},
                       force=force)
        if not quiet:
            typer.echo(f"{len(runs)} mislabelled runs ({sum(r.swap for r in runs)} in swaps)"
                       + (f"; fixed in {out}" if fix else ""))
        return
    with labelling:
        result = lc.label_capture(tpl, raw, clouds=None if mode == "auto" else mode == "clouds")
    lc.check_match(raw, result)
    data = label_report(tpl, result, first_frame=raw.first_frame)
    labelled = lc.labelled_trajectories(tpl, raw, result, keep_unlabelled=not drop_unlabelled)
    del raw, result  # the output is as large as the capture: hold one of them, not both
    write_trajectories(labelled, out, force=force)
    write_json(report, data, force=force)
    if not quiet:
        typer.echo(summary_line(data))
        typer.echo(f"wrote {out} and {report}")
