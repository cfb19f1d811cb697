"""Every technique's frame, split into its parts: ``shadowlab bench --only frames``
(``frames.json`` / ``frames.md``; not in the full run, like ``scaling``).

A frame is what a real-time renderer pays per image: the G-buffer, the shadow pass (the light
views) and the technique's lookups, as [Buljan 2020, §4.5] counts its frames per second (the shadow
pass included) and [Tamás 2015, §7] its milliseconds. For every technique that applies (its
``unsupported`` and ``unavailable`` say None; real engines left out) on :data:`PLAN`'s scenes, at
1920×1080 by default (``--size WxH``), from one run:

* **new frame**: ``make_frame`` (G-buffer and unshadowed light) on a fresh frame, then the
  technique's render on it, every light view cast anew, after :data:`WARMUP_FRAMES` untimed new
  frames (the G-buffer and the light views are replayed stages, :mod:`shadowlab.render.replay`: the
  first frame traces them, the second records them, the third is the first replay): the median
  wall time of :data:`PLAIN_FRAMES` frames run as a user's run runs them (:func:`plain_frame`: no
  kernel history, no wait inside the frame; after as many untimed, as Dr.Jit records its stages
  again without the history). This is the figure of the goals and of new / limit;
* **split** of a new frame, from :data:`NEW_FRAMES` more new frames, instrumented
  (:func:`new_frame`; the one of median wall time): *G-buffer* (``make_frame``),
  *light views* (the wall time of the casts, ``FrameContext.cast``, and of the calls to
  ``top_tree``, each between ``dr.sync_thread()`` calls, the views evaluated) and *technique* (the
  render's wall time less its light views), with Dr.Jit's kernel history on. *Host* is the part
  of that frame's wall time in which no kernel ran: wall time minus the kernels' execution times
  from the kernel history (``execution_time`` of every entry: JIT kernels, reductions, copies,
  memsets), i.e. tracing, Python, numpy and waiting on readbacks. It overlaps the other three (it
  is a share of them, not a fourth addend). The waits between the parts stop the host from
  tracing one part while the device runs the last, and the history costs a little per kernel, so
  the split's total (*split total*) exceeds the new frame, most for frames of many kernels.
  Virtual maps cast their tiles inside the technique at every render, without a cache: there the
  shadow pass is in *technique*, and warm ≈ new;
* **warm**: the render again on the same frame, its light views cached (median of warm runs);
* **kernels and transfers** per frame, from the kernel history of the timed new frame and of one
  more warm render: JIT kernels launched, other entries (reductions, memsets, copies), and
  ``Memcpy`` entries. What is and is not counted: on the LLVM backend a ``Memcpy`` entry is a
  copy Dr.Jit makes itself, e.g. a synchronous read of one element (``x[0]``, a reduction's result
  read into Python); a whole array read into numpy (``.numpy()``, ``np.asarray``) or a numpy
  array made a Dr.Jit array is plain host memory there and leaves no entry; on CUDA copies are not
  in the history at all. So the part also reports the **first host synchronisation** of a new and
  of a warm frame: the frame run again with ``JitFlag.ForbidSynchronization``, which raises at the
  first wait for the device (a numpy readback, ``dr.sync_thread``, a compress) but not at a
  one-element read, named by the innermost shadowlab line that caused it;
* **raw limit**: the same number of rays, texels cast (the technique's ``maps`` stats) plus one
  tap per valid point and light (the techniques do not report their filters' tap counts, so a k-tap
  filter's limit is lower than its real work), as Mitsuba ``ray_test`` from the G-buffer's points in
  one wavefront (:func:`shadowlab.bench.rays.raw_ray_test`), and the new frame's time over it. SDF
  scenes have no Mitsuba geometry to cast against: no limit there;
* **replay floor**, per scene: a replayed stage that does no work but takes the scene as its input
  (:func:`replay_floor`), what each of a frame's replayed stages pays before its kernels (Dr.Jit
  walks the scene's variables at every call; the more shapes, the longer); and per technique the
  **scene replays** of a new frame (the split's calls of stages over the scene through the frozen
  function, :func:`shadowlab.render.replay.frozen_calls`) with their floors' share of the new frame
  (replays × floor / new frame): what the frame pays Dr.Jit before any of its own work.
"""

