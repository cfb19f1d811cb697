"""``shadowlab bench``: speed measured in one run, written to reports/bench/*.json and *.md.

Measured (never asserted in tests):

* ground truth: rays per second, wall time of a 512² visibility truth at standard error
  ≤ 0.005 (goal: ≤ 5 s on 2 cores; on a CUDA variant a 1920×1080 truth, goal ≤ 0.1 s), and
  shadow rays used by the adaptive sampler vs uniform (i.i.d., non-adaptive) sampling at the
  same worst-pixel standard error. The uniform cost is measured: i.i.d. rounds give each
  pixel's variance, and the worst pixel fixes the sample count every pixel needs
  (N = n_measured · (worst_se / target)²). Beside it, in the same run on the same points: raw
  Mitsuba ``ray_test`` throughput (:func:`raw_ray_test`, 256 shadow rays per point in one
  wavefront), the truth's share of it (goals: ≥ 80 % on the CPU, ≥ 50 % on a GPU), and the
  truth's Mitsuba image (``mitsuba_render``, 256 spp in 4 passes with its variance) against one
  256-spp ``mi.render`` of Mitsuba's ``direct`` integrator (goal: ≤ 2×);
* per technique: compile time (Dr.Jit codegen + LLVM backend time of kernels not found in
  the cache, from ``dr.kernel_history``) and warm run time (median of repeats, after
  ``dr.sync_thread()``);
* filtered shadow maps ([Buljan 2020, ch. 3] tables, as ratios from one run): cost vs kernel size
  (1×1 … 7×7) and vs shadow-map size (512 … 2048) for PCF, VSM, ESM, EVSM;
* a 50-value sweep of one continuous parameter per technique: kernels compiled after the first
  value (0 when parameters are opaque) and kernel-cache hits;
* parameter fitting (``shadowlab.bench.fit``): pcss.light_scale by Adam vs the grid-search optimum
  and the grid of equal final loss;
* virtual shadow maps (``shadowlab.bench.virtual``, [Giegl 2007]): ``virtual.json`` / ``virtual.md``;
* shadow maps fused with deep partitioned shadow volumes (``shadowlab.bench.dpsv``, [Wang 2022]):
  ``dpsv.json`` / ``dpsv.md``;
* layered screen-space soft shadows (``shadowlab.bench.ssss``, [Tamás 2015]): ``ssss.json`` /
  ``ssss.md``.

Each part also writes its run record, ``runs/DATE_PART_MACHINE.json`` (:mod:`shadowlab.bench.record`):
committed under ``docs/bench/runs/``, it is what the docs' bench page is generated from.
"""

from __future__ import annotations

import datetime
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from ..errors import InputError
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..pipeline import load_scene
from ..reference.truth import mitsuba_render, visibility
from ..render.frame import make_frame
from ..render.shading import sample_light
from ..scene import load
from ..techniques import base
from .cascades import run as cascades_bench
from .dpsv import run as dpsv_bench
from .scaling import run as scaling_bench
from .fit import markdown as fit_markdown
from .frames import run as frames_bench
from .fit import measure as bench_fit
from .sdf import run as sdf_bench
from .ssss import run as ssss_bench
from .transfer import run as transfer_bench
from .rays import raw_ray_test
from .record import write_record
from .timing import machine_text, timed
from .virtual import run as virtual_bench


def _kernels():
    h = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]  # not memsets/copies
    compiled = [k for k in h if not k.get("cache_hit") and not k.get("cache_disk")]
    return {
        "kernels": len(h),
        "compiled": len(compiled),
        "from_memory_cache": sum(1 for k in h if k.get("cache_hit")),
        "from_disk_cache": sum(1 for k in h if k.get("cache_disk")),
        "compile_ms": float(sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in compiled)),
        "load_ms": float(sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in h if k.get("cache_disk"))),
        "execution_ms": float(sum(k.get("execution_time", 0) for k in h)),
    }


