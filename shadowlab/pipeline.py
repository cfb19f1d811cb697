"""The main jobs, as functions the CLI and tests call: make a reference, compare techniques.

    reference(scene)  : scene -> FrameContext -> ground truth -> references/<scene>/<W>x<H>/
    compare(scene, …) : scene -> FrameContext (once) -> each technique -> metrics -> report
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import drjit as dr
import numpy as np

from . import backend
from .errors import InputError, ReferenceError_
from .metrics import compare_shaded, penumbra_mask, pooled_visibility
from .reference import sdf_truth, store
from .reference.truth import SEED_MAX, render_truth, target_missed
from .render.frame import make_frame
from .render.shading import compose
from .report import build
from .report.images import cascade_colours
from .report.outdir import claim_dir
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


def load_scene(scene: str, resolution=None):
    backend.init()
    return load(scene, resolution=resolution)


def reference(scene: str, resolution=None, *, force: bool = False, seed: int = 0, target_se: float = 0.005,
              strata: int = 8, max_rounds: int = 64, spp: int = 256, base: Path | None = None,
              progress: bool = True, ss: int = 1) -> tuple[Path, dict]:
    """Render and store the ground truth of ``scene``; returns (path, meta).

    ``ss``: s×s sub-pixel shading points per pixel (G-buffer supersampling); techniques compared
    with this reference are evaluated at the same points. Numeric arguments are range-checked
    (InputError, exit 2) before anything is loaded."""
    check_reference_args(seed=seed, target_se=target_se, spp=spp, ss=ss, max_rounds=max_rounds)
    sc = load_scene(scene, resolution)
    if base is None and os.environ.get(store.ROOT_ENV) and not Path(os.environ[store.ROOT_ENV]).is_dir():
        print(f"note: {store.ROOT_ENV}={os.environ[store.ROOT_ENV]} does not exist; creating a new reference "
              "store there", file=sys.stderr)
    dest = store.path_for(sc.name, sc.resolution, base, create=True)
    with store.writing(dest, force=force, scene_name=sc.name, resolution=sc.resolution):
        truth, meta = _render_reference(sc, seed=seed, target_se=target_se, strata=strata, max_rounds=max_rounds,
                                        spp=spp, progress=progress, ss=ss)
        path = store.save(truth, meta, dest, force=force)
    return path, meta


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
    meta = {"scene": sc.name, "scene_hash": sc.spec.digest(), "resolution": list(sc.resolution),
            "mitsuba": info["mitsuba"], "drjit": info["drjit"], "variant": info["variant"], "seed": seed, "supersampling": ss,
            "wall_time_s": wall, "max_std_error": truth.stats["max_std_error"],
            "samples": {"strata": f"{strata}x{strata} per round", "target_se": target_se, "max_rounds": max_rounds,
                        "shadow_rays": truth.stats["shadow_rays"],
                        "mean_rays_per_pixel": {n: float(l.samples[truth.mask].mean()) if truth.mask.any() else 0.0
                                                for n, l in truth.lights.items()},
                        "mitsuba_spp": spp},
            "lights": [l.name for l in sc.lights], "stats": truth.stats, "machine": info}
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
    """(metrics, per_light, images) of one ShadowResult against the truth."""
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
    shaded = compose(frame, result.visibility)
    m = compare_shaded(shaded, truth.shaded, penumbra=pen, valid=mask)
    m.update(pooled)
    imgs = {"shaded": shaded, "vis": vis_imgs}
    cascades = {l.name: cascade_colours(result.aovs[f"{l.name}.cascade"], result.aovs.get(f"{l.name}.blend_weight"),
                                        lights[l.name][0]) / 255.0
                for l in frame.lights if f"{l.name}.cascade" in result.aovs}
    if cascades:                              # csm's cascade AOV, coloured as [Buljan 2020, Slika 4.3/4.5]
        imgs["cascade"] = cascades
    return m, per_light, imgs


def compare(scene: str, techniques: list[str], sets: list[str] | None = None, out: Path | None = None,
            resolution=None, *, render_missing: bool = False, progress: bool = True, base: Path | None = None,
            params: dict | None = None, preset: dict | None = None, force: bool = False) -> dict:
    """Compare ``techniques`` with the stored truth of ``scene``; write a report to ``out``.

    ``out`` is checked before anything is rendered: never inside the reference store, not an
    existing file, and an existing directory only if shadowlab made it or ``force``
    (:func:`shadowlab.report.outdir.claim_dir`).

    A missing reference is an error (exit 2) naming the ``shadowlab reference`` command that makes it,
    as is a stale or damaged one; ``render_missing=True`` renders and stores a missing one first.
    ``params``: {technique: {param: value}} applied under ``sets`` (e.g. a preset's values);
    ``preset``: {name, path, values} of that preset, recorded in the run (metrics.json, report).
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
    try:
        truth, meta = store.load(sc.spec, sc.resolution, base)
    except ReferenceError_ as e:
        if "no reference" not in str(e) or not render_missing:
            raise
        reference(scene, sc.resolution, base=base, progress=progress)
        truth, meta = store.load(sc.spec, sc.resolution, base)
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    results = run_techniques(frame, techniques, overrides)
    run = {"scene": sc.name, "resolution": list(sc.resolution),
           "reference": {"spp": float(np.mean(list(meta["samples"]["mean_rays_per_pixel"].values()))),
                         "rays_per_pixel": meta["samples"]["mean_rays_per_pixel"], "max_std_error": meta["max_std_error"],
                         "shadow_rays": meta["samples"]["shadow_rays"], "seed": meta.get("seed"),
                         "supersampling": int(meta.get("supersampling", 1)),
                         "path": str(store.path_for(sc.name, sc.resolution, base))},
           "lights": [l.name for l in sc.lights], "techniques": {},
           "images": {"truth": {"shaded": truth.shaded, "vis": {n: lt.V for n, lt in truth.lights.items()}},
                      "techniques": {}}, "machine": backend.machine_info()}
    if truth.mitsuba is not None:
        run["images"]["mitsuba"] = truth.mitsuba
    if preset is not None:
        run["preset"] = preset
    for n, (res, p, timing) in results.items():
        m, per_light, imgs = technique_metrics(frame, truth, res)
        run["techniques"][n] = {"params": p, **timing, "metrics": m, "per_light": per_light,
                                "stats": res.stats}
        run["images"]["techniques"][n] = imgs
    if out is not None:
        build(Path(out), run, force=force, protected=[store_root])
    return run
