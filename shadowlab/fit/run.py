"""Fitting jobs: one technique (``shadowlab fit SCENE --technique T``) or all (``--all``).

A job validates everything first (scene, reference, techniques, parameter names, values,
ranges, preset, output paths), so bad input stops it with an ``InputError`` (exit 2) before
anything is rendered or written; then it builds the FrameContext once, fits, renders the start
and the fitted values once more for the report's metrics and images, and writes the report.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import numpy as np

from ..errors import InputError, ReferenceError_, ShadowlabError
from ..pipeline import check_memory, frame_list, load_scene, technique_metrics
from ..reference import store
from ..render.frame import make_frame
from ..scene.spec import scene_spec
from ..techniques import base as tbase
from . import preset as P
from . import report as R
from . import search as S
from .objective import DIFFERENTIABLE_LOSSES, KernelCounter, Objective, check_loss
from .parts import Kernels, Part, PartsObjective

#: the ``compare`` metric that measures what each loss measures, over the same pixels (the shaded
#: image where the loss reads visibility: what ``compare`` reports): a fit may not make it worse
#: than at its start. The fitted values are kept only if it does not rise, else the fit ends at its
#: start and says so in its notes (the loss pools the lights' visibility errors by pixel count, the
#: shaded image weighs each light by its radiance, so the two can disagree on several lights)
GUARD_METRIC = {"rmse_penumbra": "rmse_penumbra", "rmse": "rmse", "flip": "flip_penumbra"}


#: fractions of the way from the start to a rejected fitted point tried before keeping the start
BACKTRACK = (0.5, 0.25, 0.125)


def guard_metrics(loss: str, frame) -> tuple:
    """The ``compare`` metrics a fit may not make worse than its start: the one of its loss
    (:data:`GUARD_METRIC`) and, on a scene with several lights, also the shaded image's RMSE,
    ``compare``'s first column (the lights' visibility errors are pooled by pixel count in the
    loss, weighed by each light's radiance in the image)."""
    g = [GUARD_METRIC[loss]]
    if len(frame.lights) > 1 and "rmse" not in g:
        g.append("rmse")
    return tuple(g)


def _toward(p, fitted: dict, t: float) -> dict:
    """The point ``t`` of the way from the start to ``fitted`` (float and int parameters; the
    others keep their fitted value), inside each window, as the preset would store it."""
    out = {}
    for d in p.dims:
        a, b = p.start[d.name], fitted[d.name]
        if d.param.kind == "float":
            out[d.name] = _inside(d.param, _clean(float(a) + t * (float(b) - float(a))))
        elif d.param.kind == "int":
            out[d.name] = int(round(int(a) + t * (int(b) - int(a))))
        else:
            out[d.name] = b
    return out


def _worse(after, before) -> bool:
    """``after`` is a worse metric value than ``before`` (NaN never counts as better)."""
    if after is None or before is None:
        return False
    if math.isnan(before):
        return False
    return math.isnan(after) or after > before


def default_loss(tech_name: str) -> str:
    """The loss a technique is fitted with when ``--loss`` is not given: its declared
    :attr:`~shadowlab.techniques.base.Technique.fit_loss` (checked against the losses)."""
    return check_loss(tbase.get(tech_name).fit_loss)


@dataclass
class Budget:
    steps: int = 25          # Adam steps
    lr: float = 0.1          # Adam learning rate, in units of the window
    evals: int = 20          # evaluations of one 1-D golden search
    points: int = 21         # grid points per parameter
    rounds: int = 0          # coordinate rounds (0 = 1 for one parameter, else 2)
    beta_1: float = 0.7      # Adam's first-moment weight
    decay: float = 0.1       # Adam's learning rate at the last step, as a fraction of lr

    def check(self):
        for name, v, lo, hi in (("--steps", self.steps, 1, 10000), ("--evals", self.evals, 3, 10000),
                                ("--grid-points", self.points, 2, 100000), ("--rounds", self.rounds, 0, 100)):
            if not (isinstance(v, int) and lo <= v <= hi):
                raise InputError(f"{name} {v}: expected an integer in [{lo}, {hi}]")
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and 0 < self.lr <= 1):
            raise InputError(f"--lr {self.lr}: expected a learning rate in (0, 1] (a fraction of the window)")
        return self


