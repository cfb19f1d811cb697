"""Ground truth: per-light visibility at the G-buffer points and the shaded image (Mitsuba).

Visibility of light L at shading point x (docs/ARCHITECTURE.md, Reference):

    V_L(x) = ∫ f(x, y) v(x, y) dy / ∫ f(x, y) dy     (shadowed / unshadowed direct light)
    A_L(x) = mean of v over the emitter's sample domain (visible area or solid-angle fraction)

with f = bsdf · Le · cos / pdf from Mitsuba's emitter sampling and v from Mitsuba shadow rays
(``render/shading.py``). Sampling is adaptive, in rounds of k×k jittered strata:

1. every pixel gets ``min_rounds`` rounds;
2. a pixel whose samples all agreed (all visible or all blocked) is done: lit and umbra
   pixels converge at once (its error bound is then the rule of three, 3/n, stored as ``bound``);
3. the others (penumbra) get a pilot of 8 rounds, whose variance plans the number of rounds
   R = 1.25 · var / target_se², at least 16 (so half the rounds are fresh) and at most
   ``max_rounds``; the standard error reported is
   sqrt(var_rounds / R) over all rounds. Planning from the pilot rather than stopping when the
   running estimate first dips below the target keeps the reported error honest (stopping
   on it under-reports the error by ~20%, measured on analytic_sphere).

Wavefronts. Each point's stopping rule reads only its own samples, and between the pilot's end
and its plan's end it decides nothing, so the sampler runs as few, large kernels instead of one
small kernel per round: every valid point's first ``min_rounds`` rounds in one (a lane per point
looping over the rounds), then one per decision (the pilot's end, each plan's end), each point's
rounds summed in round order in float64. Their lanes differ by device:

* on a GPU, a lane per (point, round): a point's rounds in adjacent lanes, each writing its
  round's values to a float64 buffer, and a second, cheap kernel per point that adds them to the
  point's sums in round order (the same additions as a loop). Every plan made at the pilot's end
  covers at least 2·MIN_SE_ROUNDS rounds, so the pilot's wavefront samples those too and keeps
  the sums at the pilot's end for its decision;
* on the CPU, a lane per point looping over its rounds, the lanes ordered by their number of
  rounds (neighbouring lanes finish together). Embree traces packets of neighbouring lanes and a
  ray's result can depend on its packet, so the CPU keeps this layout, that of the committed bits
  (a GPU traces each lane alone: its layout changes no bit).

The per-point state (interaction, float64 sums) stays on the device: the valid and the penumbra
points are found with ``dr.compress``, a wavefront gathers its lanes' interactions from the
G-buffer inside its kernel, and the host reads back, in one transfer per decision, only the three
sums the rule needs of the points deciding. Random numbers: PCG32 seeded by (seed, round) on the
point's own stream, its rank among the valid points for the first rounds and among the points
that sample on after them for all later ones, whatever lane runs the round; a fixed seed gives
the same bits.

Translucent casters (a scene with ``transmittance`` shapes): a shadow ray's visibility is the RGB
straight-line transmittance of its segment (``shading.transmitted``), so a light of such a scene
gets V_c = Σ f·τ_c / Σ f per channel with its standard error (``LightTruth.V_rgb``; V is their
mean), kept by :func:`render_truth` for the lights whose shadows have colour (channels that
differ somewhere), and a point's samples are unanimous only when all were fully lit or all fully
blocked.

Allocation across lights (the scene's ``truth_allocation``). ``per_light`` (the default): every
light's V to ``target_se`` at every pixel, so a scene's cost grows with its lights however little
each adds to a pixel. ``contribution``: light L's target at a point is

    t_L = target_se · sqrt(S / U_L),   U_L its unshadowed light there (the channel sum), S = Σ_M U_M,

capped at :data:`CONTRIBUTION_MAX_SE`, and a point where the light adds nothing (outside its range,
facing away) is not sampled for it at all: V = 1 there, with no samples. The shaded pixel's error then stays within the
same bound
relative to its light, Σ_L U_L² t_L² = target_se² · S · Σ_L U_L = (target_se · S)², and since a
point's rounds grow as 1/t², each light's rays there are in proportion to its share U_L / S of the
pixel's unshadowed light: a light that adds 5 % of a pixel's light gets a twentieth of the rays
(:func:`light_targets`). A light's own V is then only as precise as its share needs.

The rounds are independent, so the standard error is an honest estimate. The shaded truth is
Σ_L U_L · V_L at the same pixel centres as the techniques (so metrics isolate shadows), and
Mitsuba's own ``direct`` integrator image (``mi.render``, box filter over the pixel) is stored
beside it with a per-pixel variance from independent passes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..render.frame import FrameContext
from ..render.gbuffer import vec_numpy
from ..render.lightview import cast_first_hit
from ..render import shading
from ..render.shading import light_samples, seed_hash
from ..scene.lights import forward as lights_fwd

#: the largest seed a truth render takes: Mitsuba's ``mi.render`` gets seed·1000 + i (i < 1000), a 32-bit
#: unsigned integer (``shadowlab reference --seed`` has the same range)
SEED_MAX = (2 ** 32 - 1000) // 1000

MIN_SE_ROUNDS = 8  # pilot rounds of a penumbra pixel before its number of rounds is planned
#: allocation "contribution": the largest standard error a light's visibility is sampled to (where its
#: share of a pixel's light is below (target/cap)², and where it has none)
CONTRIBUTION_MAX_SE = 0.05
PLAN_MARGIN = 1.25  # planned rounds = margin · pilot variance / target²


@dataclass
class LightTruth:
    V: np.ndarray          # (H, W) visibility ratio
    V_se: np.ndarray       # (H, W) standard error of V
    A: np.ndarray          # (H, W) plain visible fraction
    A_se: np.ndarray
    samples: np.ndarray    # (H, W) shadow rays per pixel
    bound: np.ndarray      # (H, W) error bound for unanimous pixels (3/n), 0 elsewhere
    rays: int = 0
    #: with translucent casters: (H, W, 3) RGB visibility V_c = Σ f·τ_c / Σ f (V is its channel
    #: mean) and its standard error; None elsewhere
    V_rgb: np.ndarray | None = None
    V_rgb_se: np.ndarray | None = None


@dataclass
class Truth:
    lights: dict                      # name -> LightTruth
    U: dict                           # name -> (H, W, 3) unshadowed radiance
    shaded: np.ndarray                # (H, W, 3) Σ U V
    shaded_var: np.ndarray            # (H, W, 3)
    mitsuba: np.ndarray | None        # (H, W, 3) mi.render direct
    mitsuba_var: np.ndarray | None
    mask: np.ndarray                  # (H, W) bool
    view_depth: np.ndarray            # (H, W)
    stats: dict = field(default_factory=dict)


def _round_values(mi_scene, si, emitter, rng, k, kk, rays, win):
    """One round of ``sample_light``'s k×k samples with shadow rays at ``si`` from ``rng``: the
    round's ratio Vr = Σ f·v / Σ f and visible fraction Ar (float64, as the numpy version
    computed them) and its number of visible samples. ``rays``: (alpha, table) of
    ``light_samples`` (the scene's alpha-tested and translucent casters).

    With translucent casters (``table``) v is a sample's channel-mean transmittance, Vr and Ar
    are their channel means, three more values follow, the round's RGB ratios Σ f·τ_c / Σ f,
    and the third value is the unanimity code (lit − dark + k²)/2 of the round's fully lit and
    fully blocked samples: k² or 0 exactly when they all were (without translucency it is the
    number of visible samples, as before), so the stopping rule's test is the same."""
    alpha, table = rays
    out = light_samples(mi_scene, si, emitter, rng, k, True, True, alpha, win, radiance=False, table=table)
    fv, fsum, v = mi.Float64(out[1]), mi.Float64(out[2]), mi.Float64(out[3])
    ok = fsum > 0
    inv = dr.select(ok, fsum, 1.0)
    Vr = dr.select(ok, fv / inv, 1.0)
    if table is None:
        return Vr, v / mi.Float64(kk), v
    rgb, lit, dark = out[4], mi.Float64(out[5]), mi.Float64(out[6])
    code = (lit - dark + mi.Float64(kk)) * 0.5
    return (Vr, v / mi.Float64(kk), code) + tuple(
        dr.select(ok, mi.Float64(c) / inv, 1.0) for c in (rgb.x, rgb.y, rgb.z)
    )


def _round_hashes(seed: int, max_rounds: int):
    """The PCG32 state of each round, as ``sample_light`` seeds it: one UInt64 array in memory
    that the kernels gather from, so the seed never enters a kernel as a literal."""
    return mi.UInt64(np.array([seed_hash(seed, r) for r in range(max(max_rounds, 1))], np.uint64))


def _round(mi_scene, si, emitter, idx, hashes, r, k, kk, rays, win, sums):
    """Round ``r`` at every lane (PCG32 seeded by the round's hash and the lane's stream key
    ``idx``), folded into the lane's float64 sums (s_v, s_v2, s_a, s_a2, s_vis)."""
    rng = mi.PCG32(dr.width(idx), dr.gather(mi.UInt64, hashes, r), mi.UInt64(idx))
    return _fold(sums, *_round_values(mi_scene, si, emitter, rng, k, kk, rays, win))


def n_sums(rays) -> int:
    """Float64 sums per point: (Σ Vr, Σ Vr², Σ Ar, Σ Ar², Σ v), and with translucent casters
    (Σ V_c, Σ V_c²) for each channel c."""
    return 5 if rays[1] is None else 11


@dr.syntax
def _fixed_rounds(mi_scene, si, emitter, idx, hashes, n_rounds, k, kk, rays, win):
    """Rounds 0 … n_rounds−1 at every lane: one wavefront (a symbolic loop over the rounds)."""
    n = dr.width(idx)
    sums = tuple(dr.zeros(mi.Float64, n) for _ in range(n_sums(rays)))
    r = dr.zeros(mi.UInt32, n)
    while r < n_rounds:
        sums = _round(mi_scene, si, emitter, idx, hashes, r, k, kk, rays, win, sums)
        r += 1
    return sums


@dr.syntax
def _more_rounds(mi_scene, si, emitter, key, r, T, hashes, k, kk, rays, win, sums):
    """Rounds ``r`` … ``T``−1 of each lane (a point of rank ``key``; ``r`` and ``T`` per lane), folded
    into its float64 ``sums`` in round order: one wavefront (a symbolic loop over the rounds).

    PCG32 adds the lane's index to the state and to the sequence it is given; the lane is given
    what makes them the point's own in a wavefront of one lane per point (``_round``): a point of
    rank ``key`` starts at the round's hash + key on sequence 2·key, wherever its lane lies."""
    n = dr.width(key)
    lane, key64 = dr.arange(mi.UInt64, n), mi.UInt64(key)
    r = mi.UInt32(r)
    while r < T:
        sums = _lane_round(mi_scene, si, emitter, key64, lane, r, hashes, k, kk, rays, win, sums)
        r += 1
    return sums


def _lane_round(mi_scene, si, emitter, key, lane, r, hashes, k, kk, rays, win, sums):
    """Round ``r`` of each lane of ``_more_rounds`` folded into its sums (PCG32 as documented there)."""
    rng = mi.PCG32(dr.width(key), dr.gather(mi.UInt64, hashes, r) + key - lane, key + key - lane)
    return _fold(sums, *_round_values(mi_scene, si, emitter, rng, k, kk, rays, win))


def _lane_rounds(mi_scene, si, emitter, key, r, hashes, k, kk, rays, win):
    """One round per lane: lane i is round ``r[i]`` of the point of rank ``key[i]`` (Vr, Ar and
    visible samples, float64, as ``_round_values``).

    PCG32 adds the lane's index to the state and to the sequence it is given; the lane is given
    what makes them its point's own in a wavefront of one lane per point (``_round``): a point of
    rank ``key`` starts round r at the round's hash + key on sequence 2·key, wherever its lane lies."""
    lane, key64 = dr.arange(mi.UInt64, dr.width(key)), mi.UInt64(key)
    rng = mi.PCG32(dr.width(key), dr.gather(mi.UInt64, hashes, r) + key64 - lane, key64 + key64 - lane)
    return _round_values(mi_scene, si, emitter, rng, k, kk, rays, win)


@dr.syntax
def _fold_rounds(vals, start, n_dec, n_all, sums):
    """Each point's rounds, lanes ``start`` … ``start + n_all − 1`` of ``vals`` (Vr, Ar, v), added
    to its float64 ``sums`` in round order; returns the sums after its first ``n_dec`` of them (the
    decision's) and after all of them."""
    j = dr.zeros(mi.UInt32, dr.width(start))
    while j < n_dec:
        i = start + j
        sums = _fold(sums, *[dr.gather(mi.Float64, x, i) for x in vals])
        j += 1
    dec = sums
    while j < n_all:
        i = start + j
        sums = _fold(sums, *[dr.gather(mi.Float64, x, i) for x in vals])
        j += 1
    return dec, sums


def _lane_rows(first, total: int):
    """The row of each of ``total`` lanes when row i owns lanes first[i] … first[i+1]−1 (``first``
    ascending from 0; a row may own none): the number of rows i ≥ 1 that begin at or before the lane."""
    n = dr.width(first)
    marks = dr.zeros(mi.UInt32, total)
    i = dr.arange(mi.UInt32, 1, n) if n > 1 else None
    if i is not None:
        f = dr.gather(mi.UInt32, first, i)
        dr.scatter_reduce(dr.ReduceOp.Add, marks, mi.UInt32(1), f, f < total)
    return dr.prefix_reduce(dr.ReduceOp.Add, marks, exclusive=False)


def _fold(sums, Vr, Ar, v, *rgb):
    """A round's (Vr, Ar, visible samples[, V_R, V_G, V_B]) added to a lane's float64 sums (s_v,
    s_v2, s_a, s_a2, s_vis[, s_R, s_R², s_G, s_G², s_B, s_B²])."""
    s_v, s_v2, s_a, s_a2, s_vis = sums[:5]
    out = (s_v + Vr, s_v2 + Vr * Vr, s_a + Ar, s_a2 + Ar * Ar, s_vis + v)
    for i, c in enumerate(rgb):
        out += (sums[5 + 2 * i] + c, sums[6 + 2 * i] + c * c)
    return out


def _lanes_per_round() -> bool:
    """Whether the penumbra wavefronts run a lane per (point, round): on a GPU, which traces each
    lane's rays alone. The CPU (Embree) traces packets of neighbouring lanes, and there a ray's
    result can depend on the rays beside it, so the CPU keeps the lane per point of the committed bits."""
    return dr.backend_v(mi.Float) == dr.JitBackend.CUDA


def _point_lanes(mi_scene, gsi, emitter, pts, hashes, k, kk, rays, spec, live, Rl, T, S):
    """A wavefront of one lane per point (the CPU's): rows ``live`` of ``pts`` sample rounds Rl … T−1,
    each lane looping over its point's rounds, the lanes ordered by their number of rounds (longest
    first: lanes that finish together side by side, on the CPU 1.7× faster than in point order).
    Returns (sums at T, sums at T, the rows: as an index array and in numpy)."""
    order = np.argsort(-(T - Rl), kind="stable")
    rows = live[order]
    q = mi.UInt32(rows.astype(np.uint32))
    si_q = dr.gather(type(gsi), gsi, dr.gather(mi.UInt32, pts, q))
    Sq = _more_rounds(mi_scene, si_q, emitter, q, mi.UInt32(Rl[order].astype(np.uint32)),
                      mi.UInt32(T[order].astype(np.uint32)), hashes, k, kk, rays,
                      shading.range_window(spec, si_q.p), tuple(dr.gather(mi.Float64, x, q) for x in S))
    return Sq, Sq, q, rows


def _round_lanes(mi_scene, gsi, emitter, pts, hashes, k, kk, rays, spec, live, Rl, T, G, S):
    """A wavefront of one lane per (point, round) (a GPU's): rows ``live`` of ``pts`` sample rounds
    Rl … G−1, a point's rounds in adjacent lanes, each lane one round (``_lane_rounds``) written to
    a float64 buffer; a second kernel (``_fold_rounds``) adds each point's rounds to its sums in
    round order. Returns (sums at T, sums at G, the rows: as an index array and in numpy)."""
    cnt = G - Rl                          # rounds each point samples now (0: a decision only)
    off = np.cumsum(cnt) - cnt            # its first lane
    total = int(cnt.sum())
    q = mi.UInt32(live.astype(np.uint32))
    Sq = tuple(dr.gather(mi.Float64, x, q) for x in S)
    if not total:
        return Sq, Sq, q, live
    offd = mi.UInt32(off.astype(np.uint32))
    row = _lane_rows(offd, total)
    key = dr.gather(mi.UInt32, q, row)
    rnd = dr.gather(mi.UInt32, mi.UInt32(Rl.astype(np.uint32)), row) + dr.arange(mi.UInt32, total) \
        - dr.gather(mi.UInt32, offd, row)
    si_l = dr.gather(type(gsi), gsi, dr.gather(mi.UInt32, pts, key))
    vals = _lane_rounds(mi_scene, si_l, emitter, key, rnd, hashes, k, kk, rays, shading.range_window(spec, si_l.p))
    dr.eval(vals)
    dec, Sq = _fold_rounds(vals, offd, mi.UInt32((T - Rl).astype(np.uint32)), mi.UInt32(cnt.astype(np.uint32)), Sq)
    return dec, Sq, q, live


def _read(*xs):
    """Equally long float64 device arrays read back to the host as numpy copies, in one transfer."""
    n = dr.width(xs[0])
    buf = dr.zeros(mi.Float64, n * len(xs))
    for i, x in enumerate(xs):
        dr.scatter(buf, x, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, i * n))
    dr.eval(buf)
    return tuple(np.array(buf.numpy().reshape(len(xs), n), copy=True))


