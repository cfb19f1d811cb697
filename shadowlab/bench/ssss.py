"""Layered screen-space soft shadows measured ([Tamás 2015], its tables 1 and 2):
``shadowlab bench --only ssss`` (``ssss.json``, ``ssss.md``; the full ``shadowlab bench`` writes
them too).

Every figure from one run, as ratios beside the source's (:data:`PAPER_KERNEL`,
:data:`PAPER_LIGHTS`; [Tamás 2015] measured full frames on a GPU at 720p and 1080p):

* **cost against kernel** on ``many_lights`` (16 lights, 6 layers): ``hard``; ``pcf`` with a k×k
  grid (k = 5, 11, 23: a bench-only copy of ``pcf`` whose ``kernel`` range reaches the source's 23,
  :func:`wide_pcf`); ``pcss`` with a 5×5 blocker search (25 taps) and its PCF step at the nearest
  tap set it has (16 / 32 / 64 Poisson taps for k = 5 / 11 / 23: ``pcss`` has no k×k grid); ``ssss``
  in the source's three variants, kernel k: ``blocker_search`` (25 taps), ``min_filter``, and
  "optimised" (min filter, blur at half resolution). Time: median of warm renders after one
  untimed, every light's shadow map already cast and cached on the frame (the source's times are
  whole frames, shadow maps included; the cast of all 16 maps is reported apart); every case of
  the run is timed round-robin (:class:`Timer`), so a busy spell of a shared machine slows all
  of them alike. Ratios are to
  ``hard``'s time, the source's to its hard-shadow frame;
* **cost against lights** (1, 4, 8, 12, 16): ``pcss`` (5×5 + 11×11: 25 blocker taps, 32 PCF taps)
  and ``ssss`` optimised, kernel 11, on ``many_lights`` keeping its first n lights (the scene's
  order: the sun, then the clusters, then the lone and edge lights). Ratios to ``pcss`` with one
  light, the source's to its 10.2 ms;
  ``ssss`` with the blocker search, kernel 11, beside them;
* **past the document**: 32 / 64 / 128 generated lights
  (:func:`shadowlab.scene.generate.many_lights_spec`, seed 0; shadow maps 256²), the same three.

``ssss``'s min filter is three Dr.Jit passes over each light's low-resolution map at every render
(their cost grows with the maps and the search radius, not the screen), and ``many_lights``'s two
coloured panes make ``ssss`` blur a translucency map per layer too; the Markdown says so beside the
tables.
"""

from __future__ import annotations

import datetime
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..render.frame import make_frame
from ..scene import build
from ..scene.generate import many_lights_spec
from ..scene.spec import scene_spec
from ..techniques import base
from ..techniques.shadow_map import view_for
from .timing import machine_text, render_evaluated, timed

