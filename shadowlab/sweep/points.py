"""The points of a sweep: ``NAME=LO:HI:N`` parsed against a technique's Param table, and one
sweep point as a picklable job with the module-level function that evaluates it wherever it runs
[Dask 2024, "Futures"].

A point is evaluated exactly as ``shadowlab compare`` evaluates a technique: the scene's stored
truth, a FrameContext made with the truth's supersampling and seed, then
:func:`shadowlab.pipeline.run_techniques` and :func:`shadowlab.pipeline.technique_metrics`; the
metrics of a point are those of ``compare`` with the same parameters, bit for bit.
"""

from __future__ import annotations

import math
import sys
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..pipeline import load_scene, run_techniques, technique_metrics
from ..reference import store
from ..render.frame import make_frame
from ..report.jsonable import to_jsonable
from ..techniques import base as tbase

__all__ = ["SPACINGS", "ParamRange", "parse_range", "SweepPoint", "evaluate_point", "clear_cache"]

SPACINGS = ("lin", "log")
_FORM = "NAME=LO:HI:N (e.g. depth_bias=0:64:9; add :log for log spacing, e.g. softness=0.25:8:6:log)"


@dataclass(frozen=True)
class ParamRange:
    """A swept parameter: its declaration and the values, in increasing order."""

    param: tbase.Param
    lo: float
    hi: float
    n: int
    spacing: str
    values: tuple

    def describe(self) -> dict:
        p = self.param
        return {"name": p.name, "kind": p.kind, "units": p.units, "lo": self.lo, "hi": self.hi, "n": self.n,
                "spacing": self.spacing, "values": list(self.values), "default": p.default,
                "declared_range": [p.lo, p.hi]}


def parse_range(text: str, technique: str) -> ParamRange:
    """``NAME=LO:HI:N`` (or ``TECHNIQUE.NAME=…``, or ``…:N:log``) -> the values swept.

    N ≥ 2 points from LO to HI (LO ≤ HI, both included), evenly spaced (``log``: evenly in log,
    LO > 0, rounded to 12 significant digits). An ``int`` parameter's values are rounded to the nearest integer and
    duplicates merged
    (a note on stderr says so); fewer than 2 distinct values are refused. Only ``float`` and
    ``int`` parameters can be swept, and every value must lie in the parameter's declared range.
    Bad input is an InputError (exit 2) naming the problem and the fix.

    >>> parse_range("depth_bias=0:8:3", "hard").values
    (0, 4, 8)
    >>> parse_range("softness=0.5:2:3:log", "pcf").values
    (0.5, 1.0, 2.0)
    """
    t = tbase.get(technique)
    s = str(text).strip()
    if "=" not in s:
        raise InputError(f"--param {text!r}: expected {_FORM}")
    name, _, rng = s.partition("=")
    name = name.strip()
    if "." in name and name not in {p.name for p in t.params}:      # LIGHT.PARAM of a technique per light stays
        tech, _, name = name.partition(".")
        if tech != technique:
            raise InputError(f"--param {text!r}: names technique {tech!r}, but the sweep runs {technique!r}; "
                             f"give {name}=… (a parameter of {technique})")
    p = t.param(name)   # unknown name: InputError listing the technique's parameters
    if p.kind not in ("float", "int"):
        numeric = ", ".join(q.name for q in t.params if q.kind in ("float", "int")) or "(none)"
        vals = p.range_text()
        raise InputError(f"--param {name}: {technique}.{name} is a {p.kind} parameter ({vals}), not a number; "
                         f"sweep one of {technique}'s numeric parameters ({numeric}), or compare its values with "
                         f"`shadowlab compare SCENE -t {technique} --set {technique}.{name}=VALUE`")
    parts = [x.strip() for x in rng.split(":")]
    spacing = "lin"
    if len(parts) == 4 and parts[3].lower() in SPACINGS:
        spacing = parts.pop().lower()
    if len(parts) != 3:
        raise InputError(f"--param {text!r}: expected {_FORM}")
    try:
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"--param {text!r}: LO and HI must be numbers; expected {_FORM}") from None
    try:
        n = int(parts[2])
    except ValueError:
        raise InputError(f"--param {text!r}: N must be a whole number of points (2 or more); expected {_FORM}") \
            from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"--param {text!r}: LO and HI must be finite numbers")
    if n < 2:
        raise InputError(f"--param {text!r}: N = {n} points; a sweep needs N >= 2 (to evaluate one value, use "
                         f"`shadowlab compare SCENE -t {technique} --set {technique}.{name}=VALUE`)")
    if n > 1000:
        raise InputError(f"--param {text!r}: N = {n} points; give at most 1000")
    if lo > hi:
        raise InputError(f"--param {text!r}: LO = {parts[0]} is greater than HI = {parts[1]}; give LO <= HI, "
                         f"e.g. {name}={parts[1]}:{parts[0]}:{n}")
    if spacing == "log" and lo <= 0:
        raise InputError(f"--param {text!r}: log spacing needs LO > 0 (got {parts[0]}); use linear spacing "
                         "(leave :log out) or a positive LO")
    # log: rounded to 12 significant digits, so that 0.25:4:5:log is 0.25, 0.5, 1, 2, 4 exactly
    raw = np.array([float(f"{x:.12g}") for x in np.geomspace(lo, hi, n)]) if spacing == "log" \
        else np.linspace(lo, hi, n)
    raw[0], raw[-1] = lo, hi
    if p.kind == "int":
        rounded = [int(math.floor(float(x) + 0.5)) for x in raw]
        values = tuple(dict.fromkeys(rounded))
        if len(values) < len(rounded):
            print(f"note: --param {name}: {technique}.{name} is an integer; {n} points from {parts[0]} to {parts[1]} "
                  f"round to {len(values)} distinct values {', '.join(map(str, values))} (duplicates merged)",
                  file=sys.stderr)
    else:
        values = tuple(dict.fromkeys(float(x) for x in raw))
    if len(values) < 2:
        raise InputError(f"--param {text!r}: gives only the value {values[0]}; a sweep needs 2 or more distinct "
                         f"values: give LO < HI")
    for v in values:
        p.parse(v, technique)   # out of the declared range: InputError naming it
    return ParamRange(p, lo, hi, n, spacing, values)


