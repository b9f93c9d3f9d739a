"""``report.html``: one self-contained page (plotly.js embedded, no network) from plain data.

The data (see :func:`report_html`) is embedded as one JSON block; ``page.js`` draws it with
plotly's offline bundle. Same data, same plotly version → byte-identical HTML.
"""

from __future__ import annotations

import os
import re
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
    return _page_bytes(data).decode("utf-8")


def _page_bytes(data: dict) -> bytes:
    """:func:`report_html` of ``data`` as UTF-8 bytes: each piece encoded once, the ~10 MB page
    neither re-scanned per placeholder nor encoded again to be measured and written."""
    import plotly
    import plotly.offline

    body = dict(data, format=FORMAT, version=VERSION, plotly_version=plotly.__version__,
                size=_SIZE_MARK)
    fill = {"TITLE": _escape(str(data.get("title", "mocaptk report"))), "CSS": _asset("page.css"),
            "PLOTLY": plotly.offline.get_plotlyjs(), "DATA": _script_json(body), "APP": _asset("page.js")}
    pieces = re.split("@@(" + "|".join(fill) + ")@@", _asset("page.html"))  # odd pieces: names
    page = b"".join((fill[piece] if k % 2 else piece).encode("utf-8") for k, piece in enumerate(pieces))
    size = f"{len(page) / 1e6:.1f} MB"  # within 0.1 MB of the final size
    return page.replace(_SIZE_MARK.encode("ascii"), size.encode("ascii"))


def write_report(path: str | os.PathLike[str], data: dict, *, force: bool = True) -> tuple[Path, int]:
    """Write :func:`report_html` of ``data`` atomically; returns (path, size in bytes)."""
    from mocaptk.atomic import write_bytes

    page = _page_bytes(data)
    return write_bytes(path, page, force=force), len(page)


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