from __future__ import annotations

import dataclasses
import datetime
import gc
import math
import os
import sys
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .. import backend
from ..errors import InputError
from ..io.jsonio import write_json_atomic
from ..io.png import write_bytes_atomic
from ..pipeline import check_memory, load_scene
from ..render.frame import FrameContext, make_frame
from ..render.replay import frozen_calls, replayed
from ..techniques import base
from .rays import raw_ray_test
from .timing import history, kernel_summary, machine_text, render_evaluated, timed

#: (scene, which techniques): None = every one that applies; a tuple names them
PLAN = (("contact", None), ("two_lights", None), ("street", ("csm", "vtsm", "fvsm")),
        ("many_lights", ("ssss",)), ("mandelbulb", None))
SIZE = (1920, 1080)
#: warm renders timed per technique (median)
REPEATS = 5
#: new frames before the timed one: the first traces and compiles every kernel, the second records the
#: frame's stages (render/replay.py), the third replays them for the first time (the virtual maps still
#: compiled a kernel or two there on a GPU), so the timed one is as every later frame of a run
WARMUP_FRAMES = 3
#: instrumented new frames per technique (the split): the row is the one of median wall time (a single
#: frame's host time varies by milliseconds from frame to frame on a GPU)
NEW_FRAMES = 3
#: plain new frames per technique (:func:`plain_frame`): the new frame is their median, after as many
#: untimed as WARMUP_FRAMES (Dr.Jit records a frozen stage again under other JIT flags, and the kernel
#: history the instrumented frames turn on is one: the first plain frame after them records anew)
PLAIN_FRAMES = 5
_PACKAGE = str(Path(__file__).resolve().parents[1])
_BENCH = str(Path(__file__).resolve().parent)


@dataclasses.dataclass
class TimedFrame(FrameContext):
    """A :class:`~shadowlab.render.frame.FrameContext` that times the light views and TOP trees it
    casts (while ``timing["on"]``): each cast between ``dr.sync_thread()`` calls, the view evaluated,
    its kernels taken from the kernel history apart from the technique's."""

    timing: dict = dataclasses.field(default_factory=lambda: {"on": True, "views_s": 0.0, "casts": 0,
                                                              "view_kernels": [], "other_kernels": []})

    @classmethod
    def of(cls, frame: FrameContext) -> "TimedFrame":
        return cls(scene=frame.scene, gbuffer=frame.gbuffer, unshadowed=frame.unshadowed, sdf=frame.sdf)

    def _timed(self, cast, n: int):
        if not self.timing["on"]:
            return cast()
        dr.sync_thread()
        self.timing["other_kernels"] += dr.kernel_history()
        t0 = time.perf_counter()
        out = cast()
        dr.eval(out)
        dr.sync_thread()
        self.timing["views_s"] += time.perf_counter() - t0
        self.timing["casts"] += n
        self.timing["view_kernels"] += dr.kernel_history()
        return out

    def cast(self, requests):
        return self._timed(lambda: super(TimedFrame, self).cast(requests), len(requests))

    def top_tree(self, *args, **kwargs):
        return self._timed(lambda: super(TimedFrame, self).top_tree(*args, **kwargs), 0)


def first_sync(fn) -> str | None:
    """Where ``fn`` first waits for the device (``JitFlag.ForbidSynchronization`` raises there): the
    innermost line of shadowlab outside the bench, as ``module.py:LINE (function)`` (``<lambda>``
    written ``lambda``, so that Markdown shows it); None if it never does.

    The line is taken from the frames the error passes through while it propagates (a trace
    function's ``exception`` events), not from its traceback: walking the traceback of an error
    Dr.Jit raised inside a compress crashed the interpreter (a freed frame in it). Python's garbage
    is collected before ``fn`` and not during it: an object freed there (a scene of an earlier
    measurement) may wait for the device in its destructor, where the raise ends the process."""
    seen = []

    def local(frame, event, arg):
        if event == "exception":
            seen.append((arg[1], frame.f_code.co_filename, frame.f_lineno, frame.f_code.co_name))
        return local

    def enter(frame, event, arg):
        name = frame.f_code.co_filename
        if not name.startswith(_PACKAGE) or name.startswith(_BENCH):
            return None
        frame.f_trace_lines = False  # only its exception events are wanted, not one call per line
        return local

    collecting = gc.isenabled()
    gc.collect()
    gc.disable()
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.ForbidSynchronization, True)
    previous = sys.gettrace()
    sys.settrace(enter)
    try:
        fn()
    except RuntimeError as e:
        sys.settrace(previous)
        if "synchroniz" not in str(e):
            raise
        ours = [s for s in seen if s[0] is e]
        if not ours:
            return "outside shadowlab"
        _, filename, lineno, name = ours[0]
        return f"{os.path.relpath(filename, os.path.dirname(_PACKAGE))}:{lineno} ({name.strip('<>')})"
    finally:
        sys.settrace(previous)
        dr.set_flag(dr.JitFlag.ForbidSynchronization, False)
        if collecting:
            gc.enable()
    return None


