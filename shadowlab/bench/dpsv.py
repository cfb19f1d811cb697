"""Shadow maps fused with deep partitioned shadow volumes measured ([Wang 2022, §1.2–1.4]):
``shadowlab bench --only dpsv`` (``dpsv.json``, ``dpsv.md``; the full ``shadowlab bench`` writes
them too).

Every figure from one run:

* **hard shadows**: ``hard`` (the shadow map), ``sm_dpsv`` (fused) and ``dpsv`` (the TOP tree at
  every point), default parameters, on two scenes built here: a generated mesh floor (a displaced
  grid, :data:`CONFIGS`' ``grid`` quads a side, two triangles each) under a large slab ("large
  shadow") or under a few small cubes ("little shadow"), each lit by a point light and by a
  directional light. Time: median of warm renders after one untimed, the light's shadow map and
  TOP tree already cached on the frame (their cast and build are reported apart). The ratios
  fused/SM and fused/DPSV stand beside the source's (:data:`PAPER`); the edge fraction and nodes
  per query come from the renders' stats; mismatches are the valid pixels the light reaches where
  (V > ½) ≠ (V_centre > ½), V_centre the exact visibility of the light's centre
  (:func:`shadowlab.reference.truth.centre_visibility`);
* **soft shadows**: ``sm_dpsv_soft`` against ``pcss`` on ``parallel_planes`` (rect light): the
  time ratio and each one's visibility RMSE against the stored truth (``--quick``: the committed
  CI reference; otherwise one rendered for the run) and against each other;
* **build time against triangle count**: :func:`shadowlab.render.top_tree.build_top_tree` (on the
  device, its kernels compiled by an untimed build first) on a displaced grid and on a field of small
  boxes of about :data:`CONFIGS`' ``build_sizes`` triangles under a point light: seconds, nodes,
  depth, dropped (the goal: 70 000 triangles in ≤ :data:`BUILD_GOAL_S` s on 2 cores; reported, not
  asserted).
"""

from __future__ import annotations

import datetime
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import backend
from ..exchange.ply import write_ply
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..pipeline import load_scene, reference, technique_metrics
from ..reference import store
from ..reference.truth import centre_visibility
from ..render.frame import make_frame
from ..render.top_tree import build_top_tree
from ..scene import build, parse
from ..techniques import base
from ..techniques.shadow_map import view_for
from .timing import machine_text, render_evaluated, timed

HARD = ("hard", "sm_dpsv", "dpsv")
SOFT = ("pcss", "sm_dpsv_soft")
SOFT_SCENE = "parallel_planes"
#: the source's figures [Wang 2022]: time ratios fused/SM (≈ 50 % slower), fused/DPSV (29.8 % faster),
#: soft/PCSS (63 % slower)
PAPER = {"fused_over_sm": 1.5, "fused_over_dpsv": 1.0 - 0.298, "soft_over_pcss": 1.63}
#: the build-time goal: 70 000 triangles under a point light on 2 cores
BUILD_GOAL_S = 10.0
BUILD_GOAL_TRIANGLES = 70_000
#: a render slower than this (s) is timed :data:`SLOW_REPEATS` times, without a second warm-up
SLOW_S = 1.0
SLOW_REPEATS = 3


@dataclass(frozen=True)
class Config:
    """One run's sizes: the hard-shadow scenes at ``res``² with a ``grid``×``grid``-quad floor and
    ``shadow_map``-texel maps, ``repeats`` warm renders per timing; ``parallel_planes`` at
    ``soft_res``² (``committed``: the stored CI reference, else a truth rendered for the run);
    TOP-tree builds of about ``build_sizes`` triangles."""

    res: int
    grid: int
    shadow_map: int
    repeats: int
    soft_res: int
    committed: bool
    build_sizes: tuple


CONFIGS = {
    "full": Config(384, 160, 1024, 7, 512, False, (1000, 4000, 16000, 70000)),
    "quick": Config(80, 40, 512, 3, 128, True, (1000, 4000)),
    # [Wang 2022, §2]: 1024² frame and map, scenes of 54 783 to 170 487 triangles (a GPU's sizes)
    "paper": Config(1024, 260, 1024, 7, 1024, False, (1000, 4000, 16000, 70000, 135000)),
}

