"""The main jobs, as functions the CLI and tests call: make a reference, compare techniques.

    reference(scene)  : scene -> FrameContext -> ground truth -> references/<scene>/<W>x<H>/
    compare(scene, …) : scene -> FrameContext (once) -> each technique -> metrics -> report

A scene with a camera path has one truth per frame (``frame=`` / ``frames=``; the store keeps them
in ``<W>x<H>-f<NNNN>/``). ``compare(..., frames=(A, B))`` writes one report per frame and a
top-level page with a technique × frame table and the temporal stability (shimmer,
:mod:`shadowlab.metrics.temporal`) of every technique, measured at the first frame's G-buffer
points while each frame's light views follow that frame's camera (:func:`shimmer`).
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import numpy as np

from . import backend
from .cluster import Embedded, Executor, run_id
from .errors import InputError, ReferenceError_
from .metrics import compare_shaded, penumbra_mask, pooled_visibility
from .metrics.bands import by_distance, by_label
from .metrics.temporal import shimmer_per_light
from .reference import sdf_truth, store
from .reference.truth import SEED_MAX, render_truth, target_missed
from .render.frame import FrameContext, make_frame
from .render.gbuffer import vec_numpy
from .render.shading import compose
from .report import Reference, Run, RunImages, TechniqueRun, build
from .report.frames import build_frames
from .report.images import emitter_pixels
from .report.lights import light_info
from .io.outdir import claim_dir
from .scene import load
from .scene.spec import builtin_dir
from .techniques import base as tbase


def _progress_bar(total_hint: int | None, desc: str, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total_hint, desc=desc, unit="ray", unit_scale=True, disable=not enabled, leave=False)


def parse_resolution(text) -> tuple | None:
    """'128x96' or '128' -> (128, 96) / (128, 128); None stays None."""
    if text is None or text == "":
        return None
    if isinstance(text, (tuple, list)):
        return tuple(int(x) for x in text)
    t = str(text).lower().replace("×", "x")
    try:
        parts = [int(x) for x in t.split("x")] if "x" in t else [int(t)] * 2
    except ValueError:
        raise InputError(f"--resolution {text!r}: expected WIDTHxHEIGHT such as 128x128") from None
    if len(parts) != 2 or min(parts) < 1 or max(parts) > 8192:
        raise InputError(f"--resolution {text!r}: expected WIDTHxHEIGHT with sizes in 1..8192")
    return tuple(parts)


def check_reference_args(*, seed=0, target_se=0.005, spp=256, ss=1, max_rounds=64) -> None:
    """Refuse out-of-range options of ``shadowlab reference`` (a negative or NaN ``--target-se``
    was accepted once): InputError naming the option and its range."""
    def integer(opt, v, lo, hi):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= int(v) <= hi:
            raise InputError(f"{opt} {v!r}: expected an integer in [{lo}, {hi}]")
    if isinstance(target_se, bool) or not isinstance(target_se, (int, float)) or not math.isfinite(target_se) \
            or not 0 < target_se <= 0.5:
        raise InputError(f"--target-se {target_se!r}: expected a standard error in (0, 0.5] (visibility lies in "
                         "[0, 1]), e.g. 0.005")
    integer("--seed", seed, 0, SEED_MAX)
    integer("--spp", spp, 0, 1 << 20)
    integer("--ss", ss, 1, 8)
    integer("--max-rounds", max_rounds, 1, 1 << 16)


def parse_frames(text) -> tuple[int, int] | None:
    """``--frames A:B`` -> (A, B), both ends included (``0:3`` is frames 0, 1, 2 and 3); a
    (A, B) pair or None passes through. InputError (exit 2) for anything else."""
    if text is None or text == "":
        return None
    if isinstance(text, (tuple, list)):
        a, b = (int(x) for x in text)
    else:
        parts = str(text).split(":")
        try:
            if len(parts) != 2:
                raise ValueError
            a, b = int(parts[0]), int(parts[1])
        except ValueError:
            raise InputError(f"--frames {text!r}: expected A:B, two frame indices with A <= B (both included), "
                             "e.g. 0:3 for frames 0, 1, 2 and 3") from None
    if a < 0 or b < a:
        raise InputError(f"--frames {text!r}: expected A:B with 0 <= A <= B (both included), e.g. 0:3")
    return a, b


def frame_list(spec, frame: int | None = None, frames=None) -> list[int] | None:
    """The frames ``--frame N`` / ``--frames A:B`` select on a scene (None: neither was given),
    each checked against the scene's path (SceneError, exit 2, naming the valid range: 0..frames−1;
    a scene without a camera path has only frame 0)."""
    ab = parse_frames(frames)
    if frame is not None and ab is not None:
        raise InputError("--frame and --frames: give one of them (--frame N for one frame, --frames A:B for a range)")
    if frame is not None:
        return [spec.check_frame(frame)]
    if ab is None:
        return None
    spec.check_frame(ab[0])
    spec.check_frame(ab[1])
    return list(range(ab[0], ab[1] + 1))


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
    jobs = []
    for scene in scenes:
        sc = load_scene(scene, resolution)
        if frames == "all":
            todo = list(range(sc.spec.frames)) if sc.spec.path is not None else [None]
        else:
            todo = frame_list(sc.spec, frame, frames) or [None]
        for f in todo:
            s_ = sc if f is None else sc.at_frame(f)
            store.check_writable(
                store.path_for(s_.name, s_.resolution, base, create=True, frame=s_.frame), force, s_.name, s_.resolution
            )
            jobs.append(ReferenceJob(scene, tuple(sc.resolution), f, seed, target_se, strata, max_rounds, spp, ss,
                                     force, root, run, progress))
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
        with store.writing(dest, force=job.force, scene_name=sc.name, resolution=sc.resolution):
            truth, meta = _render_reference(sc, seed=job.seed, target_se=job.target_se, strata=job.strata,
                                            max_rounds=job.max_rounds, spp=job.spp, progress=job.progress, ss=job.ss)
            meta["run"] = job.run
            path = store.save(truth, meta, dest, force=job.force)
    return sc.name, sc.frame, path, meta


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
    return ex.map(render_reference_job, jobs, desc="references", progress=progress and not isinstance(ex, Embedded))


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


def run_techniques(frame, names: list[str], params: dict) -> dict:
    """Render each technique on ``frame``: a first run (builds the light views it needs and
    compiles its kernels) and a timed warm run. Returns {name: (ShadowResult, params, timing)}
    with timing = {"time_s": warm run, "first_run_s": first run}."""
    out = {}
    for n in names:
        t = tbase.get(n)
        p = t.resolve(params.get(n, {}))
        times = []
        for _ in range(2):
            dr.sync_thread()
            t0 = time.perf_counter()
            res = t.render(frame, p)
            dr.eval(*res.visibility.values())
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        out[n] = (res, p, {"time_s": times[1], "first_run_s": times[0]})
    return out


def technique_metrics(frame, truth, result) -> tuple[dict, dict, dict]:
    """(metrics, per_light, images) of one ShadowResult against the truth. ``images``: the shaded
    image, the visibility per light and, for a technique whose family declares ``panels``, the
    images its ``report_images`` builds from the AOVs, with those panels (what the report draws)."""
    mask = truth.mask
    vis_imgs, lights = {}, {}
    pen = np.zeros_like(mask)
    for l in frame.lights:
        v = frame.image(result.visibility[l.name])
        valid = mask & frame.lit_mask(l.name)
        tv = truth.lights[l.name].V
        # where the light does not reach, visibility does not matter: the report shows the truth there
        vis_imgs[l.name] = np.where(valid, v, tv)
        lights[l.name] = (v, tv, valid)
        pen |= penumbra_mask(tv, valid)
    per_light, pooled = pooled_visibility(lights)
    shaded = compose(frame, result.visibility, result.colour)
    m = compare_shaded(shaded, truth.shaded, penumbra=pen, valid=mask)
    m.update(pooled)
    imgs = {"shaded": shaded, "vis": vis_imgs}
    t = result.technique
    if t is not None and t.panels:            # the family's own report images, built from its AOVs
        extra = t.report_images(frame, result, mask, {ln: x[0] for ln, x in lights.items()})
        if extra:
            imgs.update(extra)
            imgs["panels"] = t.panels
    return m, per_light, imgs


def error_bands(frame, truth, result) -> dict:
    """Per light: the visibility error by distance band from the camera
    (:func:`shadowlab.metrics.bands.by_distance`) and, for each label AOV the technique declares
    (``Technique.band_aovs``), by label (:func:`~shadowlab.metrics.bands.by_label`):
    {light: {"distance": rows, <label AOV>: rows}}."""
    labels = result.technique.band_aovs if result.technique is not None else ()
    out = {}
    for l in frame.lights:
        v = frame.image(result.visibility[l.name])
        tv = truth.lights[l.name].V
        valid = truth.mask & frame.lit_mask(l.name)
        d = {"distance": by_distance(v, tv, truth.view_depth, valid)}
        for k in labels:
            if f"{l.name}.{k}" in result.aovs:
                d[k] = by_label(v, tv, result.aovs[f"{l.name}.{k}"], valid)
        out[l.name] = d
    return out


def _truth_of(sc, scene: str, base, render_missing: bool, progress: bool):
    """(truth, meta) of a loaded scene at its frame; renders a missing one if ``render_missing``."""
    try:
        return store.load(sc.spec, sc.resolution, base)
    except ReferenceError_ as e:
        if "no reference" not in str(e) or not render_missing:
            raise
        reference(scene, sc.resolution, base=base, progress=progress, frame=sc.frame)
        return store.load(sc.spec, sc.resolution, base)


def _compare_at(sc, scene, techniques, overrides, base, render_missing, progress, preset, loaded=None):
    """(run, frame, results) of one frame of a loaded scene (see :func:`compare`); ``loaded``: its
    (truth, meta), when the caller has read them already."""
    truth, meta = loaded or _truth_of(sc, scene, base, render_missing, progress)
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    results = run_techniques(frame, techniques, overrides)
    ref = Reference(
        spp=float(np.mean(list(meta["samples"]["mean_rays_per_pixel"].values()))),
        max_std_error=meta["max_std_error"],
        details={"rays_per_pixel": meta["samples"]["mean_rays_per_pixel"],
                 "shadow_rays": meta["samples"]["shadow_rays"],
                 "seed": meta.get("seed"),
                 "supersampling": int(meta.get("supersampling", 1)),
                 "path": str(store.path_for(sc.name, sc.resolution, base, frame=sc.frame))})
    techs, timgs = {}, {}
    for n, (res, p, timing) in results.items():
        m, per_light, timgs[n] = technique_metrics(frame, truth, res)
        techs[n] = TechniqueRun(p, timing["time_s"], m, per_light, first_run_s=timing["first_run_s"],
                                stats=res.stats, bands=error_bands(frame, truth, res), name=n)
    lights = [l.name for l in sc.lights]
    images = RunImages.checked({
        "truth": {"shaded": truth.shaded, "vis": {n: lt.V for n, lt in truth.lights.items()}},
        "techniques": timgs, "mitsuba": truth.mitsuba,
        # an SDF G-buffer's shape ids index SDF primitives, not Mitsuba shapes
        "emitter": emitter_pixels(frame.gbuffer.shape_id, sc.light_shapes) if sc.kind == "mitsuba" else None,
    }, (sc.resolution[1], sc.resolution[0]), lights, techs)
    extras = {"machine": backend.machine_info()}
    if sc.frame is not None:
        extras["frame"] = sc.frame
    if preset is not None:
        extras["preset"] = preset
    run = Run(sc.name, sc.resolution, ref, lights, techs, images, light_info(sc.spec.lights), extras)
    return run, frame, results


def shimmer(scenes: list, fixed, results: dict, techniques: dict | None = None) -> dict:
    """Temporal stability of each technique along ``scenes`` (the loaded scene at each frame of a
    path, in order): visibility at ``fixed``'s G-buffer points (the FrameContext of the first
    frame) with each frame's light views, which read that frame's camera:
    ``FrameContext(scene=scene_t, gbuffer=fixed.gbuffer, unshadowed=fixed.unshadowed, sdf=fixed.sdf)``.
    ``results``: {technique: (ShadowResult on ``fixed``, params, ...)}; the first frame's
    visibility is that result. Points counted: valid and lit by the light (U_L > 0).
    ``techniques``: {name: Technique} for names not in the registry (default: the registry).

    Returns {"techniques": {name: {"pooled": {...}, "per_light": {...}}}, "truth": {...}, "frames": [...]}
    (:func:`shadowlab.metrics.temporal.shimmer_per_light`). The truth's own shimmer is measured from
    what the truth at a fixed point depends on, the lights and the shapes: when they are the same
    in every frame (the scene format moves only the camera), V_t(x) = V_{t−1}(x) and it is 0
    exactly, which ``truth["why"]`` says; otherwise it is not measured (``None``)."""
    out = {"frames": [s.frame for s in scenes], "points": "G-buffer points of frame "
           f"{scenes[0].frame} (valid and lit by the light)", "techniques": {}}
    gvalid = np.asarray(fixed.gbuffer.valid.numpy(), bool).reshape(-1)
    valid = {l.name: gvalid & (vec_numpy(fixed.unshadowed[l.name]).sum(1) > 0) for l in fixed.lights}
    for n, (res0, p, *_rest) in results.items():
        t = (techniques or {}).get(n) or tbase.get(n)
        V = {l.name: [np.asarray(res0.visibility[l.name].numpy(), np.float64).reshape(-1)] for l in fixed.lights}
        for sc_t in scenes[1:]:
            ctx = FrameContext(scene=sc_t, gbuffer=fixed.gbuffer, unshadowed=fixed.unshadowed, sdf=fixed.sdf)
            r = t.render(ctx, p)
            dr.eval(*r.visibility.values())
            for l in fixed.lights:
                V[l.name].append(np.asarray(r.visibility[l.name].numpy(), np.float64).reshape(-1))
        per, pooled = shimmer_per_light({k: (np.stack(v), valid[k]) for k, v in V.items()})
        out["techniques"][n] = {"pooled": pooled, "per_light": per}
    s0 = scenes[0].spec
    static = all(s.spec.lights == s0.lights and s.spec.shapes == s0.shapes and s.spec.sdf == s0.sdf for s in scenes)
    if static:
        zero = {"mean": 0.0, "p99": 0.0, "max": 0.0}
        out["truth"] = {"pooled": dict(zero), "per_light": {l.name: dict(zero) for l in fixed.lights},
                        "why": "0 exactly: the truth at a fixed world point depends only on the lights and the shapes, "
                               "which are the same in every frame of the path (only the camera moves)"}
    else:  # pragma: no cover - the scene format cannot move lights or shapes along a path
        out["truth"] = {"pooled": None, "per_light": None,
                        "why": "not measured: lights or shapes differ between frames"}
    return out


def compare(scene: str, techniques: list[str], sets: list[str] | None = None, out: Path | None = None,
            resolution=None, *, render_missing: bool = False, progress: bool = True, base: Path | None = None,
            params: dict | None = None, preset: dict | None = None, force: bool = False,
            frame: int | None = None, frames=None) -> dict:
    """Compare ``techniques`` with the stored truth of ``scene``; write a report to ``out``.

    ``out`` is checked before anything is rendered: never inside the reference store, not an
    existing file, and an existing directory only if shadowlab made it or ``force``
    (:func:`shadowlab.io.outdir.claim_dir`).

    A missing reference is an error (exit 2) naming the ``shadowlab reference`` command that makes it,
    as is a stale or damaged one; ``render_missing=True`` renders and stores a missing one first.
    ``params``: {technique: {param: value}} applied under ``sets`` (e.g. a preset's values);
    ``preset``: {name, path, values} of that preset, recorded in the run (metrics.json, report).
    ``frame``: compare at that frame of the camera path. ``frames``: (A, B) or "A:B", both ends
    included: one report per frame in ``out/frame_<NNNN>/`` and a top-level index.html,
    summary.md and metrics.json with a technique × frame table and, with two frames or more, the
    shimmer of each technique (:func:`shimmer`); returns that top-level summary.
    """
    store_root = base or store.root()
    if out is not None:
        claim_dir(Path(out), "compare", force=force, protected=[store_root])
    for n in techniques:
        tbase.get(n)  # unknown names fail before any rendering
    overrides = tbase.parse_sets(sets or [], techniques)
    for n, p in (params or {}).items():
        if n in overrides:
            overrides[n] = {**p, **overrides[n]}
    sc = load_scene(scene, resolution)
    sel = frame_list(sc.spec, frame, frames)
    if frames is None:
        if sel:
            sc = sc.at_frame(sel[0])
        run, _, _ = _compare_at(sc, scene, techniques, overrides, base, render_missing, progress, preset)
        if out is not None:
            build(Path(out), run, force=force, protected=[store_root])
        return run
    scenes = [sc.at_frame(f) for f in sel]
    # every frame's truth is read (and checked) before anything is rendered or written
    truths = {} if render_missing else {s_.frame: store.load(s_.spec, s_.resolution, base) for s_ in scenes}
    runs, fixed, first = [], None, None
    for s_ in scenes:
        run, fr, results = _compare_at(s_, scene, techniques, overrides, base, render_missing, progress, preset,
                                       truths.get(s_.frame))
        runs.append(run)
        if fixed is None:
            fixed, first = fr, results
        if out is not None:
            build(Path(out) / f"frame_{s_.frame:04d}", run, force=force, protected=[store_root])
    summary = {
        "scene": sc.name,
        "resolution": list(sc.resolution),
        "frames": sel,
        "techniques": list(techniques),
        "lights": [l.name for l in sc.lights],
        "per_frame": {
            str(r.extras.get("frame", 0)): {
                n: {"metrics": t.metrics, "time_s": t.time_s} for n, t in r.techniques.items()
            }
            for r in runs
        },
        "reports": {str(f): f"frame_{f:04d}/index.html" for f in sel} if out is not None else {},
        "params": {n: runs[0].techniques[n].params for n in techniques},
    }
    if len(scenes) >= 2:
        summary["shimmer"] = shimmer(scenes, fixed, first)
    if out is not None:
        build_frames(Path(out), summary, force=force, protected=[store_root])
    summary["runs"] = runs
    return summary
