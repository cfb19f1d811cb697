"""Virtual shadow maps measured ([Giegl 2007, §3–5]): ``shadowlab bench --only virtual``
(``virtual.json``, ``virtual.md`` and the plot ``virtual.png``; the full ``shadowlab bench`` writes
them too).

Every figure from one run, on the sun of two built-in scenes:

* **cost and tiles against ξ** ([Giegl 2007, §4.9]): ``fvsm`` with ξ = 0 … 5 on ``street``: the
  median frame time of warm renders (the technique's whole render: the demand (SMTMM, SMTG,
  pyramid, traversal), the tiles ray cast one ray a texel, and the deferred pass; timed by
  :func:`shadowlab.bench.timing.timed`, which calls ``dr.sync_thread()`` around every run), tiles,
  texels (rays), the memory of every tile texture mode ([Giegl 2007, §4.10]), the traversal depth
  and the root's demand;
* **fitted against brute force** ([Giegl 2007, §3]): ``vtsm`` with the same ``t_max`` and ``grid``
  in the same run: its time over fvsm's (beside the source's claim that fitting is at least
  :data:`CLAIMED_SPEEDUP` times faster than the brute-force virtual tiled map), the hard-shadow
  error rates of both and fvsm's tiles as a fraction of vtsm's;
* **aliasing error along a camera path**: ``boulevard``'s frames, fvsm for each ξ: the
  *hard-shadow error rate*, the share of the valid pixels the sun reaches where
  (V ≥ ½) ≠ (V_centre ≥ ½), V_centre the exact ray-traced visibility of the light's centre
  (:func:`shadowlab.reference.truth.centre_visibility`, what a map converges to as its resolution
  grows [Giegl 2007, §5]); and the RMSE against the area-light truth away from its penumbra
  (:func:`shadowlab.metrics.masks.penumbra_mask`: truth V ≤ 0.02 or ≥ 0.98), both as a mean over
  the frames; tiles and memory per frame (mean and max);
* **equal memory** (a comparison the sources do not make): ``csm`` (3 cascades, hard filter
  [Buljan 2020, §4]), ``fvsm`` (ξ = 0, ``pow2`` textures), ``vtsm``, one focused map (``csm`` with
  one cascade, hard filter: the sphere fit of [Buljan 2020, §4.2]) and one scene-fitted map
  (``hard`` [Buljan 2020, §2.3]) at the same shadow-map memory, 4 bytes a texel: the budget is
  fvsm's largest along the path (its memory depends on the view), csm and the single maps take
  the largest resolution whose texels fit in it, vtsm the power-of-two ``t_max`` whose t_max² is
  nearest to it (its tiles are drawn one after another into one t_max² texture). The two errors above per frame, and the
  shimmer
  (:func:`shadowlab.pipeline.shimmer`) along the path as in :mod:`shadowlab.bench.cascades`.

The area-light truth of the path's frames is rendered for the run into a temporary store
(``--quick``: the committed CI references of frames 0–3). Sizes: :data:`CONFIGS`.
"""

from __future__ import annotations

import datetime
import io
import math
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from ..errors import InputError
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..metrics.masks import penumbra_mask
from ..pipeline import load_scene, reference_frames, shimmer
from ..reference import store
from ..reference.truth import centre_visibility
from ..render.frame import make_frame
from ..techniques import base
from ..techniques.shadow_map import RES_MAX, RES_MIN
from .timing import machine_text, render_evaluated, timed

SCENE = "street"
PATH_SCENE = "boulevard"
LIGHT = "sun"
XIS = (0, 1, 2, 3, 4, 5)
#: [Giegl 2007]'s results: fitted virtual shadow maps at least this many times faster than the
#: brute-force virtual tiled shadow map
CLAIMED_SPEEDUP = 10.0
BYTES_PER_TEXEL = 4
#: label of fvsm in the equal-memory comparison
FVSM_LABEL = "fvsm, ξ = 0, pow2 textures"


@dataclass(frozen=True)
class Config:
    """The sizes of one run: ``street`` at ``res`` (cost against ξ), ``boulevard`` at ``path_res``
    for ``frames`` frames (``committed``: the stored CI references, else truths rendered for the
    run), fvsm / vtsm with ``t_max`` and ``grid``, ``repeats`` warm renders per timing (vtsm:
    ``vtsm_repeats``)."""

    res: tuple
    path_res: tuple
    frames: int
    t_max: int
    grid: int
    repeats: int
    vtsm_repeats: int
    committed: bool


