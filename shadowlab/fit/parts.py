"""The fit's objective as jobs: one job per part (a scene's frame) of the mean objective.

A fit over several scenes (and frames of a camera path) minimises the mean of the parts'
objectives (:class:`~shadowlab.fit.objective.Objective`: each a mean over its own mask). Each
evaluation of that mean sends one :class:`PartJob` per part to an executor
(:func:`shadowlab.cluster.open_executor`): (technique, scene, resolution, frame, loss, fixed
parameters, the point's values) and, for an Adam step, the unit coordinates u of the
differentiable parameters with their windows. :func:`evaluate_part` returns the part's
objective and, for Adam, ∂objective/∂u computed on the worker by ``dr.backward`` through
``Dim.from_unit_dr`` (plain floats: nothing Dr.Jit crosses a process). The mean and the mean
gradient are formed here, in part order, so the numbers do not depend on which worker ran
which part: a run on N workers gives the same bits as the embedded run (each part's objective
is a Dr.Jit reduction whose result does not depend on the thread count; measured).

Workers keep the loaded (scene, frame, truth, :class:`Objective`) per process in
:data:`_CACHE`, keyed by (scene, resolution, frame, scene digest, reference store, technique,
loss, fixed parameters); the fitting process lends the jobs the objectives it built itself
(:data:`_OWN`, for the length of its fit), so the embedded executor renders exactly what the
in-process fit rendered before, and loads nothing twice.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..cluster import Embedded
from ..errors import InputError
from ..pipeline import load_scene
from ..reference import store
from ..render.frame import make_frame
from ..techniques import base as tbase
from . import search as S
from .objective import KernelCounter, Objective

#: parts a worker process keeps loaded (least recently used dropped first); a fit's parts are
#: all evaluated at every point, so this should exceed the parts of the largest fit run
CACHE_SIZE = 64
_CACHE: OrderedDict = OrderedDict()
#: the objectives the fitting process built itself, held until its fit ends (never evicted)
_OWN: dict = {}

KERNEL_KEYS = ("launched", "compiled", "disk", "new")


@dataclass(frozen=True)
class Part:
    """One scene frame of a fit: what a worker needs to load it (picklable)."""

    scene: str                    # the scene as given: a built-in name or a .toml path
    name: str                     # the scene's name (reports group parts by it)
    resolution: tuple
    frame: int | None
    digest: str                   # SceneSpec.digest(): a worker refuses a scene that changed
    base: str                     # the reference store, resolved here (workers may not share our env)

    @classmethod
    def of(cls, sc, base: Path | None = None) -> "Part":
        """The part of a loaded scene (``Scene``, at its frame)."""
        src = str(getattr(sc.spec, "source", "") or "") or sc.name
        return cls(src, sc.name, tuple(int(x) for x in sc.resolution), sc.frame, sc.spec.digest(),
                   str(Path(base or store.root()).resolve()))

    def label(self) -> str:
        w, h = self.resolution
        return f"{self.name} {w}x{h}" + ("" if self.frame is None else f" frame {self.frame}")


def _items(d: dict) -> tuple:
    return tuple(sorted(d.items()))


@dataclass(frozen=True)
class PartJob:
    """One part's objective at one point (and, with ``grad``, its gradient in unit coordinates)."""

    part: Part
    technique: str
    loss: str
    fixed: tuple                  # sorted (name, value) of the parameters held fixed
    values: tuple                 # sorted (name, value) of the point
    grad: tuple = ()              # ((name, u, lo, hi, scale), ...): Adam's differentiable parameters

    def key(self) -> tuple:
        p = self.part
        return (p.scene, p.resolution, p.frame, p.digest, p.base, self.technique, self.loss, self.fixed)


def cache_key(part: Part, technique: str, loss: str, fixed: dict) -> tuple:
    return PartJob(part, technique, loss, _items(fixed), ()).key()


def _remember(key: tuple, objective) -> None:
    _CACHE[key] = objective
    _CACHE.move_to_end(key)
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)


def register(key: tuple, objective) -> None:
    """Lend an objective built by the fitting process to the jobs run in it (until :func:`forget`)."""
    _OWN[key] = objective


def forget(keys) -> None:
    for k in keys:
        _OWN.pop(k, None)


def _objective(job: PartJob) -> Objective:
    key = job.key()
    if key in _OWN:
        return _OWN[key]
    obj = _CACHE.get(key)
    if obj is not None:
        _CACHE.move_to_end(key)
        return obj
    p = job.part
    sc = load_scene(p.scene, p.resolution, p.frame)
    if sc.spec.digest() != p.digest:
        raise InputError(f"scene {p.scene} changed while it was being fitted (its digest differs from the one the "
                         "fit started with); run the fit again")
    truth, meta = store.load(sc.spec, sc.resolution, Path(p.base))
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    obj = Objective(frame, truth, tbase.get(job.technique), job.loss, fixed=dict(job.fixed))
    _remember(key, obj)
    return obj


def evaluate_part(job: PartJob) -> dict:
    """A part's objective at ``job.values`` ({"objective"}), and with ``job.grad`` also the
    values the Dr.Jit parameters held ({"x"}) and ∂objective/∂u ({"grad"}), as floats; plus the
    kernels it launched ({"kernels"}) when it ran in a process that is not counting them already
    (a worker; the embedded executor runs under the fit's own counter)."""
    counting = not dr.flag(dr.JitFlag.KernelHistory)
    if counting:
        with KernelCounter() as kc:
            out = _evaluate(job)
            dr.sync_thread()
            out["kernels"] = kc.take()
        return out
    return _evaluate(job)