def default_params(tech, values: dict | None = None) -> tuple:
    """The parameters fitted when ``--params`` is not given: what the technique declares
    (:meth:`~shadowlab.techniques.base.Technique.fit_params`) for ``values`` (default: its defaults)."""
    return tuple(tech.fit_params(values if values is not None else tech.resolve({})))


def parse_params(csv) -> list | None:
    if csv is None:
        return None
    items = csv if isinstance(csv, (list, tuple)) else str(csv).split(",")
    names = [str(x).strip() for x in items if str(x).strip()]
    if not names:
        raise InputError("--params is empty; name parameters such as --params light_scale")
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise InputError(f"--params names {', '.join(sorted(dup))} twice")
    return names


def parse_ranges(items, techniques: list[str]) -> dict:
    """``["light_scale=0.2:3", "pcf.softness=0.5:4"]`` -> {technique: {param: (lo, hi)}}; an item
    without ``TECH.`` applies to the only technique being fitted."""
    out = {t: {} for t in techniques}
    for it in items or []:
        if "=" not in it or ":" not in it.split("=", 1)[1]:
            raise InputError(f"--range {it!r}: expected [TECHNIQUE.]PARAM=LO:HI, e.g. light_scale=0.2:3")
        key, val = it.split("=", 1)
        if len(techniques) == 1 and "." in key and key in {p.name for p in tbase.get(techniques[0]).params}:
            tech, pname = techniques[0], key          # LIGHT.PARAM of a technique per light
        elif "." in key:
            tech, pname = key.split(".", 1)
        elif len(techniques) == 1:
            tech, pname = techniques[0], key
        else:
            raise InputError(f"--range {it!r}: with several techniques write TECHNIQUE.PARAM=LO:HI")
        if tech not in out:
            raise InputError(f"--range {it!r}: technique {tech!r} is not being fitted ({', '.join(techniques)})")
        try:
            lo, hi = (float(x) for x in val.split(":", 1))
        except ValueError:
            raise InputError(f"--range {it!r}: LO and HI must be numbers") from None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputError(f"--range {it!r}: LO and HI must be finite")
        out[tech][pname.strip()] = (lo, hi)
    return out


def reference_value(tech, name: str, value, frame):
    """The value a window is centred on and a "from the scene" default replaced by: the value
    itself, or what the parameter's :attr:`~shadowlab.techniques.base.Param.from_scene` sentinel
    stands for on ``frame``. (Light sizes need no rule: ``light_scale`` multiplies each light's
    own size, so 1 is the scene's lights, one scale for all of them.)"""
    return tech.param(name).scene_value(value, frame)


def scene_floor(tech, name: str, ref):
    """The lower end of the window of a parameter with a "from the scene" sentinel: a fitted
    value must not become that sentinel (its :class:`~shadowlab.techniques.base.FromScene` floor)."""
    fs = tech.param(name).from_scene
    return None if fs is None else fs.floor


def _f32(x):
    """Shortest decimal of a float32 value (what a Dr.Jit parameter actually held)."""
    return float(str(np.float32(x)))


def _clean(v):
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _f32(v)
    return v


def _inside(prm, v):
    """A fitted value inside its declared range (the float32 round trip may step over an end)."""
    if prm.kind == "float":
        if prm.lo is not None:
            v = max(v, float(prm.lo))
        if prm.hi is not None:
            v = min(v, float(prm.hi))
    return v


@dataclass
class Plan:
    tech: object
    names: list
    dims: list
    start: dict
    fixed: dict
    loss: str
    method: str


