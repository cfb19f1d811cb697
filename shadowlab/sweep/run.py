"""``shadowlab sweep``: every metric of one technique against one parameter, per scene.

    sweep(scenes, technique, "NAME=LO:HI:N", executor=...)
        -> a job per (scene, value) (:class:`~shadowlab.sweep.points.SweepPoint`), all checked first
        -> executor.map(evaluate_point, jobs)   (this process, or Dask workers [Dask 2024, "Futures"])
        -> sweep.json, summary.md, index.html (:mod:`shadowlab.sweep.report`)

Everything is checked before any job runs: the output directory, the technique, the parameter
range, the ``--set`` values, that the technique renders each scene, and that each scene has its
stored truth at the resolution and frame (a missing one names the ``shadowlab reference``
command). A job depends only on its own fields (the truth's seed, the parameters), so the
metrics are the same bits whatever the number of workers; run times are kept apart from them.
"""

from __future__ import annotations

import re

from contextlib import nullcontext
from pathlib import Path

from ..cluster import Executor, open_executor
from ..cluster.executor import check_address, check_workers
from ..errors import InputError
from ..pipeline import check_memory, frame_list, load_scene
from ..reference import store
from ..report.tables import higher_is_better
from ..io.outdir import claim_dir
from ..techniques import base as tbase
from .points import SweepPoint, evaluate_point, parse_range, remember
from .report import OUTPUT_FILES, write_report

__all__ = ["sweep", "sweep_jobs", "best_points", "default_out", "results_only"]


def default_out(technique: str, param_text: str) -> Path:
    """``reports/sweep/<technique>-<param>``."""
    name = str(param_text).split("=", 1)[0].strip().split(".")[-1] or "param"
    return Path("reports") / "sweep" / re.sub(r"[^A-Za-z0-9_.+-]+", "_", f"{technique}-{name}")


def _scene_arg(scene: str) -> str:
    """A scene file as an absolute path (a worker may run elsewhere in the tree); a name as it is."""
    p = Path(scene)
    return str(p.resolve()) if p.suffix == ".toml" and p.is_file() else scene


def sweep_jobs(scenes, technique: str, param: str, sets=None, resolution=None, frame: int | None = None,
               base: Path | None = None):
    """(ParamRange, fixed params, {scene name: info}, jobs): the sweep's jobs, every one checked
    before any runs (see the module docstring)."""
    if not scenes:
        raise InputError("no scene given: name one or more scenes (`shadowlab scenes` lists the built-in ones)")
    t = tbase.get(technique)
    rng = parse_range(param, technique)
    overrides = tbase.parse_sets(sets or [], [technique])[technique]
    if rng.param.name in overrides:
        raise InputError(f"--set {technique}.{rng.param.name}=… and --param {rng.param.name}=…: the swept parameter "
                         "takes the values of --param; leave it out of --set")
    fixed = t.resolve(overrides)
    root = Path(base) if base is not None else store.root()
    infos, jobs = {}, []
    for scene in scenes:
        sc = load_scene(scene, resolution)
        sel = frame_list(sc.spec, frame)
        if sel:
            sc = sc.at_frame(sel[0])
        if sc.name in infos:
            raise InputError(f"scene {sc.name!r} is given twice; name each scene once")
        why = t.unsupported(sc.spec)
        if why:
            raise InputError(f"{technique} cannot render scene {sc.name!r}: {why}; sweep it on another scene")
        for v in rng.values:                                  # exit 3 before any point runs
            check_memory(sc.spec, {technique: {**overrides, rng.param.name: v}})
        # missing, stale, damaged: exit 2, `shadowlab reference …`
        truth, meta = store.load(sc.spec, sc.resolution, root)
        infos[sc.name] = {"scene": scene, "resolution": list(sc.resolution), "frame": sc.frame,
                          "reference": str(store.path_for(sc.name, sc.resolution, root, frame=sc.frame)),
                          "lights": [l.name for l in sc.lights]}
        for v in rng.values:
            params = tuple(sorted({**overrides, rng.param.name: v}.items()))
            jobs.append(SweepPoint(technique, _scene_arg(scene), tuple(sc.resolution), sc.frame, params,
                                   sc.spec.digest(), str(root), len(jobs), meta.get(store.CHECKSUM_KEY)))
        remember(jobs[-1], sc, truth, meta)      # points run in this process reuse what was just read
    return rng, fixed, infos, jobs