CONFIGS = {
    "full": Config((512, 288), (256, 144), 16, 1024, 8, 5, 3, False),
    "quick": Config((128, 72), (128, 72), 4, 256, 4, 2, 2, True),
    # the paper's sizes ([Giegl 2007, §3, §5]: 4096² tiles, 16 per axis, a 1024-pixel-wide frame),
    # which a full run takes on a GPU (cuda variants): 16² VTSM tiles of 4096² are 4.3 G rays
    "paper": Config((1024, 576), (256, 144), 8, 4096, 16, 3, 2, False),
}


def config_name(quick: bool) -> str:
    """``quick``, or ``paper`` on a CUDA variant, else ``full``."""
    return "quick" if quick else ("paper" if mi.variant().startswith("cuda") else "full")


# ----------------------------------------------------------------------------------------------
# measures

@dataclass
class Target:
    """What a frame's visibility is measured against: the frame, the valid pixels the light
    reaches (H, W), the centre's exact visibility (H, W) and the area-light truth V (None: not
    rendered)."""

    frame: object
    valid: np.ndarray
    centre: np.ndarray
    V: np.ndarray | None = None


def hard_error_rate(v, centre, valid) -> float:
    """Share of ``valid`` pixels where (v ≥ ½) ≠ (centre ≥ ½); 0.0 with no valid pixel."""
    n = int(np.count_nonzero(valid))
    wrong = (np.asarray(v) >= 0.5) != (np.asarray(centre) >= 0.5)
    return float(np.count_nonzero(wrong & valid)) / n if n else 0.0


def rmse_off_penumbra(v, V, valid) -> float:
    """RMSE of ``v`` against the truth ``V`` over the ``valid`` pixels outside its penumbra."""
    away = valid & ~penumbra_mask(V, valid)
    if not away.any():
        return 0.0
    return float(np.sqrt(np.mean((np.asarray(v, np.float64)[away] - np.asarray(V, np.float64)[away]) ** 2)))


def measures(target: Target, result) -> dict:
    v = target.frame.image(result.visibility[LIGHT])
    out = {"hard_error_rate": hard_error_rate(v, target.centre, target.valid)}
    if target.V is not None:
        out["rmse_off_penumbra"] = rmse_off_penumbra(v, target.V, target.valid)
    return out


def light_stats(result) -> dict:
    """The sun's per-light stats of a virtual map (or a map's texels and memory)."""
    s = result.stats
    out = {k: s[k][LIGHT] for k in ("tiles", "texels", "memory_bytes", "memory_modes", "traversal_depth",
                                    "demand", "unshadowed_fraction", "hit_texels")
           if isinstance(s.get(k), dict) and LIGHT in s[k]}
    if "memory_bytes" not in out:        # an ordinary map or cascades: its texels, 4 bytes each
        out["texels"] = int(s.get("shadow_map_texels", 0))
        out["memory_bytes"] = BYTES_PER_TEXEL * out["texels"]
    return out


def _target(frame, V=None, mask=None) -> Target:
    gb = frame.gbuffer
    if mask is None:
        mask = gb.to_image(gb.mask.reshape(-1).astype(np.float32)) > 0.5
    centre = frame.image(centre_visibility(frame, LIGHT))
    return Target(frame, mask & frame.lit_mask(LIGHT), centre, V)


def _fvsm(cfg: Config, xi: int) -> dict:
    return {"xi": int(xi), "t_max": cfg.t_max, "grid": cfg.grid, "tile_mode": "pow2"}


def _vtsm(t_max: int, grid: int) -> dict:
    return {"t_max": int(t_max), "grid": int(grid)}


# ----------------------------------------------------------------------------------------------
# 1 + 2: cost and tiles against ξ, fitted against brute force (street)

def timed_render(name: str, params: dict, target: Target, repeats: int) -> dict:
    """Median seconds of ``repeats`` warm renders (one untimed render compiles), the stats and
    the hard-shadow error of the last."""
    t = base.get(name)
    p = t.resolve(params)
    r, ts = timed(lambda: render_evaluated(t, target.frame, p), repeats, warmup=1)
    return {"params": params, "frame_s": float(np.median(ts)), "runs_s": ts, **light_stats(r),
            **measures(target, r)}


