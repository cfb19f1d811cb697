"""The pytest plugin (entry point pytest11): shadowlab_gate against baselines, --shadowlab-update,
never writing a baseline on failure or bad input. Run through pytest's own `pytester`."""

import hashlib
import json

import pytest
from conftest import plugin_installed

# Inner sessions run in subprocesses: in-process runs share sys.modules with this session, and
# native extensions loaded by other test files (Mitsuba, Dr.Jit, OpenEXR) do not survive pytester's
# module snapshots (aborts / segfaults while formatting a traceback).
pytest_plugins = ["pytester"]
pytestmark = plugin_installed

# the image under test: a lit plane with a soft shadow disc (linear RGB), parameters from the test
IMAGE = '''
import numpy as np
def image(bright=1.0, shift=0, nan=False, size=32, rgb=True):
    y, x = np.mgrid[0:size, 0:size] + 0.5
    r = np.hypot(x - 16 - shift, y - 16)
    v = np.clip((r - 6.0) / 4.0, 0.0, 1.0)          # umbra r < 6, penumbra 6..10, lit beyond
    img = np.stack([v * 0.8, v * 0.7, v * 0.6], -1) * bright + 0.05
    if nan:
        img[3, 4, 0] = np.nan
    return img if rgb else v
'''


def _sha(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture
def suite(pytester):
    pytester.makepyfile(imgsrc=IMAGE)
    return pytester


def _test(pytester, body, name="test_img"):
    pytester.makepyfile(**{name: "from imgsrc import image\n" + body})


def test_plugin_is_registered_by_entry_point(pytester):
    res = pytester.runpytest_subprocess("--help")
    res.stdout.fnmatch_lines(["*--shadowlab-update*", "*--shadowlab-baseline-dir*"])
    pytester.makepyfile("def test_f(shadowlab_gate):\n    assert callable(shadowlab_gate)\n")
    pytester.runpytest_subprocess().assert_outcomes(passed=1)


def test_missing_baseline_fails_then_update_writes_it_and_later_runs_pass(suite):
    _test(suite, "def test_a(shadowlab_gate):\n    shadowlab_gate(image(), 'soft/disc')\n")
    res = suite.runpytest_subprocess()
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*no baseline for 'soft/disc'*run pytest with --shadowlab-update*"])
    base = suite.path / "baselines"
    assert not base.exists()  # a failure writes nothing

    res = suite.runpytest_subprocess("--shadowlab-update")
    res.assert_outcomes(passed=1)
    res.stdout.fnmatch_lines(["*shadowlab: wrote 1 baseline(s)*", "*baselines/soft/disc.exr"])
    exr, meta = base / "soft" / "disc.exr", base / "soft" / "disc.json"
    m = json.loads(meta.read_text())
    assert m["shape"] == [32, 32, 3] and m["target"] == "shaded" and m["stamp"] is None
    assert m["exr_sha256"] == _sha(exr)

    suite.runpytest_subprocess().assert_outcomes(passed=1)


def test_a_failing_gate_never_touches_the_baseline(suite, monkeypatch):
    _test(suite, "import os\ndef test_a(shadowlab_gate):\n"
                 "    shadowlab_gate(image(bright=float(os.environ.get('B', '1'))), 'disc')\n")
    suite.runpytest_subprocess("--shadowlab-update").assert_outcomes(passed=1)
    exr = suite.path / "baselines" / "disc.exr"
    before = (_sha(exr), _sha(exr.with_suffix(".json")))
    monkeypatch.setenv("B", "1.05")
    res = suite.runpytest_subprocess("--shadowlab-results", "failed")
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*shadowlab_gate 'disc' failed against*", "*FAIL  disc  stat.pixels*",
                              "*failure page: failed/disc.html*", "*re-run with --shadowlab-update*"])
    assert (_sha(exr), _sha(exr.with_suffix(".json"))) == before
    page = (suite.path / "failed" / "disc.html").read_text()
    assert "p-value map" in page and page.count("data:image/png;base64,") == 4
    # bad input with --shadowlab-update: an error, and the old baseline stays
    _test(suite, "def test_a(shadowlab_gate):\n    shadowlab_gate(image(nan=True), 'disc')\n")
    res = suite.runpytest_subprocess("--shadowlab-update")
    res.assert_outcomes(errors=0, failed=1)
    res.stdout.fnmatch_lines(["*InputError*non-finite value (NaN/Inf), first at pixel (x=4, y=3)*"])
    assert (_sha(exr), _sha(exr.with_suffix(".json"))) == before


