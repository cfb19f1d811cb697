"""``shadowlab bench``: speed measured in one run, written to reports/bench/*.json and *.md.

Measured (never asserted in tests):

* ground truth: rays per second, wall time of a 512² visibility truth at standard error
  ≤ 0.005 (goal: ≤ 5 s on 2 cores), and shadow rays used by the adaptive sampler vs uniform
  (i.i.d., non-adaptive) sampling at the same worst-pixel standard error. The uniform cost is
  measured: i.i.d. rounds give each pixel's variance, and the worst pixel fixes the sample
  count every pixel needs (N = n_measured · (worst_se / target)²);
* per technique: compile time (Dr.Jit codegen + LLVM backend time of kernels not found in
  the cache, from ``dr.kernel_history``) and warm run time (median of repeats, after
  ``dr.sync_thread()``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from . import backend
from .io.jsonio import write_json_atomic


def _timed(fn, repeats=1):
    import drjit as dr
    ts = []
    out = None
    for _ in range(repeats):
        dr.sync_thread()
        t0 = time.perf_counter()
        out = fn()
        dr.sync_thread()
        ts.append(time.perf_counter() - t0)
    return out, ts


def _kernels():
    import drjit as dr
    h = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]  # not memsets/copies
    compiled = [k for k in h if not k.get("cache_hit") and not k.get("cache_disk")]
    return {"kernels": len(h), "compiled": len(compiled),
            "from_memory_cache": sum(1 for k in h if k.get("cache_hit")),
            "from_disk_cache": sum(1 for k in h if k.get("cache_disk")),
            "compile_ms": float(sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in compiled)),
            "load_ms": float(sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in h if k.get("cache_disk"))),
            "execution_ms": float(sum(k.get("execution_time", 0) for k in h))}


def bench_truth(scene="contact", res=512, target_se=0.005, uniform_res=128, uniform_rounds=16):
    """Adaptive truth at res² and the measured cost of uniform sampling at the same worst error."""
    import drjit as dr
    from .reference.truth import visibility
    from .render.frame import make_frame
    from .render.shading import sample_light
    from .scene import load

    light = load(scene).spec.lights[0].name
    # warm up the kernels on a small frame, so the timing below is the sampler, not the compiler
    small = make_frame(load(scene, resolution=(32, 32)))
    visibility(small, light, target_se=target_se)
    sc = load(scene, resolution=(res, res))
    frame = make_frame(sc)
    lt, ts = _timed(lambda: visibility(frame, light, target_se=target_se))
    m = frame.gbuffer.to_image(frame.gbuffer.mask.reshape(-1).astype(np.float32)) > 0.5
    adaptive = {"resolution": [res, res], "time_s": ts[0], "shadow_rays": lt.rays,
                "rays_per_s": lt.rays / ts[0], "rays_per_pixel": lt.rays / float(m.sum()),
                "worst_se": float(lt.V_se[m].max()), "target_se": target_se,
                "pixels_at_target": float((lt.V_se[m] <= target_se * 1.0001).mean())}

    # uniform i.i.d. sampling at uniform_res² (per-pixel variance does not depend on resolution)
    scu = load(scene, resolution=(uniform_res, uniform_res))
    fu = make_frame(scu)
    k = 16
    s1 = s2 = 0.0
    t0 = time.perf_counter()
    for r in range(uniform_rounds):
        _, fv, fs, _ = sample_light(scu, fu.gbuffer.si, scu.emitters[light], k, 1, r, True, stratified=False)
        fv, fs = fv.numpy(), fs.numpy()
        Vr = np.where(fs > 0, fv / np.where(fs > 0, fs, 1), 1.0).astype(np.float64)
        s1, s2 = s1 + Vr, s2 + Vr * Vr
    dr.sync_thread()
    tu = time.perf_counter() - t0
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
            "ray_ratio_uniform_over_adaptive": uniform_rays / lt.rays}


def bench_techniques(scene="contact", res=256, repeats=5):
    import drjit as dr
    from .pipeline import load_scene
    from .render.frame import make_frame
    from .techniques import base
    sc = load_scene(scene, (res, res))
    frame = make_frame(sc)
    out = {}
    for n in base.names():
        t = base.get(n)
        p = t.resolve({})
        for l in sc.spec.lights:  # light views are shared inputs, not the technique's cost
            frame.light_view(l.name, res=p.get("resolution") or None, bits=p.get("depth_bits") or None,
                             backface=bool(p.get("backface", False)))
        dr.sync_thread()
        dr.kernel_history()  # clear
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        _, first = _timed(lambda: dr.eval(*t.render(frame, p).visibility.values()))
        k = _kernels()
        _, warm = _timed(lambda: dr.eval(*t.render(frame, p).visibility.values()), repeats)
        kw = _kernels()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        out[n] = {"params": p, "first_run_s": first[0], "warm_run_s": float(np.median(warm)),
                  "compile_ms": k["compile_ms"], "kernels_compiled_first_run": k["compiled"],
                  "kernels_compiled_warm_runs": kw["compiled"], "kernel_cache": k}
    return {"scene": scene, "resolution": [res, res], "techniques": out}


def _markdown(res: dict) -> str:
    m = res["machine"]
    tr = res["truth"]
    a, u = tr["adaptive"], tr["uniform"]
    lines = [f"# shadowlab bench ({res['date']})", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, mitsuba {m['mitsuba']}, drjit {m['drjit']}, "
             f"variant {m['variant']}, libLLVM {m['libllvm']}. All figures from one run.", "",
             f"## Ground truth ({tr['scene']}, {a['resolution'][0]}×{a['resolution'][1]}, target standard error {a['target_se']})", "",
             "| measure | value | goal |", "|---|---|---|",
             f"| wall time of the visibility truth | {a['time_s']:.2f} s | ≤ 5 s |",
             f"| worst pixel standard error | {a['worst_se']:.4f} | ≤ {a['target_se']} |",
             f"| pixels at target | {100 * a['pixels_at_target']:.2f} % | |",
             f"| shadow rays (adaptive, stratified) | {a['shadow_rays']:,} ({a['rays_per_pixel']:.0f} per pixel) | |",
             f"| shadow rays per second | {a['rays_per_s'] / 1e6:.1f} M/s | |",
             f"| uniform i.i.d. sampling, rays per pixel for the same worst error | {u['samples_per_pixel_needed']:.0f} "
             f"(measured: worst se {u['worst_se_measured']:.4f} at {u['samples_per_pixel_measured']} spp) | |",
             f"| uniform / adaptive shadow rays | **{tr['ray_ratio_uniform_over_adaptive']:.1f}×** | ≥ 4× |", ""]
    te = res["techniques"]
    lines += [f"## Techniques ({te['scene']}, {te['resolution'][0]}×{te['resolution'][1]})", "",
              "| technique | compile (ms) | kernels compiled / from disk cache | first run (ms) | warm run (ms) | kernels compiled when warm |",
              "|---|---|---|---|---|---|"]
    for n, t in te["techniques"].items():
        kc = t["kernel_cache"]
        lines.append(f"| {n} | {t['compile_ms']:.1f} | {t['kernels_compiled_first_run']} / {kc['from_disk_cache']} | "
                     f"{1e3 * t['first_run_s']:.1f} | {1e3 * t['warm_run_s']:.2f} | {t['kernels_compiled_warm_runs']} |")
    lines += ["", "Compile time: Dr.Jit codegen + LLVM time of JIT kernels served from neither the memory nor the "
              "disk cache (~/.drjit); kernels a previous process compiled are loaded from disk instead."]
    return "\n".join(lines) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Run every benchmark; write ``out/bench.json`` and ``out/bench.md``; return the .md path."""
    import datetime
    backend.init()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick}
    res["truth"] = bench_truth(res=128 if quick else 512, uniform_res=64 if quick else 128)
    res["techniques"] = bench_techniques(res=128 if quick else 512)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "bench.json", res)
    md = out / "bench.md"
    tmp = md.with_suffix(".md.tmp")
    tmp.write_text(_markdown(res))
    tmp.replace(md)
    return md