def bench_cost(cfg: Config) -> dict:
    sc = load_scene(SCENE, cfg.res)
    target = _target(make_frame(sc))
    fv = {xi: timed_render("fvsm", _fvsm(cfg, xi), target, cfg.repeats) for xi in XIS}
    vt = timed_render("vtsm", _vtsm(cfg.t_max, cfg.grid), target, cfg.vtsm_repeats)
    for row in fv.values():
        row["speedup_over_vtsm"] = vt["frame_s"] / row["frame_s"]
        row["tiles_fraction_of_vtsm"] = row["tiles"] / vt["tiles"]
    return {"scene": SCENE, "resolution": list(cfg.res), "t_max": cfg.t_max, "grid": cfg.grid,
            "repeats": cfg.repeats, "vtsm_repeats": cfg.vtsm_repeats, "fvsm": fv, "vtsm": vt,
            "claimed_speedup": CLAIMED_SPEEDUP}


# ----------------------------------------------------------------------------------------------
# 3 + 4: along boulevard's camera path

def path_targets(cfg: Config) -> list:
    """A :class:`Target` with the area-light truth for each frame of the path."""
    sc0 = load_scene(PATH_SCENE, cfg.path_res, frame=0)
    if cfg.frames > sc0.spec.frames:
        raise InputError(f"virtual bench: {cfg.frames} frames asked of {PATH_SCENE!r}, which has "
                         f"{sc0.spec.frames}; use at most {sc0.spec.frames}")
    with tempfile.TemporaryDirectory(prefix="shadowlab-bench-") as tmp:
        where = None if cfg.committed else Path(tmp)
        if where is not None:
            reference_frames(PATH_SCENE, cfg.path_res, frames=(0, cfg.frames - 1), base=where, progress=False)
        out = []
        for i in range(cfg.frames):
            sc = sc0.at_frame(i)
            truth, meta = store.load(sc.spec, sc.resolution, where)
            frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
            out.append(_target(frame, truth.lights[LIGHT].V, truth.mask))
    return out


def along_path(targets: list, name: str, params: dict) -> dict:
    """One render per frame: its measures and stats, and the frame-0 result (for the shimmer)."""
    t = base.get(name)
    p = t.resolve(params)
    rows, first = [], None
    for tg in targets:
        r = render_evaluated(t, tg.frame, p)
        first = r if first is None else first
        rows.append({**measures(tg, r), **light_stats(r)})
        tg.frame.clear_light_views()              # a map or cascade set is cast again where it is needed
    return {"technique": name, "params": params, "frames": rows, "summary": summarise(rows), "_first": (first, p)}


def summarise(rows: list) -> dict:
    """Mean over frames of the errors; mean and max of tiles and memory."""
    col = lambda k: np.array([r[k] for r in rows if k in r], np.float64)  # noqa: E731
    out = {}
    for k in ("hard_error_rate", "rmse_off_penumbra", "unshadowed_fraction"):
        if len(col(k)):
            out[k] = float(col(k).mean())
    for k in ("tiles", "texels", "memory_bytes"):
        if len(col(k)):
            out[k] = {"mean": float(col(k).mean()), "max": float(col(k).max())}
    return out


def bench_xi(cfg: Config, targets: list) -> dict:
    rows = {xi: along_path(targets, "fvsm", _fvsm(cfg, xi)) for xi in XIS}
    return {"scene": PATH_SCENE, "resolution": list(cfg.path_res), "frames": cfg.frames, "t_max": cfg.t_max,
            "grid": cfg.grid, "xi": rows}


