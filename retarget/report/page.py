"""``report.html``: one self-contained page (plotly.js embedded, no network) from plain data.

The data (see :func:`report_html`) is embedded as one JSON block; ``page.js`` draws it with
plotly's offline bundle. Same data, same plotly version → byte-identical HTML.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

from mocaptk.jsonio import to_plain

__all__ = ["FORMAT", "VERSION", "report_html", "write_report"]

FORMAT = "mocaptk.report"
VERSION = 1
_SIZE_MARK = "@@REPORT_SIZE@@"


def _asset(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def _script_json(obj) -> str:
    import json

    text = json.dumps(to_plain(obj, digits=4), ensure_ascii=False, allow_nan=False,
                      separators=(",", ":"), sort_keys=True)
    return text.replace("</", "<\\/")  # never closes the <script> element early


def report_html(data: dict) -> str:
    """The page for ``data``: ``title``, ``kind`` (cluster/evaluate/compare/solve), the scene
    (:func:`~mocaptk.retarget.report.scene.scene_data`), ``clips`` (replay clips), optional
    ``errors`` ({name: per-marker error mm}), ``tables`` ([{title, columns, rows}]) and
    ``summary`` (text). The summary panel states the file's own size."""
    import plotly
    import plotly.offline

    body = dict(data, format=FORMAT, version=VERSION, plotly_version=plotly.__version__,
                size=_SIZE_MARK)
    page = (_asset("page.html")
            .replace("@@TITLE@@", _escape(str(data.get("title", "mocaptk report"))))
            .replace("@@CSS@@", _asset("page.css"))
            .replace("@@PLOTLY@@", plotly.offline.get_plotlyjs())
            .replace("@@DATA@@", _script_json(body))
            .replace("@@APP@@", _asset("page.js")))
    size = len(page.encode("utf-8"))
    return page.replace(_SIZE_MARK, f"{size / 1e6:.1f} MB")  # within 0.1 MB of the final size


def write_report(path: str | os.PathLike[str], data: dict, *, force: bool = True) -> tuple[Path, int]:
    """Write :func:`report_html` of ``data`` atomically; returns (path, size in bytes)."""
    from mocaptk.atomic import write_text

    page = report_html(data)
    return write_text(path, page, force=force), len(page.encode("utf-8"))


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
