"""The report page in a real browser: headless Chromium (Debian's ``chromium``, which ``make
setup`` installs) loads a report from ``file://`` and is driven through the DevTools protocol over
a pipe (``--remote-debugging-pipe``: NUL-terminated JSON on file descriptors 3 and 4, so no
websocket client and no Python package beyond the standard library).

A page passes when it loads with no uncaught exception, no console error and no failed resource
(a missing image is a console error), every image on it has loaded, it fits a 1400 px window,
its charts are there and the comparator's script built its viewer. The comparator is then used as
a person would: keys flip technique and truth and pick the modes, pointing at a mode button
previews it, + zooms with nearest-neighbour pixels, arrows change the technique. A page with a
deliberate JavaScript error must fail the same check (so the check can fail).

Without Chromium these tests fail (they do not skip) and say how to install it.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from test_report import make_run

from shadowlab.report import build

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
WIDTH, HEIGHT = 1400, 900


def chromium() -> str:
    """The Chromium binary ($SHADOWLAB_CHROMIUM, else the first of NAMES on PATH); fails the test
    with the fix when there is none."""
    exe = os.environ.get("SHADOWLAB_CHROMIUM") or next(filter(None, map(shutil.which, NAMES)), None)
    if exe and not shutil.which(exe):
        pytest.fail(f"SHADOWLAB_CHROMIUM={exe} is not an executable file; point it at a Chromium binary or unset "
                    "it (then `make setup` installs the Debian package chromium)", pytrace=False)
    if not exe:
        pytest.fail("Chromium is not installed; the report's browser test needs it. Run `make setup` (as root it "
                    "installs the Debian package chromium with apt-get; otherwise run `sudo apt-get install "
                    "chromium`), or point SHADOWLAB_CHROMIUM at a Chromium binary.", pytrace=False)
    return exe


def _high(fd: int) -> int:
    """``fd`` moved to a descriptor ≥ 10, so that the child's 3 and 4 can be set without clashes."""
    h = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return h