def _plan(R, s_v, s_v2, s_vis, planned, kk: int, target_se, max_rounds: int):
    """The stopping rule of the module docstring at points that have ``R`` rounds (numpy): plan
    the rounds from the pilot, re-plan when the plan fell short; ``target_se`` one number or one
    per point. Returns (planned, done)."""
    n = R * kk
    unanimous = (s_vis == 0) | (s_vis == n)
    mean = s_v / R
    var = np.maximum(s_v2 / R - mean * mean, 0.0) * R / np.maximum(R - 1, 1)
    se = np.sqrt(var / R)
    need = np.ceil(PLAN_MARGIN * var / target_se ** 2)
    replan = (R >= MIN_SE_ROUNDS) & ((planned == 0) | ((R >= planned) & (se > target_se)))
    planned = np.where(replan, np.clip(need, np.maximum(R + (planned > 0), 2 * MIN_SE_ROUNDS), max_rounds),
                       planned).astype(np.int64)
    done = unanimous | ((planned > 0) & (R >= planned)) | (R >= max_rounds)
    return planned, done


def light_targets(U: dict, target_se: float) -> dict:
    """Per-light target standard errors of the ``contribution`` allocation (module docstring):
    ``U`` light name -> unshadowed light (numpy, (..., 3): flat points or an image), the result
    light name -> targets (...,) float64.

    >>> U = {"a": np.array([[0.6, 0.1, 0.1], [1.0, 1.0, 1.0]]), "b": np.array([[0.1, 0.05, 0.05], [0, 0, 0]])}
    >>> t = light_targets(U, 0.005)
    >>> [round(float(x), 5) for x in t["a"]], [round(float(x), 5) for x in t["b"]]
    ([0.00559, 0.005], [0.01118, 0.05])
    """
    lum = {n: np.asarray(u, np.float64).sum(-1) for n, u in U.items()}
    S = sum(lum.values())
    out = {}
    for n, l in lum.items():
        with np.errstate(divide="ignore", invalid="ignore"):
            t = target_se * np.sqrt(S / l)
        out[n] = np.where(l > 0, np.minimum(t, CONTRIBUTION_MAX_SE), CONTRIBUTION_MAX_SE)
    return out


