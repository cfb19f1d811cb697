"""Cascaded shadow maps measured ([Buljan 2020, §2.5, ch. 4]): ``shadowlab bench --only cascades``
(``cascades.json`` / ``cascades.md``; the full ``shadowlab bench`` writes them too).

On the built-in ``street`` scene, every figure from one run:

* **cost** beside the source's FPS table (1920×1080, three 1024² cascades, [Buljan 2020, §4.5]):
  map size 512 / 1024 / 2048 (158 / 146 / 103 FPS), PCF kernel 1 / 3 / 5 / 7 (146 / 121 / 86 /
  61), blending (146 → 137) and map-based selection (146 → 143), as ratios to the base
  configuration (1024², kernel 1, interval selection, no blending). A frame's time is the shadow
  pass (casting the cascades' maps) plus the lookup (the technique's render with the maps
  cached), each the median of warm runs; the source's FPS includes its shadow pass too;
* **quality at equal total texels** against the truth: the number of cascades (1 … 6) and the
  split λ (0 … 1) with T = 3·1024² texels shared by the cascades, and ``csm`` against one
  scene-fitted map (``pcf``) of the same T;
* **temporal stability** along ``boulevard``'s camera path: the shimmer of the sphere and box fits,
  with and without whole-texel snapping, beside one scene-fitted map and the truth's own;
* **error against texels**: a resolution sweep per cascade ([Buljan 2020, §2.5]: 512 … 8192; the
  sizes this run reached are listed), with the error by distance band from the camera
  (:func:`shadowlab.metrics.bands.by_distance`) and per cascade (:func:`~shadowlab.metrics.bands.by_label`).

The truth of the quality sections is rendered for the run into a temporary store (``--quick``:
the committed CI reference).
"""

from __future__ import annotations

import datetime
import math
import tempfile
from pathlib import Path

import numpy as np

from .. import backend
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..metrics.bands import by_distance, by_label
from ..pipeline import load_scene, reference, shimmer, technique_metrics
from ..reference import store
from ..render import memory
from ..render.frame import make_frame
from ..techniques import base
from .timing import machine_text, render_evaluated, timed, timed_kernels

SCENE = "street"
PATH_SCENE = "boulevard"
#: the fits compared for temporal stability: (label, csm parameters)
SHIMMER_CONFIGS = (("sphere fit, snapped (stable CSM)", {"fit": "sphere", "snap": True}),
                   ("sphere fit, not snapped", {"fit": "sphere", "snap": False}),
                   ("box fit, snapped", {"fit": "box", "snap": True}),
                   ("box fit, not snapped", {"fit": "box", "snap": False}),
                   ("one scene-fitted map (fit = scene, 1 cascade)", {"fit": "scene", "cascades": 1}))
LIGHT = "sun"
#: [Buljan 2020, §4.5]: FPS at 1920×1080, three cascades (1024² unless varied, PCF kernel 1)
SOURCE_FPS = {"map_size": {512: 158, 1024: 146, 2048: 103}, "kernel": {1: 146, 3: 121, 5: 86, 7: 61},
              "blend": {"off": 146, "on": 137}, "selection": {"interval": 146, "map": 143}}
BASE = {"cascades": 3, "resolution": 1024, "filter": "pcf", "pcf_kernel": 1, "pcf_pattern": "grid",
        "selection": "interval", "blend": 0.0}
def frame_time(frame, params: dict, repeats: int = 3, lookups: int = 7) -> dict:
    """Median seconds of the shadow pass (the cascades' maps cast afresh, ``repeats`` times) and
    of the lookup (the render with the maps cached, ``lookups`` times) of ``csm`` with
    ``params`` on ``frame``, in wall time and in the device's kernel time (``*_kernel_ms``: the
    execution time of the kernels each part launched, without the host's tracing and waits)."""
    t = base.get("csm")
    p = t.resolve(params)
    render_evaluated(t, frame, p)                     # compile
    run = lambda: render_evaluated(t, frame, p)  # noqa: E731
    shadow, shadow_k, lookup_k = [], [], []
    for _ in range(repeats):
        # wall times without the kernel history (which times each kernel), then the kernels' times with it
        frame.clear_light_views()
        _, total = timed(run)
        _, warm = timed(run)
        shadow.append(max(total[0] - warm[0], 0.0))
        frame.clear_light_views()
        k_total, k_warm = timed_kernels(run)[2], timed_kernels(run)[2]
        shadow_k.append(max(k_total - k_warm, 0.0))
        lookup_k.append(k_warm)
    _, lookup = timed(run, lookups)
    s, lk = float(np.median(shadow)), float(np.median(lookup))
    sk, lkk = float(np.median(shadow_k)), float(np.median(lookup_k))
    frame.clear_light_views()
    return {"shadow_pass_s": s, "lookup_s": lk, "frame_s": s + lk, "shadow_pass_runs_s": shadow,
            "lookup_runs_s": lookup, "shadow_pass_kernel_ms": sk, "lookup_kernel_ms": lkk,
            "frame_kernel_ms": sk + lkk}


