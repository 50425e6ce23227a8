"""Drive headless Chromium over the DevTools protocol on a pipe: load a page, wait, evaluate, screenshot.

No extra package: Chromium's ``--remote-debugging-pipe`` reads JSON commands (NUL-terminated) on its
fd 3 and writes replies and events on fd 4. :class:`HeadlessChromium` starts the browser with a fresh
profile and software WebGL (SwiftShader through ANGLE: ``--use-angle=swiftshader
--enable-unsafe-swiftshader``; ``shared/docs/deps.md`` §5), attaches to its page and offers
:meth:`~HeadlessChromium.goto`, :meth:`~HeadlessChromium.evaluate`, :meth:`~HeadlessChromium.wait_for`
and :meth:`~HeadlessChromium.screenshot` (an exact ``width x height`` PNG of the viewport at device
scale 1). Used by the viewer test and for measuring the viewer's frame rate.
"""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = ("--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--ignore-gpu-blocklist", "--force-color-profile=srgb", "--hide-scrollbars", "--mute-audio",
         "--disable-quic", "--no-first-run", "--no-default-browser-check", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--disable-extensions", "--disable-dev-shm-usage",
         "--disable-features=Translate,MediaRouter")


def find_chromium() -> str | None:
    """Path of a Chromium / Chrome executable on ``PATH`` (``$OMNIRECON_CHROMIUM`` first), or ``None``."""
    env = os.environ.get("OMNIRECON_CHROMIUM")
    if env and shutil.which(env):
        return shutil.which(env)
    return next((shutil.which(n) for n in CHROMIUM_NAMES if shutil.which(n)), None)


class BrowserError(RuntimeError):
    """The browser failed, timed out or the page reported an error."""


class BrowserTimeout(BrowserError):
    """No reply in time."""


