"""Gate thresholds: the statistical test's settings and the error budget, validated once.

A gate has one or both kinds of threshold (see :mod:`shadowlab.gate` for their meaning):

``statistical`` (for candidates that should equal the reference up to noise)
    ``alpha``               family-wise significance level, 0 < alpha ≤ 0.5 (default 0.001)
    ``min_pass_fraction``   fraction of tested pixels that must pass the per-pixel Z-test
                            (default 0.9975, Mitsuba's render tests)
    ``atol``, ``rtol``, ``ptol``  a value also passes when |c − r| ≤ atol + rtol·|r| + ptol·peak
                            (peak = the reference's maximum over the tested pixels); the tolerance
                            is what a zero-variance comparison (a deterministic technique against
                            its own baseline) is judged by (defaults 0, 0, 0.001: the unshadowed
                            radiance U in Σ U·V is an estimate whose noise the reference does not
                            record; between two seeds it differed by up to 0.0008 · peak at pixels
                            the light grazes, on all eight built-in scenes at 128²)
    ``bias``                run the two bias tests (mean z over all tested pixels and over the
                            penumbra), default true

``budget`` (for approximate techniques): ``{metric: limit}``; the metric must be at most the limit,
or at least it for the higher-is-better metrics ``psnr*`` and ``ssim*``. Which metrics exist
depends on the gate's target (:data:`SHADED_METRICS`, :data:`VISIBILITY_METRICS`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from ..errors import InputError
from ..metrics.compare import SHADED_KEYS, VISIBILITY_KEYS

__all__ = ["Statistical", "Thresholds", "parse_thresholds", "SHADED_METRICS", "VISIBILITY_METRICS",
           "TECHNIQUE_SHADED_METRICS", "higher_is_better", "STAT_DEFAULTS"]

#: budget metrics of a shaded (or mitsuba) target, from :func:`shadowlab.metrics.compare_shaded`
SHADED_METRICS = tuple(SHADED_KEYS)
#: budget metrics of a shaded target that also need the candidate's per-light visibility
#: (a technique candidate has it; an EXR of a shaded image does not)
TECHNIQUE_SHADED_METRICS = ("leak_rate", "overdark_rate", "vis_rmse", "vis_rmse_penumbra")
#: budget metrics of a visibility target (one light), from :func:`shadowlab.metrics.compare_visibility`
#: plus mean FLIP of the visibility shown as a grey image
VISIBILITY_METRICS = tuple(k for k in VISIBILITY_KEYS if k != "penumbra_fraction") + ("flip",)

STAT_DEFAULTS = {"alpha": 1e-3, "min_pass_fraction": 0.9975, "atol": 0.0, "rtol": 0.0, "ptol": 1e-3, "bias": True}


def higher_is_better(metric: str) -> bool:
    """psnr* and ssim* must be at least their limit; every other metric at most.

    >>> higher_is_better("ssim_penumbra"), higher_is_better("flip")
    (True, False)
    """
    return metric.startswith(("psnr", "ssim"))


@dataclass(frozen=True)
class Statistical:
    alpha: float = STAT_DEFAULTS["alpha"]
    min_pass_fraction: float = STAT_DEFAULTS["min_pass_fraction"]
    atol: float = 0.0
    rtol: float = 0.0
    ptol: float = STAT_DEFAULTS["ptol"]
    bias: bool = True


@dataclass(frozen=True)
class Thresholds:
    """``statistical``: None (no statistical test) or its settings; ``budget``: {metric: limit}."""

    statistical: Statistical | None = None
    budget: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.statistical is None and not self.budget:
            raise InputError("a gate needs a statistical test, an error budget or both: add "
                             "statistical = {} (defaults) and/or a budget such as budget = { flip = 0.1 }")


def _number(where: str, key: str, v, lo=None, hi=None, lo_open=False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}: {key} must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"{where}: {key} must be a finite number, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo) or hi is not None and v > hi:
        left = "(" if lo_open else "["
        raise InputError(f"{where}: {key} = {v:g} is out of range; allowed {left}{lo:g}, {hi:g}]"
                         if hi is not None else f"{where}: {key} = {v:g} is out of range; allowed ≥ {lo:g}")
    return v


def _statistical(where: str, table, defaults: Mapping | None = None) -> Statistical | None:
    if table is None or table is False:
        return None
    if table is True:
        table = {}
    if not isinstance(table, Mapping):
        raise InputError(f"{where}: statistical must be a table (e.g. statistical = {{ alpha = 0.001 }}) "
                         f"or true, got {table!r}")
    merged = {**(defaults or {}), **table}
    unknown = sorted(set(merged) - set(STAT_DEFAULTS))
    if unknown:
        raise InputError(f"{where}: unknown statistical setting(s) {', '.join(unknown)}; known: "
                         f"{', '.join(STAT_DEFAULTS)}")
    w = f"{where}.statistical"
    bias = merged.get("bias", True)
    if not isinstance(bias, bool):
        raise InputError(f"{w}: bias must be true or false, got {bias!r}")
    return Statistical(
        alpha=_number(w, "alpha", merged.get("alpha", STAT_DEFAULTS["alpha"]), 0.0, 0.5, lo_open=True),
        min_pass_fraction=_number(w, "min_pass_fraction", merged.get("min_pass_fraction",
                                                                     STAT_DEFAULTS["min_pass_fraction"]), 0.0, 1.0),
        atol=_number(w, "atol", merged.get("atol", 0.0), 0.0),
        rtol=_number(w, "rtol", merged.get("rtol", 0.0), 0.0, 1.0),
        ptol=_number(w, "ptol", merged.get("ptol", STAT_DEFAULTS["ptol"]), 0.0, 1.0),
        bias=bias)


_ALL_METRICS = tuple(dict.fromkeys(SHADED_METRICS + TECHNIQUE_SHADED_METRICS + VISIBILITY_METRICS))
_RANGES = {"ssim": (-1.0, 1.0)}
_RATES = ("leak_rate", "overdark_rate", "flip")


def _budget(where: str, table) -> dict:
    if table is None:
        return {}
    if not isinstance(table, Mapping):
        raise InputError(f"{where}: budget must be a table of metric limits, e.g. budget = {{ flip = 0.1, "
                         f"leak_rate = 0.01 }}, got {table!r}")
    out = {}
    for k, v in table.items():
        if k not in _ALL_METRICS:
            raise InputError(f"{where}: unknown budget metric {k!r}; known: {', '.join(_ALL_METRICS)}")
        base = k.removesuffix("_penumbra")
        if base in _RANGES:
            lo, hi = _RANGES[base]
            out[k] = _number(f"{where}.budget", k, v, lo, hi)
        elif base in _RATES:
            out[k] = _number(f"{where}.budget", k, v, 0.0, 1.0)
        elif base == "psnr":
            out[k] = _number(f"{where}.budget", k, v)
        else:
            out[k] = _number(f"{where}.budget", k, v, 0.0)
    return out


def parse_thresholds(spec, where: str = "thresholds", stat_defaults: Mapping | None = None) -> Thresholds:
    """A :class:`Thresholds` from ``{"statistical": {...} | true, "budget": {...}}`` (a gate file's
    gate table or keyword arguments); a :class:`Thresholds` is returned as it is. Unknown keys and
    out-of-range values raise :class:`InputError` naming ``where`` and the key.

    >>> t = parse_thresholds({"statistical": {"alpha": 0.01}, "budget": {"flip": 0.1}})
    >>> t.statistical.alpha, t.statistical.min_pass_fraction, t.budget
    (0.01, 0.9975, {'flip': 0.1})
    """
    if isinstance(spec, Thresholds):
        return spec
    if not isinstance(spec, Mapping):
        raise InputError(f"{where}: expected a table with statistical and/or budget, got {spec!r}")
    unknown = sorted(set(spec) - {"statistical", "budget"})
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; thresholds are `statistical` "
                         "and `budget`")
    st = _statistical(where, spec.get("statistical"), stat_defaults)
    bd = _budget(where, spec.get("budget"))
    try:
        return Thresholds(statistical=st, budget=bd)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def from_keywords(thresholds: Mapping, where: str = "gate") -> Thresholds:
    """Thresholds from flat keyword arguments, as ``shadowlab_gate(img, name, **kw)`` and
    :func:`shadowlab.gate_image` take them: the statistical settings (``alpha``, ``atol``, ...;
    ``statistical=True`` for all defaults) and budget limits (``flip=0.05``, ``rmse=...``). Without
    any, the statistical test with its defaults.

    >>> t = from_keywords({"rmse": 0.01})
    >>> t.statistical is None, t.budget
    (True, {'rmse': 0.01})
    """
    kw = dict(thresholds)
    use_stat = kw.pop("statistical", None)
    if use_stat is not None and not isinstance(use_stat, bool):
        raise InputError(f"{where}: statistical must be True or False, got {use_stat!r}")
    unknown = [k for k in kw if k not in STAT_DEFAULTS and k not in _ALL_METRICS]
    if unknown:
        raise InputError(f"{where}: unknown threshold(s) {', '.join(unknown)}; statistical settings: "
                         f"{', '.join(STAT_DEFAULTS)}; budget metrics: {', '.join(_ALL_METRICS)}")
    stat = {k: v for k, v in kw.items() if k in STAT_DEFAULTS}
    budget = {k: v for k, v in kw.items() if k not in STAT_DEFAULTS}
    spec = {}
    if stat or use_stat or (use_stat is None and not budget):
        spec["statistical"] = stat
    if budget:
        spec["budget"] = budget
    return parse_thresholds(spec, where=where)