SCENE = "many_lights"
KERNELS = (5, 11, 23)
#: pcss's PCF taps standing in for a k×k kernel (its Poisson sets: 16, 32, 64)
PCSS_TAPS = {5: 16, 11: 32, 23: 64}
#: [Tamás 2015], Table 1: whole-frame ms at (720p, 1080p), 16 lights, 4 layers
PAPER_KERNEL = {
    ("hard", None): (12.5, 13.9),
    ("pcf", 5): (14.9, 18.8), ("pcf", 11): (21.3, 31.0), ("pcf", 23): (40.0, 59.4),
    ("pcss", 5): (17.1, 22.6), ("pcss", 11): (21.5, 31.9), ("pcss", 23): (40.1, 59.5),
    ("ssss_blocker_search", 5): (24.3, 33.0), ("ssss_blocker_search", 11): (24.7, 34.4),
    ("ssss_blocker_search", 23): (25.7, 37.1),
    ("ssss_min_filter", 5): (16.5, 19.2), ("ssss_min_filter", 11): (16.9, 20.3), ("ssss_min_filter", 23): (17.8, 22.7),
    ("ssss_optimised", 5): (16.0, 18.0), ("ssss_optimised", 11): (16.5, 19.1), ("ssss_optimised", 23): (17.4, 21.1),
}
#: [Tamás 2015], Table 2: 1080p ms against lights, PCSS 5×5 + 11×11 and SSSS optimised 11×11
PAPER_LIGHTS = {1: (10.2, 4.1), 4: (18.1, 7.9), 8: (24.0, 11.8), 12: (28.1, 15.4), 16: (31.9, 19.1)}
#: the variants timed against kernel: row name -> (technique, parameters but the kernel)
VARIANTS = {
    "pcf": ("pcf", {"pattern": "grid"}),
    "pcss": ("pcss", {"blocker_samples": 25}),
    "ssss_blocker_search": ("ssss", {"penumbra": "blocker_search", "blocker_samples": 25}),
    "ssss_min_filter": ("ssss", {"penumbra": "min_filter"}),
    "ssss_optimised": ("ssss", {"penumbra": "min_filter", "half_resolution": True}),
}
LIGHT_ROWS = {"pcss": ("pcss", {"blocker_samples": 25, "pcf_samples": 32}),
              "ssss_optimised": ("ssss", {"penumbra": "min_filter", "half_resolution": True, "kernel": 11}),
              "ssss_blocker_search": ("ssss", {"penumbra": "blocker_search", "blocker_samples": 25, "kernel": 11})}


@dataclass(frozen=True)
class Config:
    res: int              # the many-light scene's resolution (square)
    repeats: int          # warm timed renders per figure
    lights: tuple         # light counts of the subsets
    generated: tuple      # generated light counts
    gen_res: int          # their resolution
    shadow_map: int | None = None   # every map of the 16-light scene (None: the scene's, 1024 sun, 512 others)
    gen_shadow_map: int = 256       # every map of the generated scenes


CONFIGS = {
    "quick": Config(
        res=48, repeats=2, lights=(1, 4, 16), generated=(32,), gen_res=48, shadow_map=128, gen_shadow_map=64
    ),
    # on 2 CPU cores (shared) the whole run took 4.5 minutes at these sizes
    "full": Config(res=320, repeats=5, lights=(1, 4, 8, 12, 16), generated=(32, 64, 128), gen_res=192),
    "gpu": Config(res=1080, repeats=5, lights=(1, 4, 8, 12, 16), generated=(32, 64, 128), gen_res=1080),
}


def config_name(quick: bool) -> str:
    """``quick``, ``gpu`` on a CUDA variant, else ``full``."""
    return "quick" if quick else ("gpu" if mi.variant().startswith("cuda") else "full")


def wide_pcf():
    """``pcf`` whose ``kernel`` may be up to 23 (its tap loop is symbolic: any n×n grid is one
    kernel); the registered ``pcf`` stops at 9, the sizes of its own source."""
    pcf = base.get("pcf")
    params = tuple(replace(p, hi=23) if p.name == "kernel" else p for p in pcf.params)
    return type("WidePCF", (type(pcf),), {"params": params})()


def _technique(name):
    return wide_pcf() if name == "pcf" else base.get(name)


class Timer:
    """Every render of the run, timed round-robin: each case's first run (it compiles) and one
    untimed warm-up, then ``repeats`` passes that time each case once. On a machine shared with
    other work a busy spell then slows every case of a pass alike instead of a few tables' rows;
    a case's figure is the median of its passes."""

    def __init__(self):
        self.cases = []

    def add(self, t, frame, params: dict) -> dict:
        """Queue a render; return its row (filled by :meth:`measure`)."""
        row = {"params": dict(params)}
        self.cases.append((t, frame, t.resolve(params), row))
        return row

    def measure(self, repeats: int):
        for t, frame, p, row in self.cases:
            r, (first,) = timed(lambda: render_evaluated(t, frame, p))
            timed(lambda: render_evaluated(t, frame, p), 0, warmup=1)
            row.update(first_run_s=first, runs_s=[])
            for k in ("layers_used", "max_degree", "layer_edges"):
                if k in r.stats:
                    row[k] = r.stats[k]
        for _ in range(int(repeats)):
            for t, frame, p, row in self.cases:
                row["runs_s"].append(timed(lambda: render_evaluated(t, frame, p))[1][0])
        for *_, row in self.cases:
            row["warm_s"] = float(np.median(row["runs_s"]))