def visibility(frame: FrameContext, light_name: str, *, k: int = 8, target_se=0.005,
               min_rounds: int = 4, max_rounds: int = 64, seed: int = 0, progress=None,
               points=None) -> LightTruth:
    """Adaptive ground-truth visibility of one light (see the module docstring).

    Few, large wavefronts instead of one small kernel per round: every valid point's first
    ``min_rounds`` rounds in one kernel (a loop over the rounds), then, for the points whose
    samples disagreed, one wavefront per decision of the stopping rule (the pilot's end, then each
    plan's end): on a GPU a lane per (point, round) and a kernel that sums each point's rounds in
    order (``_round_lanes``), on the CPU a lane per point looping over its rounds (``_point_lanes``).
    A point's random numbers are ``sample_light``'s: PCG32 keyed by (seed, round) and the point's
    rank among the valid points (first wavefront) or among the points that sample on (later
    ones); its rounds are summed in order in float64. The per-point state stays on the device
    (the valid and the penumbra points are found with ``dr.compress``); the host reads back only
    the three sums the rule needs, of the points deciding. ``progress(n)`` is called with each
    wavefront's shadow rays. ``target_se``: one number, or one per G-buffer point (numpy; the
    ``contribution`` allocation's :func:`light_targets`). ``points``: optional numpy bool per
    G-buffer point, the points to sample (the ``contribution`` allocation skips those the light
    does not reach: V = 1 there, no samples, as where there is no surface).
    """

    scene, gb = frame.scene.casters, frame.gbuffer  # shadow rays see what casts shadows (casts_shadows)
    spec = scene.spec.light(light_name)
    emitter = scene.emitters[light_name]
    if spec.is_delta:
        k, min_rounds, max_rounds = 1, 1, 1
    kk = k * k
    # the shadow rays' path: through alpha-tested casters' holes, through translucent casters
    paths = (bool(getattr(scene, "has_alpha", False)),
             scene.translucency() if getattr(scene, "has_translucent", False) else None)
    per_round = _lanes_per_round()
    valid = gb.valid if points is None else gb.valid & mi.Bool(np.asarray(points, bool).reshape(-1))
    active = dr.compress(mi.Bool(valid))  # the valid points (that it samples), in order
    n_act = dr.width(active)
    hashes = _round_hashes(seed, max_rounds)
    opq = dict(k=dr.opaque(mi.UInt32, k), kk=dr.opaque(mi.UInt32, kk))
    n_first = min(max(min_rounds, 1), max_rounds)
    rays = 0
    # per valid point, on the device: the five float64 sums (Σ Vr, Σ Vr², Σ Ar, Σ Ar², visible samples)
    sums = tuple(dr.zeros(mi.Float64, n_act) for _ in range(n_sums(paths)))
    rounds = dr.zeros(mi.Float64, n_act)
    if n_act and n_first > 0:
        # wavefront 1: every valid point's first rounds (stream key: rank among the valid points)
        si = dr.gather(type(gb.si), gb.si, active)
        sums = _fixed_rounds(scene.mi_scene, si, emitter, dr.arange(mi.UInt32, n_act), hashes,
                             dr.opaque(mi.UInt32, n_first), opq["k"], opq["kk"], paths,
                             shading.range_window(spec, si.p))
        rounds = dr.full(mi.Float64, n_first, n_act)
        dr.eval(sums, rounds)
        rays += n_act * n_first * kk
        if progress:
            progress(n_act * n_first * kk)
        # the points whose samples all agreed are done; the others sample on, each to its own plan:
        # a wavefront per decision (the pilot's end, each plan's end)
        ri = dr.compress((sums[4] != 0) & (sums[4] != dr.opaque(mi.Float64, n_first * kk)))
        n_rest = dr.width(ri)
        if n_rest:
            # the rest's G-buffer points and sums, on the device (a wavefront gathers its lanes'
            # interactions from the G-buffer itself, inside its kernel)
            pts = dr.gather(mi.UInt32, active, ri)
            S = [dr.gather(mi.Float64, x, ri) for x in sums]
            dr.eval(pts, S)
            # each row's target: one for all, or its point's
            tgt = (np.asarray(target_se, np.float64).reshape(-1)[pts.numpy()] if np.ndim(target_se)
                   else float(target_se))
            R = np.full(n_rest, n_first, np.int64)   # rounds at each point's latest decision
            Rs = R.copy()                             # rounds summed in S (≥ R: see G below)
            planned = np.zeros(n_rest, np.int64)
            if n_first < min(MIN_SE_ROUNDS, max_rounds):
                # the rule at the first check decides nothing before the pilot's end (no point here is
                # unanimous): no sums to read back
                s_v, s_v2, s_vis = (np.empty(n_rest) for _ in range(3))
                done = np.zeros(n_rest, bool)
            else:  # the rule at the first check: already a plan (min_rounds reaches the pilot's rounds)
                s_v, s_v2, s_vis = _read(S[0], S[1], S[4])
                planned, done = _plan(R, s_v, s_v2, s_vis, planned, kk, tgt, max_rounds)
            live = np.nonzero(~done)[0]          # rows of ``pts`` still sampling, in order
            while len(live):
                # up to the next decision: the pilot's end, or the end of the plan
                Pl = planned[live]
                T = np.where(Pl > 0, Pl, MIN_SE_ROUNDS)
                T = np.minimum(np.maximum(T, R[live] + 1), max_rounds)
                # lanes per round: every plan made at the pilot's end reaches G (2·MIN_SE_ROUNDS or
                # more), so the pilot's wavefront samples up to G, summing its decision's snapshot at T
                G = np.where(Pl == 0, np.minimum(np.maximum(T, 2 * MIN_SE_ROUNDS), max_rounds), T) if per_round else T
                Rl = Rs[live]
                args = (scene.mi_scene, gb.si, emitter, pts, hashes, opq["k"], opq["kk"], paths, spec)
                if per_round:
                    dec, Sq, q, rows = _round_lanes(*args, live, Rl, T, G, S)
                else:
                    dec, Sq, q, rows = _point_lanes(*args, live, Rl, T, S)
                dr.eval(dec, Sq)  # before the scatters: scattered into while its kernel still read S, Sq was wrong
                for x, y in zip(S, Sq):
                    dr.scatter(x, y, q)
                dr.eval(S)
                s_v[rows], s_v2[rows], s_vis[rows] = _read(dec[0], dec[1], dec[4])
                n_more = int((G - Rl).sum()) * kk
                R[live], Rs[live] = T, G
                rays += n_more
                if progress:
                    progress(n_more)
                planned[live], done = _plan(T, s_v[live], s_v2[live], s_vis[live], planned[live], kk,
                                            tgt[live] if np.ndim(tgt) else tgt,
                                            max_rounds)
                live = live[~done]
            # a point's sampling ends at a decision, never past it (a plan made at the pilot's end covers
            # G, and no point that sampled on can become unanimous): S holds each point's final sums
            assert np.array_equal(R, Rs)
            for x, y in zip(sums + (rounds,), S + [mi.Float64(R.astype(np.float64))]):
                dr.scatter(x, y, ri)
    lt = _light_truth(gb, sums, rounds, active, n_act, kk, bool(spec.is_delta), rays)
    if len(sums) > 5:
        lt.V_rgb, lt.V_rgb_se = _rgb_images(gb, sums, rounds, active, n_act)
    return lt


