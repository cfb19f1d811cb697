"""Headless Chromium driven through the DevTools protocol over a pipe, and a loopback HTTP server.

The browser half of shadowlab (the report's page test, the engines of ``shadowlab.techniques``'s
``engine_*`` modules) runs Debian's ``chromium`` (which ``make setup`` installs) headless and talks
to it with ``--remote-debugging-pipe``: NUL-terminated JSON messages on file descriptors 3 and 4
[Chrome DevTools 2026], so no websocket client and nothing beyond the standard library.
``webgl=True`` adds ``--use-angle=swiftshader --enable-unsafe-swiftshader``: WebGL 2 on the CPU
(ANGLE on SwiftShader), so real engines render without a GPU.

:func:`serve` runs a standard-library HTTP server on 127.0.0.1 in a thread: ES modules need
``http:`` (not ``file:``), and nothing is fetched from the network.

A missing Chromium is an :class:`~shadowlab.errors.EnvironmentProblem` (exit 3) naming the fix.
"""

from __future__ import annotations

import fcntl
import http.server
import json
import os
import select
import shutil
import subprocess
import threading
import time
from pathlib import Path

from ..errors import EnvironmentProblem

#: Chromium binaries looked for on PATH when $SHADOWLAB_CHROMIUM is not set
NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
#: Chromium's flags for WebGL 2 without a GPU (ANGLE on SwiftShader's Vulkan)
WEBGL_FLAGS = ("--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")
#: flags for pages without WebGL (the report)
PLAIN_FLAGS = ("--headless", "--disable-gpu")


class BrowserError(RuntimeError):
    """The browser or a page failed (a protocol error, a script exception, a closed pipe)."""


def chromium() -> str:
    """The Chromium binary: $SHADOWLAB_CHROMIUM, else the first of :data:`NAMES` on PATH;
    EnvironmentProblem with the fix when there is none."""
    exe = os.environ.get("SHADOWLAB_CHROMIUM") or next(filter(None, map(shutil.which, NAMES)), None)
    if exe and not shutil.which(exe):
        raise EnvironmentProblem(f"SHADOWLAB_CHROMIUM={exe} is not an executable file; point it at a Chromium binary "
                                 "or unset it (then `make setup` installs the Debian package chromium)")
    if not exe:
        raise EnvironmentProblem("Chromium is not installed (the browser tests and the engines need it): run `make "
                                 "setup` (as root it installs the Debian package chromium with apt-get; otherwise "
                                 "`sudo apt-get install chromium`), or point SHADOWLAB_CHROMIUM at a Chromium binary")
    return exe


def _high(fd: int) -> int:
    """``fd`` moved to a descriptor ≥ 10, so that the child's 3 and 4 can be set without clashes."""
    h = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return h