def equal_memory_configs(cfg: Config, budget: int) -> dict:
    """(technique, params) of the equal-memory comparison but fvsm, sized to ``budget`` bytes (a
    map's side within the shadow maps' range: the table states the memory each used)."""
    texels = budget / BYTES_PER_TEXEL
    side = lambda n: min(max(int(math.sqrt(texels / n)), RES_MIN), RES_MAX)  # noqa: E731
    r3, r1 = side(3), side(1)
    tv = 2 ** int(round(math.log2(max(math.sqrt(texels), 1.0))))
    return {"csm, 3 cascades, hard filter": ("csm", {"cascades": 3, "filter": "hard", "resolution": r3}),
            "vtsm": ("vtsm", _vtsm(tv, cfg.grid)),
            "one focused map (csm, 1 cascade, hard filter)": ("csm", {"cascades": 1, "filter": "hard",
                                                                       "resolution": r1}),
            "one scene-fitted map (hard)": ("hard", {"resolution": r1})}


def bench_equal_memory(cfg: Config, targets: list, fvsm_row: dict) -> dict:
    budget = int(fvsm_row["summary"]["memory_bytes"]["max"])
    rows = {FVSM_LABEL: fvsm_row}
    for label, (name, params) in equal_memory_configs(cfg, budget).items():
        rows[label] = along_path(targets, name, params)
    fixed = targets[0].frame
    scenes = [tg.frame.scene for tg in targets]
    results = {label: row["_first"] for label, row in rows.items()}
    techs = {label: base.get(row["technique"]) for label, row in rows.items()}
    sh = shimmer(scenes, fixed, results, techniques=techs)
    return {"scene": PATH_SCENE, "resolution": list(cfg.path_res), "frames": cfg.frames, "grid": cfg.grid,
            "budget_bytes": budget, "rows": rows, "shimmer": sh}


# ----------------------------------------------------------------------------------------------
# the report

def _mib(b) -> str:
    return f"{float(b) / 2 ** 20:.2f}"


def _ran(m: dict, scene: str, res, extra: str) -> str:
    gpu = f", {m['gpu']}" if m.get("gpu") else ""
    return (f"Ran: `{scene}`, {res[0]}×{res[1]}, {extra}; {m['cpu']}, {m['cores']} cores{gpu}, variant {m['variant']}.")