LIGHT_POS = (0.6, 4.0, 0.4)
LIGHTS = {
    "point": {"name": "L", "kind": "point", "position": list(LIGHT_POS), "intensity": 30.0},
    "directional": {"name": "L", "kind": "directional", "direction": [0.3, -1.0, 0.4], "irradiance": 3.0},
}
CAMERA = {"position": [0.0, 4.5, 4.5], "target": [0.0, 0.0, 0.3], "fov": 50}
FLOOR = {"name": "floor", "type": "ply", "filename": "floor.ply", "albedo": [0.7, 0.7, 0.7]}
#: the occluders of each scene over the mesh floor
OCCLUDERS = {
    "large shadow": [
        {"name": "slab", "type": "cube", "translate": [0.0, 1.2, 0.1], "rotate": [0, 1, 0, 20],
         "scale": [1.9, 0.05, 1.5]},
        {"name": "block", "type": "cube", "translate": [-1.6, 0.6, -1.2], "scale": [0.45, 0.6, 0.45]},
    ],
    "little shadow": [
        {"name": f"cube{i}", "type": "cube", "translate": [x, 0.15, z], "rotate": [0, 1, 0, 25 * i], "scale": 0.12}
        for i, (x, z) in enumerate([(-1.2, 0.8), (0.9, -0.6), (0.2, 1.4), (-0.5, -1.3)])
    ],
}


def config_name(quick: bool) -> str:
    """``quick``, or ``paper`` on a CUDA variant, else ``full``."""
    return "quick" if quick else ("paper" if mi.variant().startswith("cuda") else "full")


# ----------------------------------------------------------------------------------------------
# generated meshes

def displaced_grid(n: int, half: float = 3.0, amp: float = 0.03):
    """(positions, normals, uvs, faces) of an n×n-quad grid over [−half, half]² in y = 0,
    displaced by amp·sin(3.1x)·cos(2.3z): 2n² triangles, counter-clockwise seen from above."""
    xs = np.linspace(-half, half, n + 1)
    X, Z = np.meshgrid(xs, xs, indexing="xy")
    Y = amp * np.sin(3.1 * X) * np.cos(2.3 * Z)
    P = np.stack([X, Y, Z], -1).reshape(-1, 3)
    dx = amp * 3.1 * np.cos(3.1 * X) * np.cos(2.3 * Z)
    dz = -amp * 2.3 * np.sin(3.1 * X) * np.sin(2.3 * Z)
    N = np.stack([-dx, np.ones_like(X), -dz], -1).reshape(-1, 3)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    UV = np.stack([(X + half) / (2 * half), (Z + half) / (2 * half)], -1).reshape(-1, 2)
    i = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    a, b, c, d = i, i + 1, i + n + 1, i + n + 2
    F = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    return P, N, UV, F