def _maps(spec, size):
    """``spec`` with every light's shadow map ``size``² (None: as it is)."""
    return spec if size is None else replace(spec, lights=tuple(replace(l, shadow_map=int(size)) for l in spec.lights))


def _frame(spec):
    return make_frame(build(spec), u_strata=1)


def cast_all(frame) -> float:
    """Seconds to cast every light's default shadow map (cached on the frame afterwards)."""
    p = base.get("hard").resolve({})
    _, (s,) = timed(lambda: [view_for(frame, l.name, p) for l in frame.lights])
    return s


def bench_kernel(frame, cast: float, timer: Timer) -> dict:
    spec = frame.scene.spec
    rows = {"hard": timer.add(base.get("hard"), frame, {})}
    rows["hard"]["kernel"] = None
    for row, (tech, extra) in VARIANTS.items():
        for k in KERNELS:
            params = dict(extra)
            if tech == "pcss":
                params["pcf_samples"] = PCSS_TAPS[k]
            else:
                params["kernel"] = k
            rows[f"{row}/{k}"] = timer.add(_technique(tech), frame, params)
            rows[f"{row}/{k}"]["kernel"] = k
    return {"scene": SCENE, "resolution": list(frame.resolution), "lights": len(spec.lights), "map_cast_s": cast,
            "rows": rows}


def _light_row(frame, timer: Timer, cast: float | None = None) -> dict:
    out = {"map_cast_s": cast_all(frame) if cast is None else cast}
    for row, (tech, params) in LIGHT_ROWS.items():
        out[row] = timer.add(base.get(tech), frame, params)
    return out


def bench_lights(cfg: Config, full, timer: Timer) -> dict:
    """Subsets of the full frame's lights; their maps are the full frame's (the same geometry and
    fits: the cached views are shared, not cast again)."""
    spec = full.scene.spec
    rows = {}
    for n in cfg.lights:
        frame = _frame(replace(spec, lights=spec.lights[:n]))
        names = {l.name for l in spec.lights[:n]}
        frame.share_light_views(full, names)
        rows[str(n)] = {"lights": n, **_light_row(frame, timer, cast=0.0)}
    return {"scene": SCENE, "resolution": list(full.resolution), "rows": rows}


def bench_generated(cfg: Config, timer: Timer) -> dict:
    rows = {}
    for n in cfg.generated:
        spec = many_lights_spec(n, seed=0, resolution=(cfg.gen_res, cfg.gen_res))
        rows[str(n)] = {"lights": n, **_light_row(_frame(_maps(spec, cfg.gen_shadow_map)), timer)}
    return {"resolution": [cfg.gen_res, cfg.gen_res], "shadow_map": cfg.gen_shadow_map, "seed": 0, "rows": rows}


# ----------------------------------------------------------------------------------------------
# the report

def _ms(s) -> str:
    return f"{1e3 * s:.1f}"