def _cost_md(c: dict, m: dict) -> list:
    lines = [
        f"## Cost and tiles against ξ (fvsm, {c['scene']})",
        "",
        _ran(m, c["scene"], c["resolution"], f"t_max {c['t_max']}, grid {c['grid']}, sun"),
        "",
        f"Frame = the technique's whole render (demand, tiles ray cast one ray a texel, deferred pass), median of "
        f"{c['repeats']} warm renders (vtsm: {c['vtsm_repeats']}) after one untimed. Memory of the tile textures per "
        "mode (MiB, 4 bytes a texel, [Giegl 2007, §4.10]); depth: the deepest pyramid level a tile sits on; "
        "demand: the root's [L_x, L_y] (a virtual map of 2^L texels per axis); unshadowed: pixels no tile wrote; "
        "error: hard-shadow error rate against the light centre's exact visibility.",
        "",
        "| ξ | frame (ms) | tiles | texels (rays) | subrect | pow2 | exact | depth | demand | unshadowed | error rate "
        "|",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for xi, r in c["fvsm"].items():
        mm = r["memory_modes"]
        lines.append(f"| {xi} | {1e3 * r['frame_s']:.1f} | {r['tiles']} | {r['texels']:,} | {_mib(mm['subrect'])} | "
                     f"{_mib(mm['pow2'])} | {_mib(mm['exact'])} | {r['traversal_depth']} | {r.get('demand')} | "
                     f"{r['unshadowed_fraction']:.4f} | {r['hard_error_rate']:.4f} |")
    v = c["vtsm"]
    lines.append(f"| vtsm | {1e3 * v['frame_s']:.1f} | {v['tiles']} | {v['texels']:,} | {_mib(v['memory_bytes'])} | "
                 f"{_mib(v['memory_bytes'])} | {_mib(v['memory_bytes'])} | {v['traversal_depth']} | – | "
                 f"{v['unshadowed_fraction']:.4f} | {v['hard_error_rate']:.4f} |")
    return lines


def _versus_md(c: dict, m: dict) -> list:
    v = c["vtsm"]
    sp = [r["speedup_over_vtsm"] for r in c["fvsm"].values()]
    lines = ["", f"## Fitted against brute force (fvsm vs vtsm, {c['scene']})", "",
             _ran(m, c["scene"], c["resolution"], f"t_max {c['t_max']}, grid {c['grid']} for both"), "",
             f"[Giegl 2007] claims fitted virtual shadow maps are at least {c['claimed_speedup']:g}× faster than the "
             f"brute-force virtual tiled shadow map; measured here: **{min(sp):.1f}× … {max(sp):.1f}×** "
             f"(vtsm {1e3 * v['frame_s']:.1f} ms, {v['tiles']} tiles of {c['t_max']}², error rate "
             f"{v['hard_error_rate']:.4f}).", "",
             "| ξ | vtsm time / fvsm time | claim | fvsm error rate | vtsm error rate | fvsm tiles / vtsm tiles |",
             "|---|---|---|---|---|---|"]
    for xi, r in c["fvsm"].items():
        lines.append(f"| {xi} | {r['speedup_over_vtsm']:.1f}× | ≥ {c['claimed_speedup']:g}× | "
                     f"{r['hard_error_rate']:.4f} | {v['hard_error_rate']:.4f} | {r['tiles_fraction_of_vtsm']:.3f} |")
    return lines


def _xi_md(x: dict, m: dict) -> list:
    lines = ["", f"## Aliasing error along the camera path (fvsm, {x['scene']}, {x['frames']} frames)", "",
             _ran(m, x["scene"], x["resolution"], f"frames 0–{x['frames'] - 1}, t_max {x['t_max']}, grid {x['grid']}, "
                                                  "pow2 textures"), "",
             "Error rate: share of the valid pixels the sun reaches where the technique's (V ≥ ½) differs from the "
             "light centre's exact ray-traced visibility; RMSE: against the area-light truth, over its pixels "
             "outside the penumbra (V ≤ 0.02 or ≥ 0.98). Means over the frames; tiles and memory per frame.", "",
             "| ξ | error rate | RMSE off penumbra | tiles mean / max | memory MiB mean / max | unshadowed |",
             "|---|---|---|---|---|---|"]
    for xi, row in x["xi"].items():
        s = row["summary"]
        lines.append(f"| {xi} | {s['hard_error_rate']:.4f} | {s['rmse_off_penumbra']:.4f} | "
                     f"{s['tiles']['mean']:.1f} / {s['tiles']['max']:.0f} | {_mib(s['memory_bytes']['mean'])} / "
                     f"{_mib(s['memory_bytes']['max'])} | {s['unshadowed_fraction']:.4f} |")
    return lines


def _params_text(p: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in p.items())


def _equal_md(e: dict, m: dict, plot: str) -> list:
    sh = e["shimmer"]
    tr = sh["truth"]
    lines = ["", f"## Equal memory ({e['scene']}, {e['frames']} frames)", "",
             _ran(m, e["scene"], e["resolution"], f"frames 0–{e['frames'] - 1}, grid {e['grid']} (vtsm)"), "",
             f"Budget: fvsm's largest tile-texture memory along the path, {e['budget_bytes']:,} bytes "
             f"({_mib(e['budget_bytes'])} MiB); 4 bytes a texel. csm and the single maps take the largest resolution "
             "whose texels fit in it; vtsm the power-of-two t_max whose t_max² is nearest to it. The focused single "
             "map is csm with one "
             "cascade (sphere fit of the view frustum, snapped); `hard` fits the whole scene. Errors as above, means "
             f"over the frames; shimmer: |V_t(x) − V_(t−1)(x)| at frame 0's points over the path's frame pairs "
             f"(truth: {tr['pooled']['mean'] if tr['pooled'] else 'n/a'}, {tr['why']}).", "",
             "| technique | parameters | memory (bytes, mean / max) | error rate | RMSE off penumbra | shimmer mean | "
             "shimmer p99 | shimmer max |", "|---|---|---|---|---|---|---|---|"]
    for label, row in e["rows"].items():
        s, pl = row["summary"], sh["techniques"][label]["pooled"]
        mem = s["memory_bytes"]
        lines.append(f"| {label} | {_params_text(row['params'])} | {mem['mean']:,.0f} / {mem['max']:,.0f} | "
                     f"{s['hard_error_rate']:.4f} | {s['rmse_off_penumbra']:.4f} | {pl['mean']:.5f} | "
                     f"{pl['p99']:.4f} | {pl['max']:.4f} |")
    lines += ["", f"![error per frame and shimmer at equal memory; fvsm against ξ]({plot})"]
    return lines


def markdown(res: dict) -> str:
    m = res["machine"]
    lines = [f"# Virtual shadow maps ({res['date']})", "",
             f"Machine: {machine_text(m)}. All figures from one run ({res['wall_s']:.0f} s)"
             f"{' (--quick: small sizes, not for figures)' if res['quick'] else ''}.", ""]
    lines += _cost_md(res["cost"], m) + _versus_md(res["cost"], m) + _xi_md(res["xi"], m)
    lines += _equal_md(res["equal_memory"], m, res["plot"])
    return "\n".join(lines) + "\n"


def plot(res: dict) -> bytes:
    """PNG: fvsm's frame time and tiles against ξ, the error rate and RMSE per frame of each
    technique at equal memory, and their shimmer."""
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator
    c, e = res["cost"], res["equal_memory"]
    fig, ax = plt.subplots(2, 2, figsize=(11, 7.5), dpi=100)
    xis = [int(k) for k in c["fvsm"]]
    a = ax[0, 0]
    a.plot(xis, [1e3 * r["frame_s"] for r in c["fvsm"].values()], "o-", color="tab:blue", label="fvsm frame (ms)")
    a.axhline(1e3 * c["vtsm"]["frame_s"], color="tab:red", ls="--", lw=1, label="vtsm frame (ms)")
    a.set_yscale("log")
    a.set_xlabel("ξ")
    a.set_ylabel("frame (ms)")
    a2 = a.twinx()
    a2.plot(xis, [r["tiles"] for r in c["fvsm"].values()], "s:", color="tab:green", label="fvsm tiles")
    a2.set_ylabel("tiles")
    a2.yaxis.set_major_locator(MaxNLocator(integer=True))
    a.legend(handles=a.get_legend_handles_labels()[0] + a2.get_legend_handles_labels()[0], fontsize=7)
    a.set_title(f"{c['scene']} {c['resolution'][0]}×{c['resolution'][1]}, t_max {c['t_max']}, grid {c['grid']}",
                fontsize=9)
    frames = np.arange(e["frames"])
    for key, a, ylabel in (("hard_error_rate", ax[0, 1], "hard-shadow error rate"),
                           ("rmse_off_penumbra", ax[1, 0], "RMSE off penumbra")):
        for label, row in e["rows"].items():
            a.plot(frames, [f[key] for f in row["frames"]], "o-", ms=3, lw=1, label=label)
        a.set_xlabel(f"{e['scene']} frame")
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.set_ylabel(ylabel)
        a.grid(alpha=0.3)
    ax[0, 1].legend(fontsize=7)
    ax[0, 1].set_title(f"equal memory: {_mib(e['budget_bytes'])} MiB", fontsize=9)
    a = ax[1, 1]
    labels = list(e["rows"])
    a.bar(range(len(labels)), [e["shimmer"]["techniques"][k]["pooled"]["mean"] for k in labels],
          color=[f"C{i}" for i in range(len(labels))])       # the colours of the error lines above
    a.set_xticks(range(len(labels)), [k.split(" (")[0].split(",")[0] for k in labels], fontsize=7, rotation=15)
    a.set_ylabel("shimmer (mean |ΔV|)")
    a.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _strip(obj):
    """The results without the frame-0 renders kept for the shimmer."""
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k != "_first"}
    return obj


def run(out: Path, quick: bool = False) -> Path:
    """Measure; write ``out/virtual.json``, ``out/virtual.md`` and ``out/virtual.png``; return the
    .md path."""
    backend.init()
    cfg = CONFIGS[config_name(quick)]
    dr.sync_thread()
    t0 = time.perf_counter()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick, "config": asdict(cfg), "plot": "virtual.png"}
    res["cost"] = bench_cost(cfg)
    targets = path_targets(cfg)
    res["xi"] = bench_xi(cfg, targets)
    res["equal_memory"] = bench_equal_memory(cfg, targets, res["xi"]["xi"][0])
    res = _strip(res)
    dr.sync_thread()
    res["wall_s"] = time.perf_counter() - t0
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(out / res["plot"], plot(res))
    write_json_atomic(out / "virtual.json", res)
    return write_bytes_atomic(out / "virtual.md", markdown(res).encode())
