"""Screenshot a mocaptk report.html in headless Chromium (for docs/report-*.png).

Usage: python scripts/report_screenshot.py REPORT.html OUT.png [--clip K] [--seconds T]
       [--colour K] [--eye X,Y,Z] [--size 1400x900]; prints the page's load time.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from chromium_cdp import Chromium  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--clip", type=int, default=0, help="replay clip (0: session)")
    parser.add_argument("--seconds", type=float, default=None, help="time in the clip")
    parser.add_argument("--colour", type=int, default=None, help="error map to colour by (-1: clusters)")
    parser.add_argument("--eye", default=None, help="camera eye x,y,z (plotly units; front: 0,0.1,1.85)")
    parser.add_argument("--size", default="1400x900")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    with Chromium(width=width, height=height) as browser:
        seconds = browser.open(args.report, ready="window.mocaptkReport && window.mocaptkReport.ready",
                               timeout=120)
        if args.colour is not None:
            browser.evaluate(f"mocaptkReport.pick({args.colour})")
        browser.evaluate(f"mocaptkReport.setClip({args.clip})")
        if args.seconds is not None:
            browser.evaluate(f"mocaptkReport.setFrame({args.seconds} * "
                             f"mocaptkReport.data.clips[{args.clip}].rate_hz)")
        if args.eye:
            x, y, z = (float(v) for v in args.eye.split(","))
            browser.evaluate(f"mocaptkReport.view({{x: {x}, y: {y}, z: {z}}})")
        browser.evaluate("mocaptkReport.settled()")
        browser.screenshot(args.out)
        if browser.console:
            sys.exit(f"console errors: {browser.console}")
    print(f"{args.out}: page ready in {seconds:.2f} s")


if __name__ == "__main__":
    main()