def _kernel_md(k: dict) -> list:
    rows = k["rows"]
    h = rows["hard"]["warm_s"]
    ph = PAPER_KERNEL[("hard", None)]
    lines = [
        "## Cost against kernel (Table 1)",
        "",
        f"`{k['scene']}`, {k['resolution'][0]}×{k['resolution'][1]}, {k['lights']} lights, maps "
        f"{'as the scene (sun 1024², others 512²)' if k.get('shadow_map') is None else str(k['shadow_map']) + '²'} "
        f"({rows['ssss_optimised/11'].get('layers_used', '?')} layers); warm render of every light's shadows (median "
        f"of "
        f"{len(rows['hard'].get('runs_s', []))} passes, each timing every case of the run once, round-robin), "
        f"the maps cast before ({_ms(k['map_cast_s'])} ms for all of them, first cast incl. compile). "
        "Ratio: time / hard's. Source: whole frames (maps included), GPU, 720p | 1080p, and its ratio to its "
        "hard-shadow frame at 1080p. pcss's PCF step is 16 / 32 / 64 Poisson taps for k = 5 / 11 / 23.",
        "",
        "| technique | kernel | ours (ms) | ours / hard | source 720p (ms) | source 1080p (ms) | source / hard (1080p) "
        "|",
        "|---|---|---|---|---|---|---|",
    ]
    lines.append(f"| hard | – | {_ms(h)} | 1.00 | {ph[0]} | {ph[1]} | 1.00 |")
    for row in VARIANTS:
        for kk in KERNELS:
            r = rows[f"{row}/{kk}"]
            p = PAPER_KERNEL[(row, kk)]
            lab = {"pcss": f"5×5 + {kk}×{kk}", "ssss_blocker_search": f"5×5 + {kk}×{kk}"}.get(row, f"{kk}×{kk}")
            lines.append(f"| {row} | {lab} | {_ms(r['warm_s'])} | {r['warm_s'] / h:.2f} | {p[0]} | {p[1]} | "
                         f"{p[1] / ph[1]:.2f} |")
    flat = {row: rows[f"{row}/23"]["warm_s"] / rows[f"{row}/5"]["warm_s"] for row in VARIANTS}
    lines += [
        "",
        "Growth from kernel 5 to 23 (time at 23 / time at 5): "
        + ", ".join(
            f"{row} {flat[row]:.2f}× (source {PAPER_KERNEL[(row, 23)][1] / PAPER_KERNEL[(row, 5)][1]:.2f}×)"
            for row in VARIANTS
        )
        + ".",
    ]
    return lines