def _texels(stats: dict) -> int:
    """Texels the render cast: its maps' (or, without maps, its lights' ``texels``)."""
    total = 0
    for st in stats.get("lights", {}).values():
        maps = st.get("maps") or ()
        total += sum(int(m.get("texels", 0)) for m in maps) if maps else int(st.get("texels", 0) or 0)
    return total


def new_frame(sc, technique, params) -> tuple:
    """(fresh :class:`TimedFrame`, its result, the split of one new frame) of ``technique``."""
    calls = frozen_calls(sc)
    history(True)
    try:
        t0 = time.perf_counter()
        frame = make_frame(sc)
        dr.sync_thread()
        t_gb = time.perf_counter() - t0
        k_gb = dr.kernel_history()
        tf = TimedFrame.of(frame)
        t1 = time.perf_counter()
        r = render_evaluated(technique, tf, params)
        dr.sync_thread()
        t_render = time.perf_counter() - t1
        k_tech = tf.timing["other_kernels"] + dr.kernel_history()
    finally:
        history(False)
    views_s = min(tf.timing["views_s"], t_render)
    k_views = tf.timing["view_kernels"]
    tf.timing["on"] = False
    total = t_gb + t_render
    kern = kernel_summary(k_gb + k_views + k_tech)
    split = {"total_s": total, "gbuffer_s": t_gb, "light_views_s": views_s, "technique_s": t_render - views_s,
             "host_s": max(total - kern["execution_ms"] / 1e3, 0.0), "casts": tf.timing["casts"],
             "scene_replays": frozen_calls(sc) - calls,
             "kernels": kern, "kernels_by_part": {"gbuffer": kernel_summary(k_gb),
                                                  "light_views": kernel_summary(k_views),
                                                  "technique": kernel_summary(k_tech)}}
    return tf, r, split


def plain_frame(sc, technique, params):
    """One new frame as a user's run pays it (timed with :func:`~shadowlab.bench.timing.timed`):
    ``make_frame`` and the render, evaluated, with no kernel history and no wait in between (the host
    traces the next stage while the device runs the last; :func:`new_frame`'s split waits after
    each part and logs every kernel, which costs more the more kernels a frame launches)."""
    return render_evaluated(technique, make_frame(sc), params)