def plan(tech_name: str, frame, *, params=None, method="auto", loss="rmse_penumbra", sets=None, ranges=None) -> Plan:
    """Validate one technique's fit and build its search space (no rendering)."""
    tech = tbase.get(tech_name)
    check_loss(loss)
    if method not in S.METHODS:
        raise InputError(f"--method {method!r}: expected one of {', '.join(S.METHODS)}")
    names = list(params) if params else list(default_params(tech, tech.resolve(sets or {})))
    if not names:
        raise InputError(f"technique {tech.name!r} has no differentiable parameter to fit by default; name the "
                         f"parameters with --params (its parameters: {', '.join(p.name for p in tech.params)})")
    for n in names:
        tech.param(n)                                   # unknown name -> InputError listing the parameters
    ranges = dict(ranges or {})
    for n in ranges:
        tech.param(n)
        if n not in names:
            raise InputError(f"--range {tech.name}.{n}: {n!r} is not among the fitted parameters ({', '.join(names)})")
    values = tech.resolve(sets or {})                   # validated: unknown or out-of-range values -> InputError
    dims, start = [], {}
    for n in names:
        p = tech.param(n)
        ref = reference_value(tech, n, p.default, frame)
        st = reference_value(tech, n, values[n], frame)
        d = S.make_dim(p, method, st, ref, ranges.get(n), loss in DIFFERENTIABLE_LOSSES, tech.name,
                       scene_floor(tech, n, ref))
        dims.append(d)
        start[n] = st
    fixed = {k: v for k, v in values.items() if k not in names}
    return Plan(tech=tech, names=names, dims=dims, start=start, fixed=fixed, loss=loss, method=method)


def _metrics(p: Plan, values: dict, pairs, per: list | None = None) -> tuple:
    """(metrics, per_light, images, render) of ``values`` on the first (frame, truth) of ``pairs``,
    with every metric replaced by its mean over all of them (the guards of several frames);
    ``per``: a list that receives each pair's metrics."""
    res = p.tech.render(pairs[0][0], {**p.fixed, **values})
    m, pl, img = technique_metrics(pairs[0][0], pairs[0][1], res)
    ms = [m] + [technique_metrics(f, t, p.tech.render(f, {**p.fixed, **values}))[0] for f, t in pairs[1:]]
    if per is not None:
        per[:] = ms
    if len(pairs) > 1:
        m = _mean_metrics(ms)
    return m, pl, img, res


def _mean_metrics(ms: list) -> dict:
    return {k: float(np.mean([x[k] for x in ms])) if all(x.get(k) is not None for x in ms) else None for k in ms[0]}


def execute(p: Plan, frame, truth, budget: Budget, more=(), *, executor=None, parts=None) -> dict:
    """Run one planned fit; returns the result dict (JSON-able, plus ``images``: numpy).
    ``more``: further (frame, truth) pairs (frames of a camera path, other scenes) fitted together
    with ``frame``: the objective is the mean over all of them, the guards compare metrics averaged
    over them, the images are ``frame``'s. Each evaluation is one job per pair
    (:mod:`.parts`) on ``executor`` (default: this process); ``parts``: the pairs'
    :class:`~.parts.Part` (default: from their frames, references in the default store). With
    pairs of several scenes the result has ``scenes``: each scene's loss before and after."""
    pairs = [(frame, truth), *more]
    parts = list(parts) if parts is not None else [Part.of(f.scene) for f, _ in pairs]
    objs = [Objective(f, t, p.tech, p.loss, fixed=p.fixed) for f, t in pairs]
    obj = PartsObjective(executor, parts, objs, p.tech.name, p.loss, p.fixed)
    try:
        return _execute(p, frame, pairs, budget, obj)
    finally:
        obj.close()