def bench_mitsuba_image(scene, spp: int = 256, repeats: int = 3) -> dict:
    """The truth's Mitsuba image (``mitsuba_render``: ``spp`` in 4 passes, mean and variance)
    against one ``spp`` render of Mitsuba's ``direct`` integrator alone; warm medians."""
    integrator = mi.load_dict({"type": "direct"})
    _, td = timed(lambda: dr.eval(mi.render(scene.mi_scene, sensor=scene.sensor, spp=spp, seed=7,
                                            integrator=integrator)), repeats, warmup=1)
    _, tm = timed(lambda: mitsuba_render(scene, spp=spp, seed=7), repeats, warmup=1)
    d, m = float(np.median(td)), float(np.median(tm))
    return {"spp": spp, "direct_s": d, "truth_image_s": m, "ratio": m / d}


def bench_truth(scene="contact", res=512, target_se=0.005, uniform_res=128, uniform_rounds=16):
    """Adaptive truth at ``res`` (an int for res², or (W, H)), raw ``ray_test`` at the same points,
    the truth's Mitsuba image vs ``direct``, and the measured cost of uniform sampling at the same
    worst error."""

    W, H = (res, res) if isinstance(res, int) else tuple(res)
    light = load(scene).spec.lights[0].name
    # warm up the kernels on a small frame, so the timing below is the sampler, not the compiler
    small = make_frame(load(scene, resolution=(32, 32)))
    visibility(small, light, target_se=target_se)
    sc = load(scene, resolution=(W, H))
    frame = make_frame(sc)
    # medians of 3 runs after one at full size (a GPU's first one also grows its memory pools), the
    # truth's and raw ray_test's taken in turns, so that a busy machine slows both alike
    visibility(frame, light, target_se=target_se)
    raw_ray_test(frame, light, repeats=1)
    ts, raws = [], []
    for _ in range(3):
        lt, (t,) = timed(lambda: visibility(frame, light, target_se=target_se))
        ts.append(t)
        raws.append(raw_ray_test(frame, light, repeats=1, warmup=0))
    t = float(np.median(ts))
    raw = min(raws, key=lambda r: abs(r["time_s"] - float(np.median([x["time_s"] for x in raws]))))
    # one more run with Dr.Jit's kernel history: how much of the wall time the kernels take (the
    # rest is the host's: tracing, the stopping rule, transfers)
    prev = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        _, (tk,) = timed(lambda: visibility(frame, light, target_se=target_se))
        kern = _kernels()
    finally:
        dr.kernel_history_clear()
        dr.set_flag(dr.JitFlag.KernelHistory, prev)
    kern.update(wall_s=tk, kernel_share=kern["execution_ms"] / 1e3 / tk)
    m = frame.gbuffer.to_image(frame.gbuffer.mask.reshape(-1).astype(np.float32)) > 0.5
    adaptive = {"resolution": [W, H], "time_s": t, "shadow_rays": lt.rays,
                "rays_per_s": lt.rays / t, "rays_per_pixel": lt.rays / float(m.sum()),
                "worst_se": float(lt.V_se[m].max()), "target_se": target_se,
                "pixels_at_target": float((lt.V_se[m] <= target_se * 1.0001).mean())}
    image = bench_mitsuba_image(sc)

    # uniform i.i.d. sampling at uniform_res² (per-pixel variance does not depend on resolution)
    scu = load(scene, resolution=(uniform_res, uniform_res))
    fu = make_frame(scu)
    k = 16

    def sample_rounds():
        s1 = s2 = 0.0
        for r in range(uniform_rounds):
            _, fv, fs, _ = sample_light(scu, fu.gbuffer.si, scu.emitters[light], k, 1, r, True, stratified=False)
            fv, fs = fv.numpy(), fs.numpy()
            Vr = np.where(fs > 0, fv / np.where(fs > 0, fs, 1), 1.0).astype(np.float64)
            s1, s2 = s1 + Vr, s2 + Vr * Vr
        return s1, s2

    (s1, s2), (tu,) = timed(sample_rounds)
    R = uniform_rounds
    var_rounds = np.maximum(s2 / R - (s1 / R) ** 2, 0) * R / (R - 1)
    valid = fu.gbuffer.valid.numpy()
    n_measured = R * k * k
    se = np.sqrt(var_rounds / R)[valid]
    worst = float(np.quantile(se, 0.9999))
    n_needed = n_measured * (worst / target_se) ** 2
    uniform_rays = n_needed * float(m.sum())
    uniform = {"measured_at": [uniform_res, uniform_res], "samples_per_pixel_measured": n_measured,
               "worst_se_measured": worst, "samples_per_pixel_needed": n_needed,
               "shadow_rays_needed_at_res": uniform_rays, "time_s": tu}
    return {"scene": scene, "adaptive": adaptive, "uniform": uniform,
            "ray_ratio_uniform_over_adaptive": uniform_rays / lt.rays,
            "raw_ray_test": raw, "truth_over_raw": adaptive["rays_per_s"] / raw["rays_per_s"], "truth_kernels": kern,
            "mitsuba_image": image}