def _lights_md(l: dict, g: dict) -> list:
    rows = l["rows"]
    base1 = rows[min(rows, key=int)]["pcss"]["warm_s"]
    lines = ["", "## Cost against lights (Table 2)", "",
             f"`{l['scene']}` keeping its first n lights, {l['resolution'][0]}×{l['resolution'][1]} (the maps cast "
             "once, above); pcss 5×5 + 11×11 (25 blocker taps, 32 PCF taps), ssss optimised (min filter, half "
             "resolution) 11×11 as the source, and ssss with the blocker search (25 taps) 11×11. Ratio: time / "
             "pcss's with one light (source: / 10.2 ms, 1080p). Below the line: generated scenes "
             f"(`many_lights_spec(n, seed=0)`, {g['resolution'][0]}×{g['resolution'][1]}, maps {g['shadow_map']}²), "
             "their ratios to the same one-light pcss time.", "",
             "| lights | layers | pcss (ms) | ssss opt. (ms) | ssss b.s. (ms) | pcss ratio | ssss opt. ratio | "
             "ssss b.s. ratio | ssss opt. / pcss | source pcss | source ssss opt. | source ssss / pcss |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def line(n, r, src):
        a, b, c = (r[k]["warm_s"] for k in ("pcss", "ssss_optimised", "ssss_blocker_search"))
        s = (f"{src[0]} ms ({src[0] / PAPER_LIGHTS[1][0]:.2f}) | {src[1]} ms ({src[1] / PAPER_LIGHTS[1][0]:.2f}) | "
             f"{src[1] / src[0]:.2f}") if src else "– | – | –"
        return (f"| {n} | {r['ssss_optimised'].get('layers_used', '?')} | {_ms(a)} | {_ms(b)} | {_ms(c)} | "
                f"{a / base1:.2f} | {b / base1:.2f} | {c / base1:.2f} | {b / a:.2f} | {s} |")

    for n, r in rows.items():
        lines.append(line(n, r, PAPER_LIGHTS.get(int(n))))
    if g["rows"]:
        lines.append("| *generated* | | | | | | | | | | | |")
        for n, r in g["rows"].items():
            lines.append(line(n, r, None))
    ns = sorted(int(n) for n in rows)
    if len(ns) > 1:
        lo, hi = rows[str(ns[0])], rows[str(ns[-1])]
        sl = {k: (hi[k]["warm_s"] - lo[k]["warm_s"]) / (ns[-1] - ns[0]) / base1 for k in LIGHT_ROWS}
        psl = [(PAPER_LIGHTS[16][i] - PAPER_LIGHTS[1][i]) / 15 / PAPER_LIGHTS[1][0] for i in (0, 1)]
        lines += ["", f"Cost per added light ({ns[0]} → {ns[-1]}), in units of one-light pcss: pcss {sl['pcss']:.3f}, "
                      f"ssss optimised {sl['ssss_optimised']:.3f}, ssss blocker search {sl['ssss_blocker_search']:.3f} "
                      f"(source: pcss {psl[0]:.3f}, ssss optimised {psl[1]:.3f})."]
    lines += [
        "",
        "ssss's min filter is three Dr.Jit passes over each light's low-resolution map (a block minimum, then "
        "minima along rows and columns over the search radius) at every render: its cost grows with the "
        "maps and the radius, not the screen. `many_lights` has two coloured translucent panes, so every "
        "ssss row also packs and blurs a translucency map per layer (three more blurred channels); the "
        "generated scenes have panes too.",
    ]
    return lines


def markdown(res: dict) -> str:
    m = res["machine"]
    cfg = res["config"]
    lines = [f"# Layered screen-space soft shadows ({res['date']})", "",
             f"Machine: {machine_text(m)}. All figures from one run ({res['wall_s']:.0f} s), configuration "
             f"`{res['config_name']}` ({cfg['res']}² for the 16-light scene, {cfg['gen_res']}² generated"
             f"{'; --quick: small sizes, not for figures' if res['quick'] else ''}"
             f"{'; sizes that keep the run under 10 minutes on 2 CPU cores' if res['config_name'] == 'full' else ''}). "
             "[Tamás 2015] measured whole frames on a GPU; ours are Dr.Jit "
             f"{'CUDA kernels on this GPU' if m.get('gpu') else 'LLVM kernels on this CPU'}, shadows only.", ""]
    lines += _kernel_md(res["kernel"]) + _lights_md(res["lights"], res["generated"])
    return "\n".join(lines) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Measure; write ``out/ssss.json`` and ``out/ssss.md``; return the .md path."""
    backend.init()
    name = config_name(quick)
    cfg = CONFIGS[name]
    dr.sync_thread()
    t0 = time.perf_counter()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "variant": mi.variant(), "quick": quick, "config_name": name, "config": asdict(cfg)}
    full = _frame(_maps(scene_spec(SCENE, (cfg.res, cfg.res)), cfg.shadow_map))
    cast = cast_all(full)          # every light's map, once (first cast incl. compile)
    timer = Timer()
    res["kernel"] = bench_kernel(full, cast, timer)
    res["kernel"]["shadow_map"] = cfg.shadow_map
    res["lights"] = bench_lights(cfg, full, timer)
    res["generated"] = bench_generated(cfg, timer)
    timer.measure(cfg.repeats)     # every case's passes, round-robin
    dr.sync_thread()
    res["wall_s"] = time.perf_counter() - t0
    res["paper"] = {"kernel": {f"{k[0]}/{k[1]}": v for k, v in PAPER_KERNEL.items()},
                    "lights": {str(k): v for k, v in PAPER_LIGHTS.items()}}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "ssss.json", res)
    return write_bytes_atomic(out / "ssss.md", markdown(res).encode())