class HeadlessChromium:
    """One headless Chromium with one page (use as a context manager; :meth:`close` ends the process)."""

    def __init__(self, width: int = 800, height: int = 600, executable: str | None = None, timeout: float = 30.0,
                 flags: tuple[str, ...] = ()):
        exe = executable or find_chromium()
        if exe is None:
            raise BrowserError("no Chromium on PATH (apt-get install chromium)")
        self.timeout = timeout
        self.events: list[dict] = []
        """Events received so far (console messages and exceptions of the page among them)."""
        for attempt in range(self.STARTS):
            try:
                self._start(exe, width, height, flags)
                return
            except BrowserTimeout:  # a browser that never answered its first command: start a new one
                if attempt == self.STARTS - 1:
                    raise

    STARTS = 2
    """Browsers started at most, when one does not answer its first protocol command in time."""

    def _start(self, exe: str, width: int, height: int, flags: tuple[str, ...]) -> None:
        """Start the browser process on a new profile, attach to its page and size the viewport; on any failure the
        process is ended (:meth:`close`) and the error raised."""
        self.profile = tempfile.mkdtemp(prefix="omnirecon-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        # the browser reads commands on fd 3 and writes replies on fd 4: move our ends there in the child
        # (first out of the way of 3 and 4, which the pipes themselves may occupy)
        high_r = fcntl.fcntl(to_browser_r, fcntl.F_DUPFD_CLOEXEC, 10)
        high_w = fcntl.fcntl(from_browser_w, fcntl.F_DUPFD_CLOEXEC, 10)
        for fd in (to_browser_r, from_browser_w):
            os.close(fd)
        to_browser_r, from_browser_w = high_r, high_w

        def wire() -> None:  # in the child, before exec; dup2 clears close-on-exec
            os.dup2(high_r, 3)
            os.dup2(high_w, 4)

        args = [exe, *FLAGS, *flags, f"--user-data-dir={self.profile}", f"--window-size={width},{height}",
                "--remote-debugging-pipe", "about:blank"]
        self.log = tempfile.TemporaryFile()
        # close_fds=False keeps the new 3 and 4; Python's own descriptors are close-on-exec anyway
        self.proc = subprocess.Popen(args, close_fds=False, preexec_fn=wire, stdin=subprocess.DEVNULL,
                                     stdout=self.log, stderr=self.log, start_new_session=True)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buf = b""
        self._next_id = 0
        self._replies: dict[int, dict] = {}
        self.session = None
        try:
            targets = self.command("Target.getTargets")["targetInfos"]
            page = next((t for t in targets if t["type"] == "page"), None)
            target = page["targetId"] if page else self.command("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.command("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            self.command("Runtime.enable", session=True)
            self.command("Page.enable", session=True)
            self.set_viewport(width, height)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ protocol
    def _read_message(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserTimeout("no reply from Chromium in time")
            ready, _, _ = select.select([self._from_browser], [], [], min(left, 1.0))
            if not ready:
                if self.proc.poll() is not None:
                    raise BrowserError(f"Chromium exited with code {self.proc.returncode}: {self.stderr_tail()}")
                continue
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise BrowserError(f"Chromium closed the pipe: {self.stderr_tail()}")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def send(self, method: str, session: bool = False, **params) -> int:
        """Send one protocol command (to the page's session with ``session=True``); returns its id."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        data = json.dumps(msg).encode() + b"\0"
        while data:
            data = data[os.write(self._to_browser, data):]
        return self._next_id

    def reply(self, id: int, method: str = "", timeout: float | None = None) -> dict:
        """The result of command ``id`` (replies to other commands are kept for their own call)."""
        deadline = time.monotonic() + (timeout or self.timeout)
        while id not in self._replies:
            msg = self._read_message(deadline)
            if "id" in msg:
                self._replies[msg["id"]] = msg
            elif "method" in msg:
                self.events.append(msg)
        msg = self._replies.pop(id)
        if "error" in msg:
            raise BrowserError(f"{method or 'command'}: {msg['error'].get('message')}")
        return msg.get("result", {})

    def command(self, method: str, session: bool = False, timeout: float | None = None, **params) -> dict:
        """Send one protocol command and return its result."""
        return self.reply(self.send(method, session, **params), method, timeout)

    def stderr_tail(self, n: int = 2000) -> str:
        self.log.seek(0)
        return self.log.read().decode(errors="replace")[-n:]

    # ------------------------------------------------------------------ page
    def set_viewport(self, width: int, height: int) -> None:
        self.command("Emulation.setDeviceMetricsOverride", session=True, width=int(width), height=int(height),
                     deviceScaleFactor=1, mobile=False)

    def goto(self, url: str, timeout: float | None = None) -> None:
        """Navigate and wait for the page's load event."""
        self.events = [e for e in self.events if e.get("method") != "Page.loadEventFired"]
        result = self.command("Page.navigate", session=True, url=url)
        if result.get("errorText"):
            raise BrowserError(f"cannot load {url}: {result['errorText']}")
        deadline = time.monotonic() + (timeout or self.timeout)
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events):
            self.events.append(self._read_message(deadline))

    def evaluate(self, expression: str, await_promise: bool = False, timeout: float | None = None):
        """Value of a JavaScript expression in the page (JSON-serialisable values only)."""
        out = self.command("Runtime.evaluate", session=True, timeout=timeout, expression=expression,
                           awaitPromise=await_promise, returnByValue=True)
        if "exceptionDetails" in out:
            d = out["exceptionDetails"]
            text = d.get("exception", {}).get("description") or d.get("text")
            raise BrowserError(f"{expression[:80]}: {text}")
        return out.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout: float | None = None, interval: float = 0.05):
        """Poll until ``expression`` is truthy; returns its value."""
        deadline = time.monotonic() + (timeout or self.timeout)
        while time.monotonic() < deadline:
            try:
                value = self.evaluate(expression)
            except BrowserError:  # e.g. the document is being replaced
                value = None
            if value:
                return value
            time.sleep(interval)
        raise BrowserError(f"timed out waiting for {expression!r}; page messages: {self.console()[-5:]}")

    def console(self) -> list[str]:
        """The page's console messages and uncaught exceptions so far."""
        out = []
        for e in self.events:
            if e.get("method") == "Runtime.consoleAPICalled":
                p = e["params"]
                out.append(f"{p['type']}: " + " ".join(str(a.get('value', a.get('description', ''))) for a in p["args"]))
            elif e.get("method") == "Runtime.exceptionThrown":
                d = e["params"]["exceptionDetails"]
                out.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
        return out

    def screenshot(self, path: Path | None = None, width: int | None = None, height: int | None = None,
                   redraw: str | None = None) -> bytes:
        """PNG of the viewport's top-left ``width x height`` pixels (default: all of it), device scale 1.

        A capture waits for a new compositor frame, and in headless mode a page that draws only on
        demand makes none by itself: while waiting, the page is asked to redraw with the JavaScript
        ``redraw`` (it should draw the same picture again; default: toggle a 1-px element between
        opacity 0 and 0.01 in the bottom-right corner, which may shift that pixel by a few levels)."""
        params = {"format": "png", "fromSurface": True}
        if width and height:
            params["clip"] = {"x": 0, "y": 0, "width": int(width), "height": int(height), "scale": 1}
        redraw = redraw or (
            "(() => { let d = document.getElementById('__redraw'); if (!d) { d = document.createElement('div');"
            " d.id = '__redraw'; d.style.cssText = 'position:fixed;right:0;bottom:0;width:1px;height:1px;"
            "pointer-events:none;opacity:0'; document.body.appendChild(d); }"
            " d.style.opacity = d.style.opacity === '0' ? '0.01' : '0'; return 1; })()")
        shot = self.send("Page.captureScreenshot", session=True, **params)
        deadline = time.monotonic() + self.timeout
        while True:
            try:
                result = self.reply(shot, "Page.captureScreenshot", timeout=0.25)
                break
            except BrowserTimeout:
                if time.monotonic() > deadline:
                    raise
                self.command("Runtime.evaluate", session=True, expression=redraw)
        png = base64.b64decode(result["data"])
        if path is not None:
            Path(path).write_bytes(png)
        return png

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        if getattr(self, "proc", None) is None:
            return
        try:
            if self.proc.poll() is None:
                try:
                    if self.session is not None:  # a browser that never attached its page is not asked
                        self.command("Browser.close", timeout=5)
                except (BrowserError, OSError):
                    pass
                try:
                    self.proc.wait(5 if self.session is not None else 0)
                except subprocess.TimeoutExpired:  # the browser and its helpers: our own process group
                    os.killpg(self.proc.pid, signal.SIGKILL)
                    self.proc.wait(5)
        finally:
            for fd in (self._to_browser, self._from_browser):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self.log.close()
            shutil.rmtree(self.profile, ignore_errors=True)
            self.proc = None

    def __enter__(self) -> HeadlessChromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