def bench_techniques(scene="contact", res=256, repeats=5):
    sc = load_scene(scene, (res, res))
    frame = make_frame(sc)
    out = {}
    for n in base.names():
        t = base.get(n)
        if t.unsupported(sc.spec) or t.external:
            continue
        p = t.resolve({})
        for l in sc.spec.lights:  # light views are shared inputs, not the technique's cost
            frame.light_view(l.name, res=p.get("resolution") or None, bits=p.get("depth_bits") or None,
                             backface=bool(p.get("backface", False)))
        dr.sync_thread()
        dr.kernel_history()  # clear
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        _, first = timed(lambda: dr.eval(*t.render(frame, p).visibility.values()))
        k = _kernels()
        _, warm = timed(lambda: dr.eval(*t.render(frame, p).visibility.values()), repeats)
        kw = _kernels()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        out[n] = {"params": p, "first_run_s": first[0], "warm_run_s": float(np.median(warm)),
                  "compile_ms": k["compile_ms"], "kernels_compiled_first_run": k["compiled"],
                  "kernels_compiled_warm_runs": kw["compiled"], "kernel_cache": k}
    return {"scene": scene, "resolution": [res, res], "techniques": out}


FILTERED = ("pcf", "vsm", "esm", "evsm")


def _render_once(t, frame, p):
    res = t.render(frame, p)
    dr.eval(*res.visibility.values())
    return res


def _warm_time(t, frame, p, repeats):
    """(first run incl. compile, median warm run) of technique ``t`` with params ``p``."""
    for l in frame.lights:  # shared input, not the technique's cost
        frame.light_view(l.name, res=p.get("resolution") or None, bits=p.get("depth_bits") or None,
                         backface=bool(p.get("backface", False)))
    _, first = timed(lambda: _render_once(t, frame, p))
    _, warm = timed(lambda: _render_once(t, frame, p), repeats)
    return first[0], float(np.median(warm))


def bench_filters(scene="contact", res=256, kernels=(1, 3, 5, 7), map_sizes=(512, 1024, 2048), repeats=5):
    """Cost vs kernel size and vs shadow-map size for PCF and the prefiltered maps ([Buljan 2020, ch. 3]
    tables): PCF should grow with the kernel's area, prefiltered ones stay nearly flat;
    prefiltered ones grow with the map size (they filter every texel), PCF not."""
    sc = load_scene(scene, (res, res))
    frame = make_frame(sc)
    names = [n for n in FILTERED if n in base.names()]
    by_kernel, by_map = {}, {}
    for n in names:
        t = base.get(n)
        by_kernel[n] = {}
        for k in kernels:
            p = t.resolve({"kernel": k, "resolution": map_sizes[0]})
            first, warm = _warm_time(t, frame, p, repeats)
            by_kernel[n][k] = {"first_run_s": first, "warm_run_s": warm}
        by_map[n] = {}
        for m in map_sizes:
            p = t.resolve({"kernel": 5, "resolution": m})
            first, warm = _warm_time(t, frame, p, repeats)
            by_map[n][m] = {"first_run_s": first, "warm_run_s": warm}
    return {"scene": scene, "resolution": [res, res], "kernels": list(kernels), "map_sizes": list(map_sizes),
            "by_kernel": by_kernel, "by_map_size": by_map}