def _rgb_images(gb, sums, rounds, active, n_act):
    """(V_rgb, V_rgb_se) images (H, W, 3) from the channel sums of a light with translucent casters
    (1 and 0 where no surface is), as :func:`_light_truth` makes V and V_se."""
    s2 = gb.ss * gb.ss
    if not n_act:
        return np.ones((gb.height, gb.width, 3), np.float32), np.zeros((gb.height, gb.width, 3), np.float32)
    img = gb.to_image if s2 > 1 else (lambda x: np.asarray(x, np.float32).reshape(gb.height, gb.width))
    mean, se = [], []
    for c in range(3):
        m, v = _mean_var(sums[5 + 2 * c], sums[6 + 2 * c], rounds)
        a, b = _on_points(m, 1.0, gb.size, active), _on_points(v, 0.0, gb.size, active)
        dr.eval(a, b)
        mean.append(img(a.numpy()))
        se.append(np.sqrt(img(b.numpy()) / s2))
    return np.stack(mean, -1), np.stack(se, -1).astype(np.float32)


def _mean_var(s, s2, rounds):
    """A point's mean over its rounds and the variance of that mean (0 with one round), from the
    float64 sums of a value and of its square."""
    R = dr.maximum(rounds, 1.0)
    m = s / R
    var = dr.maximum(s2 / R - m * m, 0.0) * R / dr.maximum(R - 1.0, 1.0)
    return m, dr.select(rounds > 1, var / R, 0.0)


