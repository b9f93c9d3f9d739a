"""The ``report.html`` each command writes beside its other outputs (see docs/report.md)."""

from __future__ import annotations

from pathlib import Path


def report_line(path: Path, size: int, clips: list[dict]) -> str:
    """``report.html: 14.2 MB (...; replay 30 Hz, every 2nd frame of 60 Hz)`` for summaries."""
    replay = ""
    if clips:
        step = clips[0]["step"]
        nth = {1: "every frame", 2: "every 2nd frame", 3: "every 3rd frame"}.get(step, f"every {step}th frame")
        replay = f"; replay {clips[0]['rate_hz']:g} Hz = {nth} of {clips[0]['source_rate_hz']:g} Hz"
    return f"{path.name}: {size / 1e6:.1f} MB (self-contained, opens offline{replay})"


def write_cluster_report(result, build, path: Path, *, summary: str) -> str:
    """``mocaptk cluster``'s report (``build``: the rig, None without one); its size and replay
    rate are added to ``summary.txt`` beside it. Returns that line."""
    from mocaptk.atomic import write_text
    from mocaptk.retarget.report import cluster_report, write_report

    layout = result.layout
    title = (f"mocaptk cluster: {layout.source.get('path', '')} · factor "
             f"{layout.parameters.get('factor')} · {len(layout.clusters)} layout markers")
    data = cluster_report(layout, result.trajectories, build=build, summary=summary, title=title,
                          neutral=result.neutral)
    written, size = write_report(path, data)
    line = report_line(written, size, data["clips"])
    write_text(path.with_name("summary.txt"), summary + line + "\n")
    return line


def write_evaluation_report(path: Path, layout, session, layout_idx, result: dict, *, errors, test,
                            summary: str) -> str:
    """``mocaptk evaluate``'s report beside its JSON: the layout's per-marker held-out RMSE on
    the face (``errors`` (frames, markers) mm: the result's own held-out errors of the layout),
    the method table, session + performance replay. Returns the line stating its size."""
    from mocaptk.retarget.report import evaluation_report, per_marker_rmse, write_report

    held_out = "held-out performance" if test is not None else result["protocol"]["test"]
    title = (f"mocaptk evaluate: {layout.source.get('path', '')} · {len(layout_idx)}-marker layout"
             f" · {held_out}")
    data = evaluation_report(layout, session, rmse=per_marker_rmse(errors), result=result,
                             performance=test, summary=summary, title=title)
    written, size = write_report(path, data)
    return report_line(written, size, data["clips"])


def write_compare_report(path: Path, session, rows, *, test, summary: str, protocol: str) -> str:
    """``mocaptk compare``'s report: each method x count's per-marker held-out RMSE with its layout
    on the face (with ``test``: fitted on the session, scored on it, as the table; without: the
    whole-session layout kept fixed across the held-out takes/blocks). Run times stay out of the
    page (compare.md / compare.json have them), so the same input gives the same bytes. Returns
    the size line."""
    from mocaptk.clustering.evaluation import heldout_errors_of_layouts, holdout_splits
    from mocaptk.retarget.report import compare_report, per_marker_rmse, write_report

    if test is not None:
        splits, note = [], "Per-marker maps: fitted on the session, scored on the held-out performance."
    else:
        scheme = "takes" if len(session.takes) >= 2 else "blocks"
        splits = holdout_splits(session.n_frames, session.takes, split=scheme, folds=5)
        note = (f"Per-marker maps: the whole-session layout kept fixed across held-out {scheme} "
                "(the table re-chooses it per fold, so its numbers are a little higher).")
    from mocaptk.threads import one_thread

    scored = [row for row in rows if row.error is None]
    with one_thread():  # a small ridge fit per gap pattern: BLAS threads only contend
        # each training set summarised once for all rows: the same fits to ~1e-9 mm
        errors = heldout_errors_of_layouts(session.positions, [row.layout for row in scored], splits,
                                           test=None if test is None else test.positions)
        per_row = {id(row): per_marker_rmse(e) for row, e in zip(scored, errors)}
    entries = []
    for row in rows:
        entry = {"method": row.method, "count": row.count, "rmse_mm": row.rmse_mm, "p95_mm": row.p95_mm,
                 "lost_rmse_mm": row.lost_rmse_mm, "error": row.error}
        if row.error is None:
            entry.update(rmse=per_row[id(row)], layout=[session.labels[i] for i in row.layout])
        entries.append(entry)
    data = compare_report(session, rows=entries, performance=None if test is None else test.positions,
                          summary=summary, title=f"mocaptk compare: {protocol}",
                          note=note + " Click a row to show its layout and error. Run times: "
                          "compare.md / compare.json (measured, so kept out of this page).")
    written, size = write_report(path, data)
    return report_line(written, size, data["clips"])


def write_solve_report(path: Path, layout, solver, *, solved: Path, rigid, training, summary: dict,
                       text: str) -> str:
    """``mocaptk solve``'s report: the solved performance (``solved``: its dense.c3d, made
    head-relative on ``rigid`` when head motion was solved) on the face, each dense marker coloured
    by the model's expected error on the ``training`` session (None with ``--model``: no map),
    the model table and ``text`` (solve's summary). Returns the line stating its size."""
    from mocaptk.acquisition.c3d_read import read_c3d
    from mocaptk.clustering.pipeline import stabilize
    from mocaptk.retarget.report import per_marker_rmse, solve_report, write_report

    from mocaptk.errors import OptionError

    motion = read_c3d(solved)
    if rigid:  # into the training session's head frame, the face's
        try:
            motion = stabilize(motion, rigid=rigid, reference=solver.rigid_reference)[0]
        except OptionError:  # the model solves no frame of the rigid markers: the capture's frame
            pass
    error = None if training is None else per_marker_rmse(solver.model.check_residuals(training.positions))
    model, frames, expected = summary["model"], summary["frames"], summary["expected_error_mm"]
    head = summary["head_motion"]
    mm = lambda v: "–" if v is None else f"{v:.2f} mm"  # noqa: E731
    table = [["model", model["kind"]],
             ["layout markers used", len(model["layout_markers"])],
             ["dense markers", model["dense_markers"]],
             ["expected error, all layout markers present", mm(model["expected_error_all_present_mm"])],
             ["frames solved", f"{frames['solved']} of {summary['capture']['frames']}"],
             ["frames with lost markers", frames["with_lost_markers"]],
             ["expected error mean / p95 / max", " / ".join(mm(expected[k]) for k in ("mean", "p95", "max"))],
             ["head motion", "removed and put back" if head["removed_and_restored"] else "none removed"],
             ["mesh", f"{summary['mesh']['vertices']} vertices, {summary['mesh']['triangles']} triangles"],
             ["colour map", "per-marker expected error on the training session (all layout markers present)"
              if error is not None else "none: a --model file holds no per-marker errors"]]
    title = (f"mocaptk solve: {summary['capture']['path']} · {model['kind']} · "
             f"{len(model['layout_markers'])} layout markers")
    data = solve_report(layout, motion, marker_error=error, kind=model["kind"], table=table,
                        summary=text, title=title)
    written, size = write_report(path, data)
    return report_line(written, size, data["clips"])