def _execute(p: Plan, frame, pairs, budget: Budget, obj) -> dict:
    with KernelCounter() as local:
        counter = Kernels(local, obj)
        dr.sync_thread()
        t0 = time.perf_counter()
        s = S.Search(obj, counter, tuple(p.names), start=dict(p.start))
        S.optimise(s, p.dims, steps=budget.steps, lr=budget.lr, evals=budget.evals, points=budget.points,
                   rounds=budget.rounds, fallback=p.method == "auto", beta_1=budget.beta_1, decay=budget.decay)
        dr.sync_thread()
        wall = time.perf_counter() - t0
    best_obj, best = s.best
    fitted = {d.name: _inside(d.param, _clean(best[d.name])) for d in p.dims}
    for d in p.dims:                              # a narrowed window may hide a better value outside it
        if d.param.kind in ("float", "int"):
            for end, bound, side in ((d.lo, d.param.lo, "lower"), (d.hi, d.param.hi, "upper")):
                if abs(float(fitted[d.name]) - end) <= 1e-6 * max(abs(end), 1e-12) and end != bound:
                    s.notes.append(f"{d.name} ended on the {side} end {end:g} of its window (declared range "
                                   f"[{d.param.lo:g}, {d.param.hi:g}]): widen it with --range {p.tech.name}."
                                   f"{d.name}=LO:HI")
    obj_before = s.history[0]["objective"]
    hist = s.history
    evaluations, gradients = obj.evaluations, obj.gradients
    # the report's metrics and images (outside the search: not counted)
    per_b, per_a = [], []
    m_b, pl_b, img_b, res_b = _metrics(p, p.start, pairs, per_b)
    m_a, pl_a, img_a, res_a = _metrics(p, fitted, pairs, per_a)
    # never end worse than the start as ``compare`` measures it: these renders are exactly what
    # ``compare --preset`` renders (same frame, plain values, the preset's repr round trip)
    guards = guard_metrics(p.loss, max((f for f, _ in pairs), key=lambda f: len(f.lights)))
    bad = [g for g in guards if _worse(m_a.get(g), m_b.get(g))]
    if bad:
        tried = [fitted]
        found = None
        for t in BACKTRACK:                     # back toward the start: the loss is ≤ the start's there
            cand = _toward(p, fitted, t)
            if cand in tried:
                continue
            tried.append(cand)
            o = obj.value(cand)                  # outside the search: not counted
            if o > obj_before:
                continue
            per_c = []
            m_c, pl_c, img_c, res_c = _metrics(p, cand, pairs, per_c)
            if not any(_worse(m_c.get(g), m_b.get(g)) for g in guards):
                found = (cand, o, res_c, m_c, pl_c, img_c, per_c)
                break
        what = ", ".join(f"{g} {m_b[g]:.6g} → {m_a[g]:.6g}" for g in bad)
        best_txt = ", ".join(f"{k} {v}" for k, v in fitted.items())
        if found is not None:
            fitted, best_obj, res_a, m_a, pl_a, img_a, per_a = found
            s.notes.append(f"the search's best point ({best_txt}) lowered the {p.loss} loss but made compare's "
                           f"{what}: ended at {', '.join(f'{k} {v}' for k, v in fitted.items())}, part of the way "
                           f"from the start, which is no worse in {', '.join(guards)}")
        else:
            s.notes.append(f"the search's best point ({best_txt}) lowered the {p.loss} loss but made compare's "
                           f"{what}: kept the start")
            fitted = {d.name: _clean(p.start[d.name]) for d in p.dims}
            best_obj = obj_before                # the start's objective, evaluated first by the search
            m_a, pl_a, img_a, per_a = m_b, pl_b, img_b, per_b
    defaults = p.tech.defaults()
    nondefault = {k: _clean(v) for k, v in p.fixed.items() if v != defaults.get(k)}
    new_per_it = [h["kernels_new"] for h in hist]
    scenes = _by_scene(obj, hist[0]["values"], fitted, per_b, per_a)
    return {
        "technique": p.tech.name, "method": p.method, "loss": obj.describe(),
        "params": {d.name: {**d.describe(), "start": _clean(p.start[d.name]), "fitted": fitted[d.name],
                            "reference": _clean(d.ref)} for d in p.dims},
        "fixed": nondefault,
        "loss_before": obj.report(obj_before), "loss_after": obj.report(best_obj),
        "objective_before": obj_before, "objective_after": best_obj,
        "iterations": len(hist) - 1, "evaluations": evaluations, "gradient_evaluations": gradients,
        "wall_time_s": wall,
        "kernels": {"compiled": int(sum(h["kernels_compiled"] for h in hist)),
                    "loaded_from_disk": int(sum(h["kernels_new"] - h["kernels_compiled"] for h in hist)),
                    "launched": int(sum(h["kernels_launched"] for h in hist)),
                    "iterations_with_new_kernels": int(sum(1 for k in new_per_it if k)),
                    "new_per_iteration": new_per_it},
        "metrics_before": m_b, "metrics_after": m_a, "per_light_before": pl_b, "per_light_after": pl_a,
        "notes": list(s.notes),
        "history": hist,
        "preset_values": {**nondefault, **fitted},
        **({"scenes": scenes} if scenes else {}),
        "images": {"before": img_b, "after": img_a},
    }