@dataclass(frozen=True)
class SweepPoint:
    """One point of a sweep: what a worker needs to evaluate it, and nothing it cannot pickle.

    ``scene``: a built-in name or an absolute path; ``resolution``: (W, H); ``frame``: the camera
    path frame (None: the scene as loaded); ``params``: the technique's overrides (the swept value
    and the ``--set`` ones); ``digest``: the scene's content hash when the sweep was checked;
    ``base``: the reference store."""

    technique: str
    scene: str
    resolution: tuple
    frame: int | None
    params: tuple          # ((name, value), ...): hashable, picklable
    digest: str
    base: str
    index: int = 0
    truth_sha256: str | None = None   # the stored truth's checksum: a re-rendered truth is a new cache entry


#: per process: (scene, resolution, frame, digest, base, truth checksum) -> [scene, truth, meta, FrameContext or None]
_CACHE: OrderedDict = OrderedDict()
_CACHE_SIZE = 2


def clear_cache() -> None:
    _CACHE.clear()


def _key(pt: SweepPoint) -> tuple:
    return pt.scene, tuple(pt.resolution), pt.frame, pt.digest, pt.base, pt.truth_sha256


def load_context(pt: SweepPoint) -> list:
    """[scene, truth, meta, frame] of a point's scene, from this process's cache (a worker that
    evaluates many points of one scene loads the scene and its truth and builds the FrameContext
    once). The FrameContext is made on first use; the truth is read and checked (stale, damaged:
    ReferenceError_, exit 2) when first loaded."""
    k = _key(pt)
    if k in _CACHE:
        _CACHE.move_to_end(k)
        return _CACHE[k]
    sc = load_scene(pt.scene, pt.resolution, pt.frame)
    if sc.spec.digest() != pt.digest:
        raise InputError(f"scene {pt.scene} changed while the sweep was running (its content hash differs from "
                         "when the sweep was checked); run the sweep again")
    truth, meta = store.load(sc.spec, sc.resolution, Path(pt.base))
    remember(pt, sc, truth, meta)
    return _CACHE[k]


def remember(pt: SweepPoint, sc, truth, meta) -> None:
    """Put a scene and its truth, already loaded and checked (by :func:`shadowlab.sweep.sweep_jobs`),
    into this process's cache, so that points run here do not read the truth again (an entry already
    there for the same scene and truth is kept, with its FrameContext and light views)."""
    k = _key(pt)
    if k in _CACHE:
        _CACHE.move_to_end(k)
        return
    _CACHE[k] = [sc, truth, meta, None]
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)


def evaluate_point(pt: SweepPoint) -> dict:
    """The metrics of one sweep point (on whichever process runs it), as plain JSON values:
    {"metrics": pooled metrics, "per_light": {light: metrics}, "timing": {"time_s", "first_run_s"}}.
    NaN metrics (e.g. no penumbra) are None. ``timing`` is measured, not computed: it is the one
    part that differs between runs and is never part of a sweep's "same bits" comparison."""
    entry = load_context(pt)
    sc, truth, meta = entry[0], entry[1], entry[2]
    if entry[3] is None:
        entry[3] = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    frame = entry[3]
    res, _, timing = run_techniques(frame, [pt.technique], {pt.technique: dict(pt.params)})[pt.technique]
    metrics, per_light, _ = technique_metrics(frame, truth, res)
    return {"metrics": to_jsonable(metrics, "metrics"), "per_light": to_jsonable(per_light, "per_light"),
            "timing": to_jsonable(timing, "timing")}