def bench_sweep(scene="contact", res=128, values=50):
    """A sweep of ``values`` values of one continuous parameter per technique: with opaque
    parameters only the first value may compile; report the kernel-cache hits."""
    sc = load_scene(scene, (res, res))
    frame = make_frame(sc)
    out = {}
    for n in base.names():
        t = base.get(n)
        if t.unsupported(sc.spec) or t.external:
            continue
        cont = [p for p in t.params if p.kind == "float" and p.lo is not None and p.hi is not None and p.hi > p.lo]
        if not cont:
            continue
        prm = next((p for p in cont if p.differentiable), cont[0])
        lo, hi = float(prm.lo), float(prm.hi)
        if prm.default is not None and lo <= prm.default <= hi:  # sweep around the default, inside the range
            span = max(abs(prm.default), (hi - lo) * 0.01)
            lo, hi = max(lo, prm.default - 0.5 * span), min(hi, prm.default + 0.5 * span)
        vals = np.linspace(lo, hi, values)
        _render_once(t, frame, t.resolve({prm.name: vals[0]}))
        dr.sync_thread()
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        for v in vals[1:]:
            _render_once(t, frame, t.resolve({prm.name: v}))
        dr.sync_thread()
        k = _kernels()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        out[n] = {"param": prm.name, "values": values, "range": [float(lo), float(hi)],
                  "kernels_launched": k["kernels"], "kernels_compiled_after_first": k["compiled"],
                  "cache_hits": k["from_memory_cache"] + k["from_disk_cache"]}
    return out


def _raw_rows(tr: dict, gpu: bool) -> list:
    """The truth part's rows on raw ``ray_test`` and on the Mitsuba image (empty for an old result)."""
    if "raw_ray_test" not in tr:
        return []
    r, im = tr["raw_ray_test"], tr["mitsuba_image"]
    return [
        f"| raw Mitsuba `ray_test`, same points ({r['rays_per_point']} rays per point, one wavefront) | "
        f"{r['rays_per_s'] / 1e6:.1f} M/s | |",
        f"| truth / raw `ray_test` rays per second | **{100 * tr['truth_over_raw']:.0f} %** | ≥ {50 if gpu else 80} % "
        f"|",
        *(
            []
            if "truth_kernels" not in tr
            else [
                f"| the truth's kernels (one more run, kernel history) | {tr['truth_kernels']['kernels']} launched, "
                f"{tr['truth_kernels']['execution_ms']:.0f} ms of {1e3 * tr['truth_kernels']['wall_s']:.0f} ms wall "
                f"({100 * tr['truth_kernels']['kernel_share']:.0f} %; the rest is the host's) | |"
            ]
        ),
        f"| Mitsuba image of the truth ({im['spp']} spp in 4 passes, with variance) | {im['truth_image_s']:.3f} s | |",
        f"| Mitsuba `direct` integrator alone ({im['spp']} spp, one render) | {im['direct_s']:.3f} s | |",
        f"| truth image / `direct` time | **{im['ratio']:.2f}×** | ≤ 2× |",
    ]


def _truth_markdown(res: dict) -> list:
    """The title, machine line and ground-truth table of a bench result (lines)."""
    m = res["machine"]
    tr = res["truth"]
    a, u = tr["adaptive"], tr["uniform"]
    lines = [
        f"# shadowlab bench ({res['date']})",
        "",
        f"Machine: {machine_text(m)}, libLLVM {m['libllvm']}. All figures from one run.",
        "",
        f"## Ground truth ({tr['scene']}, {a['resolution'][0]}×{a['resolution'][1]}, target standard error "
        f"{a['target_se']})",
        "",
        "| measure | value | goal |",
        "|---|---|---|",
        f"| wall time of the visibility truth (median of 3 warm runs) | {a['time_s']:.3f} s | "
        f"{'≤ 0.1 s at 1920×1080' if str(m.get('variant', '')).startswith('cuda') else '≤ 5 s at 512²'} |",
        f"| worst pixel standard error | {a['worst_se']:.4f} | ≤ {a['target_se']} |",
        f"| pixels at target | {100 * a['pixels_at_target']:.2f} % | |",
        f"| shadow rays (adaptive, stratified) | {a['shadow_rays']:,} ({a['rays_per_pixel']:.0f} per pixel) | |",
        f"| shadow rays per second | {a['rays_per_s'] / 1e6:.1f} M/s | |",
        f"| uniform i.i.d. sampling, rays per pixel for the same worst error | {u['samples_per_pixel_needed']:.0f} "
        f"(measured: worst se {u['worst_se_measured']:.4f} at {u['samples_per_pixel_measured']} spp) | |",
        f"| uniform / adaptive shadow rays | **{tr['ray_ratio_uniform_over_adaptive']:.1f}×** | ≥ 4× |",
    ]
    return lines + _raw_rows(tr, gpu=str(m.get("variant", "")).startswith("cuda")) + [""]