def best_points(points: list, values, metrics) -> dict:
    """{metric: {"index", "value" (of the parameter), "metric"}}: the best point of each metric
    (highest for psnr / ssim, lowest for the others; the first of equal ones); metrics without a
    value at any point are left out."""
    out = {}
    for m in metrics:
        cand = [(i, pt["metrics"].get(m)) for i, pt in enumerate(points) if pt["metrics"].get(m) is not None]
        if not cand:
            continue
        hib = higher_is_better(m)
        i, v = max(cand, key=lambda c: (c[1], -c[0])) if hib else min(cand, key=lambda c: (c[1], c[0]))
        out[m] = {"index": i, "value": values[i], "metric": v}
    return out


def sweep(scenes, technique: str, param: str, *, sets=None, resolution=None, frame: int | None = None,
          out: Path | None = None, force: bool = False, executor: Executor | None = None, workers: int | None = None,
          scheduler: str | None = None, progress: bool = False, base: Path | None = None) -> dict:
    """Sweep ``technique``'s parameter ``param`` (``NAME=LO:HI:N``) on ``scenes``; the other
    parameters are the defaults updated by ``sets`` (``TECHNIQUE.PARAM=VALUE``). Runs the points
    on ``executor`` or, without one, on the executor of ``workers`` / ``scheduler``
    (:func:`shadowlab.cluster.open_executor`, opened only once every job has been checked; neither:
    this process) and, with ``out``, writes the report there. Returns the sweep's record (what
    ``sweep.json`` holds)."""
    check_workers(workers)
    if scheduler:
        check_address(scheduler)
    root = Path(base) if base is not None else store.root()
    if out is not None:
        claim_dir(Path(out), "sweep", force=force, protected=[root], files=OUTPUT_FILES)
    rng, fixed, infos, jobs = sweep_jobs(scenes, technique, param, sets, resolution, frame, root)
    desc = f"sweep {technique}.{rng.param.name}"
    with nullcontext(executor) if executor is not None else open_executor(workers, scheduler) as ex:
        results = ex.map(evaluate_point, jobs, desc=desc, progress=progress)
    n = len(rng.values)
    record = {"technique": technique, "param": rng.describe(),
              "fixed": {k: v for k, v in fixed.items() if k != rng.param.name},
              "executor": ex.describe(), "metrics": [], "scenes": {}}
    for si, (name, info) in enumerate(infos.items()):
        pts = []
        for j, v in enumerate(rng.values):
            r = results[si * n + j]
            pts.append({"value": v, "metrics": r["metrics"], "per_light": r["per_light"], "timing": r["timing"]})
            for m in r["metrics"]:
                if m not in record["metrics"]:
                    record["metrics"].append(m)
        record["scenes"][name] = {**info, "points": pts}
    for s in record["scenes"].values():
        s["best"] = best_points(s["points"], rng.values, record["metrics"])
    if out is not None:
        record["report"] = str(write_report(Path(out), record, force=force, protected=[root]))
    return record


def results_only(record: dict) -> dict:
    """The part of a sweep's record that must be the same bits whatever ran it: per scene, per
    point, the parameter value, the metrics and the per-light metrics (no timing, no executor)."""
    return {name: [{"value": p["value"], "metrics": p["metrics"], "per_light": p["per_light"]} for p in s["points"]]
            for name, s in record["scenes"].items()}