def _on_points(x, outside, size, active):
    """Every G-buffer point: ``x`` at the sampled ones (``active``), ``outside`` elsewhere, as float32."""
    out = dr.full(mi.Float64, outside, size)
    dr.scatter(out, x, active)
    return mi.Float32(out)


def _point_values(size, sums, rounds, active, n_act, kk, delta, flat=False):
    """V, se(V)², A, se(A)², samples and bound at every G-buffer point (float32, on the device);
    ``flat``: se(V) and se(A) instead of their squares, and all six in one array, one after the other."""
    s_v, s_v2, s_a, s_a2, s_vis = sums[:5]
    (m_v, var_v), (m_a, var_a) = _mean_var(s_v, s_v2, rounds), _mean_var(s_a, s_a2, rounds)
    se_v, se_a = dr.sqrt(var_v), dr.sqrt(var_a)
    n = rounds * kk
    unanimous = (s_vis == 0) | (s_vis == n)
    bound = dr.select(unanimous, 3.0 / dr.maximum(n, 1.0), 0.0) if not delta else dr.zeros(mi.Float64, n_act)

    def full(x, outside):
        return _on_points(x, outside, size, active)

    out = [full(m_v, 1.0), full(se_v * se_v, 0.0), full(m_a, 1.0), full(se_a * se_a, 0.0), full(n, 0.0),
           full(bound, 0.0)]
    if not flat:
        dr.eval(out)
        return out
    # the square root of the float32 square in float64, rounded to float32: numpy's float32 square
    # root (correctly rounded; a float64 root rounded to float32 is too, 53 ≥ 2·24 + 2 bits)
    for i in (1, 3):
        out[i] = mi.Float32(dr.sqrt(mi.Float64(out[i])))
    buf = dr.zeros(mi.Float32, 6 * size)
    for i, x in enumerate(out):
        dr.scatter(buf, x, dr.arange(mi.UInt32, size) + dr.opaque(mi.UInt32, i * size))
    dr.eval(buf)
    return buf


