"""Load time of a report.html in headless Chromium, against the floor of its plotly bundle.

Baseline (same run, same browser): a page holding only the embedded plotly.js bundle and one
3-point 3-D scatter — what any plotly-based offline page pays before drawing anything. The two
pages are loaded in turns (load on a shared machine hits both alike); the median of ``--rounds``
is reported, with the machine's load average.

Usage: python benchmarks/bench_report.py REPORT.html [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from chromium_cdp import Chromium  # noqa: E402

READY = "window.mocaptkReport && window.mocaptkReport.ready"


def floor_page(folder: Path) -> Path:
    import plotly.offline

    page = folder / "plotly_floor.html"
    page.write_text("<!DOCTYPE html><html><head><meta charset='utf-8'><script>" + plotly.offline.get_plotlyjs()
                    + "</script></head><body><div id='s' style='width:900px;height:800px'></div><script>"
                    "Plotly.newPlot('s',[{type:'scatter3d',mode:'markers',x:[1,2,3],y:[1,2,3],z:[1,2,3]}])"
                    ".then(()=>{window.mocaptkReport={ready:true};});</script></body></html>", encoding="utf-8")
    return page


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        floor = floor_page(Path(tmp))
        times: dict[str, list[float]] = {"report": [], "plotly floor": []}
        with Chromium() as browser:
            for _ in range(args.rounds):
                for name, page in (("report", args.report), ("plotly floor", floor)):
                    times[name].append(browser.open(page, ready=READY, timeout=180))
                    browser.open("about:blank", ready="true")
    load = os.getloadavg()
    size = args.report.stat().st_size / 1e6
    print(f"load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} cores")
    for name, values in times.items():
        print(f"{name:<14} median {statistics.median(values):6.2f} s  "
              f"(rounds: {', '.join(f'{v:.2f}' for v in values)})")
    ratio = statistics.median(times["report"]) / statistics.median(times["plotly floor"])
    print(f"report ({size:.1f} MB) / plotly floor: {ratio:.2f}x; target < 3 s: "
          f"{'met' if statistics.median(times['report']) < 3 else 'not met'}")


if __name__ == "__main__":
    main()