def _markdown(res: dict) -> str:
    lines = _truth_markdown(res)
    te = res["techniques"]
    lines += [
        f"## Techniques ({te['scene']}, {te['resolution'][0]}×{te['resolution'][1]})",
        "",
        "| technique | compile (ms) | kernels compiled / from disk cache | first run (ms) | warm run (ms) | kernels "
        "compiled when warm |",
        "|---|---|---|---|---|---|",
    ]
    for n, t in te["techniques"].items():
        kc = t["kernel_cache"]
        lines.append(
            f"| {n} | {t['compile_ms']:.1f} | {t['kernels_compiled_first_run']} / {kc['from_disk_cache']} | "
            f"{1e3 * t['first_run_s']:.1f} | {1e3 * t['warm_run_s']:.2f} | {t['kernels_compiled_warm_runs']} |"
        )
    lines += ["", "Compile time: Dr.Jit codegen + LLVM time of JIT kernels served from neither the memory nor the "
              "disk cache (~/.drjit); kernels a previous process compiled are loaded from disk instead."]
    fl = res.get("filters")
    if fl and fl["by_kernel"]:
        ks, ms = fl["kernels"], fl["map_sizes"]
        lines += ["", f"## Filtered shadow maps: cost vs kernel size ({fl['scene']}, {fl['resolution'][0]}², "
                      f"{ms[0]}² map; warm run, ms; ratio to 1×1)", "",
                  "| technique | " + " | ".join(f"{k}×{k}" for k in ks) + f" | {ks[-1]}×{ks[-1]} / 1×1 |",
                  "|---|" + "---|" * (len(ks) + 1)]
        for n, d in fl["by_kernel"].items():
            w = [d[k]["warm_run_s"] * 1e3 for k in ks]
            lines.append(f"| {n} | " + " | ".join(f"{x:.2f}" for x in w) + f" | {w[-1] / w[0]:.2f}× |")
        lines += ["", "## Filtered shadow maps: cost vs shadow-map size (5×5 kernel; warm run, ms)", "",
                  "| technique | " + " | ".join(f"{m}²" for m in ms) + f" | {ms[-1]}² / {ms[0]}² |",
                  "|---|" + "---|" * (len(ms) + 1)]
        for n, d in fl["by_map_size"].items():
            w = [d[m]["warm_run_s"] * 1e3 for m in ms]
            lines.append(f"| {n} | " + " | ".join(f"{x:.2f}" for x in w) + f" | {w[-1] / w[0]:.2f}× |")
    sw = res.get("sweep")
    if sw:
        lines += [
            "",
            "## Parameter sweeps (kernel cache)",
            "",
            "| technique | parameter | values | range | kernels launched | compiled after the first value | cache hits "
            "|",
            "|---|---|---|---|---|---|---|",
        ]
        for n, d in sw.items():
            lines.append(f"| {n} | `{d['param']}` | {d['values']} | [{d['range'][0]:.4g}, {d['range'][1]:.4g}] | "
                         f"{d['kernels_launched']} | {d['kernels_compiled_after_first']} | {d['cache_hits']} |")
    if res.get("fit"):
        lines += fit_markdown(res["fit"])
    if res.get("sdf"):
        lines += [
            "",
            f"SDF soft shadows ([Bán 2019, ch. 6]): see `{Path(res['sdf']).name}` (`shadowlab bench --only sdf`).",
        ]
    if res.get("cascades"):
        lines += ["", f"Cascaded shadow maps ([Buljan 2020, ch. 4]): see `{Path(res['cascades']).name}` "
                      "(`shadowlab bench --only cascades`)."]
    if res.get("virtual"):
        lines += ["", f"Virtual shadow maps ([Giegl 2007]): see `{Path(res['virtual']).name}` "
                      "(`shadowlab bench --only virtual`)."]
    if res.get("dpsv"):
        lines += ["", f"Shadow maps fused with deep partitioned shadow volumes ([Wang 2022]): see "
                      f"`{Path(res['dpsv']).name}` (`shadowlab bench --only dpsv`)."]
    if res.get("ssss"):
        lines += ["", f"Layered screen-space soft shadows ([Tamás 2015]): see `{Path(res['ssss']).name}` "
                      "(`shadowlab bench --only ssss`)."]
    return "\n".join(lines) + "\n"


