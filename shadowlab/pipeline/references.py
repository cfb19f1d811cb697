"""Making references: a scene's ground truth rendered and stored, per frame of a camera path, as
jobs that any executor runs (this process, a Dask cluster) with the same bits."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from .. import backend
from ..cluster import Embedded, Executor, run_id
from ..errors import InputError, Interrupted
from ..reference import sdf_truth, store, vacuous
from ..reference.truth import render_truth, target_missed
from ..render.frame import make_frame
from ..scene import load
from ..scene.spec import builtin_dir
from .args import check_reference_args, frame_list

__all__ = ["load_scene", "reference", "reference_frames", "ReferenceJob", "reference_jobs", "render_reference_job",
           "reference_batch"]


def _progress_bar(total_hint: int | None, desc: str, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total_hint, desc=desc, unit="ray", unit_scale=True, disable=not enabled, leave=False)


def load_scene(scene: str, resolution=None, frame: int | None = None):
    backend.init()
    sc = load(scene, resolution=resolution)
    return sc if frame is None else sc.at_frame(frame)


def reference(scene: str, resolution=None, *, force: bool = False, seed: int = 0, target_se: float = 0.005,
              strata: int = 8, max_rounds: int = 64, spp: int = 256, base: Path | None = None,
              progress: bool = True, ss: int = 1, frame: int | None = None) -> tuple[Path, dict]:
    """Render and store the ground truth of ``scene``; returns (path, meta).

    ``ss``: s×s sub-pixel shading points per pixel (G-buffer supersampling); techniques compared
    with this reference are evaluated at the same points. ``frame``: the camera path frame (None:
    the scene as loaded, frame 0 of a path). Numeric arguments are range-checked
    (InputError, exit 2) before anything is loaded."""
    return reference_frames(scene, resolution, frame=frame, force=force, seed=seed,
                            target_se=target_se, strata=strata, max_rounds=max_rounds, spp=spp, base=base,
                            progress=progress, ss=ss)[0][1:]


def reference_frames(scene: str, resolution=None, frames=None, *, frame: int | None = None, force: bool = False,
                     seed: int = 0, target_se: float = 0.005, strata: int = 8, max_rounds: int = 64, spp: int = 256,
                     base: Path | None = None, progress: bool = True, ss: int = 1) -> list[tuple]:
    """:func:`reference` for frame ``frame`` or each frame of ``frames`` (an (A, B) pair or "A:B",
    both ends included; neither: the scene as loaded), each stored separately under the same rules
    (its own lock, atomic save, ``force``), in this process. Returns [(frame, path, meta)]."""
    done = reference_batch([scene], resolution, frames, frame=frame, force=force, seed=seed, target_se=target_se,
                           strata=strata, max_rounds=max_rounds, spp=spp, base=base, progress=progress, ss=ss)
    return [(f, path, meta) for _, f, path, meta in done]


@dataclass(frozen=True)
class ReferenceJob:
    """One reference to render and store: what a worker needs, and nothing it cannot pickle."""

    scene: str
    resolution: tuple | None
    frame: int | None
    seed: int
    target_se: float
    strata: int
    max_rounds: int
    spp: int
    ss: int
    force: bool
    base: str
    run: str
    progress: bool = False
    dest: str = ""         # where it is stored (for the message of an interrupted batch)


def reference_jobs(scenes: list[str], resolution=None, frames=None, *, frame: int | None = None, force=False,
                   seed: int = 0, target_se: float = 0.005, strata: int = 8, max_rounds: int = 64, spp: int = 256,
                   base: Path | None = None, ss: int = 1, progress: bool = False) -> list[ReferenceJob]:
    """The jobs of a reference batch, every one checked before any is run: arguments in range,
    scenes that load, frames on each scene's path (``frames="all"``: every frame of each path; a
    scene without one has only the scene as loaded) and, without ``force``, no reference already
    stored at any destination (ReferenceError_, exit 2, naming it)."""
    check_reference_args(seed=seed, target_se=target_se, spp=spp, ss=ss, max_rounds=max_rounds)
    if not scenes:
        raise InputError("no scene given: name one or more scenes (`shadowlab scenes` lists the built-in ones), "
                         "or pass --all")
    run = run_id()
    root = str(Path(base) if base is not None else store.root(create=True))  # workers may not share our environment
    jobs, given = [], {}
    for scene in scenes:
        sc = load_scene(scene, resolution)
        if frames == "all":
            todo = list(range(sc.spec.frames)) if sc.spec.path is not None else [None]
        else:
            todo = frame_list(sc.spec, frame, frames) or [None]
        for f in todo:
            s_ = sc if f is None else sc.at_frame(f)
            dest = store.path_for(s_.name, s_.resolution, base, create=True, frame=s_.frame)
            if str(dest) in given:   # as fit and sweep: refused before any work, in process and on a cluster alike
                twice = "" if given[str(dest)] == scene else f" (as {given[str(dest)]} too)"
                raise InputError(f"scene {scene} is given twice{twice}: both are the reference at {dest}; name each "
                                 "scene once")
            given[str(dest)] = scene
            store.check_writable(dest, force, store.scene_arg(s_.spec), s_.resolution)
            jobs.append(ReferenceJob(scene, tuple(sc.resolution), f, seed, target_se, strata, max_rounds, spp, ss,
                                     force, root, run, progress, str(dest)))
    return jobs


def render_reference_job(job: ReferenceJob) -> tuple:
    """Render and store one reference (on whichever process runs it); (scene, frame, path, meta).

    Re-runnable: a job whose worker died after the save finds its own result (same run id in
    meta.json) and returns it instead of refusing the existing reference."""
    sc = load_scene(job.scene, job.resolution, job.frame)
    base = Path(job.base)
    dest = store.path_for(sc.name, sc.resolution, base, create=True, frame=sc.frame)
    with store.locked(dest):
        mine = store.stored_by_run(dest, job.run)
        if mine is not None:
            return sc.name, sc.frame, dest, mine
        with store.writing(dest, force=job.force, scene_name=store.scene_arg(sc.spec), resolution=sc.resolution):
            truth, meta = _render_reference(sc, seed=job.seed, target_se=job.target_se, strata=job.strata,
                                            max_rounds=job.max_rounds, spp=job.spp, progress=job.progress, ss=job.ss)
            _check_measures(sc, truth, meta)
            meta["run"] = job.run
            path = store.save(truth, meta, dest, force=job.force)
    return sc.name, sc.frame, path, meta


def _check_measures(sc, truth, meta: dict) -> None:
    """Refuse (exit 2, nothing stored) a truth that measures nothing (:mod:`shadowlab.reference.vacuous`:
    a blind camera, every light unreached or enclosed); record the lights that measure nothing in
    ``meta["vacuous"]`` (the command prints them, and every reader warns again)."""
    found = vacuous.of_truth(truth)
    cmd = store.reference_command(store.scene_arg(sc.spec), sc.resolution, sc.frame)
    vacuous.refuse_empty(found, [l.name for l in sc.lights], where=f"the reference of scene {sc.name!r}",
                         fix_tail=f"run `{cmd}` again (nothing was stored)")
    if found:
        meta["vacuous"] = {n: vacuous.WHY[why][0] for n, why in found.items()}


def reference_batch(scenes: list[str], resolution=None, frames=None, *, executor: Executor | None = None,
                    progress: bool = True, **options) -> list[tuple]:
    """References of several scenes and frames, one job each (:func:`reference_jobs`), on
    ``executor`` (default: this process). The results are the same bits whatever runs them:
    each job's seed is the batch's, and a job depends on nothing but its own fields.
    Returns [(scene, frame, path, meta)] in job order."""
    env = os.environ.get(store.ROOT_ENV)
    new_store = options.get("base") is None and env and not Path(env).is_dir()
    ex = executor or Embedded()
    jobs = reference_jobs(scenes, resolution, frames, progress=progress and isinstance(ex, Embedded), **options)
    if new_store:
        print(f"note: {store.ROOT_ENV}={env} did not exist; created a new reference store there", file=sys.stderr)
    try:
        return ex.map(render_reference_job, jobs, desc="references", progress=progress and not isinstance(ex, Embedded))
    except Interrupted as e:
        if len(jobs) > 1 and not e.detail:
            # a job a worker is running still saves when it ends: the store is read when the line is
            # printed, after the command has closed its executor (a local cluster's workers with it)
            remote = not isinstance(ex, Embedded) and getattr(ex, "cluster", None) is None
            e.detail = lambda: interrupted_detail(jobs, remote=remote)
        raise


def interrupted_detail(jobs: list[ReferenceJob], *, remote: bool = False) -> str:
    """What an interrupted batch left: which references its jobs had stored (their run id in
    meta.json) and which not (nothing partial of those: the store's saves are atomic). ``remote``:
    the jobs ran on a cluster shadowlab did not start, whose workers finish a job they had begun."""
    done = [j for j in jobs if j.dest and store.stored_by_run(Path(j.dest), j.run) is not None]
    rest = [j for j in jobs if j not in done]
    text = f"stored {len(done)} of {len(jobs)} references"
    if done:
        text += " (" + ", ".join(j.dest for j in done) + ")"
    if rest:
        text += "; not stored, each left as it was: " + ", ".join(j.dest or j.scene for j in rest)
        if remote:
            text += " (a job the cluster's workers had begun may still store its reference when it ends)"
    return text


def _render_reference(sc, *, seed, target_se, strata, max_rounds, spp, progress, ss):
    """(Truth, meta.json dict) of a loaded scene."""
    t0 = time.perf_counter()
    frame = make_frame(sc, ss=ss, seed=seed)
    with _progress_bar(None, f"truth {sc.name}", progress) as bar:
        if sc.kind == "sdf":  # SDF-only objects: Mitsuba cannot see them; the MC cone reference ([Bán 2019, §3.3.1])
            truth = sdf_truth.render_truth(frame, seed=seed, progress=bar.update)
        else:
            truth = render_truth(frame, k=strata, target_se=target_se, max_rounds=max_rounds, seed=seed, spp=spp,
                                 progress=bar.update)
    wall = time.perf_counter() - t0
    info = backend.machine_info()
    meta = {
        "scene": sc.name,
        "scene_hash": sc.spec.digest(),
        "resolution": list(sc.resolution),
        **({} if sc.frame is None else {"frame": sc.frame, "frames": sc.spec.frames}),
        "mitsuba": info["mitsuba"],
        "drjit": info["drjit"],
        "variant": info["variant"],
        "seed": seed,
        "supersampling": ss,
        "wall_time_s": wall,
        "max_std_error": truth.stats["max_std_error"],
        "samples": {
            "strata": f"{strata}x{strata} per round",
            "target_se": target_se,
            "max_rounds": max_rounds,
            "shadow_rays": truth.stats["shadow_rays"],
            "mean_rays_per_pixel": {
                n: float(l.samples[truth.mask].mean()) if truth.mask.any() else 0.0 for n, l in truth.lights.items()
            },
            "mitsuba_spp": spp,
        },
        "lights": [l.name for l in sc.lights],
        "stats": truth.stats,
        "machine": info,
    }
    meta.update(sc.mitsuba_notes())  # e.g. alpha-tested casters that mi.render's direct integrator ignores
    if sc.kind == "sdf":
        meta.update(truth=sdf_truth.TRUTH_KIND, not_mitsuba_truth=sdf_truth.NOTE)
        meta["samples"] = {"mc_cone_samples": truth.stats["mc_cone_samples"], "shadow_rays": truth.stats["shadow_rays"],
                           "mean_rays_per_pixel": meta["samples"]["mean_rays_per_pixel"], "mitsuba_spp": 0}
    if sc.kind != "sdf":
        meta["target_missed"] = target_missed(truth, target_se, max_rounds)
    if sc.spec.source and Path(sc.spec.source).resolve().parent != builtin_dir().resolve():
        meta["scene_file"] = str(Path(sc.spec.source).resolve())
    return truth, meta
