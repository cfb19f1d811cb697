"""pytest plugin (entry point ``pytest11``): gate an image against its stored baseline.

    def test_pcf_contact(shadowlab_gate):
        img = render_something()                       # H×W×3 (shaded) or H×W (visibility)
        shadowlab_gate(img, "pcf/contact")             # exact up to the tolerance
        shadowlab_gate(img, "pcf/contact-budget", flip=0.02, rmse=0.01)   # error budget
        shadowlab_gate(truth, "truth/contact", variance=var, alpha=1e-3)  # statistical

``shadowlab_gate(image, name, *, variance=None, target=None, valid=None, penumbra=None, stamp=None,
**thresholds)`` compares ``image`` with the baseline ``<baseline dir>/<name>.exr`` using
:func:`shadowlab.gate.check` and returns the :class:`~shadowlab.gate.GateResult`; a failed gate
fails the test with one line per check. Thresholds are keyword arguments: the statistical settings
(``alpha``, ``min_pass_fraction``, ``atol``, ``rtol``, ``ptol``, ``bias``; ``statistical=True`` for
all defaults) and budget limits (``flip=0.05``, ``rmse_penumbra=...``; see
:mod:`shadowlab.gate.thresholds`). Without any, the statistical test with its defaults runs: for
an image without variance on either side that is "equal up to atol + rtol·|r| + ptol·peak". The
baseline's variance (if it was stored with one) and ``variance`` enter the Z-test. ``target``
defaults to ``shaded`` for H×W×3 images and ``visibility`` for H×W. ``stamp`` is any string that
identifies what the image was made from (a scene hash, parameters): a baseline stored with another
stamp is stale and fails the test.

Baselines are written only on request, never because a gate failed (pytest-mpl's flow):
``pytest --shadowlab-update`` writes each gated image as its new baseline (atomically: EXR with
channels ``image.R|G|B`` / ``image`` and ``image.var...``, plus ``<name>.json`` with shape, target,
stamp) and does not evaluate the gates; the run then reports the baselines it wrote. The images are
validated at the call and written when the test has passed: a test that fails or errors (after
the call, or in a later call with bad input) writes none of its baselines, and the run lists them
as not written. A name may be written once per run. A missing baseline fails the test and names
the command. Bad input (NaN/Inf, wrong shape, unknown threshold) raises
:class:`~shadowlab.errors.InputError` and writes nothing.

Where baselines live: ``--shadowlab-baseline-dir DIR`` > the ini option ``shadowlab_baseline_dir``
(relative to the ini file) > ``baselines/`` next to the test file. ``--shadowlab-results DIR``
writes an HTML page (candidate, baseline, error and p-value maps) for every failed gate.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import re
from pathlib import Path

import numpy as np
import pytest

from ..errors import InputError
from ..io.exr import read_exr, split_rgb, write_exr
from ..io.jsonio import read_json, write_json_atomic
from .check import GateResult, as_image, check
from .html import write_page
from .thresholds import from_keywords

_written_key = pytest.StashKey[list]()      # config: baselines written this run
_skipped_key = pytest.StashKey[list]()      # config: baselines not written (their test failed)
_pending_key = pytest.StashKey[set]()       # config: baseline paths claimed this run
_call_key = pytest.StashKey[object]()       # item: the report of its call phase
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")


def pytest_addoption(parser):
    g = parser.getgroup("shadowlab", "shadowlab image gates (fixture shadowlab_gate)")
    g.addoption("--shadowlab-update", action="store_true", default=False,
                help="write the images given to shadowlab_gate as new baselines (replacing old ones) "
                     "instead of gating them")
    g.addoption("--shadowlab-baseline-dir", default=None, metavar="DIR",
                help="directory of shadowlab_gate baselines (default: ini shadowlab_baseline_dir, else "
                     "baselines/ next to each test file)")
    g.addoption("--shadowlab-results", default=None, metavar="DIR",
                help="write an HTML page of every failed shadowlab_gate to DIR")
    parser.addini("shadowlab_baseline_dir", "directory of shadowlab_gate baselines, relative to the ini file",
                  default=None)


def _baseline_dir(request) -> Path:
    cfg = request.config
    opt = cfg.getoption("--shadowlab-baseline-dir")
    if opt:
        return Path(opt).resolve()
    ini = cfg.getini("shadowlab_baseline_dir")
    if ini:
        base = Path(cfg.inipath).parent if cfg.inipath else Path(cfg.rootpath)
        return (base / ini).resolve()
    return Path(request.node.path).parent / "baselines"


class ShadowlabGate:
    """The callable the ``shadowlab_gate`` fixture returns (see the module docstring)."""

    def __init__(self, request):
        self.request = request
        self.update = bool(request.config.getoption("--shadowlab-update"))
        self.dir = _baseline_dir(request)
        self.results_dir = request.config.getoption("--shadowlab-results")
        self.pending = []                   # (exr, json, channels, meta): written when the test passed

    def write_pending(self):
        """Write the baselines of this test (fixture teardown: only if its call phase passed)."""
        cfg = self.request.config
        rep = self.request.node.stash.get(_call_key, None)
        if rep is None or not rep.passed:
            cfg.stash.setdefault(_skipped_key, []).extend(str(exr) for exr, *_ in self.pending)
            return
        for exr, meta_path, ch, meta in self.pending:
            write_exr(exr, ch)
            # the JSON (written second) holds the EXR's hash: an update interrupted between the two
            # files is detected instead of pairing a new image with old metadata
            write_json_atomic(meta_path, {**meta, "exr_sha256": hashlib.sha256(exr.read_bytes()).hexdigest(),
                                          "written": _dt.datetime.now().isoformat(timespec="seconds")})
            cfg.stash.setdefault(_written_key, []).append(str(exr))

    def paths(self, name: str) -> tuple[Path, Path]:
        if not isinstance(name, str) or not _NAME.match(name) or ".." in name.split("/"):
            raise InputError(f"shadowlab_gate: baseline name {name!r} must be letters, digits, '_', '-', '.', "
                             "with '/' between parts (e.g. 'pcf/contact')")
        return self.dir / f"{name}.exr", self.dir / f"{name}.json"

    def __call__(self, image, name: str, *, variance=None, target: str | None = None, valid=None, penumbra=None,
                 stamp: str | None = None, **thresholds):

        exr, meta_path = self.paths(name)
        th = from_keywords(thresholds, where="shadowlab_gate")
        arr = np.asarray(image)
        if target is None:
            target = "shaded" if arr.ndim == 3 and arr.shape[-1] == 3 else "visibility"
        img = as_image(f"shadowlab_gate image {name!r}", arr, target)
        var = (
            None
            if variance is None
            else as_image(f"shadowlab_gate variance {name!r}", variance, target, img.shape[:2])
        )
        if var is not None and (var < 0).any():
            raise InputError(f"shadowlab_gate: variance of {name!r} has negative values")
        if stamp is not None and not isinstance(stamp, str):
            raise InputError(f"shadowlab_gate: stamp must be a string, got {stamp!r}")

        if self.update:
            claimed = self.request.config.stash.setdefault(_pending_key, set())
            if exr in claimed:
                raise InputError(f"shadowlab_gate: baseline {name!r} is gated twice in this --shadowlab-update run; "
                                 "give each image its own name")
            claimed.add(exr)
            ch = split_rgb(img, "image") if img.ndim == 3 else {"image": img}
            if var is not None:
                ch.update(split_rgb(var, "image.var") if var.ndim == 3 else {"image.var": var})
            self.pending.append((exr, meta_path, ch, {"name": name, "shape": list(img.shape), "target": target,
                                                      "stamp": stamp, "variance": var is not None,
                                                      "test": self.request.node.nodeid}))
            return GateResult(name=name, target=target, info={"updated": str(exr)})

        hint = "run pytest with --shadowlab-update to write it" if not exr.exists() else \
            "if the change is intended, re-run with --shadowlab-update to replace the baseline"
        if not exr.exists() or not meta_path.exists():
            pytest.fail(f"shadowlab_gate: no baseline for {name!r} at {exr}; {hint}", pytrace=False)
        meta = read_json(meta_path)
        if meta.get("stamp") != stamp:
            pytest.fail(f"shadowlab_gate: the baseline {exr} is stale: it was made from stamp {meta.get('stamp')!r}, "
                        f"this image from {stamp!r}; {hint}", pytrace=False)
        if meta.get("exr_sha256") != hashlib.sha256(exr.read_bytes()).hexdigest():
            pytest.fail(f"shadowlab_gate: baseline {exr} does not match {meta_path} (an interrupted update or an "
                        f"edited file); {hint}", pytrace=False)
        ch = read_exr(exr)
        if img.ndim == 3:
            names = ["image.R", "image.G", "image.B"]
            if not all(n in ch for n in names):
                pytest.fail(f"shadowlab_gate: baseline {exr} is not an RGB image but the image is "
                            f"{img.shape}; {hint}", pytrace=False)
            ref = np.stack([ch[n] for n in names], -1)
            rvar = np.stack([ch[f"image.var.{c}"] for c in "RGB"], -1) if "image.var.R" in ch else None
        else:
            if "image" not in ch:
                pytest.fail(f"shadowlab_gate: baseline {exr} is an RGB image but the image is {img.shape}; {hint}",
                            pytrace=False)
            ref, rvar = ch["image"], ch.get("image.var")
        if ref.shape[:2] != img.shape[:2]:
            pytest.fail(f"shadowlab_gate: baseline {exr} is {ref.shape[1]}×{ref.shape[0]} but the image is "
                        f"{img.shape[1]}×{img.shape[0]}; {hint}", pytrace=False)
        res = check(img, ref, th, target=target, candidate_var=var, reference_var=rvar, valid=valid,
                    penumbra=penumbra, name=name)
        res.info.update({"candidate": f"test {self.request.node.nodeid}", "reference": str(exr)})
        if not res.passed:
            if self.results_dir:
                page = Path(self.results_dir) / f"{name.replace('/', '__')}.html"
                write_page(page, [res], title=f"shadowlab_gate {name}")
                extra = f"\nfailure page: {page}"
            else:
                extra = ""
            pytest.fail(f"shadowlab_gate {name!r} failed against {exr}:\n" + "\n".join(res.lines())
                        + f"{extra}\n({hint})", pytrace=False)
        return res


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.when == "call":
        item.stash[_call_key] = rep


@pytest.fixture
def shadowlab_gate(request):
    """Gate an image against its baseline: ``shadowlab_gate(image, name, **thresholds)``; see
    :mod:`shadowlab.gate.pytest_plugin`."""
    gate = ShadowlabGate(request)
    yield gate
    if gate.pending:
        gate.write_pending()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    written = config.stash.get(_written_key, [])
    if written:
        terminalreporter.write_sep("-", f"shadowlab: wrote {len(written)} baseline(s)")
        for p in written:
            terminalreporter.write_line(f"  {p}")
    skipped = config.stash.get(_skipped_key, [])
    if skipped:
        terminalreporter.write_sep("-", f"shadowlab: {len(skipped)} baseline(s) NOT written: their test failed")
        for p in skipped:
            terminalreporter.write_line(f"  {p}")
