"""``shadowlab bench --only sdf``: the single-ray soft-shadow measurements of [Bán 2019, ch. 6].

Measured in one run (never asserted in tests), written to ``OUT/sdf.json`` and ``OUT/sdf.md``:

* **variants** ([Bán 2019, Tables 6.1–6.3]): the shadow pass of ``base``, ``linear``, ``discrete`` and
  ``convex``, directions A and B, ε ∈ {1/10, 1/20, 1/30, 1/256}, on ``sdf_simple``,
  ``sdf_composite`` and ``mandelbulb``: warm time (median of repeats after ``dr.sync_thread()``),
  SDF evaluations per shaded point (machine-independent), the fraction of points stopped by
  ``i_max``, and the time ratio base / linear (the thesis: linear ≈ 2–3× faster). The shadow
  pass is the cone set-up, the march and the final τ, evaluated; it excludes the G-buffer, which
  every variant shares. Baselines in the same table: ``sdf_hard`` (one sphere trace toward the
  light) and ``sdf_quilez``. Penumbra RMSE against the scene's stored 128² truth (V; the
  mandelbulb's is the Monte-Carlo cone reference) for each configuration.
* **error vs ε and light radius** ([Bán 2019, §6.3, Fig. 6.10]): ``sdf_composite`` with its light's
  radius set to 0.25, 0.5, 1, 2, 4 (a Mitsuba truth rendered per radius), ``linear``, direction
  A, ε = 1/2 … 1/256: time and penumbra RMSE per (radius, ε), and per radius the largest ε with
  no visible gain, by two criteria: (a) the image differs from the ε = 1/256 image by at most
  two 8-bit levels (2/255) at 99 % of the soft-shadow pixels (banding, Figs. 6.12/6.14, is gone);
  (b) its penumbra RMSE against the truth is within 0.5/255 of the ε = 1/256 RMSE. The thesis
  found 1/16, 1/16, 1/32, 1/32, 1/64 for radii 0.25 … 4.
"""

from __future__ import annotations

import datetime
from dataclasses import replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from ..errors import ReferenceError_
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..reference import sdf_truth, store
from ..reference.truth import render_truth
from ..render.frame import make_frame
from ..scene import build, load
from ..scene.lights import light_sphere
from ..scene.spec import load_spec, resolve
from ..sdf import soft
from ..techniques import get
from ..techniques.sdf_shadows import SURFACE_RADIUS, surface_points
from .timing import machine_text, warm_median

VARIANTS = ("base", "linear", "discrete", "convex")
DIRECTIONS = ("A", "B")
EPSILONS = (1 / 10, 1 / 20, 1 / 30, 1 / 256)
SCENES = ("sdf_simple", "sdf_composite", "mandelbulb")
RADII = (0.25, 0.5, 1.0, 2.0, 4.0)
CURVE_EPS = (1 / 2, 1 / 4, 1 / 8, 1 / 16, 1 / 32, 1 / 64, 1 / 128, 1 / 256)
I_MAX = 8192


def _frac(e: float) -> str:
    return f"1/{round(1 / e)}"


def _truth(name, res, light_radius=None):
    """(frame, truth V image, penumbra mask) of ``name`` at res²: the stored reference when it
    matches (and no radius is overridden), else a fresh one (Mitsuba; the MC cone reference for
    SDF-only scenes), not stored."""
    spec = load_spec(resolve(name)).with_resolution(res, res)
    if light_radius is not None:
        spec = replace(spec, lights=tuple(replace(l, radius=float(light_radius)) for l in spec.lights))
    sc = build(spec)
    frame = make_frame(sc)
    truth = None
    if light_radius is None:
        try:
            truth, _ = store.load(sc.spec, sc.resolution)
        except ReferenceError_:
            truth = None
    if truth is None:
        if sc.kind == "sdf":
            truth = sdf_truth.render_truth(frame)
        else:
            truth = render_truth(frame, spp=0)
    L = sc.spec.lights[0].name
    V = truth.lights[L].V
    m = truth.mask & frame.lit_mask(L)
    return frame, V, m, m & (V > 0.02) & (V < 0.98)


def _pass(frame, variant, direction, eps, i_max=I_MAX, scale=1.0):
    """The shadow pass of one configuration; returns (visibility image, SDF evaluations, stopped)."""
    light = frame.lights[0]
    o, R0 = surface_points(frame, SURFACE_RADIUS.default)
    c, R = light_sphere(frame.scene, light)
    cone = soft.make_cone(o, R0, c, dr.opaque(mi.Float, R * scale), direction, bbox=soft.bounds(frame.sdf))
    m = soft.march(frame.sdf, cone, variant, eps=eps, i_max=i_max)
    dr.eval(m.visibility, m.iterations)
    return m


