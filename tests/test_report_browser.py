"""The report page in a real browser: headless Chromium (Debian's ``chromium``, which ``make
setup`` installs) loads a report from ``file://`` and is driven through the DevTools protocol over
a pipe by :class:`shadowlab.io.browser.Browser` (``--remote-debugging-pipe``, standard library only;
the engines use the same driver).

A page passes when it loads with no uncaught exception, no console error and no failed resource
(a missing image is a console error), every image on it has loaded, it fits a 1400 px window,
its charts are there and the comparator's script built its viewer. The comparator is then used as
a person would: keys flip technique and truth and pick the modes, pointing at a mode button
previews it, + zooms with nearest-neighbour pixels, arrows change the technique. A page with a
deliberate JavaScript error must fail the same check (so the check can fail).

Without Chromium these tests fail (they do not skip): EnvironmentProblem says how to install it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from test_report import make_run

from shadowlab.io.browser import Browser
from shadowlab.report import build

WIDTH, HEIGHT = 1400, 900


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
    b = Browser(tmp_path / "profile", size=(WIDTH, HEIGHT))
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