def bench_cost(res=(1920, 1080), map_sizes=(512, 1024, 2048), kernels=(1, 3, 5, 7), repeats=3, lookups=7) -> dict:
    """The FPS table's rows as warm times and ratios to the base configuration (:data:`BASE`)."""
    sc = load_scene(SCENE, res)
    frame = make_frame(sc)
    base_res = BASE["resolution"] if BASE["resolution"] in map_sizes else map_sizes[len(map_sizes) // 2]
    b = {**BASE, "resolution": base_res}
    frame_time(frame, b, 1, 1)               # warm-up: the first cast of a new frame pays one-off costs
    ft = lambda q: frame_time(frame, {**b, **q}, repeats, lookups)  # noqa: E731
    rows = {"map_size": {m: ft({"resolution": m}) for m in map_sizes},
            "kernel": {k: ft({"pcf_kernel": k}) for k in kernels},
            "blend": {"on": ft({"blend": 0.1})}, "selection": {"map": ft({"selection": "map"})}}
    rows["blend"]["off"] = rows["selection"]["interval"] = rows["kernel"].get(1) or rows["map_size"][base_res]
    return {"scene": SCENE, "resolution": list(res), "base": b, "rows": rows, "source_fps": SOURCE_FPS}


def _truth(res, quick: bool, tmp: Path):
    sc = load_scene(SCENE, res)
    if not quick:
        reference(SCENE, res, base=tmp, progress=False)
    truth, meta = store.load(sc.spec, sc.resolution, None if quick else tmp)
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    return frame, truth


def _quality(frame, truth, tech: str, params: dict) -> dict:
    t = base.get(tech)
    p = t.resolve(params)
    r = render_evaluated(t, frame, p)
    m, per_light, _ = technique_metrics(frame, truth, r)
    v = frame.image(r.visibility[LIGHT])
    tl = truth.lights[LIGHT]
    valid = truth.mask & frame.lit_mask(LIGHT)
    out = {"params": {k: params[k] for k in sorted(params)}, "vis_rmse": m["vis_rmse"],
           "vis_rmse_penumbra": m["vis_rmse_penumbra"], "leak_rate": m["leak_rate"],
           "overdark_rate": m["overdark_rate"], "shaded_rmse": m["rmse"],
           "texels": int(r.stats.get("shadow_map_texels", 0)),
           "bands": by_distance(v, tl.V, truth.view_depth, valid)}
    if f"{LIGHT}.cascade" in r.aovs:
        out["by_cascade"] = by_label(v, tl.V, r.aovs[f"{LIGHT}.cascade"], valid)
    frame.clear_light_views()
    return out


def bench_quality(res=(256, 144), total=3 * 1024 * 1024, counts=(1, 2, 3, 4, 5, 6),
                  lambdas=(0.0, 0.25, 0.5, 0.6, 0.75, 1.0), sweep=(512, 1024, 2048, 4096, 8192),
                  quick: bool = False) -> dict:
    """Error against the truth at equal total texels (cascade count, λ, one map) and against
    texels per cascade (the resolution sweep)."""
    with tempfile.TemporaryDirectory(prefix="shadowlab-bench-") as tmp:
        frame, truth = _truth(res, quick, Path(tmp))
    per = lambda n: max(64, int(math.sqrt(total / n)))  # noqa: E731 - texels per side of n equal cascades
    counts_rows = {n: _quality(frame, truth, "csm", {"cascades": n, "resolution": per(n)}) for n in counts}
    lam_rows = {lam: _quality(frame, truth, "csm", {"split_lambda": lam, "resolution": per(3)}) for lam in lambdas}
    one_map = _quality(frame, truth, "pcf", {"resolution": per(1)})
    mem, _ = memory.free_memory()
    reached = [s for s in sweep if memory.views_bytes([(1, s, 3)]) <= mem // 2]
    sweep_rows = {s: _quality(frame, truth, "csm", {"resolution": s}) for s in reached}
    return {"scene": SCENE, "resolution": list(frame.resolution), "total_texels": total, "counts": counts_rows,
            "lambdas": lam_rows, "one_map": one_map, "csm_equal": counts_rows.get(3), "sweep": sweep_rows,
            "sweep_not_run": [s for s in sweep if s not in reached],
            "sweep_not_run_why": f"three cascades of these sizes (shadowlab.render.memory.views_bytes) need more "
                                 f"than half of the {mem / 2**30:.0f} GiB free"}


def bench_shimmer(res=(256, 144), resolution: int = 1024, frames=None) -> dict:
    """Shimmer (:func:`shadowlab.pipeline.shimmer`) of each fit of :data:`SHIMMER_CONFIGS` along
    the camera path of ``boulevard``, at frame 0's points, and the same split by the path's two
    halves (sub-texel steps, then multi-texel steps)."""
    sc0 = load_scene(PATH_SCENE, res, frame=0)
    n = sc0.spec.frames if frames is None else int(frames)
    scenes = [sc0] + [sc0.at_frame(i) for i in range(1, n)]
    fixed = make_frame(sc0)
    t = base.get("csm")
    results, techs, params = {}, {}, {}
    for label, cfg in SHIMMER_CONFIGS:
        p = t.resolve({**cfg, "resolution": resolution})
        results[label] = (render_evaluated(t, fixed, p), p)
        techs[label], params[label] = t, cfg
    out = shimmer(scenes, fixed, results, techniques=techs)
    return {"scene": PATH_SCENE, "resolution": list(res), "map_resolution": resolution, "frames": n,
            "configs": params, "shimmer": out}


def _ratio_row(label, t, base_t, fps, fps_base) -> str:
    return (f"| {label} | {1e3 * t['shadow_pass_s']:.1f} | {1e3 * t['lookup_s']:.1f} | {1e3 * t['frame_s']:.1f} | "
            f"{base_t['frame_s'] / t['frame_s']:.2f} | {base_t['lookup_s'] / t['lookup_s']:.2f} | "
            f"{t['shadow_pass_kernel_ms']:.2f} | {t['lookup_kernel_ms']:.2f} | "
            f"{base_t['frame_kernel_ms'] / t['frame_kernel_ms']:.2f} | "
            f"{fps if fps is not None else '–'} | {fps / fps_base if fps is not None else float('nan'):.2f} |")


def markdown(res: dict) -> str:
    m = res["machine"]
    lines = [
        f"# Cascaded shadow maps ({res['date']})",
        "",
        f"Machine: {machine_text(m)}. All figures from one "
        f"run{' (--quick: small sizes, not for figures)' if res['quick'] else ''}.",
        "",
    ]
    c = res["cost"]
    rows, src = c["rows"], c["source_fps"]
    tb = rows["kernel"][1] if 1 in rows["kernel"] else rows["map_size"][c["base"]["resolution"]]
    W, H = c["resolution"]
    lines += [
        f"## Cost beside the source's FPS table ({c['scene']}, {W}×{H}, 3 cascades)",
        "",
        f"Base: {c['base']['resolution']}² per cascade, PCF kernel 1, interval selection, no blending. "
        "Speed = base time / time, of the whole frame (shadow pass + lookup) and of the lookup alone; the "
        "source's = FPS / base FPS ([Buljan 2020, §4.5], 1920×1080, 1024², a GPU that rasterises its maps). "
        "Here the shadow pass casts one Mitsuba ray per texel, a light's cascades in one replayed Dr.Jit stage "
        "(render/replay.py); what it costs beyond its kernel is host time (the replay walks the scene's arrays, "
        "the cascades' fits are computed), so it still dominates the frame; the lookup is the per-pixel work the "
        "kernel, blending and selection rows vary. Kernels: the device's execution time of the kernels each "
        "part launched (Dr.Jit's kernel history), the work without the host's tracing and waits, and the "
        "frame's speed in kernel time: the figure comparable with a GPU rasteriser's frame rate.",
        "",
        "| configuration | shadow pass (ms) | lookup (ms) | frame (ms) | frame speed | lookup speed | "
        "shadow pass kernels (ms) | lookup kernels (ms) | frame speed, kernels | source FPS | source speed |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for k, t in rows["map_size"].items():
        lines.append(_ratio_row(f"map {k}²", t, tb, src["map_size"].get(int(k)), 146))
    for k, t in rows["kernel"].items():
        lines.append(_ratio_row(f"kernel {k}×{k}", t, tb, src["kernel"].get(int(k)), 146))
    lines.append(_ratio_row("blending ±10 %", rows["blend"]["on"], tb, src["blend"]["on"], 146))
    lines.append(_ratio_row("map-based selection", rows["selection"]["map"], tb, src["selection"]["map"], 146))
    q = res["quality"]
    lines += [
        "",
        f"## Quality at equal total texels ({q['scene']}, {q['resolution'][0]}×{q['resolution'][1]}, "
        f"{q['total_texels']:,} texels)",
        "",
        "Visibility RMSE over the pixels the sun lights, in the truth's penumbra, and the leak / "
        "over-darkening rates (defaults: practical λ 0.6, PCF 3×3, sphere fit, snapping, ±10 % blend).",
        "",
        "| configuration | per cascade | RMSE | RMSE penumbra | leak rate | over-dark rate |",
        "|---|---|---|---|---|---|",
    ]

    def qrow(label, r):
        side = r["params"].get("resolution")
        return (f"| {label} | {side}² | {r['vis_rmse']:.4f} | {r['vis_rmse_penumbra']:.4f} | {r['leak_rate']:.4f} | "
                f"{r['overdark_rate']:.4f} |")
    for n, r in q["counts"].items():
        lines.append(qrow(f"csm, {n} cascade{'s' if int(n) > 1 else ''}", r))
    for lam, r in q["lambdas"].items():
        lines.append(qrow(f"csm, 3 cascades, λ = {float(lam):g}", r))
    lines.append(qrow("one scene-fitted map (pcf)", q["one_map"]))
    if q.get("csm_equal"):
        bands_c = {(b["lo"], b["hi"]): b for b in q["csm_equal"]["bands"]}
        lines += [
            "",
            "### By distance from the camera: 3 cascades vs one map of the same texels",
            "",
            "| distance (m) | pixels | csm RMSE | one map RMSE | csm leak | one map leak |",
            "|---|---|---|---|---|---|",
        ]
        for b in q["one_map"]["bands"]:
            cb = bands_c.get((b["lo"], b["hi"]))
            if cb:
                lines.append(f"| {b['lo']:g}–{b['hi']:g} | {b['pixels']} | {cb['rmse']:.4f} | {b['rmse']:.4f} | "
                             f"{cb['leak_rate']:.4f} | {b['leak_rate']:.4f} |")
    lines += [
        "",
        "## Error against texels per cascade (3 cascades)",
        "",
        "| per cascade | total texels | RMSE | RMSE penumbra | leak rate | RMSE by cascade |",
        "|---|---|---|---|---|---|",
    ]
    for s, r in q["sweep"].items():
        byc = ", ".join(f"{c['label']}: {c['rmse']:.4f}" for c in r.get("by_cascade", []) if c["label"] >= 0)
        lines.append(f"| {s}² | {r['texels']:,} | {r['vis_rmse']:.4f} | {r['vis_rmse_penumbra']:.4f} | "
                     f"{r['leak_rate']:.4f} | {byc} |")
    if q["sweep_not_run"]:
        lines += ["", f"Not run: {', '.join(f'{s}²' for s in q['sweep_not_run'])} ({q['sweep_not_run_why']})."]
    sh = res.get("shimmer")
    if sh:
        tr = sh["shimmer"]["truth"]
        lines += ["", f"## Temporal stability ({sh['scene']}, {sh['frames']} frames, {sh['resolution'][0]}×"
                      f"{sh['resolution'][1]}, {sh['map_resolution']}² per cascade)", "",
                  f"|V_t(x) − V_(t−1)(x)| at frame 0's points over the path's frame pairs. Truth: "
                  f"{tr['pooled']['mean'] if tr['pooled'] else 'n/a'} ({tr['why']}).", "",
                  "| fit | mean | 99th percentile | max |", "|---|---|---|---|"]
        for label, d in sh["shimmer"]["techniques"].items():
            pl = d["pooled"]
            lines.append(f"| {label} | {pl['mean']:.5f} | {pl['p99']:.4f} | {pl['max']:.4f} |")
    return "\n".join(lines) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Measure; write ``out/cascades.json`` and ``out/cascades.md``; return the .md path."""
    backend.init()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick}
    if quick:
        res["cost"] = bench_cost(res=(480, 270), map_sizes=(256, 512, 1024), kernels=(1, 3), repeats=1, lookups=2)
        res["quality"] = bench_quality(res=(128, 72), total=3 * 256 * 256, counts=(1, 3), lambdas=(0.0, 0.6),
                                       sweep=(256, 512), quick=True)
        res["shimmer"] = bench_shimmer(res=(128, 72), resolution=256, frames=4)
    else:
        res["cost"] = bench_cost()
        res["quality"] = bench_quality()
        res["shimmer"] = bench_shimmer()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "cascades.json", res)
    return write_bytes_atomic(out / "cascades.md", markdown(res).encode())