def _timed(fn, repeats):
    """Median warm time of ``fn`` (one untimed call compiles)."""
    return warm_median(fn, repeats, warmup=1)


def _stats(frame, m, V, mask, pen):
    vis = frame.image(m.visibility)
    its = m.iterations.numpy()[frame.gbuffer.valid.numpy()]
    e = (vis - V)[pen]
    return vis, {"evals_per_point": float(its.mean()), "at_i_max": float((its >= I_MAX).mean()),
                 "rmse_penumbra": float(np.sqrt(np.mean(e * e))) if pen.any() else float("nan"),
                 "bias_penumbra": float(e.mean()) if pen.any() else float("nan")}


def bench_variants(res=256, err_res=128, repeats=5, scenes=SCENES, epsilons=EPSILONS):
    out = {}
    for name in scenes:
        fr_t = make_frame(load(name, resolution=(res, res)))
        fr_e, V, mask, pen = _truth(name, err_res)
        rows = {}
        for tname in ("sdf_hard", "sdf_quilez"):
            t = get(tname)
            r, ts = _timed(lambda: _eval(t.render(fr_t, {"i_max": I_MAX})), repeats)
            ve = fr_e.image(t.render(fr_e, {"i_max": I_MAX}).visibility[fr_e.lights[0].name])
            e = (ve - V)[pen]
            rows[tname] = {"time_ms": 1e3 * ts, "evals_per_point": r.stats["sdf_evals_per_point"]["all"],
                           "rmse_penumbra": float(np.sqrt(np.mean(e * e)))}
        table = {}
        for eps in epsilons:
            for d in DIRECTIONS:
                for v in VARIANTS:
                    m, ts = _timed(lambda: _pass(fr_t, v, d, eps), repeats)
                    its = m.iterations.numpy()[fr_t.gbuffer.valid.numpy()]
                    _, st = _stats(fr_e, _pass(fr_e, v, d, eps), V, mask, pen)
                    table[f"{_frac(eps)}|{d}|{v}"] = {"eps": eps, "direction": d, "variant": v, "time_ms": 1e3 * ts,
                                                      "evals_per_point_timed": float(its.mean()),
                                                      "at_i_max_timed": float((its >= I_MAX).mean()), **st}
        out[name] = {"resolution": [res, res], "error_resolution": [err_res, err_res], "baselines": rows,
                     "table": table, "penumbra_pixels": int(pen.sum())}
    return out


def _eval(r):
    dr.eval(*r.visibility.values())
    return r


def bench_radius_curve(scene="sdf_composite", res=128, radii=RADII, epsilons=CURVE_EPS, repeats=3):
    curve = {}
    for R in radii:
        frame, V, mask, pen = _truth(scene, res, light_radius=R)
        ref = band = None
        rows = {}
        for eps in sorted(epsilons):              # smallest ε first: the reference image
            m, ts = _timed(lambda: _pass(frame, "linear", "A", eps), repeats)
            vis, st = _stats(frame, m, V, mask, pen)
            if ref is None:
                ref = vis
                band = mask & (((ref > 0.02) & (ref < 0.98)) | pen)   # where the shadow is soft
            diff = np.abs(vis - ref)[band]
            rows[_frac(eps)] = {"eps": eps, "time_ms": 1e3 * ts, **st,
                                "diff_to_finest_p99": float(np.quantile(diff, 0.99)) if diff.size else 0.0,
                                "diff_to_finest_max": float(diff.max()) if diff.size else 0.0}
        fin = rows[_frac(min(epsilons))]
        no_band = [r["eps"] for r in rows.values() if r["diff_to_finest_p99"] <= 2 / 255]
        no_gain = [r["eps"] for r in rows.values() if r["rmse_penumbra"] <= fin["rmse_penumbra"] + 0.5 / 255]
        curve[str(R)] = {"radius": R, "penumbra_pixels": int(pen.sum()), "by_eps": rows,
                         "largest_eps_no_visible_change": max(no_band), "largest_eps_no_error_gain": max(no_gain)}
    return {"scene": scene, "resolution": [res, res], "variant": "linear", "direction": "A", "curve": curve}


