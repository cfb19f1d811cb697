"""Search spaces and optimisers: Adam on Dr.Jit gradients, golden-section, grid, exhaustive.

Every fitted parameter is a :class:`Dim`: its declaration (:class:`~shadowlab.techniques.base.Param`),
the window searched, its scale and the method. With r the parameter's reference value (the
technique's default, e.g. ``light_scale`` 1, each light's own size):

* **log scale** when the declared range starts at lo ≥ 0 and reaches at least 1000·r above r > 0
  (the value's order of magnitude is what is unknown: ``vsm.min_variance`` [0, 0.01] with
  r = 10⁻⁶, ``msm.moment_bias`` [0, 0.1] with r = 3·10⁻⁵): window [max(lo, r/1000), hi], searched
  in u = log(x/a)/log(b/a);
* else **linear**: the declared range, narrowed to [max(lo, r − 3|r|), min(hi, r + 3|r|)] when it
  is wider than 10·|r| (``light_scale`` [0, 16] with r = 1 → [0, 4]; ``hard.depth_bias``
  [−10⁶, 10⁶] with r = 16 → [−32, 64]), searched in u = (x − a)/(b − a);

then widened to contain the start value. ``--range PARAM=LO:HI`` replaces the window (within the
declared range; linear scale unless the rule above gives log and LO > 0).

Methods:

* ``adam``: Dr.Jit reverse-mode AD through the technique and ``mi.ad.Adam`` (``drjit.opt.Adam``) on
  u ∈ [0, 1] (so one learning rate suits every parameter), projected back into [0, 1] after each
  step. Defaults: 25 steps, learning rate 0.1 decaying exponentially to 10 % of it at the last
  step, β₁ = 0.7 (less momentum than the usual 0.9), β₂ = 0.999: over 5 scenes × 3 starts of
  ``pcss.light_scale`` (``shadowlab.bench.fit``) this was the most robust of the settings tried
  (β₁ 0.5–0.9, final rate 2–20 %): a rough loss (``contact``: the blocker search's taps jump as
  the search region grows, which no gradient sees) can hold Adam in a local dip 10 % away from
  the optimum with other settings. Each step is one forward render and one backward pass.
* ``golden`` (float): 5 points equally spaced in u over the window (a bracket, so that a non-unimodal
  loss does not trap the search at the wrong end), then golden-section search in the bracket
  [x_{i−1}, x_{i+1}] around the best of them, ``evals`` evaluations in all (default 20: the
  bracket shrinks to 1.6 % of its width, 0.8 ‰ of the window);
  (int): exhaustive when the window holds ≤ 33 values, else golden section on the integers
  (``evals`` points, plus at most 4 to finish a bracket of ≤ 4 values);
* ``grid``: ``points`` values equally spaced in u over the window (ints rounded and deduplicated);
* ``exhaustive``: every value of a ``choice`` or ``bool``.

A parameter whose gradient is exactly zero at every Adam step (a plateau of the loss: ``esm.exponent``
80 on ``parallel_planes``, where exp(−c·Δz) has saturated) is then searched by ``golden``
(``auto`` only; ``adam`` leaves it and says so in the result's notes).

Several parameters: ``adam`` moves all of its parameters at once; the derivative-free methods
run one parameter at a time (coordinate search), ``rounds`` times (``grid`` with several
parameters evaluates the full product when it has at most ``max_grid`` points). The result is
the best evaluated point; evaluations of a point already evaluated are served from a cache and
not counted.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError

METHODS = ("auto", "adam", "golden", "grid")
PHI = (math.sqrt(5.0) - 1.0) / 2.0          # 0.618…
COARSE = 5                                   # bracket points of a float golden search
EXHAUSTIVE_INT = 33                          # int windows up to this many values are searched exhaustively


def _f32_inside(lo: float, hi: float) -> tuple[float, float]:
    """The float32 values nearest to [lo, hi] from inside (a float32 of hi may exceed hi)."""
    a, b = np.float32(lo), np.float32(hi)
    if float(a) < lo:
        a = np.nextafter(a, np.float32(np.inf))
    if float(b) > hi:
        b = np.nextafter(b, np.float32(-np.inf))
    return float(a), float(b)


@dataclass
class Dim:
    """One fitted parameter: declaration, window [lo, hi] and scale (float/int) or values
    (choice/bool), method, start and reference values."""

    param: object
    method: str
    start: object
    ref: object = None
    lo: float | None = None
    hi: float | None = None
    values: tuple = ()
    user_range: bool = False
    scale: str = "linear"

    @property
    def name(self) -> str:
        return self.param.name

    def to_unit(self, x: float) -> float:
        if self.scale == "log":
            return math.log(max(float(x), self.lo) / self.lo) / math.log(self.hi / self.lo)
        return (float(x) - self.lo) / (self.hi - self.lo)

    def from_unit_dr(self, u):
        """Dr.Jit u ∈ [0, 1] -> x in the window (float32-safe: never outside the declared range)."""
        a, b = _f32_inside(self.lo, self.hi)
        # the window enters opaquely: a fit over another window reuses the compiled kernels
        lo, a, b = (dr.opaque(mi.Float, v) for v in (self.lo, a, b))
        if self.scale == "log":
            return dr.clip(lo * dr.exp(u * dr.opaque(mi.Float, math.log(self.hi / self.lo))), a, b)
        return dr.clip(lo + u * dr.opaque(mi.Float, self.hi - self.lo), a, b)

    def from_unit(self, u: float) -> float:
        a, b = _f32_inside(self.lo, self.hi)
        x = (
            self.lo * math.exp(u * math.log(self.hi / self.lo))
            if self.scale == "log"
            else self.lo + u * (self.hi - self.lo)
        )
        if self.param.kind == "int":
            return int(round(min(max(x, self.lo), self.hi)))
        return float(np.clip(np.float32(x), a, b))

    def describe(self) -> dict:
        d = {"kind": self.param.kind, "method": self.method, "differentiable": self.param.differentiable,
             "units": self.param.units}
        if self.param.kind in ("float", "int"):
            d["window"] = [self.lo, self.hi]
            d["scale"] = self.scale
            d["window_from"] = "--range" if self.user_range else "declared range" if (
                self.lo == self.param.lo and self.hi == self.param.hi) else "declared range narrowed around the default"
        else:
            d["values"] = list(self.values)
        return d


def log_scale(p, ref) -> bool:
    """Search ``p`` on a log scale (module docstring)?"""
    return (p.kind == "float" and p.lo is not None and p.hi is not None and p.lo >= 0 and ref is not None
            and not isinstance(ref, bool) and float(ref) > 0 and p.hi >= 1000 * float(ref))


def window(p, ref, start, user=None, where: str = "?", floor=None) -> tuple:
    """(lo, hi, scale) searched for a float/int parameter (module docstring). ``floor``: the
    smallest value with its ordinary meaning, for parameters whose lower end means something
    else (``resolution`` 0 = the lights' own maps)."""
    log = log_scale(p, ref)
    if user is not None:
        lo, hi = user
        for v in (lo, hi):
            p.parse(v, where.split(".")[0])          # inside the declared range, else InputError
        if not lo < hi:
            raise InputError(f"--range {where}={lo:g}:{hi:g}: expected LO < HI")
        if floor is not None and lo < floor:
            lo = float(floor)
            if not lo < hi:
                raise InputError(f"--range {where}: HI must be above {floor:g} (0 means \"from the scene\")")
        if not lo <= float(start) <= hi:
            raise InputError(f"{where}: the start value {start} lies outside --range {lo:g}:{hi:g}; "
                             f"set a start inside it with --set {where}=VALUE or widen the range")
        if p.kind == "int":
            return int(math.ceil(lo)), int(math.floor(hi)), "linear"
        return float(lo), float(hi), "log" if log and lo > 0 else "linear"
    if p.lo is None or p.hi is None:
        raise InputError(f"{where} has no declared range; give one with --range {where.split('.')[-1]}=LO:HI")
    lo, hi = float(p.lo), float(p.hi)
    r = abs(float(ref))
    if log:
        lo = max(lo, r / 1000.0)
    elif r > 0 and hi - lo > 10 * r:
        lo, hi = max(lo, float(ref) - 3 * r), min(hi, float(ref) + 3 * r)
    if floor is not None:
        lo = max(lo, float(floor))
        hi = max(hi, lo)
    st = float(start)
    if log and st <= 0:
        log = False                                  # a start at 0 needs the linear scale
    lo, hi = min(lo, st), max(hi, st)
    if p.kind == "int":
        return int(math.ceil(lo)), int(math.floor(hi)), "linear"
    return lo, hi, "log" if log else "linear"


def make_dim(p, method: str, start, ref, user=None, differentiable_loss: bool = True, tech: str = "?",
             floor=None) -> Dim:
    """The Dim of parameter ``p`` for the requested ``method`` (auto/adam/golden/grid)."""
    where = f"{tech}.{p.name}"
    if method not in METHODS:
        raise InputError(f"--method {method!r}: expected one of {', '.join(METHODS)}")
    if p.kind in ("choice", "bool"):
        if user is not None:
            raise InputError(f"--range {where}: {p.kind} parameters have no range (their values: {p.range_text()})")
        if method == "adam":
            raise InputError(f"{where} is a {p.kind} parameter: it has no gradient; use --method golden, grid or auto")
        vals = tuple(p.choices) if p.kind == "choice" else (False, True)
        return Dim(p, "grid" if method == "grid" else "exhaustive", start, ref, values=vals)
    lo, hi, scale = window(p, ref, start, user, where, floor)
    if p.kind == "int" and hi - lo < 1 and method != "grid":
        raise InputError(f"{where}: the window [{lo}, {hi}] holds one integer; nothing to fit")
    if method == "adam":
        if not p.differentiable or p.kind != "float":
            raise InputError(f"{where} is not differentiable (declared differentiable=False, kind {p.kind}); "
                             f"fit it with --method golden, grid or auto")
        if not differentiable_loss:
            raise InputError("--loss flip has no gradient: fit with --method golden, grid or auto")
    m = method
    if method == "auto":
        m = "adam" if (p.differentiable and p.kind == "float" and differentiable_loss) else "golden"
    return Dim(p, m, start, ref, lo=lo, hi=hi, user_range=user is not None, scale=scale)


# ------------------------------------------------------------------------------------------------
# the search state: evaluations, history, best point


def point_key(values: dict) -> tuple:
    """A search point as a hashable key (numbers as floats, names sorted): the key of every
    evaluation cache of a fit."""
    return tuple(sorted((k, float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v)
                        for k, v in values.items()))


@dataclass
class Search:
    """Evaluates an :class:`~shadowlab.fit.objective.Objective` on parameter dicts; keeps the
    history (one entry per evaluation / Adam step, with the kernels it launched and compiled),
    a cache of evaluated points and the best point."""

    obj: object
    counter: object
    names: tuple
    start: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    cache: dict = field(default_factory=dict)
    best: tuple = (math.inf, None)
    t0: float = field(default_factory=time.perf_counter)
    notes: list = field(default_factory=list)

    def evaluate(self, values: dict, stage: str, param: str | None = None) -> float:
        k = point_key(values)
        if k in self.cache:
            return self.cache[k]
        o = self.obj.value(values)
        self.record(values, o, stage, param)
        return o

    def record(self, values: dict, o: float, stage: str, param=None, grad=None):
        dr.sync_thread()
        kern = self.counter.take()
        if not math.isfinite(o):
            o = math.inf
        self.cache[point_key(values)] = o
        e = {"i": len(self.history), "stage": stage, "values": {n: values[n] for n in self.names},
             "objective": o, "loss": self.obj.report(o) if math.isfinite(o) else None,
             "kernels_launched": kern["launched"], "kernels_new": kern["new"], "kernels_compiled": kern["compiled"],
             "t_s": time.perf_counter() - self.t0}
        if param is not None:
            e["param"] = param
        if grad is not None:
            e["grad_unit"] = grad
        self.history.append(e)
        if o < self.best[0]:
            self.best = (o, dict(values))

    @property
    def current(self) -> dict:
        """The best point so far (the start point before any evaluation)."""
        return dict(self.best[1] if self.best[1] is not None else self.start)


# ------------------------------------------------------------------------------------------------
# optimisers


def adam(s: Search, dims: list, steps: int = 25, lr: float = 0.1, beta_1: float = 0.7, decay: float = 0.1):
    """Adam on the unit-scaled ``dims`` from the current best point (module docstring)."""
    base = s.current
    opt = mi.ad.Adam(lr=lr, beta_1=beta_1, params={d.name: dr.opaque(mi.Float, d.to_unit(base[d.name])) for d in dims})
    jobs = getattr(s.obj, "loss_grad", None)      # fit.parts.PartsObjective: the gradient comes back as floats
    for k in range(steps):
        opt.set_learning_rate(lr * decay ** (k / max(steps - 1, 1)))
        if jobs is not None:
            o, xs, grads = jobs(base, dims, {d.name: float(opt[d.name][0]) for d in dims})
            for d in dims:
                dr.set_grad(opt[d.name], dr.opaque(mi.Float, grads[d.name]))   # opaque: no kernel per value
            vals = {**base, **xs}
        else:
            xs = {d.name: d.from_unit_dr(opt[d.name]) for d in dims}
            loss, _ = s.obj.loss_dr({**base, **xs})
            dr.backward(loss)
            o = float(loss[0])
            vals = {**base, **{n: float(x[0]) for n, x in xs.items()}}
            grads = {d.name: float(dr.grad(opt[d.name])[0]) for d in dims}
        s.obj.gradients += 1
        opt.step()
        for d in dims:
            opt[d.name] = dr.clip(opt[d.name], 0.0, 1.0)
        dr.eval(*[opt[d.name] for d in dims])
        s.record(vals, o, "adam", grad=grads)
    final = {**base, **{d.name: d.from_unit(float(opt[d.name][0])) for d in dims}}
    s.evaluate(final, "adam")


def golden(s: Search, d: Dim, evals: int = 20):
    """1-D derivative-free search of ``d`` from the current best point (module docstring)."""
    base = s.current

    def f(x):
        return s.evaluate({**base, d.name: x}, "golden", d.name)

    if d.param.kind == "int":
        _golden_int(f, d.lo, d.hi, evals)
        return
    fu = lambda u: f(d.from_unit(u))  # noqa: E731 - searched in u ∈ [0, 1] (linear or log scale)
    us = np.linspace(0.0, 1.0, COARSE)
    fs = [fu(float(u)) for u in us]
    i = int(np.argmin(fs))
    a, b = float(us[max(i - 1, 0)]), float(us[min(i + 1, COARSE - 1)])
    left = evals - COARSE
    if left < 2:
        return
    c, e = b - PHI * (b - a), a + PHI * (b - a)
    fc, fe = fu(c), fu(e)
    for _ in range(left - 2):
        if fc <= fe:
            b, e, fe = e, c, fc
            c = b - PHI * (b - a)
            fc = fu(c)
        else:
            a, c, fc = c, e, fe
            e = a + PHI * (b - a)
            fe = fu(e)


def _golden_int(f, lo: int, hi: int, evals: int):
    """Golden section on the integers of [lo, hi]: at most ``evals`` distinct points while the
    bracket is wider than 4 values, then (only once it is that narrow) the rest of the bracket,
    so at most ``evals`` + 4 points in all; a window of ≤ EXHAUSTIVE_INT values is searched
    exhaustively."""
    if hi - lo + 1 <= EXHAUSTIVE_INT:
        for x in range(lo, hi + 1):
            f(x)
        return
    seen: dict = {}

    def g(x):                               # the interior point kept by a step is not re-counted
        if x not in seen:
            seen[x] = f(x)
        return seen[x]

    a, b = lo, hi
    while b - a > 3 and len(seen) + 2 <= evals:
        c = int(round(b - PHI * (b - a)))
        e = int(round(a + PHI * (b - a)))
        if e <= c:
            e = c + 1
        if g(c) <= g(e):
            b = e
        else:
            a = c
    if b - a <= 3:
        for x in range(a, b + 1):
            g(x)


def grid_values(d: Dim, points: int) -> list:
    if d.param.kind in ("choice", "bool"):
        return list(d.values)
    if d.param.kind == "int":
        return sorted({int(round(x)) for x in np.linspace(d.lo, d.hi, points)})
    return [d.from_unit(float(u)) for u in np.linspace(0.0, 1.0, points)]


def grid(s: Search, d: Dim, points: int = 21):
    base = s.current
    for x in grid_values(d, points):
        s.evaluate({**base, d.name: x}, "grid", d.name)


def exhaustive(s: Search, d: Dim):
    base = s.current
    for x in d.values:
        s.evaluate({**base, d.name: x}, "exhaustive", d.name)


def full_grid(s: Search, dims: list, points: int):
    base = s.current
    for combo in itertools.product(*[grid_values(d, points) for d in dims]):
        s.evaluate({**base, **{d.name: x for d, x in zip(dims, combo)}}, "grid")


# unit-scaled gradient below which Adam is taken to stand on a plateau of the loss
PLATEAU_GRAD = 1e-5


def optimise(s: Search, dims: list, *, steps=25, lr=0.1, evals=20, points=21, rounds=0, max_grid=1000,
             fallback: bool = True, beta_1: float = 0.7, decay: float = 0.1):
    """Run the searches of ``dims`` from ``s.start``: its first evaluation is the start point (an
    Adam step there when Adam runs first, else a forward render); ``fallback``: search parameters
    Adam left on a plateau by golden section (``--method auto``)."""
    grad = [d for d in dims if d.method == "adam"]
    free = [d for d in dims if d.method != "adam"]
    if not grad:
        s.evaluate(dict(s.start), "start")
    if len(free) > 1 and all(d.method == "grid" for d in free) and \
            math.prod(len(grid_values(d, points)) for d in free) <= max_grid and not grad:
        full_grid(s, free, points)
        return
    if rounds <= 0:
        rounds = 2 if (len(free) > 1 or (grad and free)) else 1
    for _ in range(rounds):
        before = s.best[0]
        free_before = {d.name: s.current.get(d.name) for d in free}
        if grad:
            n0 = len(s.history)
            adam(s, grad, steps=steps, lr=lr, beta_1=beta_1, decay=decay)
            # a plateau (a vanishing gradient at every step, e.g. esm.exponent where exp(−c·Δz)
            # has saturated: |∂L/∂x| ~ 1e-7 in unit scale) leaves Adam where it started, or sends
            # it on normalised steps that change nothing: search such a parameter without gradients
            for d in grad:
                if all(abs(h.get("grad_unit", {}).get(d.name, 0.0)) < PLATEAU_GRAD for h in s.history[n0:]):
                    if not fallback:
                        s.notes.append(f"{d.name}: zero gradient at every Adam step (a plateau of the loss): "
                                       f"it stayed at its start; fit it with --method auto or golden")
                        continue
                    s.notes.append(f"{d.name}: zero gradient at every Adam step (a plateau of the loss); "
                                   f"searched by golden section instead")
                    golden(s, d, evals)
        for d in free:
            if d.method == "golden":
                golden(s, d, evals)
            elif d.method == "grid":
                grid(s, d, points)
            else:
                exhaustive(s, d)
        if (s.best[0] >= before and not grad) or (grad and free and
                                                   {d.name: s.current.get(d.name) for d in free} == free_before):
            break                                  # another round would repeat this one
