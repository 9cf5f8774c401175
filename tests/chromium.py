"""Debian's chromium, headless, driven over its DevTools protocol on a pipe
(``--remote-debugging-pipe``: the browser reads commands on its fd 3 and writes answers and
events on its fd 4, each message one JSON object ended by a NUL byte), so no WebSocket
library is needed. For tests/test_web.py, ``make docs-figures`` (the page's screenshot) and
benchmarks/bench_web.py.

    with Chromium() as browser:
        page = browser.open("http://127.0.0.1:8080/")
        page.wait_for("window.qradarView && window.qradarView.stats().targets > 0", 5.0)
        page.screenshot(Path("view.png"))

The browser dies with the process that started it (``PR_SET_PDEATHSIG``, set by a small
launcher that then execs it) and its profile is a fresh temporary directory, removed at
the end. Every wait is bounded in time. Missing chromium: the test is skipped, or fails
when ``QRADAR_REQUIRE_CHROMIUM=1`` (CI)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

#: CI sets this to 1: a missing chromium then fails the browser tests instead of skipping them
REQUIRE_ENV = "QRADAR_REQUIRE_CHROMIUM"
#: where Debian's package puts it, and other names it goes by
CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "/usr/bin/chromium")
#: headless, nothing fetched from the network on its own, a window of a fixed size
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-default-apps", "--disable-extensions", "--mute-audio", "--hide-scrollbars",
         "--remote-debugging-pipe")
#: the launcher: die with the parent, move the pipe's ends to fds 3 and 4, exec the browser
_LAUNCH = """import ctypes, fcntl, os, signal, sys
ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
r, w = (fcntl.fcntl(int(fd), fcntl.F_DUPFD, 10) for fd in sys.argv[1:3])
os.dup2(r, 3)
os.dup2(w, 4)
os.execv(sys.argv[3], sys.argv[3:])
"""


class BrowserError(RuntimeError):
    """The browser did not start, or a DevTools command failed or timed out."""


def find_chromium() -> str | None:
    """The chromium executable, or None."""
    for name in CANDIDATES:
        path = shutil.which(name)
        if path:
            return path
    return None


def require_chromium() -> str:
    """The chromium executable; skips the calling test without one (fails under
    QRADAR_REQUIRE_CHROMIUM=1)."""
    import pytest

    exe = find_chromium()
    if exe:
        return exe
    why = "chromium is not installed (Debian/Ubuntu: apt-get install chromium); the browser tests need it"
    if os.environ.get(REQUIRE_ENV) == "1":
        pytest.fail(f"{why}, and {REQUIRE_ENV}=1 requires them", pytrace=False)
    pytest.skip(why)


class Chromium:
    """A headless chromium and its DevTools connection (a context manager)."""

    def __init__(self, exe: str | None = None, width: int = 1400, height: int = 900, timeout_s: float = 15.0):
        self.exe = exe or find_chromium()
        if self.exe is None:
            raise BrowserError("no chromium found (Debian: apt-get install chromium)")
        self.width, self.height, self.timeout_s = width, height, timeout_s
        self.proc: subprocess.Popen | None = None
        self.profile = ""
        self._next_id = 0
        self._pending: dict[int, list] = {}  # id -> [threading.Event, message]
        self._lock = threading.Lock()
        self._console: list[str] = []
        self._closed = threading.Event()

    def __enter__(self) -> "Chromium":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> "Chromium":
        self.profile = tempfile.mkdtemp(prefix="qradar-chromium-")
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        argv = [self.exe, *FLAGS, f"--user-data-dir={self.profile}", f"--window-size={self.width},{self.height}",
                "about:blank"]
        self._log = open(Path(self.profile) / "stderr.log", "wb")
        try:
            self.proc = subprocess.Popen([sys.executable, "-c", _LAUNCH, str(to_browser_r), str(from_browser_w), *argv],
                                         pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL,
                                         stdout=self._log, stderr=subprocess.STDOUT)
        finally:
            os.close(to_browser_r)
            os.close(from_browser_w)
        self._reader = threading.Thread(target=self._read, name="cdp-reader", daemon=True)
        self._reader.start()
        self.send("Browser.getVersion")  # it answers: the pipe works
        return self

    def _read(self) -> None:
        buf = b""
        with open(self._from_browser, "rb", buffering=0) as pipe:
            while True:
                chunk = pipe.read(1 << 16)
                if not chunk:
                    break
                buf += chunk
                *messages, buf = buf.split(b"\0")
                for raw in messages:
                    self._dispatch(json.loads(raw))
        self._closed.set()
        with self._lock:  # whoever waits learns it now, not at its timeout
            for waiter in self._pending.values():
                waiter[0].set()

    def _dispatch(self, msg: dict) -> None:
        if "id" in msg:
            with self._lock:
                waiter = self._pending.get(msg["id"])
            if waiter is not None:
                waiter[1] = msg
                waiter[0].set()
        elif msg.get("method") == "Runtime.consoleAPICalled":
            args = msg["params"].get("args", [])
            line = " ".join(str(a.get("value", a.get("description", ""))) for a in args)
            with self._lock:
                self._console.append(f"{msg['params'].get('type')}: {line}")
        elif msg.get("method") == "Runtime.exceptionThrown":
            details = msg["params"]["exceptionDetails"]
            with self._lock:
                where = f" at {details.get('url', '')}:{details.get('lineNumber')}"
                self._console.append(f"exception: {details.get('exception', {}).get('description', details.get('text'))}"
                                     f"{where}")

    def console(self) -> list[str]:
        """The pages' console lines and uncaught exceptions so far."""
        with self._lock:
            return list(self._console)

    def send(self, method: str, params: dict | None = None, session: str | None = None,
             timeout_s: float | None = None) -> dict:
        """One DevTools command; its result (BrowserError on an error or after the timeout)."""
        with self._lock:
            self._next_id += 1
            ident = self._next_id
            waiter = self._pending[ident] = [threading.Event(), None]
        msg = {"id": ident, "method": method, "params": params or {}}
        if session is not None:
            msg["sessionId"] = session
        try:
            os.write(self._to_browser, json.dumps(msg).encode() + b"\0")
            if not waiter[0].wait(self.timeout_s if timeout_s is None else timeout_s) or waiter[1] is None:
                gone = " (the browser is gone)" if self._closed.is_set() else ""
                raise BrowserError(f"DevTools {method}: no answer{gone}; browser log: {self.log_tail()}")
        except OSError as exc:
            raise BrowserError(f"DevTools {method}: the pipe to the browser failed ({exc})") from None
        finally:
            with self._lock:
                self._pending.pop(ident, None)
        if "error" in waiter[1]:
            raise BrowserError(f"DevTools {method}: {waiter[1]['error']}")
        return waiter[1].get("result", {})

    def log_tail(self, n: int = 2000) -> str:
        try:
            return (Path(self.profile) / "stderr.log").read_text(errors="replace")[-n:]
        except OSError:
            return ""

    def open(self, url: str) -> "Page":
        """A new tab at ``url`` (navigation started, not waited for)."""
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(self, target, session)
        for domain in ("Page.enable", "Runtime.enable"):
            self.send(domain, session=session)
        self.send("Emulation.setDeviceMetricsOverride", {"width": self.width, "height": self.height,
                                                         "deviceScaleFactor": 1, "mobile": False}, session=session)
        page.navigate(url)
        return page

    def close(self) -> None:
        """Close the browser (Browser.close, then SIGKILL if it lingers) and remove its profile."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                self.send("Browser.close", timeout_s=5.0)
            except BrowserError:
                pass
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        try:
            os.close(self._to_browser)
        except (OSError, AttributeError):
            pass
        if getattr(self, "_reader", None) is not None:
            self._reader.join(5.0)
        if getattr(self, "_log", None) is not None:
            self._log.close()
        if self.profile:
            shutil.rmtree(self.profile, ignore_errors=True)
            self.profile = ""


class Page:
    """One tab of a :class:`Chromium`."""

    def __init__(self, browser: Chromium, target: str, session: str):
        self.browser, self.target, self.session = browser, target, session

    def send(self, method: str, params: dict | None = None, timeout_s: float | None = None) -> dict:
        return self.browser.send(method, params, session=self.session, timeout_s=timeout_s)

    def navigate(self, url: str) -> None:
        result = self.send("Page.navigate", {"url": url})
        if result.get("errorText"):
            raise BrowserError(f"cannot open {url}: {result['errorText']}")

    def evaluate(self, expression: str, timeout_s: float | None = None):
        """The value of a JavaScript expression in the page (a promise is awaited)."""
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                "awaitPromise": True}, timeout_s=timeout_s)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise BrowserError(f"{expression[:80]!r} raised in the page: "
                               f"{details.get('exception', {}).get('description', details.get('text'))}")
        return result["result"].get("value")

    def wait_for(self, condition: str, timeout_s: float, what: str | None = None):
        """Wait, in the page, until the expression ``condition`` is truthy (checked every
        20 ms and at each animation frame); its value. BrowserError after ``timeout_s``."""
        js = ("new Promise((resolve, reject) => { const t0 = performance.now(); "
              "const poll = () => { let v; try { v = (%s); } catch (e) { v = undefined; } "
              "if (v) resolve(v); else if (performance.now() - t0 > %d) reject(new Error('timed out')); "
              "else setTimeout(poll, 20); }; poll(); })") % (condition, int(timeout_s * 1000))
        try:
            return self.evaluate(js, timeout_s=timeout_s + 5.0)
        except BrowserError as exc:
            raise BrowserError(f"waited {timeout_s:g} s for {what or condition}: {exc}; "
                               f"console: {self.browser.console()[-5:]}") from None

    def screenshot(self, path: Path) -> Path:
        """A PNG of the page as it is shown (its viewport)."""
        data = self.send("Page.captureScreenshot", {"format": "png"})["data"]
        path.write_bytes(base64.b64decode(data))
        return path
