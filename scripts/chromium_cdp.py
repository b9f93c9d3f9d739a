"""Headless Chromium driven over the DevTools protocol (used by the report tests and screenshots).

Needs Debian's ``chromium`` (``scripts/install-readers.sh``) and PyPI ``websocket-client``.
The browser runs with a fresh empty profile, no network services, and software WebGL.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--use-angle=swiftshader", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--disable-default-apps", "--mute-audio", "--hide-scrollbars",
         "--remote-debugging-port=0"]


def chromium_path() -> str | None:
    """The Chromium executable, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


class Chromium:
    """One headless browser with one page. ``console`` collects console errors and exceptions."""

    def __init__(self, *, width: int = 1400, height: int = 900, timeout: float = 60.0):
        import websocket

        exe = chromium_path()
        if exe is None:
            raise RuntimeError("chromium not found (run scripts/install-readers.sh)")
        self.profile = tempfile.mkdtemp(prefix="mocaptk-chromium-")
        self.process = subprocess.Popen(
            [exe, *FLAGS, f"--user-data-dir={self.profile}", f"--window-size={width},{height}",
             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        browser_url = self._devtools_url(timeout)
        port = re.search(r":(\d+)/", browser_url).group(1)
        self.ws = websocket.create_connection(browser_url, timeout=timeout)
        self._ids = itertools.count(1)
        self.timeout = timeout
        self.console: list[str] = []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        self.port = int(port)
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=True)
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)

    def _devtools_url(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.process.stderr.readline()
            if not line and self.process.poll() is not None:
                break
            match = re.search(r"DevTools listening on (ws://\S+)", line)
            if match:
                return match.group(1)
        self.close()
        raise RuntimeError("chromium did not start its DevTools endpoint")

    def call(self, method: str, *, session: bool = False, **params):
        """Send one command; return its result (events met on the way are recorded)."""
        ident = next(self._ids)
        message = {"id": ident, "method": method, "params": params}
        if session:
            message["sessionId"] = self.session
        self.ws.send(json.dumps(message))
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            reply = json.loads(self.ws.recv())
            if reply.get("id") == ident:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self._event(reply)
        raise TimeoutError(method)

    def _event(self, event: dict) -> None:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            self.console.append(" ".join(str(a.get("value", a.get("description", "")))
                                         for a in params.get("args", [])))
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            self.console.append(details.get("exception", {}).get("description")
                                or details.get("text", "exception"))
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
            self.console.append(params["entry"].get("text", ""))

    def evaluate(self, expression: str):
        """Value of a JS expression (promises awaited)."""
        result = self.call("Runtime.evaluate", session=True, expression=expression,
                           returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            raise RuntimeError(result["exceptionDetails"].get("exception", {}).get("description",
                                                                                  "JS exception"))
        return result["result"].get("value")

    def open(self, path: str | os.PathLike[str], *, ready: str, timeout: float = 60.0) -> float:
        """Load a file; wait until the JS expression ``ready`` is true. Returns seconds taken."""
        start = time.monotonic()
        self.call("Page.navigate", session=True, url=Path(path).resolve().as_uri())
        while time.monotonic() - start < timeout:
            if self.evaluate(f"Boolean({ready})"):
                return time.monotonic() - start
            time.sleep(0.05)
        raise TimeoutError(f"page not ready after {timeout} s: {ready}")

    def screenshot(self, path: str | os.PathLike[str]) -> Path:
        """PNG of the viewport."""
        shot = self.call("Page.captureScreenshot", session=True, format="png")
        Path(path).write_bytes(base64.b64decode(shot["data"]))
        return Path(path)

    def close(self) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                self.ws.close()
        finally:
            if self.process.poll() is None:
                self.process.terminate()
                try:
                    self.process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.process.kill()
                    self.process.wait()
            shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
