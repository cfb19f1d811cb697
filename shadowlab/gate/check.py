"""``check(candidate, reference, thresholds) -> GateResult``: one gate on arrays (see :mod:`shadowlab.gate`)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..io.exr import check_finite
from ..metrics import compare_shaded, compare_visibility, flip, penumbra_mask, pooled_visibility
from ..reference.truth import mitsuba_render
from .stats import bias_test, z_test
from .thresholds import (SHADED_METRICS, TECHNIQUE_SHADED_METRICS, VISIBILITY_METRICS, higher_is_better,
                         parse_thresholds)

__all__ = ["Check", "GateResult", "Target", "check", "truth_target", "TARGETS", "BOUND_SIGMAS", "MIN_GATE_PIXELS"]

TARGETS = ("shaded", "visibility", "mitsuba")
#: a unanimous truth pixel (all n shadow rays agree) has sample variance 0 and the rule-of-three
#: bound B = 3/n (95 %); the statistical test counts it as a standard deviation of B / BOUND_SIGMAS
BOUND_SIGMAS = 2.0
#: a gate never passes on nothing: when fewer pixels than this are compared (the camera sees no
#: surface, the light reaches none: a light inside a closed box), the gate gets a failing
#: ``pixels`` check, whatever its other checks say
MIN_GATE_PIXELS = 16


@dataclass
class Check:
    """One check of a gate: ``name`` (``stat.pixels``, ``stat.bias``, ``stat.bias_penumbra``,
    ``budget.<metric>``), its measured ``value``, the ``threshold`` it is held to with ``op``
    ('>=', '<=' or '>'), whether it ``passed`` and a one-line ``text`` of the details."""

    name: str
    kind: str           # "statistical" | "budget"
    value: float
    threshold: float
    op: str
    passed: bool
    text: str

    def line(self, gate: str) -> str:
        """``PASS gate  check  details`` — what ``shadowlab gate`` prints per check."""
        return f"{'PASS' if self.passed else 'FAIL'}  {gate}  {self.name}  {self.text}"


@dataclass
class GateResult:
    """The outcome of one gate: its checks (all must pass) and the images for the failure page
    (``candidate``, ``reference``, ``error`` = candidate − reference, ``pvalue`` = smallest
    per-pixel p-value of the Z-test or None, ``failed_pixels`` H×W bool or None)."""

    name: str
    target: str
    checks: list = field(default_factory=list)
    images: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.checks)

    @property
    def failed(self) -> list:
        return [c for c in self.checks if not c.passed]

    def lines(self) -> list[str]:
        return [c.line(self.name) for c in self.checks]

    def check(self, name: str) -> Check:
        for c in self.checks:
            if c.name == name:
                return c
        raise KeyError(f"gate {self.name!r} has no check {name!r}; it has {[c.name for c in self.checks]}")


@dataclass
class Target:
    """What a candidate is compared with: the reference image, its per-value variance, the pixels
    tested (``valid``), the penumbra and, for a shaded target of a stored truth, each light's truth
    visibility and the pixels it reaches (for the leak / over-darkening rates)."""

    kind: str
    image: np.ndarray
    var: np.ndarray | None
    valid: np.ndarray
    penumbra: np.ndarray | None
    light: str | None = None
    lights: dict = field(default_factory=dict)   # name -> (V truth H×W, valid H×W)
    dof: float | None = None                     # degrees of freedom of ``var`` (None: exact)


def mitsuba_dof() -> int:
    """Degrees of freedom of a stored ``mitsuba.var``: the variance of the mean over the passes of
    :func:`~shadowlab.reference.truth.mitsuba_render` (its default ``passes``, minus 1)."""
    return int(inspect.signature(mitsuba_render).parameters["passes"].default) - 1


def truth_target(truth, target: str = "shaded", light: str | None = None) -> Target:
    """The :class:`Target` of a stored :class:`~shadowlab.reference.truth.Truth`.

    * ``shaded``: Σ U·V with variance ``shaded.var`` + Σ_L (U_L · B_L / 2)², tested on the hit mask;
      penumbra = union over lights of the truth penumbra (0.02 < V < 0.98 where the light reaches);
    * ``visibility`` (``light``: default the only light): V with variance se² + (B / 2)², tested
      where the light reaches (U > 0);
    * ``mitsuba``: Mitsuba's own ``direct`` image with its variance (for path-traced candidates),
      estimated from a few passes: ``dof`` = :func:`mitsuba_dof`.
    """
    if target not in TARGETS:
        raise InputError(f"unknown target {target!r}; a gate compares with one of {', '.join(TARGETS)}")
    mask = np.asarray(truth.mask, bool)
    lights = {}
    pen = np.zeros_like(mask)
    for n, lt in truth.lights.items():
        lit = mask & (np.asarray(truth.U[n]).sum(-1) > 0)
        lights[n] = (np.asarray(lt.V, np.float64), lit)
        pen |= penumbra_mask(lt.V, lit)
    if target == "visibility":
        if light is None:
            if len(truth.lights) != 1:
                raise InputError(f"target visibility needs a light: this scene has {', '.join(truth.lights)}; "
                                 "set light = \"NAME\"")
            light = next(iter(truth.lights))
        if light not in truth.lights:
            raise InputError(f"light {light!r} is not in the reference; its lights: {', '.join(truth.lights)}")
        lt = truth.lights[light]
        V, lit = lights[light]
        var = np.asarray(lt.V_se, np.float64) ** 2 + (np.asarray(lt.bound, np.float64) / BOUND_SIGMAS) ** 2
        return Target("visibility", V, var, lit, penumbra_mask(V, lit), light, {light: lights[light]})
    if target == "mitsuba":
        if truth.mitsuba is None:
            raise InputError("the reference has no mitsuba.R|G|B channels (rendered with --spp 0); "
                             "re-render it with `shadowlab reference SCENE --force` or gate target = \"shaded\"")
        return Target("mitsuba", np.asarray(truth.mitsuba, np.float64), np.asarray(truth.mitsuba_var, np.float64),
                      mask, pen, None, lights, dof=mitsuba_dof())
    var = np.asarray(truth.shaded_var, np.float64).copy()
    for n, lt in truth.lights.items():
        var += (np.asarray(truth.U[n], np.float64) * (np.asarray(lt.bound, np.float64) / BOUND_SIGMAS)[..., None]) ** 2
    return Target("shaded", np.asarray(truth.shaded, np.float64), var, mask, pen, None, lights)


def as_image(name: str, a, kind: str, hw=None) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{name} must be a numeric image, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if kind == "visibility":
        if arr.ndim != 2:
            raise InputError(f"{name} has shape {arr.shape}; a visibility target needs one H×W channel "
                             "(pick the light's channel, e.g. channel = \"V.key\")")
    elif arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"{name} has shape {arr.shape}; a {kind} target needs an H×W×3 RGB image "
                         "(drop alpha / extra channels, or gate target = \"visibility\" for one channel)")
    if hw is not None and arr.shape[:2] != tuple(hw):
        raise InputError(f"{name} is {arr.shape[1]}×{arr.shape[0]} but the reference is {hw[1]}×{hw[0]}; "
                         "render the candidate at the reference's resolution (or gate a reference of that "
                         "size: resolution = [W, H])")
    check_finite(name, arr)
    return arr


def _mask(name, m, hw):
    if m is None:
        return np.ones(hw, bool)
    m = np.asarray(m)
    if m.dtype != bool or m.shape != tuple(hw):
        raise InputError(f"{name} must be an H×W bool mask of the image's size {hw}, got {m.dtype} {m.shape}")
    return m


def _fmt(v: float) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.4g}"


_NOT = {"<=": ">", ">=": "<", ">": "<=", "<": ">="}


def verdict_text(v: float, lim: float, op: str, ok: bool, what: str = "budget") -> str:
    """The relation that holds between a measured value and its threshold, in words a reader can
    check: ``0.06 <= budget 0.07`` when it passed, ``0.0705 > budget 0.07`` when it failed; the
    two numbers get as many digits as it takes to tell them apart.

    >>> verdict_text(0.07048, 0.07, "<=", False), verdict_text(0.0700001, 0.07, "<=", False)
    ('0.0705 > budget 0.07', '0.0700001 > budget 0.07')
    """
    digits = 3
    while digits < 12 and v != lim and f"{v:.{digits}g}" == f"{lim:.{digits}g}":
        digits += 1
    return f"{v:.{digits}g} {op if ok else _NOT[op]} {what} {lim:.{digits}g}"


def _budget_metrics(cand, tgt: Target, keys, visibility) -> dict:
    out: dict = {}
    if tgt.kind == "visibility":
        if set(keys) - {"flip"}:
            out.update(compare_visibility(cand, tgt.image, tgt.valid))
        if "flip" in keys:
            out["flip"] = flip(cand, tgt.image, tgt.valid) if tgt.valid.any() else float("nan")
        return out
    if set(keys) & set(SHADED_METRICS):
        out.update(compare_shaded(cand, tgt.image, penumbra=tgt.penumbra, valid=tgt.valid))
    if set(keys) & set(TECHNIQUE_SHADED_METRICS):
        # the same numbers as pipeline.technique_metrics (the `compare` report)
        out.update(pooled_visibility({
            n: (as_image(f"candidate visibility of light {n!r}", visibility[n], "visibility", tv.shape), tv, lit)
            for n, (tv, lit) in tgt.lights.items()})[1])
    return out


def _is_truth(obj) -> bool:
    """A :class:`~shadowlab.reference.truth.Truth` (duck-typed: importing that module imports Dr.Jit,
    which array-only callers such as the pytest plugin do not need)."""
    return all(hasattr(obj, k) for k in ("lights", "U", "shaded", "shaded_var", "mask"))


def check(candidate, reference, thresholds, *, target: str = "shaded", light: str | None = None,
          candidate_var=None, reference_var=None, valid=None, penumbra=None, visibility: Mapping | None = None,
          candidate_dof=None, reference_dof=None, name: str = "gate") -> GateResult:
    """Gate ``candidate`` against ``reference``; returns a :class:`GateResult` (never raises on a
    failed check; bad input raises :class:`~shadowlab.errors.InputError`).

    ``candidate``: a linear float image, H×W×3 for the ``shaded``/``mitsuba`` targets, H×W for
    ``visibility``. ``reference``: a :class:`~shadowlab.reference.truth.Truth` (from
    ``shadowlab.reference.store.load``; ``target`` and ``light`` pick the image and
    :func:`truth_target` supplies its variance, tested pixels and penumbra) or an array of the
    candidate's shape (then ``reference_var``, ``valid`` and ``penumbra`` are optional arrays;
    with no penumbra mask a shaded target has no penumbra metrics or penumbra bias test).
    ``thresholds``: a :class:`~shadowlab.gate.thresholds.Thresholds` or a dict
    ``{"statistical": {...}, "budget": {...}}``. ``candidate_var``: the candidate's per-value
    variance if it has one (e.g. another truth); None = exact. ``candidate_dof`` /
    ``reference_dof``: the degrees of freedom of those variances when they are estimated from few
    passes (a Truth's ``mitsuba`` target brings its own); None = exact. ``visibility``: the candidate's
    per-light visibility {light: H×W}, needed for the ``leak_rate``, ``overdark_rate`` and
    ``vis_rmse*`` budgets of a shaded target.

    >>> import numpy as np
    >>> ref = np.full((8, 8), 0.5); cand = ref + 0.001
    >>> r = check(cand, ref, {"budget": {"rmse": 0.01}}, target="visibility", name="demo")
    >>> r.passed, r.lines()
    (True, ['PASS  demo  budget.rmse  0.001 <= budget 0.01'])
    """
    th = parse_thresholds(thresholds, where=f"gate {name!r}")
    if target not in TARGETS:
        raise InputError(f"gate {name!r}: unknown target {target!r}; one of {', '.join(TARGETS)}")
    if _is_truth(reference):
        tgt = truth_target(reference, target, light)
        if reference_var is not None or valid is not None or penumbra is not None or reference_dof is not None:
            raise InputError(f"gate {name!r}: reference_var, reference_dof, valid and penumbra come from the "
                             "Truth; do not pass them with a Truth reference")
    else:
        kind = target
        ref = as_image("reference image", reference, kind)
        hw = ref.shape[:2]
        rv = None if reference_var is None else np.maximum(as_image("reference variance", reference_var, kind, hw), 0)
        vm = _mask("valid", valid, hw)
        if penumbra is None and kind == "visibility":
            pen = penumbra_mask(ref, vm)
        else:
            pen = None if penumbra is None else _mask("penumbra", penumbra, hw) & vm
        tgt = Target(kind, ref, rv, vm, pen, light, dof=reference_dof)
    hw = tgt.image.shape[:2]
    cand = as_image("candidate image", candidate, tgt.kind, hw)
    cvar = (
        None if candidate_var is None else np.maximum(as_image("candidate variance", candidate_var, tgt.kind, hw), 0)
    )
    res = GateResult(name=name, target=tgt.kind if tgt.light is None else f"visibility:{tgt.light}")
    res.images = {"candidate": cand, "reference": tgt.image, "error": cand - tgt.image, "pvalue": None,
                  "failed_pixels": None, "valid": tgt.valid}
    res.info = {"pixels": int(tgt.valid.sum()), "penumbra_pixels": int(tgt.penumbra.sum()) if tgt.penumbra is not None
                else None, "resolution": [int(hw[1]), int(hw[0])]}

    covered = tgt.valid.copy()
    if tgt.lights:  # a stored truth: only pixels some light reaches (U > 0 and, in the truth, V > 0) count
        covered &= np.logical_or.reduce([np.asarray(lit, bool) & (np.asarray(V) > 0) for V, lit in tgt.lights.values()])
    n_pix = res.info["compared_pixels"] = int(covered.sum())
    if n_pix < MIN_GATE_PIXELS:
        res.checks.append(
            Check(
                "pixels",
                "coverage",
                float(n_pix),
                float(MIN_GATE_PIXELS),
                ">=",
                False,
                f"{n_pix} pixel(s) to compare (seen by the camera and lit by a light in the truth), need >= "
                f"{MIN_GATE_PIXELS}: "
                "nothing to measure, so the gate cannot pass; point the camera at the lit scene and check that no "
                "light is enclosed",
            )
        )
    st = th.statistical
    if st is not None:
        zt = z_test(cand, tgt.image, tgt.var, cvar, tgt.valid, alpha=st.alpha, atol=st.atol, rtol=st.rtol, ptol=st.ptol,
                    dof_ref=tgt.dof, dof_cand=candidate_dof)
        res.images["pvalue"] = zt.p
        res.images["failed_pixels"] = zt.tested & ~zt.passed
        worst = ""
        if zt.n_tested:
            pm = np.where(zt.tested, zt.p, np.inf)
            y, x = np.unravel_index(int(np.argmin(pm)), pm.shape)
            worst = f", smallest p {pm[y, x]:.2g} at (x={x}, y={y})"
        res.checks.append(Check(
            "stat.pixels", "statistical", zt.fraction, st.min_pass_fraction, ">=", zt.fraction >= st.min_pass_fraction,
            f"{100 * zt.fraction:.2f}% of {zt.n_tested} pixels pass the Z-test (need >= "
            f"{100 * st.min_pass_fraction:.2f}%; {zt.n_failed} fail at alpha_pixel {zt.alpha_value:.2g}{worst}"
            + (f"; Student-t p-values, variance dof {tgt.dof} / {candidate_dof}"
               if tgt.dof is not None or candidate_dof is not None else "") + ")"))
        res.info["alpha_value"] = zt.alpha_value
        if st.bias:
            regions = [("stat.bias", "all", tgt.valid)]
            if tgt.penumbra is not None:
                regions.append(("stat.bias_penumbra", "penumbra", tgt.penumbra))
            for cname, rname, region in regions:
                b = bias_test(zt, region, alpha=st.alpha, name=rname, n_regions=len(regions))
                if b.tested:
                    text = (f"mean z {b.mean_z:+.3f} over {b.n} {rname} pixels: t = {b.t:+.2f}, "
                            f"p = {b.p:.2g} (need > {b.alpha:.2g})")
                else:
                    text = f"not tested: {b.n} informative {rname} pixels (< 16)"
                res.checks.append(Check(cname, "statistical", b.p, b.alpha, ">", b.passed, text))
    if th.budget:
        allowed = VISIBILITY_METRICS if tgt.kind == "visibility" else SHADED_METRICS + TECHNIQUE_SHADED_METRICS
        bad = [k for k in th.budget if k not in allowed]
        if bad:
            raise InputError(f"gate {name!r}: budget metric(s) {', '.join(bad)} do not exist for target "
                             f"{tgt.kind!r}; available: {', '.join(allowed)}")
        need_vis = [k for k in th.budget if k in TECHNIQUE_SHADED_METRICS and tgt.kind != "visibility"]
        if need_vis:
            if not tgt.lights:
                raise InputError(f"gate {name!r}: {', '.join(need_vis)} need(s) a stored truth as the reference")
            if visibility is None or set(tgt.lights) - set(visibility):
                raise InputError(f"gate {name!r}: {', '.join(need_vis)} need(s) the candidate's visibility of "
                                 f"every light ({', '.join(tgt.lights)}): gate a technique candidate, or use "
                                 "target = \"visibility\" with one light's channel")
        vals = _budget_metrics(cand, tgt, list(th.budget), visibility)
        for k, lim in th.budget.items():
            v = float(vals[k])
            hib = higher_is_better(k)
            op = ">=" if hib else "<="
            if math.isnan(v):
                res.checks.append(Check(f"budget.{k}", "budget", v, lim, op, True,
                                        "n/a (empty region: no pixel to measure)"))
                continue
            ok = v >= lim if hib else v <= lim
            res.checks.append(Check(f"budget.{k}", "budget", v, lim, op, ok, verdict_text(v, lim, op, ok)))
        res.info["metrics"] = {k: float(v) for k, v in vals.items()}
    return res
