"""Prefiltered shadow maps: the machinery that ``vsm``, ``esm``, ``evsm`` and ``msm`` share
([Buljan 2020, §3.3–§3.5]; moment shadow maps: [Peters 2015]).

A prefiltered technique does not filter depth *comparisons* (PCF, §3.2) but stores functions
of depth ("moments") that can be blurred before the lookup, because the visibility estimate is
computed from their filtered averages (§3.3: "it suffices to apply an ordinary blur filter
directly to the shadow map"). Every step below runs in Dr.Jit, every render, for every light:
nothing of it is cached between render calls, so a timed run pays for building, blurring and
sampling the maps (only the depth map itself, the :class:`~shadowlab.render.lightview.LightView`
that ``FrameContext`` caches, is reused: a GPU would have rendered it anyway).

1. **Depth domain.** The moments are functions of the *normalised linear light-space depth*

       zn = (z − near) / (far − near) ∈ [0, 1],      empty texels (nothing hit) zn = 1,

   with z the LightView's ``z`` (the light-space depth the stored, quantised depth decodes to)
   and near/far those of the light camera (``proj.faces[0]``; all cube faces share them).
   Why linear and not the NDC depth the source's Code A.5 writes: a perspective NDC depth is
   hyperbolic and crowds most of the scene into the last per-mille below 1, where a Chebyshev
   bound on (d, d²) needs a min. variance tuned per scene and fp32 loses the variance to
   cancellation; zn is affine in z, and light-space z along one light ray is proportional to
   the distance from the light, so the ratio t = Δx/Δy of the leak formula of §3.3 is the
   same in world units and in map units; and zn ∈ [0, 1] is the interval for which §3.4
   derives the fp32 limit c ≤ ln(3.4·10³⁸) ≈ 88.72. Every technique uses the same zn; EVSM
   maps it further (see its module). The receiver's depth z̃ is the zn of its light-space z
   after the receiver biases of §2.3 (``constant_bias``, ``slope_bias``/``max_slope_bias``,
   ``normal_offset``: the declarations of :data:`~shadowlab.techniques.shadow_map.BIAS_PARAMS`,
   reused, and ``shadow_map.receiver``). The Direct3D rasterizer biases (DepthBias,
   SlopeScaledDepthBias, DepthBiasClamp) act on the depth *buffer*; the moments are colour
   values a pixel shader writes (Code A.5), so they do not reach them: only ``esm`` declares
   them, for the depth tests of its PCF fallback.
2. **Separable blur per face.** ``kernel`` = n texels per axis, ``filter`` = ``box`` (weights
   1/n, the source's n×n grid) or ``gaussian`` (σ = n/6: the n texels span ±3σ, weights
   normalised to 1 after truncation). Two passes (rows, then columns), each one kernel for
   every moment channel over every texel of every face; taps outside a face are clamped to its
   border texel, so cube faces never bleed into each other. Blurred texel j averages texels j + k,
   k = −⌊n/2⌋ … n − 1 − ⌊n/2⌋: centred on j for odd n, on j − ½ for even n (the lookup
   shifts by that half texel, so every n filters the n×n square centred on the receiver).
   n = 1 is no blur (the "no filtering" of the source's UI).
3. **Bilinear lookup** ("hardware" filtering, level 0 only): at the receiver's continuous texel
   coordinates (u, v) (centres at i + ½; + ½ for even n, see 2.) the 2×2 blurred texels around
   u − ½, v − ½ and their bilinear weights; at a face border (within half a texel of it) the
   lookup clamps to the border texels, as a clamp-addressed sampler does. Sub-texel weights are
   fp32, not the 8-bit fractions of GPU samplers. So the effective filter of blur + lookup is
   (n + 1)² texels wide: per axis, texel i0 + m weighs (1 − f)·w_m + f·w_{m−1}. For the box
   filter these are (1 − f, 1, …, 1, f)/n: exactly ``pcf`` with an n×n ``grid`` of
   ``bilinear`` taps at ``softness`` 1, i.e. the area average over the n×n-texel square
   centred on the receiver. :func:`pcf_footprint` runs ``shadow_map.depth_test`` with exactly
   these weights: the PCF that the prefiltered estimate should reproduce (§3.3: VSM = PCF for
   two parallel planes), and ``esm``'s fallback.
4. **No mip maps.** The maps are sampled at level 0 only, whatever the G-buffer pixel's
   footprint in the map: when a pixel covers many texels (minification) the result aliases
   like a plain shadow map's. §3.2 notes that prefiltered maps *allow* mip-mapping; shadowlab
   does not build mip levels, so the filter width is ``kernel`` texels everywhere.

Results are clipped to [0, 1]; points without a surface or outside the light camera get 1.

Compilation: every continuous value enters the kernels through ``dr.opaque`` (a new value
compiles no new kernel). The blur passes are unrolled over the n taps (fastest per texel), so
each (n, filter) compiles its blur once; the PCF footprint of ``esm``'s fallback is a symbolic
loop over an uploaded weight table (its cost grows with (n + 1)², its compile time does not).
A differentiable parameter may also be passed as a Dr.Jit ``mi.Float`` of width 1 with
gradients enabled: it is used as is (made opaque), so ``dr.backward`` of a loss on the
visibility reaches it through the blur and the estimate (what the parameter fitting relies on).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from .base import LightResult, Param, opaque_scalar
from .shadow_map import BIAS_PARAMS, ShadowMapTechnique, depth_test, map_entry, map_stats, receiver

SOURCE = "[Buljan 2020, §3.3]"
KERNEL_MAX = 31
_TINY = 1e-30
_HUGE = 1e38


def shared(*names) -> tuple:
    """The declarations of ``BIAS_PARAMS`` named ``names`` (the same objects, not copies)."""
    by_name = {p.name: p for p in BIAS_PARAMS}
    return tuple(by_name[n] for n in names)


#: shadow-map format of the depth map the moments are made from
MAP_PARAMS = shared("resolution", "depth_bits", "backface")
#: receiver-side biases of §2.3 (they move z̃, which every prefiltered estimate compares)
RECEIVER_PARAMS = shared("constant_bias", "slope_bias", "max_slope_bias", "normal_offset")
#: Direct3D rasterizer biases: only for depth tests on the depth map (ESM's PCF fallback)
RASTER_PARAMS = shared("depth_bias", "slope_scaled_depth_bias", "depth_bias_clamp")

FILTER_PARAMS = (
    Param("kernel", 3, "int", 1, KERNEL_MAX, "texels", False, source=SOURCE,
          doc="n: the separable prefilter blur spans n texels per axis, centred on the receiver "
              "(1 = no blur, only the bilinear lookup; 3, 5, 7 in the source)"),
    Param("filter", "box", "choice", choices=("box", "gaussian"), source=SOURCE,
          doc="prefilter weights: box 1/n (the source's n×n grid; with the bilinear lookup = `pcf` "
              "grid with bilinear taps) or gaussian with σ = n/6 texels"),
)

MIN_VARIANCE = Param("min_variance", 1e-6, "float", 0.0, 0.01, "zn²", True, source="[Buljan 2020, §3.3]",
                     doc="σ²_min: lower bound of the filtered variance (zn = normalised linear depth), "
                         "against numerical problems where z̃ ≈ μ")
BLEED = Param("bleed", 0.0, "float", 0.0, 0.95, "", True, source="[Buljan 2020, §3.3]",
              doc="light-bleeding reduction p: Reduction(v, p) = 0 if v < p else (v − p)/(1 − p)")


# ----------------------------------------------------------------------------------------------
# parameters

def scalar(values: dict, name: str):
    """Parameter ``name`` as an opaque mi.Float. A Dr.Jit array passed in is used as is (made
    opaque, gradients kept), so gradients enabled on it flow through the technique."""
    return opaque_scalar(values[name])


def bias_values(values: dict) -> dict:
    """All of BIAS_PARAMS for ``shadow_map.opaque_bias``: the technique's own values, and for
    the ones it does not declare (the rasterizer biases of VSM & co.) 0 = no bias."""
    full = {p.name: p.default for p in BIAS_PARAMS}
    for p in RASTER_PARAMS:
        full[p.name] = 0 if p.kind == "int" else 0.0
    full.update({k: v for k, v in values.items() if k in full})
    return full


# ----------------------------------------------------------------------------------------------
# depth domain

def depth_range(view) -> tuple[float, float]:
    f0 = view.proj.faces[0]
    return f0.near, f0.far


def normalised_depth(view):
    """zn per texel (flat, face-major like the LightView's maps): (z − near)/(far − near)."""
    n, f = depth_range(view)
    return dr.clip((view.dr("z") - n) * (1.0 / (f - n)), 0.0, 1.0)


def prepare_receiver(frame, view, bias) -> dict:
    """``shadow_map.receiver`` plus ``zn`` (the receiver's biased depth z̃ in the zn domain).
    Points that are not active (no surface, outside the light camera) get harmless values
    (u = v = ½, zn = 0): the base class sets visibility 1 outside ``active``, and finite values keep
    reverse-mode gradients free of NaN (0 · ∞)."""
    rec = receiver(frame, view, bias)
    n, f = depth_range(view)
    act = rec["active"]
    rec["zn"] = dr.select(act, (rec["z"] - rec["zbias"] - n) * (1.0 / (f - n)), 0.0)
    rec["u"] = dr.select(act, rec["u"], 0.5)
    rec["v"] = dr.select(act, rec["v"], 0.5)
    return rec


# ----------------------------------------------------------------------------------------------
# separable blur and max filter, per face, clamped at face borders

def tap_offsets(n: int) -> list[int]:
    """Offsets k of the n taps of blurred texel j (texels j + k): −⌊n/2⌋ … n − 1 − ⌊n/2⌋."""
    return list(range(-(n // 2), n - n // 2))


def centre_shift(n: int) -> float:
    """Where blurred texel j's taps are centred, relative to texel j: 0 (odd n) or −½ (even n)."""
    return (n - 1) / 2.0 - n // 2


def blur_weights(n: int, kind: str) -> list[float]:
    """1D weights of the n-tap prefilter at the offsets :func:`tap_offsets` (sum 1)."""
    if n < 1:
        raise InputError(f"kernel={n}: the prefilter needs at least 1 texel")
    if kind == "box":
        return [1.0 / n] * n
    if kind == "gaussian":
        s, c = n / 6.0, centre_shift(n)
        g = [math.exp(-0.5 * ((k - c) / s) ** 2) for k in tap_offsets(n)]
        t = sum(g)
        return [x / t for x in g]
    raise InputError(f"filter={kind!r}: expected box or gaussian")


def _texel_index(view):
    """(face base index, ix, iy) of every texel of every face (built inside the kernel)."""
    N = view.res
    i = dr.arange(mi.UInt32, view.nfaces * N * N)
    rem = i % (N * N)
    return i - rem, mi.Int32(rem % N), mi.Int32(rem // N)


def _pass(view, chans, w, axis: int, op: str = "sum"):
    """One separable pass over all faces: weighted sum (or max) of the taps along ``axis``."""
    N = view.res
    base, ix, iy = _texel_index(view)
    out = [None] * len(chans)
    for k, wk in zip(tap_offsets(len(w)), w):
        if axis == 0:
            idx = base + mi.UInt32(iy * N + dr.clip(ix + k, 0, N - 1))
        else:
            idx = base + mi.UInt32(dr.clip(iy + k, 0, N - 1) * N + ix)
        for c, ch in enumerate(chans):
            t = dr.gather(mi.Float, ch, idx)
            if op == "max":
                out[c] = t if out[c] is None else dr.maximum(out[c], t)
            else:
                out[c] = t * wk if out[c] is None else dr.fma(t, wk, out[c])
    return out


def blur(view, chans: list, n: int, kind: str) -> list:
    """Separable blur of the moment maps ``chans`` (flat mi.Float, all faces): rows, then
    columns (a render pass per axis on a GPU; here one kernel per pass)."""
    w = blur_weights(n, kind)
    if n == 1:
        return list(chans)
    out = list(chans)
    dr.eval(*out)
    for axis in (0, 1):
        # every channel's pass in one kernel (a pass reads its neighbours from the last one, so
        # each pass is a stage); on LLVM (2 cores, 1024²) as fast as a kernel per channel for
        # 2 channels and 7 taps, 20-25 % faster for 4 channels (4 × 3 taps 16 vs 19 ms)
        out = [_pass(view, [ch], w, axis)[0] for ch in out]
        dr.eval(*out)
    return out


def max_filter(view, chan, n: int):
    """Separable n×n maximum of ``chan`` per face (the taps of :func:`blur`, clamped at face
    borders)."""
    if n == 1:
        return chan
    out = [chan]
    for axis in (0, 1):
        dr.eval(*out)
        out = _pass(view, out, [1.0] * n, axis, op="max")
    dr.eval(*out)
    return out[0]


# ----------------------------------------------------------------------------------------------
# lookups at the receiver

def _axis(u, N: int):
    """Lower texel i0 and bilinear fraction f of a continuous texel coordinate, clamped to the
    face like a clamp-addressed sampler: i0 ∈ [0, N − 2], f = 0 / 1 past the border centres."""
    x = u - 0.5
    i0 = dr.floor(x)
    f = x - i0
    f = dr.select(i0 < 0, 0.0, dr.select(i0 > N - 2, 1.0, f))
    return dr.clip(mi.Int32(i0), 0, N - 2), f


def footprint(view, rec, n: int = 1) -> dict:
    """Where the bilinear lookup of ``rec`` in maps blurred with ``n`` taps lands: face, i0/j0
    and fractions fx/fy (shifted by half a texel for even n, see the module docstring)."""
    N = view.res
    s = -centre_shift(n)
    ix, fx = _axis(rec["u"] + s if s else rec["u"], N)
    iy, fy = _axis(rec["v"] + s if s else rec["v"], N)
    return {"face": rec["face"], "ix": ix, "iy": iy, "fx": fx, "fy": fy, "n": n}


def _corner_index(view, fp, dx: int, dy: int):
    N = view.res
    return mi.UInt32(fp["face"]) * (N * N) + mi.UInt32((fp["iy"] + dy) * N + fp["ix"] + dx)


def bilinear(view, maps: list, fp: dict) -> list:
    """Bilinear lookup of each (filtered) map at the footprint ``fp``."""
    idx = [_corner_index(view, fp, dx, dy) for dy in (0, 1) for dx in (0, 1)]
    fx, fy = fp["fx"], fp["fy"]
    out = []
    for m in maps:
        a, b, c, d = (dr.gather(mi.Float, m, i) for i in idx)
        top = dr.fma(b - a, fx, a)
        bot = dr.fma(d - c, fx, c)
        out.append(dr.fma(bot - top, fy, top))
    return out


def corner_max(view, m, fp: dict):
    """Maximum of the four texels a bilinear lookup at ``fp`` reads (the z-max over the whole
    (n + 1)² footprint when ``m`` is max-filtered with the same n)."""
    vals = [dr.gather(mi.Float, m, _corner_index(view, fp, dx, dy)) for dy in (0, 1) for dx in (0, 1)]
    return dr.maximum(dr.maximum(vals[0], vals[1]), dr.maximum(vals[2], vals[3]))


def _weight_table(n: int, kind: str):
    """The 1D tap weights padded with a 0 on both sides, as opaque Dr.Jit data: entry j + 1 is
    w at offset index j, entries 0 and n + 1 are 0 (the loop reads w_m and w_{m−1})."""
    t = mi.Float([0.0] + blur_weights(n, kind) + [0.0])
    dr.make_opaque(t)
    return t


def pcf_footprint(view, rec, fp: dict, bias, n: int, kind: str):
    """PCF over exactly the footprint of blur + bilinear lookup (§3.2's Σ k(t_i − t)·H(z(t_i) − z̃)
    with the prefilter's weights): (n + 1)² biased nearest-texel depth tests of
    ``shadow_map.depth_test`` (the same biases, empty texels lit, taps clamped to the face),
    as a symbolic loop over the taps (one kernel for every n)."""
    table = _weight_table(n, kind)
    side = dr.opaque(mi.UInt32, n + 1)
    count = dr.opaque(mi.UInt32, (n + 1) * (n + 1))
    k0 = dr.opaque(mi.Int32, tap_offsets(n)[0])
    for name in ("depth", "slope"):                      # upload before the loop records
        view.dr(name)
    fx, fy = fp["fx"], fp["fy"]
    width = dr.width(rec["u"])

    def wt(j, f):                                        # (1 − f)·w_m + f·w_{m−1}, j = m − k0
        return dr.fma(f, dr.gather(mi.Float, table, j) - dr.gather(mi.Float, table, j + 1),
                      dr.gather(mi.Float, table, j + 1))

    def body(acc, i):
        jx, jy = i % side, i // side
        w = wt(jx, fx) * wt(jy, fy)
        t = depth_test(view, rec, fp["ix"] + k0 + mi.Int32(jx), fp["iy"] + k0 + mi.Int32(jy), bias)
        return dr.fma(w, t, acc), i + 1

    acc, _ = dr.while_loop(state=(dr.zeros(mi.Float, width), dr.zeros(mi.UInt32, width)),
                           cond=lambda acc, i: i < count, body=body, labels=("acc", "i"),
                           label="prefilter pcf footprint")
    return dr.clip(acc, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# the estimates VSM and EVSM share

def chebyshev(m1, m2, zr, min_var):
    """§3.3: p_max(z̃) = σ²/(σ² + (z̃ − μ)²) for z̃ > μ, else 1; σ² = max(M2 − M1², σ²_min).

    Evaluated as the logistic function of ℓ = ln σ² − 2·ln(z̃ − μ): p = 1/(1 + e^(−ℓ)), computed
    from e = exp(−|ℓ|) ∈ (0, 1] (p = 1/(1 + e) for ℓ ≥ 0, e/(1 + e) otherwise). The same number,
    but no intermediate overflows: EVSM's warped moments reach 10³⁸, where (z̃ − μ)², σ⁴ (in
    the derivative of a quotient) or 0·∞ would turn values or reverse-mode gradients into NaN."""
    var = dr.clip(m2 - m1 * m1, dr.minimum(min_var, _HUGE), _HUGE)
    var = dr.maximum(var, _TINY)
    d = dr.maximum(zr - m1, _TINY)
    ell = dr.log(var) - 2.0 * dr.log(d)
    e = dr.exp(-dr.abs(ell))
    p = dr.select(ell >= 0, dr.rcp(1.0 + e), e * dr.rcp(1.0 + e))
    return dr.select(zr > m1, p, 1.0)


def reduction(v, p):
    """§3.3 light-bleeding reduction: 0 if v < p, else (v − p)/(1 − p)."""
    return dr.select(v < p, 0.0, (v - p) / (1.0 - p))


# ----------------------------------------------------------------------------------------------
# the technique base class

class PrefilteredTechnique(ShadowMapTechnique):
    """A shadow-map technique whose maps are prefiltered: subclasses implement :meth:`shade`
    (moments → filtered maps → visibility at the receivers) and declare ``channels``."""

    channels: int = 1

    def channel_count(self, values) -> int:
        """Moment channels per texel (for the stats: memory of the prefiltered maps)."""
        return self.channels

    def moments(self, view, values) -> list:  # pragma: no cover - interface
        """The maps to prefilter: flat mi.Float per channel over every texel of ``view``."""
        raise NotImplementedError

    def estimate(self, view, rec, fp, bias, values, maps) -> tuple:  # pragma: no cover - interface
        """From the blurred ``maps`` (:meth:`moments`, filtered) return (visibility, {aov name:
        flat Float}, {stat name: number})."""
        raise NotImplementedError

    def filtered(self, view, values) -> list:
        """The blurred moment maps of ``view``: its own stages, a light at a time (blurring every
        light's maps in one kernel per pass reads them all at once and loses the caches: on LLVM,
        many_lights at 320x180, warm msm 184 vs 117 ms, evsm 195 vs 111 ms, vsm equal)."""
        return blur(view, self.moments(view, values), int(values["kernel"]), values["filter"])

    def bias_values(self, values: dict) -> dict:
        return bias_values(values)

    def filter_variance(self, values: dict) -> float:
        """Per-axis variance (texels²) of blur + bilinear lookup: Σ w_k (k − c)² over the blur's taps
        about their centre, plus the lookup's tent 1/6."""
        n = int(values.get("kernel", 1))
        w, c = blur_weights(n, values.get("filter", "box")), centre_shift(n)
        return sum(wk * (k - c) ** 2 for wk, k in zip(w, tap_offsets(n))) + 1.0 / 6.0

    def evaluate(self, frame, light, view, values, ctx):
        n = int(values.get("kernel", 1))
        rec = prepare_receiver(frame, view, ctx.bias)
        fp = footprint(view, rec, n)
        v, extra_aovs, extra_stats = self.estimate(view, rec, fp, ctx.bias, values, self.filtered(view, values))
        mbytes = view.nfaces * view.res * view.res * self.channel_count(values) * 4
        return LightResult(dr.clip(v, 0.0, 1.0), {"texel": rec["texel"], "receiver_bias": rec["zbias"], **extra_aovs},
                           active=rec["active"], stats={**map_stats(view), **extra_stats, "moment_bytes": mbytes},
                           maps=[{**map_entry(view), "moment_bytes": mbytes}])

    def summarise(self, frame, values, ctx, lights):
        n = int(values.get("kernel", 1))
        return {**super().summarise(frame, values, ctx, lights), "moment_channels": self.channel_count(values),
                "blur_taps_per_texel": 2 * n if n > 1 else 0}