def _evaluate(job: PartJob) -> dict:
    obj = _objective(job)
    values = dict(job.values)
    if not job.grad:
        return {"objective": obj.value(values)}
    us, xs = {}, {}
    for name, u, lo, hi, scale in job.grad:          # as search.adam does with the optimiser's variables
        us[name] = dr.opaque(mi.Float, u)
        dr.enable_grad(us[name])
        d = S.Dim(obj.tech.param(name), "adam", None, lo=lo, hi=hi, scale=scale)
        xs[name] = d.from_unit_dr(us[name])
    loss, _ = obj.loss_dr({**values, **xs})
    dr.backward(loss)
    return {"objective": float(loss[0]), "x": {n: float(x[0]) for n, x in xs.items()},
            "grad": {n: float(dr.grad(u)[0]) for n, u in us.items()}}


class PartsObjective:
    """The mean over parts of one technique's objectives, each part evaluated by a job.

    ``objectives``: the parts' :class:`Objective` built in this process (for the report: pixels,
    noise floors; and the embedded executor's cache). ``value`` and ``loss_grad`` send one job
    per part; ``part_values`` keeps each evaluated point's per-part objectives (the per-scene
    results); ``evaluations`` counts the parts' renders, ``gradients`` the Adam steps."""

    def __init__(self, executor, parts: list, objectives: list, technique: str, loss: str, fixed: dict):
        if not parts or len(parts) != len(objectives):
            raise ValueError("PartsObjective needs one objective per part")
        self.ex = executor or Embedded()
        self.parts, self.objs = list(parts), list(objectives)
        first = self.objs[0]
        self.frame, self.truth, self.tech, self.loss, self.fixed = (
            first.frame,
            first.truth,
            first.tech,
            loss,
            dict(fixed),
        )
        self.lights = first.lights
        self.technique = technique
        self.pixels = sum(o.pixels for o in self.objs)
        self.noise_floor = float(np.mean([o.noise_floor for o in self.objs]))
        self.evaluations = 0
        self.gradients = 0
        self.part_values: dict = {}
        self._kernels = dict.fromkeys(KERNEL_KEYS, 0)
        self.keys = [cache_key(p, technique, loss, self.fixed) for p in self.parts]
        for k, o in zip(self.keys, self.objs):
            register(k, o)

    def close(self):
        forget(self.keys)

    def _run(self, values: dict, grad: tuple = ()) -> list:
        fixed, vals = _items(self.fixed), _items(values)
        jobs = [PartJob(p, self.technique, self.loss, fixed, vals, grad) for p in self.parts]
        out = self.ex.map(evaluate_part, jobs, desc="fit")
        self.evaluations += len(jobs)
        for r in out:
            for k, v in (r.get("kernels") or {}).items():
                self._kernels[k] += int(v)
        return out

    def take_kernels(self) -> dict:
        """The kernels the jobs reported since the last call (workers only)."""
        k, self._kernels = self._kernels, dict.fromkeys(KERNEL_KEYS, 0)
        return k

    def value(self, values: dict) -> float:
        out = [r["objective"] for r in self._run(values)]
        self.part_values[S.point_key(values)] = out
        return float(np.mean(out))

    def loss_grad(self, base: dict, dims: list, us: dict) -> tuple:
        """(mean objective, {name: value held}, {name: mean ∂/∂u}) at ``base`` with the Adam
        parameters ``dims`` at unit coordinates ``us``."""
        grad = tuple((d.name, float(us[d.name]), float(d.lo), float(d.hi), d.scale) for d in dims)
        out = self._run({k: v for k, v in base.items() if k not in us}, grad)
        xs = out[0]["x"]
        objs = [r["objective"] for r in out]
        self.part_values[S.point_key({**base, **xs})] = objs
        g = {d.name: float(np.mean([r["grad"][d.name] for r in out])) for d in dims}
        return float(np.mean(objs)), xs, g

    def report(self, objective: float, floor: float | None = None) -> float:
        if self.loss == "flip":
            return float(objective)
        return float(np.sqrt(max(objective - (self.noise_floor if floor is None else floor), 0.0)))

    def by_scene(self, values: dict) -> dict:
        """{scene name: {"objective", "loss", "frames"}}: each scene's mean over its frames of the
        parts' objectives at ``values`` (evaluated now if this point was not)."""
        k = S.point_key(values)
        if k not in self.part_values:
            self.value(values)
        vals = self.part_values[k]
        groups: dict = {}
        for i, p in enumerate(self.parts):
            groups.setdefault(p.name, []).append(i)
        out = {}
        for name, idx in groups.items():
            o = float(np.mean([vals[i] for i in idx]))
            floor = float(np.mean([self.objs[i].noise_floor for i in idx]))
            out[name] = {"objective": o, "loss": self.report(o, floor),
                         "frames": [self.parts[i].frame for i in idx]}
        return out

    def describe(self) -> dict:
        d = self.objs[0].describe()
        if len(self.objs) == 1:
            return d
        scenes = list(dict.fromkeys(p.name for p in self.parts))
        what = f"{len(self.parts)} frames" if len(scenes) == 1 else \
            f"{len(scenes)} scenes ({len(self.parts)} parts: scene frames)"
        d.update(pixels=self.pixels, frames=len(self.parts), description=d["description"] + f"; mean over {what}")
        if len(scenes) > 1:
            d["scenes"] = len(scenes)
        if self.loss != "flip":
            d["noise_floor_rmse"] = float(np.sqrt(self.noise_floor))
        return d


class Kernels:
    """The kernel counter a :class:`~shadowlab.fit.search.Search` reads: this process's kernels
    and those the jobs reported from workers."""

    def __init__(self, local: KernelCounter, obj: PartsObjective):
        self.local, self.obj = local, obj

    def take(self) -> dict:
        a, b = self.local.take(), self.obj.take_kernels()
        return {k: a[k] + b[k] for k in KERNEL_KEYS}