def warm_frame(frame, technique, params, repeats: int) -> dict:
    """Median warm render (light views cached) and one more render's kernels."""
    _, ts = timed(lambda: render_evaluated(technique, frame, params), repeats, warmup=1)
    history(True)
    try:
        t0 = time.perf_counter()
        render_evaluated(technique, frame, params)
        dr.sync_thread()
        tk = time.perf_counter() - t0
        kern = kernel_summary(dr.kernel_history())
    finally:
        history(False)
    ts = sorted(ts)
    return {"time_s": ts[len(ts) // 2], "runs_s": ts, "kernels": kern, "kernels_run_s": tk,
            "host_s": max(tk - kern["execution_ms"] / 1e3, 0.0)}


def raw_limit(frame, rays: int, light: str, cache: dict) -> dict | None:
    """``rays`` Mitsuba ``ray_test`` rays from the frame's valid points toward ``light`` in one
    wavefront (:func:`~shadowlab.bench.rays.raw_ray_test`, ⌈rays / points⌉ per point); None on an
    SDF scene or without valid points."""
    points = int(dr.count(frame.gbuffer.valid)[0]) if frame.scene.kind == "mitsuba" else 0
    if points == 0 or rays <= 0:
        return None
    spp = max(1, math.ceil(rays / points))
    if spp not in cache:
        cache[spp] = raw_ray_test(frame, light, spp=spp, repeats=3, warmup=1)
    return cache[spp]


def measure(sc, name: str, *, repeats: int = REPEATS, raw_cache: dict | None = None) -> dict:
    """One technique on one loaded scene: new frame, warm, kernels, first syncs, raw limit."""
    t = base.get(name)
    p = t.resolve({})
    for _ in range(WARMUP_FRAMES):                 # compiles every kernel, records the frame's stages, replays
        new_frame(sc, t, p)
    # the same without the kernel history, which Dr.Jit records apart: untimed first
    _, walls = timed(lambda: plain_frame(sc, t, p), PLAIN_FRAMES, warmup=WARMUP_FRAMES)
    splits = []
    for _ in range(NEW_FRAMES):
        frame = r = None  # the last frame's views freed before the next is cast (kept, they slowed its casts 2x)
        frame, r, split = new_frame(sc, t, p)
        splits.append(split)
    split = sorted(splits, key=lambda s: s["total_s"])[len(splits) // 2]
    new_s = sorted(walls)[len(walls) // 2]
    warm = warm_frame(frame, t, p, repeats)
    sync_new = first_sync(lambda: render_evaluated(t, make_frame(sc), p))
    sync_warm = first_sync(lambda: render_evaluated(t, frame, p))
    texels = _texels(r.stats)
    points = int(dr.count(frame.gbuffer.valid)[0])
    taps = points * len(frame.lights)
    raw = raw_limit(frame, texels + taps, frame.lights[0].name, {} if raw_cache is None else raw_cache)
    limit_s = None if raw is None else raw["time_s"] * (texels + taps) / raw["rays"]
    return {"new_s": new_s, "new_runs_s": walls, "new": split, "warm": warm,
            "first_sync": {"new": sync_new, "warm": sync_warm},
            "texels": texels, "taps": taps, "rays": texels + taps, "raw": raw, "limit_s": limit_s,
            "new_over_limit": None if not limit_s else new_s / limit_s}


def replay_floor(sc, repeats: int = REPEATS) -> dict | None:
    """What every replayed stage of the scene pays before its kernels: a stage that does no work
    (one width-1 addition) but takes the scene's Mitsuba scene as its input, so that Dr.Jit walks
    what a stage reads of the scene (its shapes' variables) at each call
    (:mod:`shadowlab.render.replay`), timed like a frame's stages (median wall ms of ``repeats``
    replays). None on an SDF scene (its G-buffer is not replayed)."""
    if sc.kind != "mitsuba":
        return None
    x = dr.opaque(mi.Float, 1.0, 1)

    def call():
        return dr.eval(replayed("replay_floor", (), lambda _scene, y: y + 1.0, sc, sc.mi_scene, x))

    _, ts = timed(call, repeats, warmup=3)   # traced, recorded, replayed once
    return {"shapes": len(sc.mi_scene.shapes()), "ms": 1e3 * sorted(ts)[len(ts) // 2]}


def techniques_on(spec, only=None) -> list[str]:
    """The techniques of ``only`` (None: every registered one, real engines left out) that apply to
    ``spec`` and can run here."""
    names = [n for n in base.names() if not base.get(n).external] if only is None else list(only)
    return [n for n in names if not (base.get(n).unsupported(spec) or base.get(n).unavailable())]


def bench(size=SIZE, plan=PLAN, repeats: int = REPEATS, log=None) -> dict:
    """Every scene of ``plan`` at ``size`` (W, H): {scene: {technique: :func:`measure`}}."""
    out = {}
    for scene, only in plan:
        sc = load_scene(scene, tuple(size))
        cache: dict = {}
        out[scene] = {"lights": len(sc.spec.lights), "kind": sc.kind, "replay_floor": replay_floor(sc, repeats),
                      "techniques": {}}
        for n in techniques_on(sc.spec, only):
            if log:
                log(f"frames: {scene} {n}")
            out[scene]["techniques"][n] = measure(sc, n, repeats=repeats, raw_cache=cache)
    return out


def _ms(x) -> str:
    return "–" if x is None else f"{1e3 * x:.1f}"


def _replays(n, floor, new_s) -> str:
    """A frame's scene replays and their floors' share of the new frame, e.g. ``2 (66 %)``."""
    if n is None or not floor:
        return "–"
    return f"{n} ({100.0 * n * floor['ms'] / (1e3 * new_s):.0f} %)" if new_s > 0 else str(n)


def _kern(k: dict) -> str:
    other = sum(k["other"].values())
    return f"{k['jit']} + {other}"


#: issue 29's goals on one H200 at 1920×1080: (what, scenes, measure, at most); ``measure`` names the figure
#: taken over the scenes' techniques that cast shadow maps (light views, or a virtual map's tiles inside the
#: technique; the SDF techniques cast none)
GOALS = (
    ("a shadow-map family's new frame, light views included, one light", ("contact", "street"), "new_max_ms", 10.0),
    ("the same frame over its raw ray cost", ("contact", "street"), "over_limit_max", 5.0),
    ("`many_lights` (16 lights), new frame", ("many_lights",), "new_max_ms", 50.0),
    ("`make_frame` (G-buffer and unshadowed light), median", ("contact",), "gbuffer_median_ms", 5.0),
)


def goal_rows(res: dict) -> list:
    """[(goal, at most, measured, how many of the techniques meet it, of how many)] of :data:`GOALS`
    from a run's results (measured None where the run lacks the scene); "measured" is the worst
    technique's figure, or the median for ``make_frame``."""
    rows = []
    for what, scenes, measure, limit in GOALS:
        techs = {(sc, n): r for sc in scenes for n, r in res["scenes"].get(sc, {}).get("techniques", {}).items()
                 if r["new"]["light_views_s"] > 0 or r.get("texels", 0) > 0}   # virtual maps cast in the technique
        if measure == "new_max_ms":
            vals = {n: 1e3 * r["new_s"] for n, r in techs.items()}
        elif measure == "over_limit_max":
            vals = {n: r["new_over_limit"] for n, r in techs.items() if r["limit_s"]}
        else:
            vals = {n: 1e3 * r["new"]["gbuffer_s"] for n, r in techs.items()}
        if not vals:
            rows.append((what, limit, None, 0, 0))
            continue
        v = sorted(vals.values())[len(vals) // 2] if measure == "gbuffer_median_ms" else max(vals.values())
        rows.append((what, limit, v, sum(x <= limit for x in vals.values()), len(vals)))
    return rows


def markdown(res: dict) -> str:
    m = res["machine"]
    W, H = res["size"]
    lines = [f"# Technique frames ({res['date']})", "",
             f"Machine: {machine_text(m)}. All figures from one run at {W}×{H}"
             f"{' (--quick: small sizes, not for figures)' if res['quick'] else ''}.", "",
             f"New frame: `make_frame` and the render on a fresh frame, every light view cast anew (ms), after "
             f"{WARMUP_FRAMES} untimed new frames (the first compiles the kernels, the second records the G-buffer "
             "and light-view stages, the third replays them first; the timed frames are as every later frame of "
             f"a run), the median wall time of {PLAIN_FRAMES}, run as a user's run runs them (no kernel history, no "
             f"wait inside the frame; after {WARMUP_FRAMES} more untimed, as Dr.Jit records its stages again "
             f"without the history). Split: {NEW_FRAMES} more new frames, instrumented "
             "(the one of median wall time): G-buffer, light views (the casts of maps and TOP trees, each "
             "synchronised) and technique (the rest of the render), with Dr.Jit's kernel history on; host: that "
             "frame's wall time in which no kernel ran (wall minus the kernels' execution times from the kernel "
             "history; a share of the other three, not an addend); split total: their sum, above the new frame by "
             "what the waits between the parts and the history cost (most for frames of many kernels). Scene "
             "replays: that frame's stages replayed over the scene's Mitsuba scene (the G-buffer, the light-view "
             "casts, the tile wavefronts), each paying the scene's replay floor (below), and those floors' share "
             "of the new frame. Warm: the render with the light views cached (median). Kernels: JIT kernels + other "
             "history entries (reductions, memsets, copies); copies: `Memcpy` entries (on LLVM, one-element reads; "
             "numpy readbacks leave none, and CUDA logs no copies). First sync: where a frame first waits for the "
             "device (`ForbidSynchronization`). Limit: texels cast + one tap per point and light, as raw `ray_test` "
             "rays in one wavefront; virtual maps cast their tiles inside the technique at every render.", "",
             "## Goals", "", "Set for one H200 at 1920×1080 (on another machine or size they are shown for "
             "comparison only), over the techniques that cast shadow maps on the goal's scenes (the one-light "
             "goals: `contact`'s and `street`'s, cascades and virtual maps included): the worst one's figure (the "
             "median for `make_frame`) and how many meet the goal.", "",
             "| goal | at most | measured | techniques within |", "|---|---|---|---|"]
    for what, limit, v, ok, n in goal_rows(res):
        unit = "×" if "raw" in what else " ms"
        lines.append(f"| {what} | {limit:g}{unit} | {'–' if v is None else f'{v:.1f}{unit}'} | "
                     f"{f'{ok} of {n}' if n else '–'} |")
    lines.append("")
    for scene, d in res["scenes"].items():
        lines += [f"## `{scene}` ({d['lights']} light{'s' if d['lights'] != 1 else ''})", ""]
        floor = d.get("replay_floor")
        if floor:
            lines += [f"Replay floor: {floor['ms']:.2f} ms a replayed stage (a stage that does no work but walks "
                      f"the scene's {floor['shapes']} shapes' variables, as the G-buffer's, each light-view cast's "
                      "and each tile wavefront's replays do).", ""]
        lines += [
                  "| technique | new frame | G-buffer | light views | technique | host | split total | "
                  "scene replays (floors' share) | warm | kernels new / warm | copies new / warm | "
                  "first sync, new frame | first sync, warm | rays (texels + taps) | limit | new / limit |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for n, r in d["techniques"].items():
            nw, wm = r["new"], r["warm"]
            lim = r["limit_s"]
            over = "–" if lim is None else f"{r['new_over_limit']:.0f}×"
            lines.append(
                f"| {n} | {_ms(r['new_s'])} | {_ms(nw['gbuffer_s'])} | {_ms(nw['light_views_s'])} | "
                f"{_ms(nw['technique_s'])} | {_ms(nw['host_s'])} | {_ms(nw['total_s'])} | "
                f"{_replays(nw.get('scene_replays'), floor, r['new_s'])} | {_ms(wm['time_s'])} | "
                f"{_kern(nw['kernels'])} / {_kern(wm['kernels'])} | {nw['kernels']['memcpy']} / "
                f"{wm['kernels']['memcpy']} | {r['first_sync']['new'] or 'none'} | "
                f"{r['first_sync']['warm'] or 'none'} | "
                f"{r['rays']:,} | {_ms(lim)} | {over} |")
        lines.append("")
    return "\n".join(lines) + "\n"


def parse_size(text) -> tuple:
    """``--size WxH`` -> (W, H); InputError (exit 2) for anything else."""
    try:
        w, h = (int(x) for x in str(text).lower().replace("×", "x").split("x"))
    except ValueError:
        raise InputError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 640x360") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise InputError(f"--size {text!r}: expected sizes in 8..8192, e.g. 640x360")
    return w, h


def run(out: Path, quick: bool = False, size=None, plan=PLAN) -> Path:
    """Measure; write ``out/frames.json`` and ``out/frames.md``; return the .md path. ``size``:
    (W, H) or ``"WxH"`` (default 1920×1080; ``quick``: 64×36)."""
    size = parse_size(size) if isinstance(size, str) else tuple(size or ((64, 36) if quick else SIZE))
    backend.init()
    res = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "machine": backend.machine_info(),
           "quick": quick, "size": list(size), "repeats": 2 if quick else REPEATS}
    for scene, only in plan:                                  # exit 3 before any scene is measured
        sc = load_scene(scene, size)
        check_memory(sc.spec, {n: {} for n in techniques_on(sc.spec, only)}, size_option="--size")
    res["scenes"] = bench(size, plan, res["repeats"])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "frames.json", res)
    return write_bytes_atomic(out / "frames.md", markdown(res).encode())
