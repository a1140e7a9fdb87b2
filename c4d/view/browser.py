"""Headless Chromium driven over the DevTools protocol on a pipe: screenshots and page checks.

`c4d view --screenshot` and the browser tests open pages with it. Chromium is started with
`--remote-debugging-pipe`: it reads protocol messages (JSON, each ended by a NUL byte) from its
file descriptor 3 and answers on 4, so no port is opened and no websocket client is needed. WebGL
runs on SwiftShader, Chromium's software renderer, so no GPU or display is needed either.

Finding the browser: `C4D_BROWSER` (a path) if set, else the first of `BROWSER_NAMES` on PATH;
none is one `UserError` saying how to install it (Debian/Ubuntu: `apt-get install chromium`).
"""

from __future__ import annotations

import base64
import io
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from c4d_core.errors import UserError

BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless", "--remote-debugging-pipe", "--no-first-run", "--no-default-browser-check",
    "--disable-extensions", "--disable-background-networking", "--disable-sync", "--mute-audio",
    "--hide-scrollbars", "--disable-dev-shm-usage", "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
)


def find_browser() -> str:
    """The Chromium (or Chrome) executable: `C4D_BROWSER`, else the first of `BROWSER_NAMES` on
    PATH; `UserError` when there is none."""
    chosen = os.environ.get("C4D_BROWSER")
    if chosen:
        path = shutil.which(chosen)
        if path is None:
            raise UserError(f"C4D_BROWSER={chosen} is not an executable; point it at Chromium or "
                            "Chrome, or unset it to look for one on PATH")
        return path
    for name in BROWSER_NAMES:
        path = shutil.which(name)
        if path is not None:
            return path
    raise UserError(f"no Chromium or Chrome found on PATH (looked for {', '.join(BROWSER_NAMES)}); "
                    "install it (Debian/Ubuntu: apt-get install chromium) or set C4D_BROWSER to "
                    "its path")