def _by_scene(obj, start: dict, fitted: dict, per_b: list, per_a: list) -> dict | None:
    """{scene: {loss and objective before / after, frames, compare's metrics before / after}}
    of a fit over several scenes (None for one scene): each scene's own mean over its frames,
    with the start and the joint fitted values."""
    names = list(dict.fromkeys(q.name for q in obj.parts))
    if len(names) < 2:
        return None
    b, a = obj.by_scene(dict(start)), obj.by_scene(dict(fitted))
    out = {}
    for n in names:
        idx = [i for i, q in enumerate(obj.parts) if q.name == n]
        q = obj.parts[idx[0]]
        out[n] = {"resolution": list(q.resolution), "frames": b[n]["frames"],
                  "loss_before": b[n]["loss"], "loss_after": a[n]["loss"],
                  "objective_before": b[n]["objective"], "objective_after": a[n]["objective"],
                  "metrics_before": _mean_metrics([per_b[i] for i in idx]),
                  "metrics_after": _mean_metrics([per_a[i] for i in idx])}
    return out


def prepare(scene: str, resolution=None, base: Path | None = None, frame: int | None = None, frames=None):
    """(scene, truth, meta, frame): the stored reference is required (never rendered here);
    a missing or stale one is a ReferenceError_ (exit 2) naming the command that makes it.
    ``frame`` / ``frames``: the camera path frame (the first of ``frames``; see
    :func:`prepare_frames` for all of them)."""
    return prepare_frames(scene, resolution, base, frame=frame, frames=frames)[0]


def prepare_frames(scene: str, resolution=None, base: Path | None = None, frame: int | None = None,
                   frames=None) -> list:
    """[(scene, truth, meta, frame)] of every selected frame of the camera path (one entry
    without ``frame`` / ``frames``): each frame's stored reference is required."""
    return prepare_scenes([scene], resolution, base, frame=frame, frames=frames)[0]


def prepare_scenes(scenes: list, resolution=None, base: Path | None = None, frame: int | None = None,
                   frames=None) -> list:
    """[[(scene, truth, meta, frame)] per scene]: every reference of every scene and selected
    frame is read before any frame is built, and those that are missing, stale or damaged are
    one ReferenceError_ (exit 2) listing each (scene, resolution, frame) with the
    ``shadowlab reference`` commands that make them (a single one: the store's own message)."""
    loaded, problems = [], []
    for scene in scenes:
        sc0 = load_scene(scene, resolution)
        sel = frame_list(sc0.spec, frame, frames)
        got = []
        for i in (sel or [None]):
            sc = sc0 if i is None else sc0.at_frame(i)
            try:
                truth, meta = store.load(sc.spec, sc.resolution, base)
            except ReferenceError_ as e:
                missing = not store.path_for(sc.name, sc.resolution, base, frame=sc.frame).exists()
                problems.append((sc, missing, e))
                continue
            got.append((sc, truth, meta))
        loaded.append(got)
    if len(problems) == 1:
        raise problems[0][2]
    if problems:
        raise ReferenceError_(missing_references(problems))
    return [[(sc, truth, meta, make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0))))
             for sc, truth, meta in got] for got in loaded]


def missing_references(problems: list) -> str:
    """The message for several references a fit lacks: each (scene, resolution, frame), then one
    ``shadowlab reference A B -r WxH [--frames A:B | --frame N] [--force]`` per group of scenes
    that share a resolution and frames (``--force`` for stale or damaged ones)."""
    lines, groups = [], {}
    for sc, missing, e in problems:
        w, h = sc.resolution
        at = f"{w}x{h}" + ("" if sc.frame is None else f" frame {sc.frame}")
        lines.append(f"  {sc.name} {at}: " + ("missing" if missing else str(e).split(";")[0]))
        groups.setdefault((tuple(sc.resolution), not missing, store.scene_arg(sc.spec)), []).append(sc.frame)
    cmds, by = [], {}
    for (res, force, arg), fr in groups.items():
        by.setdefault((res, force, tuple(fr)), []).append(arg)
    for (res, force, fr), args in by.items():
        if fr == (None,):
            sel = [""]
        elif len(fr) > 1 and list(fr) == list(range(fr[0], fr[0] + len(fr))):
            sel = [f" --frames {fr[0]}:{fr[-1]}"]
        else:
            sel = [f" --frame {f}" for f in fr]
        cmds += [f"shadowlab reference {' '.join(args)} -r {res[0]}x{res[1]}{x}{' --force' if force else ''}"
                 for x in sel]
    return (f"{len(problems)} references this fit needs are missing or unusable:\n" + "\n".join(lines)
            + "\nrender them with:\n" + "\n".join(f"  {c}" for c in cmds))