_CUBE_V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
_CUBE_F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                    [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


def box_field(k: int, half: float = 2.5, seed: int = 0):
    """(positions, faces) of ``k`` random small axis-aligned boxes (12 triangles each) over
    [−half, half]², 0.05 … 1.5 above y = 0."""
    rng = np.random.default_rng(seed)
    c = np.stack([rng.uniform(-half, half, k), rng.uniform(0.05, 1.5, k), rng.uniform(-half, half, k)], 1)
    s = rng.uniform(0.02, 0.08, (k, 1, 3))
    P = (_CUBE_V[None] * s + c[:, None]).reshape(-1, 3)
    F = (_CUBE_F[None] + 8 * np.arange(k)[:, None, None]).reshape(-1, 3)
    return P, F


# ----------------------------------------------------------------------------------------------
# 1: hard shadows

def _scene(tmp: Path, name: str, light: str, cfg: Config):
    spec = {"name": name.replace(" ", "_") + "_" + light,
            "camera": {**CAMERA, "resolution": [cfg.res, cfg.res]},
            "lights": [{**LIGHTS[light], "shadow_map": cfg.shadow_map}],
            "shapes": [FLOOR] + OCCLUDERS[name]}
    return build(parse(spec, str(tmp / "scene.toml")))


def _mismatch(v, centre, valid) -> dict:
    wrong = int(np.count_nonzero(((v > 0.5) != (centre > 0.5)) & valid))
    n = int(np.count_nonzero(valid))
    return {"mismatches": wrong, "mismatch_fraction": wrong / n if n else 0.0}


def _light_stat(r, key):
    s = r.stats.get(key)
    return float(s["L"]) if isinstance(s, dict) and "L" in s else None


def time_render(t, frame, p, repeats: int):
    """(last result, seconds of the first run, seconds of each warm run): a first run (it compiles),
    one untimed warm-up, then ``repeats`` timed renders. A first run slower than :data:`SLOW_S`:
    no warm-up and :data:`SLOW_REPEATS` timed renders (its compile is small beside it)."""
    _, (first,) = timed(lambda: render_evaluated(t, frame, p))
    slow = first > SLOW_S
    r, ts = timed(lambda: render_evaluated(t, frame, p), min(repeats, SLOW_REPEATS) if slow else repeats,
                  warmup=0 if slow else 1)
    return r, first, ts


def bench_case(tmp: Path, name: str, light: str, cfg: Config) -> dict:
    """One scene and light: map cast, tree build, and per technique the warm time, stats and
    mismatches against the light centre's exact visibility."""
    frame = make_frame(_scene(tmp, name, light, cfg), u_strata=1)
    gb = frame.gbuffer
    valid = (gb.to_image(gb.mask.reshape(-1).astype(np.float32)) > 0.5) & frame.lit_mask("L")
    centre = frame.image(centre_visibility(frame, "L"))
    shadowed = float(np.count_nonzero((centre < 0.5) & valid) / max(np.count_nonzero(valid), 1))
    hard = base.get("hard").resolve({})
    _, (cast_first,) = timed(lambda: view_for(frame, "L", hard))       # the first cast compiles
    frame.clear_light_views()
    _, (cast_warm,) = timed(lambda: view_for(frame, "L", hard))
    tp = base.get("dpsv").resolve({})
    tree = frame.top_tree("L", int(tp["segments"]), tp["order"])       # built once, cached on the frame
    rows = {}
    for n in HARD:
        t = base.get(n)
        p = t.resolve({})
        r, first, ts = time_render(t, frame, p, cfg.repeats)
        row = {"first_run_s": first, "warm_s": float(np.median(ts)), "runs_s": ts,
               **_mismatch(frame.image(r.visibility["L"]), centre, valid)}
        for k in ("edge_fraction", "nodes_per_query"):
            if _light_stat(r, k) is not None:
                row[k] = _light_stat(r, k)
        rows[n] = row
    h, f, d = (rows[n]["warm_s"] for n in HARD)
    orders = {}
    for order in BUILD_ORDERS:
        t = base.get("dpsv")
        p = t.resolve({"order": order})
        r, _, ts = time_render(t, frame, p, cfg.repeats)
        orders[order] = {"warm_s": float(np.median(ts)), "nodes_per_query": _light_stat(r, "nodes_per_query"),
                         "depth": r.stats["tree_depth"]["L"], "dropped": r.stats["tree_dropped"]["L"],
                         "build_s": r.stats["tree_build_seconds"]["L"],
                         **_mismatch(frame.image(r.visibility["L"]), centre, valid)}
    return {"scene": name, "light": light, "resolution": [cfg.res, cfg.res], "shadow_map": cfg.shadow_map,
            "triangles": int(len(frame.triangles(int(tp["segments"])))), "valid_pixels": int(valid.sum()),
            "shadowed_fraction": shadowed, "map_cast_first_s": cast_first, "map_cast_s": cast_warm,
            "tree": tree.stats(), "techniques": rows, "fused_over_sm": f / h, "fused_over_dpsv": f / d,
            "orders": orders}


def bench_hard(cfg: Config) -> dict:
    with tempfile.TemporaryDirectory(prefix="shadowlab-dpsv-") as tmp:
        tmp = Path(tmp)
        P, N, UV, F = displaced_grid(cfg.grid)
        write_ply(tmp / "floor.ply", P, N, UV, F, comment="shadowlab bench dpsv: displaced grid")
        cases = [bench_case(tmp, name, light, cfg) for light in LIGHTS for name in OCCLUDERS]
    return {"floor_triangles": int(len(F)), "grid": cfg.grid, "repeats": cfg.repeats, "cases": cases,
            "paper": PAPER}


# ----------------------------------------------------------------------------------------------
# 2: soft shadows

def bench_soft(cfg: Config) -> dict:
    res = (cfg.soft_res, cfg.soft_res)
    sc = load_scene(SOFT_SCENE, res)
    with tempfile.TemporaryDirectory(prefix="shadowlab-dpsv-") as tmp:
        if not cfg.committed:
            reference(SOFT_SCENE, res, base=Path(tmp), progress=False)
        truth, meta = store.load(sc.spec, sc.resolution, None if cfg.committed else Path(tmp))
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    light = sc.spec.lights[0].name
    valid = truth.mask & frame.lit_mask(light)
    params = {n: base.get(n).resolve({}) for n in SOFT}
    casts = [timed(lambda: view_for(frame, light, params[n]))[1][0] for n in SOFT]  # the same map: cast once
    tp = params["sm_dpsv_soft"]
    tree = frame.top_tree(light, int(tp["segments"]), tp["order"])
    rows, vis = {}, {}
    for n in SOFT:
        t, p = base.get(n), params[n]
        r, first, ts = time_render(t, frame, p, cfg.repeats)
        m, _, _ = technique_metrics(frame, truth, r)
        vis[n] = frame.image(r.visibility[light]).astype(np.float64)
        rows[n] = {"first_run_s": first, "warm_s": float(np.median(ts)), "runs_s": ts,
                   "vis_rmse": float(m["vis_rmse"]), "vis_rmse_penumbra": float(m["vis_rmse_penumbra"])}
        for k in ("edge_fraction", "nodes_per_query"):
            s = r.stats.get(k)
            if isinstance(s, dict) and light in s:
                rows[n][k] = float(s[light])
    diff = (vis["sm_dpsv_soft"] - vis["pcss"])[valid]
    return {
        "scene": SOFT_SCENE,
        "light": light,
        "kind": sc.spec.lights[0].kind,
        "resolution": list(res),
        "truth": "committed CI reference" if cfg.committed else "rendered for the run",
        "map_cast_first_s": casts[0],
        "tree": tree.stats(),
        "techniques": rows,
        "soft_over_pcss": rows["sm_dpsv_soft"]["warm_s"] / rows["pcss"]["warm_s"],
        "rmse_soft_vs_pcss": float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0,
        "paper_soft_over_pcss": PAPER["soft_over_pcss"],
    }


# ----------------------------------------------------------------------------------------------
# 3: build time against triangle count

#: insertion orders the build table compares (the default first)
BUILD_ORDERS = ("random", "light")


def _build_rows(mesh: str, V: np.ndarray) -> list:
    rows = []
    for order in BUILD_ORDERS:
        build_top_tree(V, np.array([*LIGHT_POS, 1.0]), order=order)   # untimed: compiles the build's kernels
        tree = build_top_tree(V, np.array([*LIGHT_POS, 1.0]), order=order)
        rows.append({"mesh": mesh, "order": order, "input_triangles": int(len(V)), **tree.stats()})
    return rows


def bench_build(cfg: Config) -> dict:
    rows = []
    for T in cfg.build_sizes:
        n = max(1, int(round(np.sqrt(T / 2))))
        P, _, _, F = displaced_grid(n)
        rows += _build_rows("displaced grid", P[F])
        P, F = box_field(max(1, T // 12))
        rows += _build_rows("box field", P[F])
    big = [r for r in rows if r["input_triangles"] >= 0.95 * BUILD_GOAL_TRIANGLES]
    return {"light": list(LIGHT_POS), "rows": rows, "goal_s": BUILD_GOAL_S, "goal_triangles": BUILD_GOAL_TRIANGLES,
            "goal_met": (all(r["build_seconds"] <= BUILD_GOAL_S for r in big) if big else None)}


# ----------------------------------------------------------------------------------------------
# the report

def _ms(s) -> str:
    return f"{1e3 * s:.2f}"


def _hard_md(h: dict) -> list:
    p = h["paper"]
    lines = [
        "## Hard shadows: fused (sm_dpsv) against the shadow map (hard) and DPSV alone (dpsv)",
        "",
        f"Scenes built for the run: a displaced-grid floor of {h['floor_triangles']:,} triangles "
        f"({h['grid']}×{h['grid']} quads, a PLY mesh) under a large slab and a block (*large shadow*) or four "
        "small cubes (*little shadow*), one light each. Time: the technique's render, median of "
        f"{h['repeats']} warm renders, not counting the first (it compiles; in the second table) and one "
        f"warm-up (a first render over {SLOW_S:.0f} s: {SLOW_REPEATS} renders, no warm-up); the shadow map "
        "and the TOP tree are cached on the frame before (cast and build below, not in the time). Edge: share of the "
        "valid points `sm_dpsv` "
        "classifies as shadow-edge points; nodes/query: mean nodes visited per tree query. Mismatches: valid "
        "pixels the light reaches where (V > ½) ≠ (V_centre > ½), V_centre the exact visibility of the "
        "light's centre.",
        "",
        "| scene | light | px | triangles | shadowed | hard (ms) | sm_dpsv (ms) | dpsv (ms) | fused/SM | "
        "fused/DPSV | edge | nodes/query sm_dpsv / dpsv | mismatches hard / sm_dpsv / dpsv |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in h["cases"]:
        t = c["techniques"]
        lines.append(
            f"| {c['scene']} | {c['light']} | {c['resolution'][0]}² | {c['triangles']:,} | "
            f"{100 * c['shadowed_fraction']:.1f} % | {_ms(t['hard']['warm_s'])} | {_ms(t['sm_dpsv']['warm_s'])} | "
            f"{_ms(t['dpsv']['warm_s'])} | **{c['fused_over_sm']:.2f}×** | **{c['fused_over_dpsv']:.3f}×** | "
            f"{100 * t['sm_dpsv'].get('edge_fraction', 0.0):.2f} % | {t['sm_dpsv'].get('nodes_per_query', 0.0):.0f} / "
            f"{t['dpsv'].get('nodes_per_query', 0.0):.0f} | {t['hard']['mismatches']} / {t['sm_dpsv']['mismatches']} "
            f"/ {t['dpsv']['mismatches']} (of {c['valid_pixels']:,}) |")
    lines.append(f"| [Wang 2022] | | | | | | | | {p['fused_over_sm']:.2f}× | {p['fused_over_dpsv']:.3f}× | | | |")
    lines += ["", "The source: fused ≈ 50 % slower than a shadow map and 29.8 % faster than DPSV, gaining more where "
                  "shadows are large. Measured here, the fused method's speed-up over DPSV (DPSV time / fused time):"]
    for light in dict.fromkeys(c["light"] for c in h["cases"]):
        by = {c["scene"]: c for c in h["cases"] if c["light"] == light}
        if "large shadow" in by and "little shadow" in by:
            a, b = (1.0 / by[k]["fused_over_dpsv"] for k in ("large shadow", "little shadow"))
            lines.append(f"- {light} light: {a:.1f}× with large shadows, {b:.1f}× with little: it gains more where "
                         f"shadows are {'large' if a > b else 'little'}.")
    lines += ["", "Shared inputs (once per frame, not in the times above): the shadow map's cast (ray cast, first "
                  "incl. compile / again) and the TOP tree's build (Algorithm 1).", "",
              "| scene | light | map | map cast first / again (s) | tree build (s) | tree triangles | nodes | depth | "
              "dropped | degenerate | first run (ms) hard / sm_dpsv / dpsv |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in h["cases"]:
        tr, t = c["tree"], c["techniques"]
        lines.append(f"| {c['scene']} | {c['light']} | {c['shadow_map']}² | {c['map_cast_first_s']:.2f} / "
                     f"{c['map_cast_s']:.2f} | {tr['build_seconds']:.3f} | {tr['triangles']:,} | {tr['nodes']:,} | "
                     f"{tr['depth']} | {tr['dropped']} | {tr['degenerate']} | {_ms(t['hard']['first_run_s'])} / "
                     f"{_ms(t['sm_dpsv']['first_run_s'])} / {_ms(t['dpsv']['first_run_s'])} |")
    lines += ["", "Insertion order (Algorithm 1's `order`): `dpsv` with each order's own tree, time as above.", "",
              "| scene | light | order | depth | dropped | build (s) | nodes/query | dpsv (ms) | mismatches |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in h["cases"]:
        for order, o in c.get("orders", {}).items():
            lines.append(f"| {c['scene']} | {c['light']} | `{order}` | {o['depth']} | {o['dropped']} | "
                         f"{o['build_s']:.3f} | {o['nodes_per_query']:.0f} | {_ms(o['warm_s'])} | {o['mismatches']} |")
    return lines


def _soft_md(s: dict) -> list:
    t = s["techniques"]
    lines = [
        "",
        f"## Soft shadows: sm_dpsv_soft against pcss ({s['scene']}, {s['kind']} light)",
        "",
        f"{s['resolution'][0]}×{s['resolution'][1]}, default parameters; time as above. Before it, once: the "
        f"map's cast ({s['map_cast_first_s']:.2f} s, first incl. compile) and the TOP tree's build "
        f"({s['tree']['build_seconds']:.4f} s, {s['tree']['triangles']} triangles, {s['tree']['nodes']} nodes). RMSE "
        f"of the visibility against the truth ({s['truth']}) over the valid pixels the light "
        "reaches, and in its penumbra; between the two: RMSE of one's visibility against the other's.",
        "",
        "| technique | warm (ms) | first run (ms) | RMSE vs truth | RMSE in penumbra | edge | nodes/query |",
        "|---|---|---|---|---|---|---|",
    ]
    for n, r in t.items():
        e = f"{100 * r['edge_fraction']:.2f} %" if "edge_fraction" in r else "–"
        q = f"{r['nodes_per_query']:.1f}" if "nodes_per_query" in r else "–"
        lines.append(f"| {n} | {_ms(r['warm_s'])} | {_ms(r['first_run_s'])} | {r['vis_rmse']:.4f} | "
                     f"{r['vis_rmse_penumbra']:.4f} | {e} | {q} |")
    lines += ["", f"sm_dpsv_soft / pcss time: **{s['soft_over_pcss']:.2f}×** ([Wang 2022]: "
                  f"{s['paper_soft_over_pcss']:.2f}×, soft 63 % slower than PCSS); RMSE between them "
                  f"{s['rmse_soft_vs_pcss']:.4f}."]
    return lines


def _build_md(b: dict) -> list:
    lines = ["", "## TOP-tree build time against triangle count", "",
             "Algorithm 1 on the device (Dr.Jit kernels, level-synchronous: one round per tree level; its kernels "
             f"compiled by an untimed build first) under a point light at {tuple(b['light'])}, insertion order "
             "`random` (the default, a fixed permutation) and `light` (nearest first): a displaced grid (a "
             "heightfield, no triangle in another's shadow) and a field of small random boxes (12 triangles each, "
             "over each other).", "",
             "| mesh | order | triangles | build (s) | nodes | depth | rounds | dropped | degenerate |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in b["rows"]:
        lines.append(
            f"| {r['mesh']} | {r.get('order', 'light')} | {r['input_triangles']:,} | {r['build_seconds']:.3f} | "
            f"{r['nodes']:,} | "
            f"{r['depth']} | {r['build_rounds']} | {r['dropped']} | {r['degenerate']} |"
        )
    g = b["goal_met"]
    lines += ["", f"Goal: {b['goal_triangles']:,} triangles in ≤ {b['goal_s']:.0f} s on 2 cores: "
                  + ("not measured (no mesh that large in this run)" if g is None else ("met" if g else "**not met**"))
                  + "."]
    return lines


def markdown(res: dict) -> str:
    m = res["machine"]
    lines = [f"# Shadow maps fused with deep partitioned shadow volumes ({res['date']})", "",
             f"Machine: {machine_text(m)}. All figures from one run "
             f"({res['wall_s']:.0f} s), configuration `{res.get('config_name', 'full')}`"
             f"{' (--quick: small sizes, not for figures)' if res['quick'] else ''}. "
             "[Wang 2022] measured on a GPU (GTX 1650); the ratios here are of Dr.Jit "
             f"{'CUDA kernels on this GPU' if m.get('gpu') else 'LLVM kernels on this CPU'}.", ""]
    lines += _hard_md(res["hard"]) + _soft_md(res["soft"]) + _build_md(res["build"])
    return "\n".join(lines) + "\n"


def run(out: Path, quick: bool = False) -> Path:
    """Measure; write ``out/dpsv.json`` and ``out/dpsv.md``; return the .md path."""
    backend.init()
    cfg = CONFIGS[config_name(quick)]
    dr.sync_thread()
    t0 = time.perf_counter()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "variant": mi.variant(), "quick": quick, "config_name": config_name(quick), "config": asdict(cfg)}
    res["hard"] = bench_hard(cfg)
    res["soft"] = bench_soft(cfg)
    res["build"] = bench_build(cfg)
    dr.sync_thread()
    res["wall_s"] = time.perf_counter() - t0
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "dpsv.json", res)
    return write_bytes_atomic(out / "dpsv.md", markdown(res).encode())