class Browser:
    """One headless Chromium process with a `width` x `height` pixel viewport; `open(url)` gives
    a `Page`. Use as a context manager: the process and its profile folder go at the end."""

    def __init__(self, width: int = 1280, height: int = 800, timeout: float = 60.0):
        self.width, self.height, self.timeout = width, height, timeout
        executable = find_browser()
        self._profile = tempfile.TemporaryDirectory(prefix="c4d-chromium-")
        to_child, self._out = _high_pipe()  # we write commands into fd 3 of the child
        self._in, from_child = _high_pipe()  # the child answers on its fd 4

        def child_fds():  # in the child before exec: dup2's copies stay open across it
            os.dup2(to_child, 3)
            os.dup2(from_child, 4)

        flags = [*FLAGS, f"--user-data-dir={self._profile.name}", f"--window-size={width},{height}",
                 *(("--no-sandbox",) if os.geteuid() == 0 else ()), "about:blank"]  # root: no sandbox
        self._executable = executable
        self._stderr = Path(self._profile.name) / "c4d-stderr.txt"  # its last line: why it ended
        try:
            with open(self._stderr, "wb") as stderr:
                self._process = subprocess.Popen(
                    [executable, *flags], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                    stderr=stderr, close_fds=False, preexec_fn=child_fds)
        except OSError as exc:
            for fd in (self._in, self._out):
                os.close(fd)
            self._profile.cleanup()
            raise UserError(f"cannot start {executable}: {exc.strerror or exc}") from exc
        finally:
            os.close(to_child)
            os.close(from_child)
        self._buffer, self._next_id = b"", 0
        self.events: list[dict] = []  # protocol events not yet looked at, oldest first

    def __enter__(self) -> "Browser":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the browser (politely, then by its process id) and remove its profile."""
        if self._process.poll() is None:
            try:
                self.send("Browser.close", timeout=5)
            except (UserError, OSError):
                pass
            try:
                self._process.wait(5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        for fd in (self._in, self._out):
            try:
                os.close(fd)
            except OSError:
                pass
        self._profile.cleanup()

    def send(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float | None = None) -> dict:
        """Send one protocol command and return its result; events read meanwhile are kept in
        `events`. A protocol error or no answer within `timeout` s is a `UserError`."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        try:
            os.write(self._out, json.dumps(message).encode() + b"\0")
        except BrokenPipeError:  # it closed its end: it has exited
            raise self._ended(method) from None
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            reply = self._read(deadline, method)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise UserError(f"Chromium refused {method}: {reply['error'].get('message')}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def _read(self, deadline: float, waiting_for: str) -> dict:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._in], [], [], left)[0]:
                raise UserError(f"Chromium did not answer {waiting_for} within {self.timeout:.0f} s")
            chunk = os.read(self._in, 1 << 20)
            if not chunk:
                raise self._ended(waiting_for)
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def _ended(self, method: str) -> UserError:
        """The `UserError` for the browser gone before answering `method`: its path, exit code
        and the last line it printed on stderr."""
        try:
            code = self._process.wait(5)
        except subprocess.TimeoutExpired:
            code = "none yet: it closed its protocol pipe"
        lines = self._stderr.read_text(errors="replace").splitlines() if self._stderr.exists() else []
        last = next((line.strip() for line in reversed(lines) if line.strip()), None)
        said = f"its last line on stderr: {last}" if last else "nothing on stderr"
        return UserError(f"the browser {self._executable} exited before answering {method} (exit "
                         f"code {code}; {said}); check that it runs headless there, or set "
                         "C4D_BROWSER to another Chromium or Chrome")

    def open(self, url: str) -> "Page":
        """A new tab showing `url`, once its load event has fired."""
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(self, session)
        for domain in ("Page", "Runtime", "Log", "Network"):
            page.send(f"{domain}.enable")
        page.send("Emulation.setDeviceMetricsOverride", {
            "width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False})
        page.navigate(url)
        return page


class Page:
    """One tab of a `Browser`: evaluate JavaScript, wait for a condition, take screenshots, read
    its protocol events (`events`) and what it reported as errors (`errors`)."""

    def __init__(self, browser: Browser, session: str):
        self.browser, self.session = browser, session
        self._seen: list[dict] = []  # this tab's events read so far

    def send(self, method: str, params: dict | None = None) -> dict:
        return self.browser.send(method, params, self.session)

    def navigate(self, url: str) -> None:
        """Open `url` in this tab and wait for its load event."""
        loads = len(self.events("Page.loadEventFired"))
        reply = self.send("Page.navigate", {"url": url})
        if reply.get("errorText"):
            raise UserError(f"Chromium cannot open {url}: {reply['errorText']}")
        deadline = time.monotonic() + self.browser.timeout
        while len(self.events("Page.loadEventFired")) == loads:
            if time.monotonic() > deadline:
                raise UserError(f"{url} did not finish loading within {self.browser.timeout:.0f} s")
            time.sleep(0.05)

    def evaluate(self, expression: str, await_promise: bool = False) -> Any:
        """The value of a JavaScript expression (JSON-serialisable values come back as Python's);
        an exception in the page is a `UserError` with its message."""
        reply = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                               "awaitPromise": await_promise})
        if "exceptionDetails" in reply:
            details = reply["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise UserError(f"the page failed to evaluate {expression!r}: {text}")
        return reply["result"].get("value")

    def wait_for(self, expression: str, timeout: float | None = None) -> Any:
        """Evaluate `expression` every 50 ms until it is truthy, and return its value;
        `UserError` after `timeout` s (the browser's timeout by default)."""
        deadline = time.monotonic() + (self.browser.timeout if timeout is None else timeout)
        while True:
            value = self.evaluate(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise UserError(f"the page did not reach {expression!r}; its errors: "
                                f"{self.errors() or 'none'}")
            time.sleep(0.05)

    def next_frames(self, count: int = 2) -> None:
        """Wait until the page has drawn `count` more animation frames (what was set is shown)."""
        self.evaluate("new Promise(done => { let n = %d; const step = () => --n ? "
                      "requestAnimationFrame(step) : done(true); requestAnimationFrame(step); })"
                      % count, await_promise=True)

    def screenshot(self) -> np.ndarray:
        """The viewport as RGB uint8 (H,W,3)."""
        from PIL import Image

        data = self.send("Page.captureScreenshot", {"format": "png"})["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def events(self, method: str) -> list[dict]:
        """The parameters of every `method` event of this tab so far (e.g.
        "Network.requestWillBeSent" once `send("Network.enable")` was called)."""
        self.evaluate("0")  # a round trip, so that events sent before it are read
        mine = [e for e in self.browser.events if e.get("sessionId") == self.session]
        self.browser.events = [e for e in self.browser.events if e.get("sessionId") != self.session]
        self._seen += mine
        return [e.get("params", {}) for e in self._seen if e["method"] == method]

    def errors(self) -> list[str]:
        """Every error the page reported so far, one line each: console.error (and failed
        console.assert), uncaught exceptions, resources that failed to load."""
        lines = ["console: " + " ".join(str(a.get("value", a.get("description", "")))
                                        for a in params.get("args", []))
                 for params in self.events("Runtime.consoleAPICalled")
                 if params.get("type") in ("error", "assert")]
        lines += ["exception: " + str(p.get("exceptionDetails", {}).get("exception", {}).get("description")
                                      or p.get("exceptionDetails", {}).get("text"))
                  for p in self.events("Runtime.exceptionThrown")]
        lines += [f"{e['source']}: {e.get('text')} {e.get('url', '')}".strip()
                  for e in (p["entry"] for p in self.events("Log.entryAdded"))
                  if e.get("level") == "error"]
        return lines


def _high_pipe() -> tuple[int, int]:
    """A pipe (read end, write end) on descriptors from 10 up, closed on exec, so that placing
    the child's ends on 3 and 4 can overwrite neither."""
    import fcntl

    ends = os.pipe()
    try:
        return tuple(fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in ends)
    finally:
        for fd in ends:
            os.close(fd)


def screenshot_file(html: Path, png: Path, frame: int, width: int, height: int) -> dict:
    """Open the viewer page `html` in headless Chromium with a `width` x `height` viewport, show
    `frame` and write the viewport to `png`; returns the page's stats. An error the page reports
    is one `UserError`."""
    from c4d_core.ownership import write_png
    from c4d_core.video import encode_image

    with Browser(width, height) as browser:
        page = browser.open(Path(html).resolve().as_uri())
        wait_for_view(page)
        page.evaluate(f"c4dView.setFrame({int(frame)})")
        page.next_frames()
        image = page.screenshot()
        errors = page.errors()
        if errors:
            raise UserError(f"the viewer page reported errors: {errors[0]}")
        stats = page.evaluate("c4dView.stats")
    write_png(png, encode_image(image, ".png"), "view")  # marked: a later --screenshot may replace it
    return stats


def wait_for_view(page: Page) -> None:
    """Wait until the viewer page says it is ready (`data-c4d-state` of <html>); its own error
    message when it failed."""
    state = page.wait_for("document.documentElement.dataset.c4dState !== 'loading' && "
                          "document.documentElement.dataset.c4dState")
    if state != "ready":
        raise UserError(f"the viewer page failed: {page.evaluate('document.title')}; "
                        f"{page.errors() or 'no error reported'}")
