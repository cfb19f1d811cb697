"""CI image-difference gates: a candidate image against a stored reference, pass or fail.

Python API (what ``shadowlab gate``, the pytest plugin and other commands call)::

    from . import check
    truth, meta = shadowlab.reference.store.load(spec)            # a stored reference
    result = check(candidate, truth, {"statistical": {}, "budget": {"flip": 0.08}},
                   target="shaded", candidate_var=None, name="contact/engine")
    result.passed                      # bool: every check passed
    for c in result.checks:            # Check(name, kind, value, threshold, op, passed, text)
        print(c.line(result.name))     # "PASS  contact/engine  budget.flip  0.0712 <= 0.08"

``reference`` may also be a plain array (with optional ``reference_var``, ``valid``, ``penumbra``);
see :func:`shadowlab.gate.check.check`.

Two kinds of threshold, either or both per gate
-----------------------------------------------
**statistical** — for a candidate that should *equal* the reference up to noise: another ground
truth (other seed, other machine, a new version of the truth renderer), an engine's path-traced
image, or a deterministic output against its own baseline. Mitsuba's render-test Z-test per pixel
value with the reference's variance and the candidate's (if it has one), Šidák-corrected α, pass
if at least ``min_pass_fraction`` of the pixels pass (``stat.pixels``); plus two Student t-tests
of the mean per-pixel z (all pixels: ``stat.bias``; penumbra: ``stat.bias_penumbra``), which see a
small systematic error (a 1 % brighter penumbra) that no single pixel shows. A zero-variance
comparison is judged by the tolerance ``atol + rtol·|r| + ptol·peak`` instead (the bias tests need
pixels with variance and are skipped without). Details: :mod:`shadowlab.gate.stats`.
A real-time technique is *not* the truth: its statistical test fails by design (PCF's penumbra is
a different function, not noise). Technique candidates get a budget.

**budget** — for approximate techniques: limits on the metrics of :mod:`shadowlab.metrics`, the
same numbers as the ``compare`` report. Shaded target: ``rmse mae psnr ssim flip delta_e2000`` and
their ``_penumbra`` versions; a technique candidate adds ``leak_rate overdark_rate vis_rmse
vis_rmse_penumbra`` (pooled over lights as in the report). Visibility target: ``rmse mae
rmse_penumbra mae_penumbra leak_rate overdark_rate leak_mean overdark_mean flip``. psnr*/ssim*
must be ≥ the limit, all others ≤. A metric over an empty region (no penumbra) is "n/a" and passes,
but a gate never passes on nothing: with fewer than ``MIN_GATE_PIXELS`` (16) compared pixels (seen
by the camera and reached by a light) it gets a failing ``pixels`` check.

Targets: ``shaded`` (Σ U·V, the stored ``shaded.*`` with ``shaded.var.*``), ``visibility`` (one
light's ``V.<light>`` with ``V.<light>.se``), ``mitsuba`` (Mitsuba's ``direct`` image with its
variance: the target for path-traced engine images, whose pixels are box-filtered, not point
samples; that variance comes from 4 passes, so its Z-test uses Student-t p-values with
Welch–Satterthwaite degrees of freedom, see :mod:`shadowlab.gate.stats`). A unanimous truth pixel (all n shadow rays
agree) has no sample variance; its
rule-of-three bound B = 3/n counts as a standard deviation of B/2.

Gate file (TOML, ``references/gates.toml``; paths relative to the file)::

    version = 1
    references = "."                 # the reference store (default: the gate file's directory)
    [defaults.statistical]           # merged into every gate's statistical table
    alpha = 0.001
    [[gate]]
    name = "contact/truth-shaded"    # unique; the JUnit test class
    scene = "contact"                # built-in name or path to a .toml scene
    resolution = [128, 128]          # optional: default the scene's
    # frame = 3                      # a camera path's frame; or frames = "0:3" (both ends included):
    #                                #   one gate per frame, named NAME@frameN (--only NAME runs them all)
    target = "shaded"                # shaded | visibility | mitsuba
    # light = "key"                  # visibility: which light (default: the only one)
    candidate = { truth = true, seed = 1 }     # or { technique = "pcss", params = { kernel = 5 } }
                                               # or { exr = "out/frame.exr", channel = "shaded" }
    statistical = {}                 # run the statistical test (settings or {} for defaults)
    budget = { flip = 0.05 }         # and/or limits

``shadowlab gate FILE [--out DIR] [--only NAME,...]`` prints one line per check, writes
``DIR/junit.xml`` and ``DIR/index.html`` (the failures with candidate, reference, error and
p-value maps) and exits 0 when every gate passed, 1 when one failed, 2 on bad input (malformed
file, unknown key / parameter / metric, value out of range, missing or stale reference, missing
candidate file or channel, wrong image size, NaN/Inf): then nothing is written.
The pytest plugin is :mod:`shadowlab.gate.pytest_plugin`.
"""

from __future__ import annotations

from .check import Check, GateResult, Target, check, truth_target
from .gatefile import GateFile, GateSpec, load_gate_file
from .runner import run_gate_file as _run
from .thresholds import Statistical, Thresholds, parse_thresholds

__all__ = ["check", "Check", "GateResult", "Target", "truth_target", "Thresholds", "Statistical",
           "parse_thresholds", "load_gate_file", "GateFile", "GateSpec", "run_gate_file"]


def run_gate_file(path, out_dir=None, only=None, variant=None, echo=print, force: bool = False, frame=None,
                  frames=None):
    """Evaluate a gate file; see :func:`shadowlab.gate.runner.run_gate_file` (every argument is
    passed on: ``force`` to claim an ``out_dir`` shadowlab did not make, ``frame`` / ``frames`` to
    run every gate at those frames of its camera path)."""
    return _run(path, out_dir=out_dir, only=only, variant=variant, echo=echo, force=force, frame=frame,
                frames=frames)