def _light_truth(gb, sums, rounds, active, n_act, kk: int, delta: bool, rays: int) -> LightTruth:
    """The images of a light's truth from each valid point's sums and rounds, computed on the
    device (float64, the operations of the numpy version they replace) and read back as the
    float32 images ``gb.to_image`` makes; a point that is not valid is lit with no samples. With
    one point per pixel the six images are the flat arrays reshaped, read back in one transfer."""
    s2 = gb.ss * gb.ss  # a pixel's value is the mean of its s² independent sub-pixel estimates
    if not n_act:  # no surface in view: every point lit, no samples
        ones, zeros = np.ones(gb.size, np.float32), np.zeros(gb.size, np.float32)
        out = [ones, zeros, ones, zeros, zeros, zeros]
    elif s2 == 1:  # gb.to_image's bits: its mean over one sub-pixel is the value, its √(se²/1) the root above
        im = np.asarray(_point_values(gb.size, sums, rounds, active, n_act, kk, delta, flat=True).numpy(),
                        np.float32).reshape(6, gb.height, gb.width)
        return LightTruth(V=im[0], V_se=im[1], A=im[2], A_se=im[3], samples=im[4], bound=im[5], rays=int(rays))
    else:
        out = _point_values(gb.size, sums, rounds, active, n_act, kk, delta)
    img = gb.to_image if s2 > 1 else (lambda x: np.asarray(x, np.float32).reshape(gb.height, gb.width))

    def se_img(se2):
        return np.sqrt(img(se2) / s2)

    return LightTruth(V=img(out[0]), V_se=se_img(out[1]), A=img(out[2]), A_se=se_img(out[3]),
                      samples=img(out[4]) * s2, bound=img(out[5]), rays=int(rays))


