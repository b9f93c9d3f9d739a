"""``label_report.json`` and the technician's summary line of a labelling."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..runs import true_runs
from .capture import Labelled, Mislabel
from .template import LabelTemplate

REPORT_FORMAT = "mocaptk.label-report"
REPORT_VERSION = 1
#: A labelled point is uncertain below this confidence (about 2.1 model spreads off).
UNCERTAIN = 0.1
#: Entries listed for the least confident frames and the uncertain runs.
LISTED = 20


def label_report(template: LabelTemplate, result: Labelled, *, first_frame: int = 0,
                 mislabels: list[Mislabel] | None = None) -> dict[str, Any]:
    """The report (frames numbered as in the capture, ``first_frame`` + index; ranges inclusive)."""
    labels, conf = result.labels, result.confidence
    n_frames = labels.shape[0]
    points = result.fragments >= 0
    labelled = labels >= 0
    per_label: dict[str, Any] = {}
    frames_of = np.zeros((n_frames, template.n_markers), dtype=bool)
    conf_of = np.zeros((n_frames, template.n_markers))
    f, c = np.nonzero(labelled)
    frames_of[f, labels[f, c]] = True
    conf_of[f, labels[f, c]] = conf[f, c]
    uncertain = []
    for m, name in enumerate(template.labels):
        seen = frames_of[:, m]
        per_label[name] = {"frames": int(seen.sum()),
                           "mean_confidence": round(float(conf_of[seen, m].mean()), 4) if seen.any() else None}
        for a, b in true_runs(seen & (conf_of[:, m] < UNCERTAIN)):
            uncertain.append({"label": name, "frames": b - a, "start": first_frame + a, "end": first_frame + b - 1})
    uncertain.sort(key=lambda u: (-u["frames"], u["start"], u["label"]))
    per_frame = np.where(frames_of, conf_of, np.nan)
    frame_conf = np.array([np.nanmean(row) if np.isfinite(row).any() else np.nan for row in per_frame])
    order = [int(k) for k in np.argsort(np.nan_to_num(frame_conf, nan=np.inf), kind="stable")[:LISTED]
             if np.isfinite(frame_conf[k])]
    fragment_labels = _fragment_labels(labels, result.fragments)
    joined = int(sum(1 for count in fragment_labels.values() if count > 1))
    report: dict[str, Any] = {
        "format": REPORT_FORMAT, "version": REPORT_VERSION, "mode": result.mode,
        "frames": n_frames, "markers": template.n_markers,
        "points": int(points.sum()), "labelled_points": int(labelled.sum()),
        "unlabelled_points": int((points & ~labelled).sum()),
        "fragments": int(len(np.unique(result.fragments[points]))), "fragments_split": result.split,
        "labels_joined_from_fragments": joined,
        "labels": per_label,
        "uncertain": uncertain[:LISTED],
        "uncertain_runs": len(uncertain),
        "lowest_confidence_frames": [{"frame": first_frame + k, "mean_confidence": round(float(frame_conf[k]), 4)}
                                     for k in order],
    }
    if mislabels is not None:
        report["mislabels"] = [{"label": r.label, "found": r.found, "start": first_frame + r.start,
                                "end": first_frame + r.end - 1, "swap": r.swap} for r in mislabels]
    return report


def _fragment_labels(labels: np.ndarray, fragments: np.ndarray) -> dict[int, int]:
    """Per template label, how many distinct fragments carry it."""
    f, c = np.nonzero(labels >= 0)
    pairs = np.unique(np.stack([labels[f, c], fragments[f, c]], axis=1), axis=0)
    lab, count = np.unique(pairs[:, 0], return_counts=True)
    return dict(zip(lab.tolist(), count.tolist()))


def summary_line(report: dict[str, Any]) -> str:
    """One line: what was labelled, what was left, and the first thing to look at."""
    points, done = report["points"], report["labelled_points"]
    line = (f"labelled {done:,} of {points:,} points ({done / max(points, 1):.2%}) as "
            f"{report['markers']} markers in {report['frames']:,} frames ({report['mode']}); "
            f"{report['unlabelled_points']:,} left unlabelled (ghosts or unmatched); "
            f"{report['fragments_split']} fragments split")
    if "mislabels" in report:
        swaps = sum(1 for m in report["mislabels"] if m["swap"])
        line += f"; {len(report['mislabels'])} mislabelled runs ({swaps} in swaps)"
    if report["uncertain"]:
        worst = report["uncertain"][0]
        span = f"{worst['start']}" if worst["start"] == worst["end"] else f"{worst['start']}–{worst['end']}"
        line += (f"; {worst['label']}: {worst['frames']} frames uncertain ({span})"
                 + (f", {report['uncertain_runs'] - 1} more uncertain runs" if report["uncertain_runs"] > 1 else ""))
    else:
        line += "; no uncertain frames"
    return line
