"""Scaling of the Dask executor [Dask 2024]: ``shadowlab bench --only scaling`` (``scaling.json``,
``scaling.md``; on a GPU ``scaling-cuda.*``).

The same workloads run in this process and on local clusters of 1, 2, 4 and 8 workers (as many
as the machine has cores on the CPU, or GPUs on ``cuda_ad_rgb``, one GPU per worker):

* **references**: every built-in scene and every frame of the camera paths
  (:func:`shadowlab.pipeline.reference_batch`, ``frames="all"``), each run into a fresh store;
* **sweep**: a sweep of :data:`SWEEP`'s parameter over the first :data:`CONFIGS`' ``sweep_scenes``
  built-in scenes (mesh scenes whose technique applies), against the references of the first run.

For each: the wall time of the jobs (the cluster is started and its workers have compiled the
kernels once before the clock starts, with a warm-up batch of every scene at 16×16 per worker; the
start-up is reported apart),
the speed-up over one worker, the scaling efficiency speed-up / workers, and whether every stored
channel or every metric equals the first run's bit for bit.
"""

from __future__ import annotations

import datetime
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import backend
from ..cluster import open_executor
from ..cluster.executor import visible_gpus
from ..io.exr import read_exr
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..pipeline import reference_batch
from ..scene.spec import builtin_names, load_spec, resolve
from ..sweep import results_only, sweep
from ..techniques import base as tbase
from .timing import machine_text

#: the swept parameter: (technique, parameter, lo, hi)
SWEEP = ("pcf", "softness", 0.5, 4.0)
#: per configuration: reference resolution, truth options, sweep points and scenes
CONFIGS = {
    "quick": {"resolution": (48, 48), "scenes": ("contact", "parallel_planes", "boulevard"), "spp": 0,
              "target_se": 0.02, "sweep_points": 4, "sweep_scenes": 2, "sweep_resolution": (48, 48)},
    "cpu": {"resolution": (128, 128), "scenes": None, "spp": 16, "target_se": 0.01, "sweep_points": 16,
            "sweep_scenes": 4, "sweep_resolution": (128, 128)},
    "gpu": {"resolution": (1920, 1080), "scenes": None, "spp": 64, "target_se": 0.005, "sweep_points": 64,
            "sweep_scenes": 8, "sweep_resolution": (480, 270)},
}


def worker_counts(available: int) -> list[int]:
    """1, 2, 4, 8 up to ``available``.

    >>> worker_counts(2), worker_counts(6), worker_counts(1)
    ([1, 2], [1, 2, 4], [1])
    """
    return [n for n in (1, 2, 4, 8) if n <= max(1, available)]


def _channels(base: Path) -> dict:
    """{(scene dir, resolution dir): channels} of every reference in a store."""
    out = {}
    for exr in sorted(base.glob("*/*/truth.exr")):
        out[(exr.parent.parent.name, exr.parent.name)] = read_exr(exr)
    return out


def _same(a: dict, b: dict) -> bool:
    if a.keys() != b.keys():
        return False
    return all(x.keys() == y.keys() and all(np.array_equal(x[k], y[k], equal_nan=True) for k in x)
               for x, y in ((a[k], b[k]) for k in a))


def _references(ex, scenes, cfg, base: Path) -> float:
    t0 = time.perf_counter()
    reference_batch(scenes, cfg["resolution"], "all", executor=ex, base=base, progress=False, seed=0,
                    spp=cfg["spp"], target_se=cfg["target_se"])
    return time.perf_counter() - t0


def _sweep(ex, scenes, cfg, base: Path) -> tuple[float, dict]:
    t, name, lo, hi = SWEEP
    t0 = time.perf_counter()
    rec = sweep(scenes, t, f"{name}={lo}:{hi}:{cfg['sweep_points']}", resolution=cfg["sweep_resolution"],
                executor=ex, base=base)
    return time.perf_counter() - t0, results_only(rec)


def sweep_scenes(scenes, n: int) -> list[str]:
    """The first ``n`` of ``scenes`` that :data:`SWEEP`'s technique renders."""
    t = tbase.get(SWEEP[0])
    return [s for s in scenes if not t.unsupported(load_spec(resolve(s)))][:n]


def _warm_up(ex, scenes, base: Path) -> None:
    """Every scene at 16×16 on every worker, untimed: each compiles (or loads from its kernel cache)
    what the timed run needs."""
    for _ in range(1 if ex is None else ex.workers):
        reference_batch(scenes, (16, 16), executor=ex, base=base, progress=False, spp=0, target_se=0.05, force=True)


