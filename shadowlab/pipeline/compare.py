"""Comparing techniques with the truth: one FrameContext per frame, each technique rendered on it,
its metrics, error bands and images gathered into a typed :class:`~shadowlab.report.run.Run`, and
a report per frame (plus, along a camera path, a technique × frame page with the shimmer)."""

from __future__ import annotations

import time
from pathlib import Path

import drjit as dr
import numpy as np

from .. import backend
from ..errors import ReferenceError_
from ..io.outdir import claim_dir
from ..metrics import compare_shaded, penumbra_mask, pooled_visibility
from ..metrics.bands import by_distance, by_label
from ..reference import store
from ..render.frame import make_frame
from ..render.shading import compose
from ..report import Reference, Run, RunImages, TechniqueRun, build
from ..report.frames import build_frames
from ..report.images import emitter_pixels
from ..report.lights import light_info
from ..techniques import base as tbase
from .args import check_memory, frame_list
from .references import load_scene, reference
from .shimmer import shimmer

__all__ = ["run_techniques", "technique_metrics", "error_bands", "compare"]


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
    check_memory(sc.spec, {n: overrides.get(n, {}) for n in techniques})      # exit 3 before any work
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