def test_update_writes_nothing_for_a_test_that_fails(suite):
    """--shadowlab-update writes a test's baselines only once the test has passed: not when it fails
    after the call, nor when a later call of the same test has bad input; a name is written once."""
    _test(suite, "def test_a(shadowlab_gate):\n    shadowlab_gate(image(), 'disc')\n    assert False, 'later'\n"
                 "def test_b(shadowlab_gate):\n    shadowlab_gate(image(), 'ok')\n"
                 "    shadowlab_gate(image(nan=True), 'bad')\n"
                 "def test_c(shadowlab_gate):\n    shadowlab_gate(image(), 'dup')\n    shadowlab_gate(image(), 'dup')\n"
                 "def test_d(shadowlab_gate):\n    shadowlab_gate(image(), 'good')\n")
    res = suite.runpytest_subprocess("--shadowlab-update")
    res.assert_outcomes(failed=3, passed=1)
    res.stdout.fnmatch_lines(["*baseline 'dup' is gated twice*"])
    res.stdout.fnmatch_lines(["*shadowlab: wrote 1 baseline(s)*", "*baselines/good.exr",
                              "*shadowlab: 3 baseline(s) NOT written: their test failed*"])
    assert sorted(p.name for p in (suite.path / "baselines").iterdir()) == ["good.exr", "good.json"]


def test_thresholds_budget_and_statistical_with_variance(suite):
    _test(suite, """
import numpy as np
def test_write(shadowlab_gate):
    shadowlab_gate(image(), 'budget')
    shadowlab_gate(image(), 'noisy', variance=np.full((32, 32, 3), 1e-4))
    shadowlab_gate(image(rgb=False), 'vis')

def test_budget_passes(shadowlab_gate):
    r = shadowlab_gate(image(shift=1), 'budget', flip=0.5, rmse=0.1)
    assert [c.name for c in r.checks] == ['budget.flip', 'budget.rmse'] and r.passed

def test_budget_fails(shadowlab_gate):
    shadowlab_gate(image(shift=1), 'budget', rmse=1e-4)

def test_noise_passes(shadowlab_gate):
    rng = np.random.default_rng(1)
    img = image() + rng.normal(0, 0.01, (32, 32, 3))
    r = shadowlab_gate(img, 'noisy', variance=np.full((32, 32, 3), 1e-4), ptol=0)
    assert r.check('stat.pixels').passed

def test_noise_with_bias_fails(shadowlab_gate):
    rng = np.random.default_rng(2)
    img = image() + rng.normal(0, 0.01, (32, 32, 3)) + 0.004
    shadowlab_gate(img, 'noisy', variance=np.full((32, 32, 3), 1e-4), ptol=0)

def test_visibility_tolerance(shadowlab_gate):
    shadowlab_gate(image(rgb=False) + 0.002, 'vis', atol=0.0025, ptol=0)
    with pytest_raises_fail():
        shadowlab_gate(image(rgb=False) + 0.002, 'vis', atol=0.001, ptol=0)

def test_unknown_threshold(shadowlab_gate):
    shadowlab_gate(image(), 'budget', alhpa=0.1)

import contextlib, pytest
@contextlib.contextmanager
def pytest_raises_fail():
    with pytest.raises(pytest.fail.Exception):
        yield
""")
    suite.runpytest_subprocess("--shadowlab-update", "-k", "write").assert_outcomes(passed=1, deselected=6)
    res = suite.runpytest_subprocess("-k", "not write", "-rf")
    res.assert_outcomes(passed=3, failed=3)
    res.stdout.fnmatch_lines(["FAILED*test_budget_fails*", "FAILED*test_noise_with_bias_fails*",
                              "FAILED*test_unknown_threshold*"])
    res.stdout.fnmatch_lines(["*FAIL  budget  budget.rmse*"])
    res.stdout.fnmatch_lines(["*FAIL  noisy  stat.bias *"])
    res.stdout.fnmatch_lines(["*unknown threshold(s) alhpa; statistical settings: alpha*"])


