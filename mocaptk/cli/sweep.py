"""``mocaptk sweep``: layout size and held-out reconstruction error over a range of refinement factors."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from mocaptk.errors import OptionError

from .app import app
from .options import Quiet, Rate, Rigid, Units, rigid_labels


#: Each factor is one clustering + evaluation run; more than this is a typo, not a sweep.
MAX_FACTORS = 500


def parse_factors(text: str) -> list[float]:
    """``"0.8:1.3:0.05"`` (start:stop:step, stop included) or ``"0.9,1.0,1.1"`` → sorted factors."""
    try:
        if ":" in text:
            start, stop, step = (float(x) for x in text.split(":"))
            if not (step > 0 and start <= stop and math.isfinite(stop)):
                raise ValueError
            count = int(round((stop - start) / step)) + 1
            if count > MAX_FACTORS:
                raise OptionError(f"--factors: {text!r} makes {count:,} factors; at most "
                                  f"{MAX_FACTORS} per sweep (use a larger step)")
            values = [round(start + i * step, 6) for i in range(count)]
        else:
            values = [float(x) for x in text.split(",") if x.strip()]
            if len(values) > MAX_FACTORS:
                raise OptionError(f"--factors: {len(values):,} factors; at most {MAX_FACTORS} per sweep")
    except ValueError:
        raise OptionError(f"--factors: expected START:STOP:STEP or a comma list, got {text!r}") from None
    if not values or min(values) <= 0 or not all(map(math.isfinite, values)):
        raise OptionError(f"--factors: factors must be finite and > 0, got {text!r}")
    return sorted(set(values))


@app.command()
def sweep(
    session: Path = typer.Argument(..., metavar="SESSION", help="Dense session file."),
    factors: str = typer.Option("0.8:1.3:0.05", "--factors", help="START:STOP:STEP (stop included) or "
                                "a comma list of refinement factors."),
    regions: Path = typer.Option(None, "--regions", help="Regions file (JSON or CSV label,region)."),
    takes: Path = typer.Option(None, "--takes", help="Takes file (default: takes in the session)."),
    step: int = typer.Option(5, "--step", help="Use every STEP-th frame for the correlation matrices."),
    no_stabilize: bool = typer.Option(False, "--no-stabilize", help="Skip removing rigid head motion."),
    rigid: Rigid = None,
    test: Path = typer.Option(None, "--test", help="Separate performance file to test on (default: "
                              "held-out blocks of the session's takes)."),
    folds: int = typer.Option(5, "--folds", help="Held-out blocks per take."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: <session>_sweep/ next to "
                             "the session)."),
    rate: Rate = None,
    units: Units = None,
    force: bool = typer.Option(False, "--force", help="Write into an existing, non-empty output folder."),
    quiet: Quiet = False,
) -> None:
    """Cluster at every factor; report measured layout markers and held-out RMSE (table, plot, JSON)."""
    from rich.progress import Progress

    from mocaptk.atomic import claim_output, staged_folder, write_text
    from mocaptk.clustering.evaluation import error_summary, heldout_errors, holdout_splits
    from mocaptk.clustering.figures import sweep_plot
    from mocaptk.clustering.pipeline import ClusterOptions, cluster_session
    from mocaptk.clustering.regions import read_regions
    from mocaptk.clustering.takes import read_takes
    from mocaptk.jsonio import write_json
    from .cluster import OUT_HINT
    from .evaluate import session_arrays

    values = parse_factors(factors)
    out_dir = claim_output(out or session.with_name(f"{session.stem}_sweep"), force=force, folder=True,
                           hint=OUT_HINT)
    traj, test_positions, source = session_arrays(session, test=test, stabilized=not no_stabilize,
                                                  rate=rate, units=units, rigid=rigid_labels(rigid))
    region_map = read_regions(regions, traj.labels) if regions else None
    take_list = read_takes(takes, traj.n_frames) if takes else None
    splits = [] if test_positions is not None else holdout_splits(
        traj.n_frames, take_list if take_list is not None else traj.takes, folds=folds)
    rows = []
    with Progress(disable=quiet, transient=True) as progress:
        task = progress.add_task("sweeping factors", total=len(values))
        for factor in values:
            # the session is stabilized once above, so clustering runs on head-relative data
            options = ClusterOptions(factor=factor, method="paper", step=step, stabilize=False, mirror=False,
                                     regions=region_map, takes=take_list)
            result = cluster_session(traj, options=options, source=source)
            index = {label: i for i, label in enumerate(result.trajectories.labels)}
            idx = [index[label] for label in result.layout.labels]
            positions = result.trajectories.positions
            test_here = None if test_positions is None else test_positions[:, [traj.labels.index(lab)
                                                                               for lab in index]]
            summary = error_summary(heldout_errors(positions, idx, splits, test=test_here))
            rows.append({"factor": factor, "markers": len(idx), "rmse_mm": summary["rmse_mm"],
                         "p95_mm": summary["p95_mm"],
                         "per_region": {r.name: len(r.representatives) for r in result.layout.regions}})
            progress.advance(task)
    table = f"{'factor':>8}{'markers':>9}{'RMSE mm':>10}{'p95 mm':>10}\n" + "".join(
        f"{r['factor']:>8.3f}{r['markers']:>9}{r['rmse_mm']:>10.3f}{r['p95_mm']:>10.3f}\n" for r in rows)
    document = {"format": "mocaptk.sweep", "version": 1, "units": "mm", "source": source,
                "parameters": {"step": step, "stabilized": not no_stabilize, "mirror": False,
                               "test": test.name if test else f"held-out blocks ({len(splits)} folds)"},
                "rows": rows}
    with staged_folder(out_dir, force=force) as folder:
        write_json(folder / "sweep.json", document)
        write_text(folder / "sweep.txt", table)
        sweep_plot([r["factor"] for r in rows], [r["markers"] for r in rows], [r["rmse_mm"] for r in rows],
                   path=folder / "sweep.png")
    if not quiet:
        typer.echo(table, nl=False)
        typer.echo(f"wrote {out_dir}/ (sweep.json, sweep.txt, sweep.png)")