def _markdown(res: dict) -> str:
    m = res["machine"]
    L = [
        f"# shadowlab bench: SDF soft shadows ({res['date']})",
        "",
        f"Machine: {machine_text(m)}. All figures from one run; i_max = {I_MAX} (no march stops early unless noted).",
        "",
    ]
    for name, d in res["variants"].items():
        W = d["resolution"][0]
        L += [
            f"## {name}: shadow pass, {W}×{W} ([Bán 2019, Tables 6.1–6.3])",
            "",
            "Each cell: warm time of the shadow pass in ms (SDF evaluations per point) · penumbra RMSE against the "
            f"{d['error_resolution'][0]}² truth ({d['penumbra_pixels']} penumbra pixels). Fastest per row in bold.",
            "",
            "| ε | D | base | linear | discrete | convex | base / linear |",
            "|---|---|---|---|---|---|---|",
        ]
        tab = d["table"]
        for eps in sorted({r["eps"] for r in tab.values()}, reverse=True):
            for D in DIRECTIONS:
                cells = [tab[f"{_frac(eps)}|{D}|{v}"] for v in VARIANTS]
                best = min(c["time_ms"] for c in cells)
                txt = [(f"**{c['time_ms']:.1f}**" if c["time_ms"] == best else f"{c['time_ms']:.1f}")
                       + f" ({c['evals_per_point_timed']:.0f}) · {c['rmse_penumbra']:.4f}" for c in cells]
                L.append(
                    f"| {_frac(eps)} | {D} | "
                    + " | ".join(txt)
                    + f" | {cells[0]['time_ms'] / cells[1]['time_ms']:.2f}× |"
                )
        b = d["baselines"]
        L += ["", "Baselines: " + ", ".join(f"{k} {v['time_ms']:.1f} ms ({v['evals_per_point']:.0f} evaluations, "
                                             f"penumbra RMSE {v['rmse_penumbra']:.4f})" for k, v in b.items()), ""]
    rc = res["radius_curve"]
    eps_list = sorted({r["eps"] for c in rc["curve"].values() for r in c["by_eps"].values()}, reverse=True)
    L += [f"## Error and time vs ε and light radius ({rc['scene']}, {rc['resolution'][0]}², linear, direction A; "
          "[Bán 2019, §6.3, Fig. 6.10])", "",
          "Penumbra RMSE against a Mitsuba truth rendered per radius · warm time (ms).", "",
          "| radius | penumbra px | " + " | ".join(_frac(e) for e in eps_list) + " | largest ε: no visible change | "
          "largest ε: no error gain | thesis |", "|---|---|" + "---|" * (len(eps_list) + 3)]
    thesis = {0.25: "1/16", 0.5: "1/16", 1.0: "1/32", 2.0: "1/32", 4.0: "1/64"}
    for c in rc["curve"].values():
        cells = [
            f"{c['by_eps'][_frac(e)]['rmse_penumbra']:.4f} · {c['by_eps'][_frac(e)]['time_ms']:.1f}" for e in eps_list
        ]
        L.append(f"| {c['radius']:g} | {c['penumbra_pixels']} | " + " | ".join(cells) +
                 f" | {_frac(c['largest_eps_no_visible_change'])} | {_frac(c['largest_eps_no_error_gain'])} | "
                 f"{thesis.get(c['radius'], '')} |")
    L += [
        "",
        f"No visible change: the image is within 2/255 of the ε = {_frac(min(eps_list))} image at 99 % of the "
        f"pixels where either that image or the truth is soft (0.02 < V < 0.98); the largest difference anywhere is "
        f"about ε/2 (the march's guarantee). No error gain: penumbra RMSE within 0.5/255 of the ε = "
        f"{_frac(min(eps_list))} RMSE.",
    ]
    return "\n".join(L) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Run the SDF benchmarks; write ``out/sdf.json`` and ``out/sdf.md``; return the .md path."""
    backend.init()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick, "i_max": I_MAX}
    if quick:
        res["variants"] = bench_variants(res=64, err_res=64, repeats=1, scenes=("sdf_simple",),
                                         epsilons=(1 / 10, 1 / 30))
        res["radius_curve"] = bench_radius_curve(res=48, radii=(0.5, 2.0), epsilons=(1 / 4, 1 / 16, 1 / 64), repeats=1)
    else:
        res["variants"] = bench_variants()
        res["radius_curve"] = bench_radius_curve()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "sdf.json", res)
    return write_bytes_atomic(out / "sdf.md", _markdown(res).encode())
