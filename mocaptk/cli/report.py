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


def write_cluster_report(result, build, path: Path, *, summary: str) -> Path:
    """``mocaptk cluster``'s report (``build``: the rig, None without one); its size and replay
    rate are added to ``summary.txt`` beside it."""
    from ..atomic import write_text
    from ..retarget.report import cluster_report, write_report

    layout = result.layout
    title = (f"mocaptk cluster: {layout.source.get('path', '')} · factor "
             f"{layout.parameters.get('factor')} · {len(layout.clusters)} layout markers")
    data = cluster_report(layout, result.trajectories, build=build, summary=summary, title=title)
    written, size = write_report(path, data)
    write_text(path.with_name("summary.txt"), summary + report_line(path, size, data["clips"]) + "\n")
    return written