def mitsuba_render(scene, spp: int = 256, passes: int = 4, seed: int = 0):
    """Mitsuba's own ``direct`` integrator image and the variance of its mean over ``passes``
    independent renders of spp/passes samples each.

    The passes are summed on the device in float64 (the same additions, in the same order, as
    numpy's mean and ``var(ddof=1)`` over the stacked passes), so one image and one variance come
    back to the host instead of every pass."""
    integrator = mi.load_dict({"type": "direct"})
    per = max(1, spp // passes)
    imgs = []
    for i in range(passes):
        img = mi.TensorXd(mi.render(scene.mi_scene, sensor=scene.sensor, spp=per, seed=seed * 1000 + i,
                                    integrator=integrator))
        dr.eval(img)  # now: the film's storage is reused by the next pass
        imgs.append(img)
    total = imgs[0]
    for im in imgs[1:]:
        total = total + im
    # opaque divisors: Dr.Jit turns a division by a literal into a multiplication by its reciprocal
    mean = total / dr.opaque(mi.TensorXd, passes)
    if passes > 1:
        sq = [(im - mean) * (im - mean) for im in imgs]
        ss = sq[0]
        for q in sq[1:]:
            ss = ss + q
        var = ss / dr.opaque(mi.TensorXd, passes - 1) / dr.opaque(mi.TensorXd, passes)
    else:
        var = dr.zeros(mi.TensorXd, mean.shape)
    dr.eval(mean, var)
    return mean.numpy().astype(np.float32), var.numpy().astype(np.float32)


def render_truth(frame: FrameContext, *, k: int = 8, target_se: float = 0.005, max_rounds: int = 64,
                 seed: int = 0, spp: int = 256, progress=None) -> Truth:
    """The whole ground truth of a frame: every light's visibility, Σ U·V and mi.render. ``stats``
    holds the cost, in all and per light (``per_light``: seconds and shadow rays of each light's
    visibility), which ``meta.json`` records: a many-light truth's cost grows with its lights, less
    so with the scene's ``truth_allocation = "contribution"`` (module docstring; ``stats["allocation"]``)."""
    gb = frame.gbuffer
    t0 = time.perf_counter()
    allocation = getattr(frame.scene.spec, "truth_allocation", "per_light")
    flatU = {l.name: vec_numpy(frame.unshadowed[l.name]) for l in frame.lights} if allocation == "contribution" else {}
    targets = light_targets(flatU, target_se) if flatU else {}
    lights, U, cost = {}, {}, {}
    shaded = 0.0
    var = 0.0
    for l in frame.lights:
        dr.sync_thread()
        t_l = time.perf_counter()
        lt = visibility(frame, l.name, k=k, target_se=targets.get(l.name, target_se), max_rounds=max_rounds,
                        seed=seed, progress=progress,
                        points=flatU[l.name].sum(-1) > 0 if flatU else None)
        dr.sync_thread()
        cost[l.name] = {"time_s": time.perf_counter() - t_l, "shadow_rays": int(lt.rays)}
        if lt.V_rgb is not None and all(np.array_equal(lt.V_rgb[..., 0], lt.V_rgb[..., c]) for c in (1, 2)):
            lt.V_rgb = lt.V_rgb_se = None  # no sample crossed a coloured surface: its shadows have no colour
        lights[l.name] = lt
        U[l.name] = gb.to_image(vec_numpy(frame.unshadowed[l.name]))
        V, V_se = (lt.V_rgb, lt.V_rgb_se) if lt.V_rgb is not None else (lt.V[..., None], lt.V_se[..., None])
        shaded = shaded + U[l.name] * V
        var = var + (U[l.name] * V_se) ** 2
    dr.sync_thread()
    t_vis = time.perf_counter() - t0
    mean, mvar = mitsuba_render(frame.scene, spp=spp, seed=seed) if spp else (None, None)
    dr.sync_thread()
    mask = gb.to_image(gb.mask.reshape(-1).astype(np.float32)) > 0.5
    stats = {"visibility_time_s": t_vis, "mitsuba_time_s": time.perf_counter() - t0 - t_vis,
             "shadow_rays": int(sum(l.rays for l in lights.values())),
             "max_std_error": float(max(float(l.V_se[mask].max()) if mask.any() else 0.0 for l in lights.values())),
             "spp_mitsuba": spp, "strata": k, "target_se": target_se, "max_rounds": max_rounds, "seed": seed,
             "per_light": cost, "allocation": allocation}
    return Truth(lights=lights, U=U, shaded=np.asarray(shaded, np.float32), shaded_var=np.asarray(var, np.float32),
                 mitsuba=mean, mitsuba_var=mvar, mask=mask, view_depth=gb.to_image(gb.view_depth.reshape(-1)),
                 stats=stats)


def target_missed(truth: Truth, target_se: float, max_rounds: int, worst: int = 32) -> dict:
    """The pixels whose standard error is still above ``target_se`` after the round cap (with the
    ``contribution`` allocation, ``stats["allocation"]``, above each light's own target there,
    :func:`light_targets` of the stored U).

    Returns ``{"target_se", "max_rounds", "pixels", "worst_se", "lights": {light: {"pixels",
    "worst_se", "worst": [[x, y, se], …]}}}`` (the ``worst`` pixels of each light, worst first);
    ``pixels`` is 0 when every pixel met the target. ``meta.json`` records it as ``target_missed``."""
    lights = {}
    per = truth.stats.get("allocation") == "contribution"
    targets = light_targets(truth.U, target_se) if per else {}
    for name, lt in truth.lights.items():
        se = np.where(truth.mask, lt.V_se, 0.0)
        ys, xs = np.nonzero(se > (targets[name] * (1 + 1e-6) if per else target_se))
        if len(xs) == 0:
            continue
        order = np.argsort(-se[ys, xs], kind="stable")[:worst]
        lights[name] = {"pixels": int(len(xs)), "worst_se": float(se[ys, xs].max()),
                        "worst": [[int(xs[i]), int(ys[i]), float(se[ys[i], xs[i]])] for i in order]}
    return {"target_se": float(target_se), "max_rounds": int(max_rounds),
            "pixels": int(sum(v["pixels"] for v in lights.values())),
            "worst_se": float(max((v["worst_se"] for v in lights.values()), default=0.0)), "lights": lights}


def centre_visibility(frame: FrameContext, light_name: str):
    """Exact hard-shadow visibility of the light's centre at the G-buffer points (flat ``mi.Float``,
    1 lit, 0 blocked; 1 where there is no surface): one Mitsuba ray per point toward the centre of
    a positional light, or against a directional light's direction, skipping the light's own
    shape (the truth's emitter: the sun's far disk, a sphere light's sphere), surfaces that cast no
    shadow (``casts_shadows``) and, in scenes with alpha-tested casters, their transparent texels.
    The truth a shadow map's aliasing is measured against: a map of the light's centre converges to
    it as its resolution grows [Giegl 2007, §5]."""
    gb = frame.gbuffer
    spec = frame.scene.spec.light(light_name)
    si = gb.si
    if spec.kind == "directional":
        d = np.asarray(lights_fwd(spec), np.float64)
        ray = si.spawn_ray(mi.Vector3f(*[float(-x) for x in d]))
        far = None
    else:
        ray = si.spawn_ray_to(mi.Point3f(*[float(x) for x in spec.position]))
        far = ray.maxt
        ray.maxt = dr.inf
    scene = frame.scene.casters
    own = scene.light_shapes.get(light_name)
    shapes = scene.mi_scene.shapes_dr()
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    hit = cast_first_hit(scene.mi_scene, ray, False, own_ptr, bool(getattr(scene, "has_alpha", False)))
    blocked = hit.is_valid() & gb.valid
    if far is not None:
        blocked &= hit.t < far
    return dr.select(blocked, 0.0, 1.0)