#: the parts ``--only`` runs alone
ONLY = ("sdf", "cascades", "virtual", "dpsv", "ssss", "scaling", "truth", "frames", "transfer")


def run(out: Path, quick: bool = False, only: str | None = None, size=None) -> Path:
    """Run every benchmark; write ``out/bench.json`` and ``out/bench.md``; return the .md path.
    ``only="cascades"``: just :mod:`shadowlab.bench.cascades` (``out/cascades.json``, ``out/cascades.md``);
    ``only="sdf"``: just the SDF soft-shadow bench (:mod:`shadowlab.bench.sdf`: ``out/sdf.json``,
    ``out/sdf.md``); ``only="virtual"``: just :mod:`shadowlab.bench.virtual` (``out/virtual.json``,
    ``out/virtual.md``, ``out/virtual.png``); ``only="dpsv"``: just :mod:`shadowlab.bench.dpsv`
    (``out/dpsv.json``, ``out/dpsv.md``); ``only="ssss"``: just :mod:`shadowlab.bench.ssss`
    (``out/ssss.json``, ``out/ssss.md``); ``only="truth"``: just the ground-truth part
    (``out/truth.json``, ``out/truth.md``); the full run writes them all. ``only="frames"``: each
    technique's frame split into its parts (:mod:`shadowlab.bench.frames`: ``out/frames.json``,
    ``out/frames.md``; not in the full run), at ``size`` ("WxH" or (W, H); default 1920×1080)."""
    if only is not None and only not in ONLY:
        raise InputError(f"--only {only!r}: expected one of {', '.join(ONLY)} (or no --only for every benchmark)")
    if size is not None and only != "frames":
        raise InputError(f"--size {size}: only the frames part takes a size; add --only frames, or leave --size out")
    if only == "frames":
        return _recorded(Path(out), "frames", frames_bench(Path(out), quick=quick, size=size))
    out = Path(out)
    parts = {"sdf": sdf_bench, "cascades": cascades_bench, "virtual": virtual_bench, "dpsv": dpsv_bench,
             "ssss": ssss_bench, "scaling": scaling_bench, "transfer": transfer_bench}
    if only in parts:
        return _recorded(out, only, parts[only](out, quick=quick))
    backend.init()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick}
    gpu = str(res["machine"]["variant"]).startswith("cuda")  # a GPU's goal is a 1080p truth
    res["truth"] = bench_truth(res=128 if quick else ((1920, 1080) if gpu else 512), uniform_res=64 if quick else 128)
    if only == "truth":
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / "truth.json", res)
        return _recorded(out, "truth", write_bytes_atomic(out / "truth.md", "\n".join(_truth_markdown(res)).encode()))
    res["techniques"] = bench_techniques(res=128 if quick else 512)
    res["filters"] = bench_filters(res=128 if quick else 256, map_sizes=(256, 512) if quick else (512, 1024, 2048),
                                   kernels=(1, 3) if quick else (1, 3, 5, 7), repeats=2 if quick else 5)
    res["sweep"] = bench_sweep(values=5 if quick else 50)
    res["fit"] = bench_fit(quick)  # pcss.light_scale: Adam vs grid search (the fitting goals)
    # [Bán 2019, ch. 6], [Buljan 2020, ch. 4], [Giegl 2007], [Wang 2022], [Tamás 2015]: PART.json / PART.md
    for part in ("sdf", "cascades", "virtual", "dpsv", "ssss"):
        res[part] = str(_recorded(out, part, parts[part](out, quick=quick)))
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "bench.json", res)
    return _recorded(out, "core", write_bytes_atomic(out / "bench.md", _markdown(res).encode()))


def _recorded(out: Path, part: str, md: Path) -> Path:
    """``md``, after writing its run record to ``out/runs/`` (:mod:`shadowlab.bench.record`)."""
    write_record(out, part, Path(md))
    return md