def scene_names(scene) -> list[str]:
    """SCENE or SCENE... as a list (a scene named twice is an InputError)."""
    names = [scene] if isinstance(scene, (str, Path)) else list(scene or [])
    names = [str(n) for n in names]
    if not names:
        raise InputError("no scene given: name one or more scenes (`shadowlab scenes` lists the built-in ones)")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"scene {', '.join(dup)} named twice; name each scene once")
    return names


def joint_name(scenes: list[str], limit: int = 48) -> str:
    """The name of a fit over ``scenes`` (reports, presets): their stems joined by ``+``, the
    first ones and a count when that grows past ``limit`` characters.

    >>> joint_name(["contact", "scenes/pp.toml"]), joint_name(["a" * 30, "b" * 30, "c"])
    ('contact+pp', 'aaaaaaaaaaaaaaaaaaaaaaaaaaaaaa+2-more')
    """
    stems = [Path(s).stem for s in scenes]
    name = "+".join(stems)
    if len(name) <= limit:
        return name
    keep = stems[:1]
    for st in stems[1:]:
        if len("+".join(keep + [st])) + len(f"+{len(stems)}-more") > limit:
            break
        keep.append(st)
    return "+".join(keep) + f"+{len(stems) - len(keep)}-more"


def default_out(scene, technique: str | None, all_techniques: bool = False) -> str:
    """``reports/fit/<scene>-<technique>``; several scenes: ``<s1>+<s2>…`` (:func:`joint_name`)."""
    name = "all" if all_techniques else re.sub(r"[^A-Za-z0-9_.+-]+", "_", technique or "fit")
    return f"reports/fit/{joint_name(scene_names(scene))}-{name}"


