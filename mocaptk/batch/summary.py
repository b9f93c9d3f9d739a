"""The batch summary: ``DIR/batch.json`` (every session's record) and ``DIR/batch.md`` (a table).

A *record* is one session under one command: ``session`` (stem), ``path``, ``command``,
``status`` (done / skipped / failed / interrupted), ``error`` (the command's one-line message),
``warnings``, ``seconds`` (wall), ``cpu_seconds`` (the runner's CPU for it), ``host``,
``finished`` (UTC), ``attempts`` (this batch's attempts at it: host, worker, pid, start, end,
ended), ``metrics`` (markers, layout markers, held-out RMSE mm, read from the session's outputs),
and for re-runs ``key`` (hash of argv + input hashes), ``inputs`` and ``outputs`` (file → SHA-256).

``batch.json`` keeps the latest record of every (session, command), so a cluster batch and a later
evaluate batch into the same DIR share one summary; batches running at the same time into one DIR
merge their records under a lock (:func:`update_summary`), the newest ``finished`` winning.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

FORMAT = "mocaptk.batch"
VERSION = 1


def _read(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


STATUSES = ("done", "skipped", "failed", "interrupted")
LOCK_NAME = ".batch.json.lock"


def session_metrics(folder: Path, *, layout_file: Path | None = None) -> dict[str, Any]:
    """Marker counts and held-out RMSE (mm) from the result files in a session's output folder
    (a labelling's points and labelled points too).

    ``layout_markers`` is always the layout file's own count (``layout_file``: the layout a solve
    used); ``solve_markers`` the ones a solve could use (those the session captured).
    """
    metrics: dict[str, Any] = {}
    info = _read(folder / "info.json")
    if isinstance(info, dict) and info.get("files") and "markers" in info["files"][0]:
        metrics["markers"] = info["files"][0]["markers"]
    layout = _read(layout_file or folder / "layout.json")
    if isinstance(layout, dict) and isinstance(layout.get("clusters"), list):
        metrics["layout_markers"] = len(layout["clusters"])
        if layout_file is None:
            metrics["markers"] = layout.get("source", {}).get("markers", metrics.get("markers"))
    solved = _read(folder / "solve.json")
    if isinstance(solved, dict) and isinstance(solved.get("model"), dict):
        metrics |= {"markers": solved["model"].get("dense_markers"),
                    "solve_markers": len(solved["model"].get("layout_markers") or [])}
    evaluation = _read(folder / "evaluation.json")
    if isinstance(evaluation, dict) and isinstance(evaluation.get("methods"), dict):
        name, scores = next(iter(evaluation["methods"].items()), (None, {}))
        if isinstance(scores, dict) and scores.get("rmse_mm") is not None:
            metrics |= {"rmse_mm": scores["rmse_mm"], "rmse_of": f"evaluate: {name}, {scores.get('count')} markers"}
    labelled = _read(folder / "label_report.json")
    if isinstance(labelled, dict) and labelled.get("format") == "mocaptk.label-report":
        metrics |= {"markers": labelled.get("markers"), "points": labelled.get("points"),
                    "labelled_points": labelled.get("labelled_points")}
    compare = _read(folder / "compare.json")
    if "rmse_mm" not in metrics and isinstance(compare, dict) and isinstance(compare.get("rows"), list):
        paper = [r for r in compare["rows"] if r.get("method") == "paper" and r.get("rmse_mm") is not None]
        if paper:
            metrics |= {"rmse_mm": paper[0]["rmse_mm"], "rmse_of": f"compare: paper, {paper[0]['count']} markers"}
    return metrics


def previous_records(out: Path) -> tuple[dict[tuple[str, str], dict[str, Any]], str | None]:
    """Records of earlier batches into ``out`` by (session, command), and a note if batch.json was
    there but unreadable (every session is then redone)."""
    path = out / "batch.json"
    if not path.exists():
        return {}, None
    doc = _read(path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("sessions"), list):
        return {}, f"{path}: not a readable batch summary; every session is redone"
    return {(r["session"], r["command"]): r for r in doc["sessions"]
            if isinstance(r, dict) and "session" in r and "command" in r}, None


def merged(previous: dict[tuple[str, str], dict[str, Any]], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Earlier records updated with these (a newer ``finished`` wins), sorted by session then command."""
    table = dict(previous)
    for r in records:
        old = table.get((r["session"], r["command"]))
        if old is None or str(r.get("finished") or "") >= str(old.get("finished") or ""):
            table[(r["session"], r["command"])] = r
    return [table[k] for k in sorted(table)]


def counts(records: list[dict[str, Any]]) -> dict[str, int]:
    """How many records are done / skipped / failed / interrupted."""
    return {status: sum(r["status"] == status for r in records) for status in STATUSES}


def summary_document(records: list[dict[str, Any]], run: dict[str, Any]) -> dict[str, Any]:
    """The batch.json document (``run``: this run's command, scheduler, workers, seconds, counts)."""
    return {"format": FORMAT, "version": VERSION, "last_run": run, "sessions": records}


def _cell(value: Any, digits: int = 3) -> str:
    if value is None:
        return "—"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def summary_markdown(records: list[dict[str, Any]], run: dict[str, Any]) -> str:
    """batch.md: this run in one line, then one table row per session and command."""
    tally = run["counts"]
    lines = [f"# mocaptk batch: {run['sessions']} sessions, --do {run['command']}", "",
             f"{tally['done']} done, {tally['skipped']} skipped (unchanged), {tally['failed']} failed"
             + (f", {tally['interrupted']} interrupted" if tally.get("interrupted") else "") + "; "
             f"{run['seconds']:.1f} s on {run['cluster']}.", "",
             "| session | command | status | markers | layout markers | held-out RMSE mm | time s | message |",
             "|---|---|---|---:|---:|---:|---:|---|"]
    for r in records:
        m = r.get("metrics") or {}
        message = (r.get("error") or "; ".join(w.removeprefix("mocaptk: ") for w in r.get("warnings", [])))
        lines.append(f"| {r['session']} | {r['command']} | {r['status']} | {_cell(m.get('markers'))} | "
                     f"{_cell(m.get('layout_markers'))} | {_cell(m.get('rmse_mm'))} | "
                     f"{_cell(r.get('seconds'), 1)} | {message.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def update_summary(out: Path, records: list[dict[str, Any]], run: dict[str, Any]) -> list[dict[str, Any]]:
    """Merge ``records`` into DIR/batch.json (as it is now: another batch may have written since
    this one started) and rewrite it and batch.md atomically, under DIR's lock; returns every record."""
    from mocaptk.atomic import write_text
    from mocaptk.jsonio import write_json

    from .lock import locked

    out.mkdir(parents=True, exist_ok=True)
    with locked(out / LOCK_NAME):
        current, _ = previous_records(out)
        every = merged(current, records)
        write_json(out / "batch.json", summary_document(every, run), digits=3)
        write_text(out / "batch.md", summary_markdown(every, run))
    return every
