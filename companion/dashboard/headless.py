"""Headless Chromium driven over the DevTools protocol on a pipe (no WebDriver, no download).

Debian's ``chromium`` package runs with ``--remote-debugging-pipe``: DevTools messages are
NUL-terminated JSON on file descriptors 3 (to the browser) and 4 (from it), the transport
Puppeteer uses. That is all the tests and ``companion bench`` need: open a page, evaluate
JavaScript in it, take a screenshot. Calls block; run it outside asyncio event loops.
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
COMMAND_TIMEOUT_S = 30.0
CLOSE_TIMEOUT_S = 5.0


class BrowserError(RuntimeError):
    """Chromium is missing, died, timed out or answered a command with an error."""


def find_chromium() -> str | None:
    """Path of an installed Chromium (Debian: ``apt-get install chromium``), or None."""
    return next((path for name in CHROMIUM_NAMES if (path := shutil.which(name))), None)


class HeadlessChromium:
    """One headless Chromium with one page; use as a context manager."""

    def __init__(self, width: int = 1600, height: int = 1000, executable: str | None = None) -> None:
        executable = executable or find_chromium()
        if executable is None:
            raise BrowserError(f"no Chromium found (looked for {', '.join(CHROMIUM_NAMES)})")
        self._profile = tempfile.TemporaryDirectory(prefix="companion-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # fds 3 and 4 in the browser: bash moves them there (no preexec_fn with threads around; dash
        # takes single-digit fds only). from_browser_w is the highest of the four, never 3.
        args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                "--no-default-browser-check", "--disable-extensions", "--remote-debugging-pipe",
                f"--window-size={width},{height}", f"--user-data-dir={self._profile.name}", "about:blank"]
        self._process = subprocess.Popen(
            ["bash", "-c", f'exec "$0" "$@" 3<&{to_browser_r} 4>&{from_browser_w}', executable, *args],
            pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._next_id = 0
        try:
            target = self._command("Target.createTarget", {"url": "about:blank"})["targetId"]
            self._session = self._command("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            self._command("Page.enable", session=True)
        except BaseException:  # no __exit__ will run: do not leave the browser and its profile behind
            self.close()
            raise

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self, url: str, timeout_s: float = COMMAND_TIMEOUT_S) -> None:
        """Navigate to ``url`` and wait until its load event."""
        self._command("Page.navigate", {"url": url}, session=True)
        self.wait_for("document.readyState === 'complete'", timeout_s, "the page to load")

    def evaluate(self, expression: str) -> Any:
        """The JSON value of a JavaScript expression in the page (promises are awaited)."""
        result = self._command("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                    "awaitPromise": True}, session=True)
        if "exceptionDetails" in result:
            raise BrowserError(f"{expression!r} threw: {result['exceptionDetails'].get('text')}")
        return result["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float, what: str, poll_s: float = 0.1) -> Any:
        """Poll ``expression`` until it is truthy; its value. Raises BrowserError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise BrowserError(f"timed out after {timeout_s:g} s waiting for {what}")
            time.sleep(poll_s)

    def screenshot(self, path: Path) -> Path:
        """Save a PNG of the page's viewport at ``path``."""
        data = self._command("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        """Close the browser (it is killed if it does not exit in time) and remove its profile."""
        if self._process.poll() is None:
            try:
                self._send("Browser.close", {}, session=False)
                self._process.wait(CLOSE_TIMEOUT_S)
            except (OSError, subprocess.TimeoutExpired):
                self._process.kill()
                self._process.wait()
        for fd in (self._to_browser, self._from_browser):
            try:
                os.close(fd)
            except OSError:
                pass
        self._profile.cleanup()

    # -- the protocol ------------------------------------------------------------------------

    def _send(self, method: str, params: dict[str, Any], session: bool) -> int:
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if session:
            message["sessionId"] = self._session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        return self._next_id

    def _command(self, method: str, params: dict[str, Any] | None = None, session: bool = False) -> dict[str, Any]:
        """Send one command and return its result, skipping the events that arrive meanwhile."""
        wanted = self._send(method, params or {}, session)
        deadline = time.monotonic() + COMMAND_TIMEOUT_S
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == wanted:
                    if "error" in reply:
                        raise BrowserError(f"{method}: {reply['error'].get('message')}")
                    return reply["result"]
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not select.select([self._from_browser], [], [], remaining)[0]:
                raise BrowserError(f"{method}: no answer from Chromium within {COMMAND_TIMEOUT_S:g} s")
            chunk = os.read(self._from_browser, 1 << 16)
            if not chunk:
                raise BrowserError(f"{method}: Chromium exited (status {self._process.poll()})")
            self._buffer += chunk