def fit(scene, technique: str | None = None, *, params=None, method: str = "auto", loss: str | None = None,
        all_techniques: bool = False, sets=None, preset=None, ranges=None, budget: Budget | None = None,
        out=None, save_preset=None, preset_name: str | None = None, resolution=None, base: Path | None = None,
        echo=None, force: bool = False, frame: int | None = None, frames=None, executor=None) -> dict:
    """The ``shadowlab fit`` job. ``scene``: one scene or a list of them: one preset minimising
    the mean over the scenes (and frames) of their objectives, with each scene's loss before and
    after beside it. ``executor``: where the evaluations run (:func:`shadowlab.cluster.open_executor`;
    default this process). Returns the run dict (``mode`` "one" or "all") and writes the report to
    ``out`` (if given) and the preset to ``save_preset`` (if given)."""
    scenes = scene_names(scene)
    budget = (budget or Budget()).check()
    if loss is not None:
        check_loss(loss)
    if method not in S.METHODS:
        raise InputError(f"--method {method!r}: expected one of {', '.join(S.METHODS)}")
    if all_techniques and technique:
        raise InputError("give either --technique NAME or --all, not both")
    if not all_techniques and not technique:
        raise InputError("name the technique to fit with --technique NAME (or fit every technique with --all)")
    if all_techniques and params:
        raise InputError("--params applies to one --technique; --all fits each technique's default parameters")
    techs = [n for n in tbase.names() if not tbase.get(n).external] if all_techniques else [technique]
    for t in techs:
        tbase.get(t)                                         # unknown technique -> InputError
    pre = P.load(preset) if preset else None
    sets_by = tbase.parse_sets(sets or [], techs)
    ranges_by = parse_ranges(ranges or [], techs)
    names = parse_params(params)
    protected = [base or store.root()]                  # nothing but references goes into the store
    if out is not None:
        R.check_out(Path(out), force, protected)
    if save_preset is not None:
        P.check_writable(save_preset, force, protected)
    for s_ in scenes:                                         # exit 3 before any frame is built
        check_memory(scene_spec(s_, resolution), {t: {**(pre.values.get(t, {}) if pre else {}), **sets_by.get(t, {})}
                                                  for t in techs})
    per_scene = prepare_scenes(scenes, resolution, base, frame=frame, frames=frames)
    prepared = [x for ps in per_scene for x in ps]
    sc, truth, meta, frame = prepared[0]
    more = [(f, t) for _, t, _, f in prepared[1:]]
    parts = [Part.of(s_, base) for s_, *_ in prepared]
    plans, skipped = {}, {}
    for t in techs:
        why = next((w for w in (tbase.get(t).unsupported(ps[0][0].spec) for ps in per_scene) if w), None) \
            if all_techniques else None
        if why:
            skipped[t] = why
            continue
        s = {**(pre.values.get(t, {}) if pre else {}), **sets_by.get(t, {})}
        try:
            plans[t] = plan(t, frame, params=names, method=method, loss=loss or default_loss(t), sets=s,
                            ranges=ranges_by.get(t))
        except InputError as e:
            if not all_techniques:
                raise
            skipped[t] = str(e).split(" (its parameters:")[0]
    if all_techniques and not plans:
        raise InputError("no technique has parameters to fit: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    results = {}
    for t, p in plans.items():
        if echo:
            echo(f"fitting {t}: {', '.join(f'{d.name} ({d.method})' for d in p.dims)} ...")
        try:
            results[t] = execute(p, frame, truth, budget, more, executor=executor, parts=parts)
        except ShadowlabError as e:               # e.g. a technique that cannot render this scene
            if not all_techniques:
                raise
            skipped[t] = str(e)
    if not results:
        raise InputError("no technique could be fitted: " + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    name = sc.name if len(scenes) == 1 else joint_name([ps[0][0].name for ps in per_scene])
    run = {"scene": name, "scene_arg": store.scene_arg(sc.spec),   # how a command names it: built-in name or path
           "resolution": list(sc.resolution), **({} if sc.frame is None else {"frame": sc.frame}),
           **({"frames": [s_.frame for s_, *_ in per_scene[0]]} if len(per_scene[0]) > 1 else {}),
           **({"scenes": [_scene_entry(ps, base) for ps in per_scene]} if len(scenes) > 1 else {}),
           **({"executor": executor.describe()} if executor is not None and executor.kind != "embedded" else {}),
           "mode": "all" if all_techniques else "one",
           "method": method, "loss": loss or ", ".join(sorted({p.loss for p in plans.values()})),
           "budget": budget.__dict__,
           "reference": {"path": str(_ref_path(sc, base)), "max_std_error": meta.get("max_std_error"),
                         "seed": meta.get("seed"), "supersampling": int(meta.get("supersampling", 1))},
           "preset_in": pre.info() if pre else None, "skipped": skipped, "techniques": results,
           "lights": [l.name for l in sc.lights],
           "truth_images": {"shaded": truth.shaded, "vis": {n: lt.V for n, lt in truth.lights.items()}}}
    pname = preset_name or (f"{name}-{technique}-fit" if not all_techniques else f"{name}-fit")
    run["preset"] = {"name": pname, "values": {t: r["preset_values"] for t, r in results.items()}}
    if out is not None:
        run["out"] = str(R.write(Path(out), run, force, protected))
    if save_preset is not None:
        P.save(save_preset, pname, run["preset"]["values"], P.FIT_DESCRIPTION, P.preset_meta(run), force=force,
               protected=protected)
        run["preset"]["path"] = str(save_preset)
    return run


def _scene_entry(prepared: list, base) -> dict:
    """One scene of a multi-scene fit, for fit.json: name, resolution, frames, its references."""
    sc = prepared[0][0]
    return {"name": sc.name, "scene": store.scene_arg(sc.spec), "resolution": list(sc.resolution),
            "frames": [s_.frame for s_, *_ in prepared],
            "references": [{"path": str(_ref_path(s_, base)), "max_std_error": m.get("max_std_error"),
                            "seed": m.get("seed")} for s_, _, m, _ in prepared]}


def _ref_path(sc, base):
    return store.path_for(sc.name, sc.resolution, base, frame=sc.frame)