class Browser:
    """Headless Chromium over the DevTools pipe; one tab at a time (:meth:`open`).

    ``profile``: the user-data directory; ``size``: the window (W, H); ``webgl``: the SwiftShader
    flags (:data:`WEBGL_FLAGS`) instead of :data:`PLAIN_FLAGS`."""

    def __init__(self, profile: Path, *, size: tuple = (1400, 900), webgl: bool = False):
        self.size = (int(size[0]), int(size[1]))
        to_r, self._w = map(_high, os.pipe())      # we write, Chromium reads fd 3
        self._r, from_w = map(_high, os.pipe())    # Chromium writes fd 4, we read

        def fds():
            os.dup2(to_r, 3)
            os.dup2(from_w, 4)

        args = [chromium(), *(WEBGL_FLAGS if webgl else PLAIN_FLAGS), "--no-sandbox", "--remote-debugging-pipe",
                f"--user-data-dir={profile}", f"--window-size={self.size[0]},{self.size[1]}", "--hide-scrollbars",
                "--no-first-run", "--disable-extensions", "--mute-audio", "about:blank"]
        self.proc = subprocess.Popen(args, pass_fds=(3, 4), preexec_fn=fds, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        os.close(to_r)
        os.close(from_w)
        self._buf, self._id, self.session, self.events = b"", 0, None, []

    def _recv(self, deadline: float) -> dict:
        while b"\0" not in self._buf:
            ready, _, _ = select.select([self._r], [], [], max(0.0, deadline - time.monotonic()))
            if not ready:
                raise TimeoutError("Chromium did not answer in time")
            chunk = os.read(self._r, 1 << 20)
            if not chunk:
                raise BrowserError("Chromium closed the DevTools pipe: " + self.proc.stderr.read().decode()[-2000:])
            self._buf += chunk
        msg, _, self._buf = self._buf.partition(b"\0")
        return json.loads(msg)

    def call(self, method: str, params: dict | None = None, *, session: bool = True, timeout: float = 20.0) -> dict:
        """Send one protocol command (to the current tab unless ``session`` is False) and return its result."""
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session and self.session:
            msg["sessionId"] = self.session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            m = self._recv(deadline)
            if m.get("id") == self._id:
                if "error" in m:
                    raise BrowserError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_for(self, event: str, timeout: float = 20.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            for e in self.events:
                if e.get("method") == event and e.get("sessionId") == self.session:
                    return e
            self.events.append(self._recv(deadline))

    def open(self, url: str, *, timeout: float = 30.0) -> None:
        """A new tab on ``url`` with its events recorded; returns after the load event (images loaded)."""
        target = self.call("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                 session=False)["sessionId"]
        self.events = []
        for m in ("Runtime.enable", "Log.enable", "Page.enable"):
            self.call(m)
        self.call("Emulation.setDeviceMetricsOverride", {"width": self.size[0], "height": self.size[1],
                                                         "deviceScaleFactor": 1, "mobile": False})
        self.call("Page.navigate", {"url": url})
        self.wait_for("Page.loadEventFired", timeout=timeout)

    def js(self, expr: str, *, timeout: float = 60.0):
        """Evaluate ``expr`` in the tab (promises awaited) and return its value; a thrown exception
        is a :class:`BrowserError` with its description."""
        r = self.call("Runtime.evaluate", {"expression": expr, "returnByValue": True, "awaitPromise": True},
                      timeout=timeout)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise BrowserError(f"{expr[:80]}: {d.get('exception', {}).get('description') or d.get('text')}")
        return r["result"].get("value")

    def errors(self) -> list[str]:
        """Uncaught exceptions, console errors and failed loads of the current tab."""
        out = []
        for e in self.events:
            m, p = e.get("method"), e.get("params", {})
            if e.get("sessionId") != self.session:
                continue
            if m == "Runtime.exceptionThrown":
                d = p["exceptionDetails"]
                out.append(f"{d.get('exception', {}).get('description') or d.get('text')} "
                           f"({d.get('url', '')}:{d.get('lineNumber')})")
            elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                out.append("console.error: " + " ".join(str(a.get("value", a.get("description"))) for a in p["args"]))
            elif m == "Log.entryAdded" and p["entry"].get("level") == "error":
                out.append(f"{p['entry'].get('text')} {p['entry'].get('url', '')}")
        return out

    def key(self, key: str, code: str | None = None, vk: int = 0) -> None:
        text = key if len(key) == 1 else ""
        base = {"key": key, "code": code or key, "windowsVirtualKeyCode": vk, "nativeVirtualKeyCode": vk}
        self.call("Input.dispatchKeyEvent", {"type": "keyDown" if text else "rawKeyDown", "text": text, **base})
        self.call("Input.dispatchKeyEvent", {"type": "keyUp", **base})

    def point_at(self, selector: str) -> None:
        """Move the mouse onto the centre of the element ``selector`` (scrolled into view)."""
        x, y = self.js(f"(() => {{ const e = document.querySelector({json.dumps(selector)}); e.scrollIntoView("
                       "{block: 'center'}); const r = e.getBoundingClientRect(); return [r.x + r.width / 2, "
                       "r.y + r.height / 2]; })()")
        self.call("Input.dispatchMouseEvent", {"type": "mouseMoved", "x": x, "y": y})

    def alive(self) -> bool:
        return self.proc.poll() is None

    def close(self) -> None:
        try:
            self.call("Browser.close", session=False, timeout=5)
        except (OSError, TimeoutError, BrowserError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._w, self._r):
            try:
                os.close(fd)
            except OSError:
                pass


class _Handler(http.server.BaseHTTPRequestHandler):
    """GET only: ``/<prefix>/<path>`` from the server's ``roots`` (a prefix -> directory), or the
    bytes the server ``blobs`` hold under the path; nothing outside a root is served."""

    protocol_version = "HTTP/1.1"         # keep-alive: a page of thousands of ES modules loads in seconds
    TYPES = {".js": "text/javascript", ".mjs": "text/javascript", ".html": "text/html", ".json": "application/json",
             ".glb": "model/gltf-binary", ".wasm": "application/wasm"}

    def do_GET(self):  # noqa: N802 (the standard library's name)
        path = self.path.split("?", 1)[0]
        blob = self.server.blobs.get(path)
        if blob is None:
            prefix, _, rest = path.lstrip("/").partition("/")
            root = self.server.roots.get(prefix)
            f = (root / rest).resolve() if root is not None else None
            if f is None or not f.is_file() or root.resolve() not in f.parents:
                self.send_error(404, f"not served: {path}")
                return
            blob = f.read_bytes()
        self.send_response(200)
        self.send_header("Content-Type", self.TYPES.get(Path(path).suffix, "application/octet-stream"))
        self.send_header("Content-Length", str(len(blob)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(blob)

    def log_message(self, *args):  # quiet
        pass


class LocalServer:
    """A loopback HTTP server in a daemon thread: ``roots`` maps a URL prefix to a directory;
    :meth:`put` serves bytes under a path (e.g. a scene's glb). ``url`` is ``http://127.0.0.1:PORT``."""

    def __init__(self, roots: dict):
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        self.httpd.roots = {k: Path(v) for k, v in roots.items()}
        self.httpd.blobs = {"/favicon.ico": b""}
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="shadowlab-http", daemon=True)
        self.thread.start()

    def put(self, path: str, data: bytes) -> str:
        """Serve ``data`` at ``path`` (starting with /); returns its URL."""
        self.httpd.blobs[path] = bytes(data)
        return self.url + path

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def serve(roots: dict) -> LocalServer:
    """Start a :class:`LocalServer` on 127.0.0.1 (a free port) serving ``roots``."""
    return LocalServer(roots)