class Browser:
    """Headless Chromium driven by the DevTools protocol over a pipe; one tab per :meth:`open`."""

    def __init__(self, profile: Path):
        to_r, self._w = map(_high, os.pipe())      # we write, Chromium reads fd 3
        self._r, from_w = map(_high, os.pipe())    # Chromium writes fd 4, we read

        def fds():
            os.dup2(to_r, 3)
            os.dup2(from_w, 4)

        args = [chromium(), "--headless", "--disable-gpu", "--no-sandbox", "--remote-debugging-pipe",
                f"--user-data-dir={profile}", f"--window-size={WIDTH},{HEIGHT}", "--hide-scrollbars",
                "--no-first-run", "--disable-extensions", "about:blank"]
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
            chunk = os.read(self._r, 1 << 16)
            if not chunk:
                raise EOFError("Chromium closed the DevTools pipe: " + self.proc.stderr.read().decode()[-2000:])
            self._buf += chunk
        msg, _, self._buf = self._buf.partition(b"\0")
        return json.loads(msg)

    def call(self, method: str, params: dict | None = None, *, session: bool = True, timeout: float = 20.0) -> dict:
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
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def wait_for(self, event: str, timeout: float = 20.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            for e in self.events:
                if e.get("method") == event and e.get("sessionId") == self.session:
                    return e
            self.events.append(self._recv(deadline))

    def open(self, url: str) -> None:
        """A new tab on ``url`` with its events recorded; returns after the load event (images loaded)."""
        target = self.call("Target.createTarget", {"url": "about:blank"}, session=False)["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                 session=False)["sessionId"]
        self.events = []
        for m in ("Runtime.enable", "Log.enable", "Page.enable"):
            self.call(m)
        self.call("Emulation.setDeviceMetricsOverride", {"width": WIDTH, "height": HEIGHT, "deviceScaleFactor": 1,
                                                         "mobile": False})
        self.call("Page.navigate", {"url": url})
        self.wait_for("Page.loadEventFired")

    def js(self, expr: str):
        r = self.call("Runtime.evaluate", {"expression": expr, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in r:
            raise AssertionError(f"{expr}: {r['exceptionDetails']}")
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

    def close(self) -> None:
        try:
            self.call("Browser.close", session=False, timeout=5)
        except (OSError, TimeoutError, EOFError, RuntimeError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._w)
        os.close(self._r)


def _rich_run() -> dict:
    """The test_report run with three techniques, light kinds, distance bands and a light in view."""
    run = make_run(names=("pcf", "pcss", "vsm"))
    run["light_info"] = {"key": {"kind": "spot", "radius": 0.1, "angle": 30.0},
                         "fill": {"kind": "rect", "size": [1.0, 0.5]}}
    for i, t in enumerate(run["techniques"].values()):
        t["metrics"]["rmse_penumbra"] = 0.03 * (i + 1)
        t["per_light"]["key"]["rmse_penumbra"] = 0.05 * (i + 1)
        t["bands"] = {"key": {"distance": [
            {"lo": lo, "hi": hi, "pixels": 10, "rmse": 0.1 * (i + 1) * (k + 1), "rmse_penumbra": 0.1,
             "leak_rate": 0.0, "overdark_rate": 0.0} for k, (lo, hi) in enumerate(((0.0, 1.0), (1.0, float("inf"))))]}}
    run["images"]["mitsuba"][:4, :4] = 32.0          # a light in view: mi.render shows its radiance
    return run


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("browser") / "rep"
    build(out, _rich_run())
    return out


@pytest.fixture
def browser(tmp_path):
    b = Browser(tmp_path / "profile")
    yield b
    b.close()


def test_the_page_loads_without_errors_and_the_comparator_is_built(report, browser):
    browser.open((report / "index.html").as_uri())
    assert browser.errors() == []
    assert browser.js("document.getElementById('cmp').getAttribute('data-ready')") == "1"
    for sel in ("#cmp-item", "#cmp-layer", "#cmp-viewport", "#cmp-stack", "#cmp-a", "#cmp-b", "#cmp-err",
                "#cmp-legend", "#cmp-status", "#cmp-zoom-in", "#cmp-gain", "#cmp-hover"):
        assert browser.js(f"document.querySelector('{sel}') !== null"), sel
    assert browser.js("[...document.querySelectorAll('#cmp-item option')].map(o => o.textContent)") == [
        "pcf", "pcss", "vsm", "mi.render (Mitsuba direct)"]
    assert browser.js("[...document.querySelectorAll('#cmp-layer option')].map(o => o.textContent)") == [
        "shaded", "key visibility", "fill visibility"]
    assert browser.js("document.querySelectorAll('#cmp button[data-mode]').length") == 4
    # every image of the page (and the comparator's) loaded
    bad = browser.js("[...document.images].filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.src)")
    assert bad == []
    assert browser.js("document.getElementById('cmp-a').naturalWidth") == 64
    # 2 bar charts, the time scatter and the distance-band chart of light key
    assert browser.js("document.querySelectorAll('svg.chart').length") == 4
    assert browser.js("document.querySelectorAll('svg.chart circle').length") >= 3
    # the page fits a 1400 px window: no horizontal scrolling
    assert browser.js("document.documentElement.scrollWidth") <= WIDTH
    assert (
        browser.js("Math.max(...[...document.querySelectorAll('table')].map(t => t.getBoundingClientRect().right))")
        <= WIDTH
    )


def test_the_comparator_flips_by_key_and_hover_and_zooms_nearest_neighbour(report, browser):
    browser.open((report / "index.html").as_uri())
    js = browser.js
    mode = lambda: js("document.getElementById('cmp').getAttribute('data-mode')")  # noqa: E731
    shown = lambda i: js(f"getComputedStyle(document.getElementById('{i}')).visibility") == "visible"  # noqa: E731
    assert mode() == "a" and shown("cmp-a") and not shown("cmp-b")
    assert js("document.getElementById('cmp-a').getAttribute('src')") == "img/t0_pcf_shaded.png"
    assert js("document.getElementById('cmp-b').getAttribute('src')") == "img/truth_shaded.png"
    browser.key(" ", "Space", 32)
    assert mode() == "b" and shown("cmp-b") and not shown("cmp-a")
    browser.key("t", "KeyT", 84)
    assert mode() == "a"
    browser.key("3", "Digit3", 51)                    # difference: technique over truth, blended by the browser
    assert mode() == "diff" and shown("cmp-a") and shown("cmp-b")
    assert js("getComputedStyle(document.getElementById('cmp-a')).mixBlendMode") == "difference"
    assert js("document.getElementById('cmp-stack').style.filter") == "brightness(4)"
    browser.key("4", "Digit4", 52)                    # the signed error map, with its colour bar and scale
    assert mode() == "err" and shown("cmp-err") and not shown("cmp-a")
    assert js("document.querySelector('#cmp-legend .cbar') !== null")
    assert js("document.getElementById('cmp-err').getAttribute('src')") == "img/t0_pcf_shaded_err.png"
    browser.key("1", "Digit1", 49)
    # hover: pointing at the truth button shows the truth, moving away shows the technique again
    browser.point_at("#cmp button[data-mode=b]")
    assert mode() == "b"
    browser.point_at("#cmp-title")
    assert mode() == "a"
    # zoom: nearest-neighbour pixels, + doubles 8× to 12×
    assert js("getComputedStyle(document.getElementById('cmp-a')).imageRendering") == "pixelated"
    w0 = js("document.getElementById('cmp-stack').getBoundingClientRect().width")
    browser.key("+", "Equal", 187)
    w1 = js("document.getElementById('cmp-stack').getBoundingClientRect().width")
    assert w1 > w0 and w1 % 64 == 0 and js("document.getElementById('cmp-zoom').textContent").endswith("×")
    # arrows: next technique, next image (light key's visibility)
    browser.key("ArrowRight", "ArrowRight", 39)
    browser.key("ArrowDown", "ArrowDown", 40)
    assert js("document.getElementById('cmp-item').value") == "1"
    assert js("document.getElementById('cmp-a').getAttribute('src')") == "img/t1_pcss_vis_0_key.png"
    assert js("document.getElementById('cmp-b').getAttribute('src')") == "img/truth_vis_0_key.png"
    # a technique's "compare" link opens it in the comparator
    js("document.querySelector('a.open[data-cmp-item=\"2\"]').click()")
    assert js("document.getElementById('cmp-a').getAttribute('src')") == "img/t2_vsm_shaded.png"
    assert browser.errors() == []


def test_a_javascript_error_or_a_missing_image_fails_the_check(report, browser, tmp_path):
    """The check can fail: the same page with a deliberate error in its script, and with an image removed."""
    bad = tmp_path / "rep"
    shutil.copytree(report, bad)
    page = (bad / "index.html").read_text()
    (bad / "index.html").write_text(page.replace('root.setAttribute("data-ready", "1");',
                                                 'root.setAttribute("data-ready", "1"); noSuchFunction();'))
    browser.open((bad / "index.html").as_uri())
    errs = browser.errors()
    assert errs and "noSuchFunction" in errs[0]
    (bad / "index.html").write_text(page)
    (bad / "img" / "t0_pcf_shaded.png").unlink()
    browser.open((bad / "index.html").as_uri())
    assert any("ERR_FILE_NOT_FOUND" in e or "t0_pcf_shaded.png" in e for e in browser.errors()), browser.errors()


def test_the_light_in_view_does_not_set_the_mitsuba_error_scale(report):
    """mi.render shows a light's radiance (32) where the truth has no shading point: the scale
    of the mi.render − truth map stays that of the surfaces."""
    html = (report / "index.html").read_text()
    i = html.index("signed error mi.render - truth")
    ticks = html[i:i + 400]
    scale = float(ticks.split("<span>0</span><span>+")[1].split("<")[0])
    run = _rich_run()
    lum = run["images"]["mitsuba"] @ np.array([0.2126, 0.7152, 0.0722])
    assert scale < 0.1 < 32 and lum.max() > 30