def run(out: Path, quick: bool = False) -> Path:
    """Run the scaling bench; write ``out/scaling[-cuda].json`` and ``.md``; return the .md path."""
    variant = backend.init()
    cuda = variant.startswith("cuda")
    cfg = CONFIGS["quick" if quick else "gpu" if cuda else "cpu"]
    scenes = list(cfg["scenes"] or builtin_names())
    counts = worker_counts(len(visible_gpus()) if cuda else os.cpu_count() or 1)
    tmp = Path(tempfile.mkdtemp(prefix="shadowlab-scaling-"))
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick, "config": dict(cfg), "scenes": scenes, "sweep": SWEEP, "runs": []}
    out = Path(out)
    stem = "scaling-cuda" if cuda else "scaling"
    try:
        base = tmp / "embedded"
        _warm_up(None, scenes, tmp / "warm")
        res["runs"].append({"executor": "embedded", "workers": 1, "references_s": _references(None, scenes, cfg, base)})
        first = _channels(base)
        res["references"] = len(first)
        swept = sweep_scenes(scenes, cfg["sweep_scenes"])
        res["sweep_scenes"] = swept
        if cfg["sweep_resolution"] != cfg["resolution"]:     # the sweep's truths, untimed
            reference_batch(swept, cfg["sweep_resolution"], executor=None, base=base, progress=False, seed=0,
                            spp=0, target_se=cfg["target_se"])
        _sweep(None, swept, {**cfg, "sweep_points": 2}, base)     # compiles the technique's kernels, untimed
        res["runs"][0]["sweep_s"], first_sweep = _sweep(None, swept, cfg, base)
        md = _write(res, out, stem)
        for n in counts:
            t0 = time.perf_counter()
            with open_executor(workers=n) as ex:
                _warm_up(ex, scenes, tmp / f"warm{n}")
                start = time.perf_counter() - t0
                b = tmp / f"w{n}"
                row = {"executor": "dask", "workers": n, "startup_s": start,
                       "references_s": _references(ex, scenes, cfg, b)}
                row["references_same_bits"] = _same(_channels(b), first)
                shutil.rmtree(b, ignore_errors=True)
                _sweep(ex, swept, {**cfg, "sweep_points": 2 * n}, base)   # each worker compiles, untimed
                row["sweep_s"], got = _sweep(ex, swept, cfg, base)
                row["sweep_same_bits"] = got == first_sweep
            res["runs"].append(row)
            md = _write(res, out, stem)   # after every row: a run cut short keeps what it measured
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return md


def _write(res: dict, out: Path, stem: str) -> Path:
    """Speed-ups against the one-worker Dask run (before it exists: the embedded run); ``out/STEM.json``
    and ``.md``."""
    one = next((r for r in res["runs"] if r["workers"] == 1 and r["executor"] == "dask"), res["runs"][0])
    for r in res["runs"]:
        for w in ("references", "sweep"):
            r[f"{w}_speedup"] = one[f"{w}_s"] / r[f"{w}_s"]
            r[f"{w}_efficiency"] = r[f"{w}_speedup"] / r["workers"]
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / f"{stem}.json", res)
    return write_bytes_atomic(out / f"{stem}.md", _markdown(res).encode())


def _markdown(res: dict) -> str:
    m, c = res["machine"], res["config"]
    W, H = c["resolution"]
    t, name, lo, hi = res["sweep"]
    lines = [f"# Scaling on Dask ({res['date']})", "",
             f"Machine: {machine_text(m)}. All figures from one run"
             + (" (--quick: a smoke run, not for figures)." if res["quick"] else "."), "",
             f"- references: {res['references']} ("
             + ("every built-in scene" if c["scenes"] is None else ", ".join(c["scenes"]))
             + f" and every frame of the camera paths) at {W}×{H}, target standard error {c['target_se']}, "
             f"{c['spp']} spp Mitsuba image;",
             f"- sweep: `{t}.{name}` = {lo}…{hi}, {c['sweep_points']} points on {len(res['sweep_scenes'])} scenes "
             f"({', '.join(res['sweep_scenes'])}) at {c['sweep_resolution'][0]}×{c['sweep_resolution'][1]}: "
             f"{c['sweep_points'] * len(res['sweep_scenes'])} jobs.", "",
             "Speed-up and efficiency against one Dask worker; the cluster's start-up is not in the times.", "",
             "| executor | workers | start-up (s) | references (s) | speed-up | efficiency | same bits "
             "| sweep (s) | speed-up | efficiency | same bits |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["runs"]:
        emb = r["executor"] == "embedded"
        same = ["—" if emb else ("yes" if r.get(f"{w}_same_bits") else "**no**") for w in ("references", "sweep")]
        start = "—" if emb else f"{r['startup_s']:.1f}"
        lines.append(f"| {r['executor']} | {r['workers']} | {start} | {r['references_s']:.2f} | "
                     f"{r['references_speedup']:.2f}× | {r['references_efficiency']:.0%} | {same[0]} | "
                     f"{r['sweep_s']:.2f} | {r['sweep_speedup']:.2f}× | {r['sweep_efficiency']:.0%} | {same[1]} |")
    return "\n".join(lines) + "\n"