def test_stale_wrong_size_and_edited_baselines_fail(suite, monkeypatch):
    _test(suite, """
import os
def test_a(shadowlab_gate):
    shadowlab_gate(image(size=int(os.environ.get('S', '32'))), 'disc', stamp=os.environ.get('STAMP', 'scene-v1'))
""")
    suite.runpytest_subprocess("--shadowlab-update").assert_outcomes(passed=1)
    suite.runpytest_subprocess().assert_outcomes(passed=1)
    monkeypatch.setenv("STAMP", "scene-v2")
    res = suite.runpytest_subprocess()
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(
        ["*baseline*disc.exr is stale: it was made from stamp 'scene-v1', this image from 'scene-v2'*"]
    )
    monkeypatch.setenv("STAMP", "scene-v1")
    monkeypatch.setenv("S", "24")
    res = suite.runpytest_subprocess()
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*disc.exr is 32×32 but the image is 24×24*"])
    monkeypatch.setenv("S", "32")
    exr = suite.path / "baselines" / "disc.exr"
    exr.write_bytes(exr.read_bytes()[:-1] + b"\x00")
    res = suite.runpytest_subprocess()
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*disc.exr does not match*disc.json*"])


def test_baseline_dir_from_ini_and_option(suite):
    suite.makeini("[pytest]\nshadowlab_baseline_dir = golden\n")
    _test(suite, "def test_a(shadowlab_gate):\n    shadowlab_gate(image(), 'a')\n")
    suite.runpytest_subprocess("--shadowlab-update").assert_outcomes(passed=1)
    assert (suite.path / "golden" / "a.exr").is_file() and not (suite.path / "baselines").exists()
    other = suite.path / "elsewhere"
    suite.runpytest_subprocess("--shadowlab-update", "--shadowlab-baseline-dir", str(other)).assert_outcomes(passed=1)
    assert (other / "a.exr").is_file()
    _test(suite, "def test_a(shadowlab_gate):\n    shadowlab_gate(image(), '../escape')\n")
    res = suite.runpytest_subprocess("--shadowlab-update")
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*baseline name '../escape' must be*"])


def test_gating_a_real_technique_render(pytester, monkeypatch):
    """The plugin on a real render: hard shadows of `contact` at 32², regression against its baseline,
    stamped with the scene hash; a changed depth bias changes the image and fails the gate."""
    pytester.makepyfile(test_real='''
import os
from shadowlab import backend
from shadowlab.render.frame import make_frame
from shadowlab.render.shading import compose
from shadowlab.scene import load
from shadowlab.techniques import base

def test_hard(shadowlab_gate):
    backend.init()
    sc = load("contact", resolution=(32, 32))
    t = base.get("hard")
    res = t.render(make_frame(sc), t.resolve({"depth_bias": float(os.environ.get("BIAS", "16"))}))
    shadowlab_gate(compose(make_frame(sc), res.visibility), "hard/contact32", stamp=sc.spec.digest())
''')
    pytester.runpytest_subprocess("--shadowlab-update").assert_outcomes(passed=1)
    pytester.runpytest_subprocess().assert_outcomes(passed=1)
    monkeypatch.setenv("BIAS", "-400000")
    res = pytester.runpytest_subprocess()
    res.assert_outcomes(failed=1)
    res.stdout.fnmatch_lines(["*FAIL  hard/contact32  stat.pixels*"])
