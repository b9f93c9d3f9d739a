"""``mocaptk evaluate``: held-out reconstruction error of a layout beside baselines of the same size."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from mocaptk.errors import OptionError, warn

from .app import app
from .options import Quiet, Rate, Units, recorded_reading
from .report import write_evaluation_report


def evaluation_table(result: dict) -> str:
    """Plain-text table: method, markers, RMSE and 95th percentile (mm), per-region RMSE."""
    methods = result["methods"]
    regions = sorted(next(iter(methods.values())).get("regions", {}))
    head = (f"{'method':<16}{'markers':>8}{'RMSE mm':>16}{'p95 mm':>16}{'1 lost mm':>11}"
            + "".join(f"{r[:10]:>11}" for r in regions))
    lines = [head]
    for name, s in methods.items():
        rmse = f"{s['rmse_mm']:.3f}" + (f" ± {s['rmse_sd_mm']:.3f}" if "rmse_sd_mm" in s else "")
        p95 = f"{s['p95_mm']:.3f}" + (f" ± {s['p95_sd_mm']:.3f}" if "p95_sd_mm" in s else "")
        lost = s.get("lost_marker", {}).get("lost_rmse_mm", float("nan"))
        lines.append(f"{name:<16}{s['count']:>8}{rmse:>16}{p95:>16}{lost:>11.3f}"
                     + "".join(f"{s['regions'][r]['rmse_mm']:>11.3f}" for r in regions))
    return ("\n".join(lines) + "\n1 lost = held-out RMSE when the layout marker whose loss hurts most "
            f"is lost (gap-free frames; random: mean over the first {LOST_MARKER_SEEDS} seeds)\n")


def session_arrays(session: Path, *, test: Path | None, stabilized: bool, rate: float | None,
                   units: str | None, rigid: tuple[str, ...] | None = None, layout=None):
    """(session Trajectories, test positions or None, source dict) prepared like the layout's input
    (read as the ``layout``'s session was, unless ``rate``/``units`` are given)."""
    from mocaptk.clustering.pipeline import load_session_and_test

    test_reading = None
    if layout is not None:
        if test is not None:
            test_reading = recorded_reading(layout, test, rate=rate, units=units)
        rate, units = recorded_reading(layout, session, rate=rate, units=units)
    traj, perf, source = load_session_and_test(session, test, stabilized=stabilized, rate=rate,
                                               units=units, rigid=rigid, test_reading=test_reading)
    return traj, None if perf is None else perf.positions, source


#: Random layouts (the first seeds) whose lost-marker error is averaged (each costs L solves).
LOST_MARKER_SEEDS = 3


def add_lost_marker(result: dict, traj, layouts: dict[str, list[np.ndarray]], *, takes, test, split: str,
                    folds: int, ridge: float) -> None:
    """Add ``lost_marker`` (intact / worst-lost RMSE, mm; worst marker) to every method of ``result``
    (``layouts``: the compared ones, of which the first ``LOST_MARKER_SEEDS`` random ones count)."""
    from mocaptk.clustering.evaluation import holdout_splits
    from mocaptk.clustering.lost_marker import heldout_folds, lost_marker_summaries

    from mocaptk.threads import one_thread

    splits = [] if test is not None else holdout_splits(traj.n_frames, takes, split=split, folds=folds)
    with one_thread():  # many small solves: BLAS threads only contend
        cv = heldout_folds(traj.positions, splits, test=test, ridge=ridge)
        kept = {name: group[:LOST_MARKER_SEEDS] if name == "random" else group for name, group in layouts.items()}
        for method, entry in lost_marker_summaries(cv, kept, traj.labels).items():
            result["methods"][method]["lost_marker"] = entry


@app.command()
def evaluate(
    session: Path = typer.Argument(..., metavar="SESSION", help="Dense session the layout was computed from."),
    layout: Path = typer.Option(..., "--layout", help="layout.json written by mocaptk cluster."),
    test: Path = typer.Option(None, "--test", help="Separate performance file (same markers) to test on; "
                              "default: held-out parts of the session."),
    takes: Path = typer.Option(None, "--takes", help="Takes file (default: takes recorded in the session); "
                               "held-out blocks follow the takes."),
    split: str = typer.Option("blocks", "--split", help="Held-out scheme without --test: 'blocks' (each take "
                              "cut in FOLDS blocks, one block of every take held out per fold) or 'takes' "
                              "(leave one take out)."),
    folds: int = typer.Option(5, "--folds", help="Folds for --split blocks."),
    seeds: int = typer.Option(10, "--seeds", help="Random layouts to average (mean ± sd)."),
    ridge: float = typer.Option(1e-3, "--ridge", help="Ridge strength, relative to the mean input variance."),
    out: Path = typer.Option(None, "--out", help="Output folder for evaluation.json and evaluation.html "
                             "(as every other --out; default: beside the layout), or a .json file name "
                             "(the HTML report goes beside it)."),
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Overwrite an existing JSON result."),
    quiet: Quiet = False,
) -> None:
    """Reconstruct every dense marker from the layout's markers; compare with baselines of equal size."""
    from rich.console import Console

    from mocaptk.atomic import claim_output
    from mocaptk.clustering.evaluation import layout_evaluation
    from mocaptk.clustering.layout import layout_rigid_set, measured_indices, read_layout
    from mocaptk.clustering.takes import read_takes
    from mocaptk.jsonio import write_json

    if seeds < 1:
        raise OptionError(f"--seeds must be >= 1, got {seeds}")
    if split not in ("blocks", "takes"):  # options before outputs; what remains is the data's
        raise OptionError(f"unknown split {split!r} (use 'blocks' or 'takes')")
    if folds < 2:
        raise OptionError(f"need at least 2 folds, got {folds}")
    from .cluster import OUT_HINT

    if out is not None and out.suffix.lower() != ".json":  # a folder, as every other command's --out
        out = out / "evaluation.json"
    out_path = claim_output(out or layout.with_name("evaluation.json"), force=force, hint=OUT_HINT)
    claim_output(out_path.with_suffix(".html"), force=force, hint=OUT_HINT)
    lay = read_layout(layout)
    stabilized = bool(lay.parameters.get("stabilized"))
    traj, test_positions, source = session_arrays(  # the test into the session's head frame, always
        session, test=test, stabilized=stabilized, rate=rate, units=units, rigid=layout_rigid_set(lay),
        layout=lay)
    index = {label: i for i, label in enumerate(traj.labels)}
    measured = [traj.labels[i] for i in measured_indices(lay, traj.labels, layout_path=layout,
                                                         session_name=session.name)]
    regions = {r.name: [index[m] for m in r.markers if m in index] for r in lay.regions}
    name = str(lay.parameters.get("method", "layout"))
    take_list = read_takes(takes, traj.n_frames) if takes else traj.takes
    if test is None:  # held-out folds of these takes, checked now so that a failure names the file
        from mocaptk.clustering.evaluation import holdout_splits
        from mocaptk.errors import source_error

        try:
            holdout_splits(traj.n_frames, take_list, split=split, folds=folds)
        except OptionError as exc:
            raise source_error(takes or session, f"{exc} (held-out blocks follow its takes)") from None
    with Console(stderr=True, quiet=quiet).status(f"evaluating {len(measured)}-marker layouts"):
        evaluation = layout_evaluation(traj.positions, [index[m] for m in measured], takes=take_list,
                                       test=test_positions, regions=regions, name=name, split=split,
                                       folds=folds, n_random=seeds, ridge=ridge)
        result = evaluation.result
        add_lost_marker(result, traj, evaluation.layouts, takes=take_list, test=test_positions, split=split,
                        folds=folds, ridge=ridge)
    result.update({"format": "mocaptk.evaluation", "version": 1, "units": "mm", "source": source,
                   "layout": layout.name, "test": test.name if test else None})
    report = write_evaluation_report(out_path.with_suffix(".html"), lay, traj, [index[m] for m in measured], result,
                                     errors=evaluation.errors, test=test_positions,
                                     summary=evaluation_table(result))
    write_json(out_path, result, force=True)
    mirrored = len(lay.clusters) - len(measured)
    if mirrored:  # after everything that can fail: a note never precedes an error
        warn(f"{mirrored} mirrored layout markers are not in the session; "
             f"evaluated the {len(measured)} measured ones", kind="note")
    if not quiet:
        typer.echo(evaluation_table(result), nl=False)
        typer.echo(f"wrote {out_path}\nwrote {out_path.parent}/{report}")  # the report line starts with its name
