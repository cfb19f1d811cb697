"""Percentage-closer filtering (``pcf``) with the kernels of [Buljan 2020, §3.2].

Filter the results of the depth comparison, not the depths (§3.1 shows why the latter stays
binary)::

    f_pcf(t, z̃) = Σ_{t_i ∈ K} k(t_i − t) · H(z(t_i) − z̃)

§3.2 names the kernels K in use — "the regular n×n grid, the Gaussian kernel and the Poisson
disk" (Slika 3.1 (d): a Poisson disk of 64 samples) — with the constant kernel function
k = 1/|K| as the most common one; the same sample positions for every fragment give visible
patterns, avoided by "rotating the kernel per fragment, the angle stored in a texture, computed
by a cheap pseudo-random function or written into the shader as an array"; and OpenGL/Vulkan and
Direct3D 10+ do a 2×2 PCF in one bilinear lookup, which "can be used to build higher-order
filters more easily". The source's Code A.4 (3×3 ``SampleCmpLevelZero``) scales the tap
spacing by ``softness``. Here:

* every tap is a biased depth test with all the variants of §2.3 (``BIAS_PARAMS`` of
  :mod:`shadowlab.techniques.shadow_map`, same declaration and defaults as ``hard``);
  tap positions are t + softness · o_i in shadow-map texels, o_i from the pattern below;
* ``pattern`` chooses K and k (weights are normalised: Σ k = 1, see :func:`taps`):

  - ``grid`` (default): the n×n grid o = (a, b), a, b ∈ {−(n−1)/2, …, (n−1)/2}, box weights
    1/n²; with nearest-texel taps the result takes one of n² + 1 values (§3.2). ``kernel`` = 1
    is exactly ``hard``, bit for bit;
  - ``gaussian``: the same n×n grid, k(a, b) ∝ exp(−(a² + b²) / (2σ²)), σ = ``sigma`` tap
    spacings (σ·softness texels); ``sigma`` = 0 (default) means σ = n/4, so the grid reaches
    ±2σ·(n−1)/n, nearly the ±2σ where a Gaussian is commonly truncated;
  - ``poisson16``, ``poisson32``, ``poisson64``: 16/32/64 Poisson-disk points of the unit disk
    (:data:`POISSON`, made by dart throwing with a fixed seed at import, minimum distance
    :data:`POISSON_MIN_DIST`), scaled to the radius n/2 of the n×n footprint, i.e. o = (n/2)·p:
    the disk inscribed in the grid's n×n texels; constant weights 1/N;
  - ``rotated_poisson``: the ``rotated_samples``-point Poisson set, rotated about t by an angle
    per shading point, θ = 2π·hash(point index, ``seed``)/2³² (lowbias32 integer hash of the
    G-buffer point index xor a hash of the seed): the source's "cheap pseudo-random function".
    It turns the fixed pattern's banding into noise; the same seed gives the same bits,
    another seed changes only points whose taps disagree (the penumbra);

* ``bilinear``: each tap is a hardware-style 2×2 PCF (a comparison sampler with linear
  filtering): the four texels around the tap position are depth-tested and the results
  weighted by the bilinear fractions of the tap's position between their centres (exact float
  fractions; GPUs quantise them to 8 bits). ``kernel`` = 1 with ``grid`` is plain 2×2 hardware
  PCF: across a straight shadow edge it is a linear ramp one texel wide. An n×n grid of
  bilinear taps at ``softness`` = 1 covers (n+1)×(n+1) texels with the separable weights
  (1 − f, 1, …, 1, f)/n per axis (f the fractional position of the footprint's edge): the
  exact area average of the nearest-texel test results over the n×n-texel square centred at
  t, so across a straight edge it is a linear ramp n texels wide. As a function of a texel's
  offset the weight is the n-texel box convolved with the 1-texel cell, a trapezoid of support
  n+1 texels (a tent for n = 1). Larger
  ``softness`` spreads the taps apart (gaps between their 2-texel footprints when > 2);
  the other patterns place bilinear taps at their own offsets with their own weights.

Taps read texels clamped to the face (clamp-to-edge addressing; no cube-seam crossing).
Points outside the light camera or without a surface are lit (1). The result is clipped to
[0, 1] (rounding of the bilinear fractions could otherwise exceed 1 by an ulp).

PCF does not remove acne (§3.2): a tap ``a`` texels away compares the receiver's depth with a
caster ``a`` texels away, so on tilted receivers wide kernels need more slope-scaled bias (or
``normal_offset``) than ``hard``: about 2·((n − 1)/2 · softness + 1/2) for a planar caster
(+1 texel with ``bilinear``). With the shared defaults (slope-scaled bias 2) the mean
over-darkening against exact point-light visibility is 0.5 % (3×3) and 11 % (5×5) on ``contact``.

Measured on ``parallel_planes`` (rect light 1 m at height 4, half-plane occluder at 2: true
penumbra 1 m on the floor ≈ 25 texels of its 1024² map; committed 128² reference), penumbra
RMSE of the visibility at ``kernel`` 9, ``softness`` 3 (27 texels), nearest / bilinear taps:
``hard`` 0.287; ``grid`` 0.041 / 0.036; ``gaussian`` (σ = n/4) 0.073 / 0.066; ``poisson16``
0.040 / 0.033; ``poisson32`` 0.029 / 0.024; ``poisson64`` 0.013 / 0.013; ``rotated_poisson``
(16) 0.039 / 0.034 (``tests/test_pcf_kernels.py``). The linear truth ramp favours flat kernels;
the narrower Gaussian does best with a wider footprint (7×7, softness 4.25: 0.056).

Kernel compilation: the taps are a symbolic loop over a tap table (offsets, weights) that is
uploaded as data, so ``kernel``, ``softness``, ``sigma``, ``seed``, the Poisson set and the
biases all enter the kernel opaquely: a new value reuses the compiled kernel. Four kernels
exist per light view: {plain, rotated} × {nearest, bilinear} taps. The loop costs run time
against the former fully unrolled grid (``contact``, 512², warm: 3×3 8.0 ms vs 4.7 ms, 7×7
29.8 ms vs 17.9 ms; bilinear taps about 1.8× nearest ones; ``hard`` 2.4 ms). The
nearest-texel filter is piecewise constant in ``softness`` and the biases; the bilinear one is continuous (piecewise
linear) in ``softness``, the Gaussian weights smooth in ``sigma``; none of them carries an AD
path (all enter through ``dr.opaque``), so no parameter is declared ``differentiable``.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._random import uniform as _uniform
from .base import Param, param_table_markdown, register
from .shadow_map import BIAS_PARAMS, ShadowMapTechnique, depth_test, receiver_plane_gradient, texel_index

PATTERNS = ("grid", "gaussian", "poisson16", "poisson32", "poisson64", "rotated_poisson")
SRC = "[Buljan 2020, §3.2]"

# ----------------------------------------------------------------------------------------------
# Poisson-disk sample sets (deterministic: a counter-based splitmix64 stream, no numpy RNG)

#: the seed of the Poisson-disk sets (fixed: the sets are part of the technique's definition)
POISSON_SEED = 0x5EED_003


def poisson_disk(count: int, seed: int = POISSON_SEED, darts: int = 4096) -> tuple[np.ndarray, float]:
    """``count`` points of the closed unit disk, pairwise at least ``d`` apart: dart throwing.

    Candidates are uniform in the disk (r = √u₁, φ = 2πu₂) and taken in order; a candidate
    closer than d to an accepted point is rejected. d starts at 0.9 × the hexagonal-packing
    spacing of the disk, √(2π/(√3·count)), and shrinks by 2 % whenever ``darts`` candidates did
    not give ``count`` points. The accepted set is then centred (centroid moved to 0, so the
    filter does not shift the shadow edge) and scaled back into the unit disk if that moved a
    point out; d scales with it. Returns (points (count, 2) float64, d)."""
    d = 0.9 * math.sqrt(2.0 * math.pi / (math.sqrt(3.0) * count))
    start = 0
    while True:
        u = _uniform(seed, start, 2 * darts).reshape(darts, 2)
        start += 2 * darts
        r, phi = np.sqrt(u[:, 0]), 2.0 * math.pi * u[:, 1]
        cand = np.stack([r * np.cos(phi), r * np.sin(phi)], 1)
        pts = np.empty((0, 2))
        d2 = d * d
        for c0 in range(0, darts, 64):            # sequential dart throwing, 64 candidates at a time
            chunk = cand[c0:c0 + 64]
            if len(pts):
                chunk = chunk[np.min(((chunk[:, None] - pts[None]) ** 2).sum(-1), axis=1) >= d2]
            close = ((chunk[:, None] - chunk[None]) ** 2).sum(-1) < d2
            kept = []
            for j in range(len(chunk)):
                if not close[j, kept].any():
                    kept.append(j)
            pts = np.concatenate([pts, chunk[kept]])[:count]
            if len(pts) == count:
                pts = pts - pts.mean(0)
                shrink = 1.0 / max(1.0, float(np.max(np.linalg.norm(pts, axis=1))))
                return pts * shrink, d * shrink
        d *= 0.98


#: Poisson-disk sets of the unit disk by size, and the minimum distance each guarantees
POISSON: dict = {}
POISSON_MIN_DIST: dict = {}
for _n in (16, 32, 64):
    POISSON[_n], POISSON_MIN_DIST[_n] = poisson_disk(_n)
del _n


# ----------------------------------------------------------------------------------------------
# tap tables

def taps(pattern: str, n: int, sigma: float = 0.0, rotated_samples: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """The tap table of ``pattern`` for kernel ``n``: (offsets (K, 2) in units of ``softness``
    texels, weights (K,) summing to 1), before any per-point rotation (``rotated_poisson``
    rotates these offsets)."""
    if pattern in ("grid", "gaussian"):
        a = np.arange(n) - (n - 1) / 2.0
        bb, aa = np.meshgrid(a, a, indexing="ij")            # row b, column a: t + (a, b)
        off = np.stack([aa.ravel(), bb.ravel()], 1)
        if pattern == "grid":
            w = np.ones(n * n)
        else:
            s = float(sigma) if sigma > 0 else n / 4.0
            w = np.exp(-(off ** 2).sum(1) / (2.0 * s * s))
    else:
        N = rotated_samples if pattern == "rotated_poisson" else int(pattern[len("poisson"):])
        off = POISSON[N] * (n / 2.0)
        w = np.ones(N)
    return off, w / w.sum()


def _raw_taps(pattern: str, n: int, sigma: float, rotated_samples: int):
    """Offsets and unnormalised weights as float32 (grid and Poisson: weight 1, so the
    accumulated sum is an exact count; the kernel divides by the accumulated weight)."""
    off, w = taps(pattern, n, sigma, rotated_samples)
    w = w / w.max()
    return off.astype(np.float32), w.astype(np.float32)


def _table(values: np.ndarray):
    """A tap table column as evaluated Dr.Jit data (never a literal: no recompilation). Padded
    to 2 entries (the loop reads ``count`` of them): Dr.Jit compiles a gather from a 1-entry
    array differently, which would give ``kernel`` = 1 a kernel of its own."""
    values = np.ascontiguousarray(values, np.float32)
    if len(values) < 2:
        values = np.concatenate([values, np.zeros(2 - len(values), np.float32)])
    x = mi.Float(values)
    dr.make_opaque(x)
    return x


# ----------------------------------------------------------------------------------------------
# per-point rotation: an integer hash of the G-buffer point index and the seed

def _lowbias32_host(x: int) -> int:
    """Chris Wellons' lowbias32 integer hash (host version, for the seed)."""
    x &= 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x846CA68B) & 0xFFFFFFFF
    x ^= x >> 16
    return x


def _lowbias32(x):
    """lowbias32 on a Dr.Jit UInt32 (multiplication wraps mod 2³²)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def rotation_angle(npoints: int, seed: int):
    """θ ∈ [0, 2π) per G-buffer point: 2π·lowbias32(index ^ lowbias32(seed + φ))/2³², with
    24 significant bits. The hashed seed enters opaquely (a new seed reuses the kernel)."""
    key = dr.opaque(mi.UInt32, _lowbias32_host(int(seed) + 0x9E3779B9))
    h = _lowbias32(dr.arange(mi.UInt32, npoints) ^ key)
    return mi.Float(h >> 8) * (2.0 * math.pi / 2.0 ** 24)


# ----------------------------------------------------------------------------------------------
# one tap

def bilinear_test(view, rec: dict, u, v, bias):
    """Hardware 2×2 PCF at continuous texel position (u, v) (centres at i + 0.5): the four
    texels around it depth-tested, weighted by the bilinear fractions."""
    x, y = u - 0.5, v - 0.5
    x0, y0 = dr.floor(x), dr.floor(y)
    fx, fy = x - x0, y - y0
    ix, iy = mi.Int32(x0), mi.Int32(y0)
    t00 = depth_test(view, rec, ix, iy, bias)
    t10 = depth_test(view, rec, ix + 1, iy, bias)
    t01 = depth_test(view, rec, ix, iy + 1, bias)
    t11 = depth_test(view, rec, ix + 1, iy + 1, bias)
    return dr.lerp(dr.lerp(t00, t10, fx), dr.lerp(t01, t11, fx), fy)


def _tap(view, rec, u, v, bias, bilinear: bool, g=None):
    if g is not None:   # receiver plane depth bias: the receiver's tangent plane at the tap
        rec = {**rec, "dt": rec["dt"] + g[0] * (u - rec["u"]) + g[1] * (v - rec["v"])}
    if bilinear:
        return bilinear_test(view, rec, u, v, bias)
    return depth_test(view, rec, texel_index(u), texel_index(v), bias)


def _table_tap(view, rec, bias, table, i, s, rot, bilinear: bool, g=None):
    """(weight, test) of tap ``i`` of the table."""
    ox_t, oy_t, w_t = table
    ox = dr.gather(mi.Float, ox_t, i)
    oy = dr.gather(mi.Float, oy_t, i)
    w = dr.gather(mi.Float, w_t, i)
    if rot is not None:
        c, sn = rot
        ox, oy = c * ox - sn * oy, sn * ox + c * oy
    return w, _tap(view, rec, rec["u"] + ox * s, rec["v"] + oy * s, bias, bilinear, g)


def _accumulate(view, rec, bias, table, count, s, rot, bilinear: bool, g=None):
    """Σ w_i·tap_i / Σ w_i over the tap table, as a symbolic loop (one kernel for any size).
    The loop state is (acc, wsum, i) only; everything else is read-only and captured."""
    n = dr.width(rec["u"])

    def body(acc, wsum, i):
        w, t = _table_tap(view, rec, bias, table, i, s, rot, bilinear, g)
        return acc + w * t, wsum + w, i + 1

    acc, wsum, _ = dr.while_loop(state=(dr.zeros(mi.Float, n), dr.zeros(mi.Float, n), dr.zeros(mi.UInt32, n)),
                                 cond=lambda acc, wsum, i: i < count, body=body, labels=("acc", "wsum", "i"),
                                 label="pcf taps")
    return acc / wsum


#: receivers lit more grazingly than this |cos| keep pcf's plain test: their tangent plane, extrapolated
#: across the taps, passes the surfaces next to them (on the outdoor scenes' cascades that turned
#: leaks into over-darkening); above it the plane removes the acne of flat-shaded meshes
#: (``tests/test_pcf_acne.py``)
RECEIVER_PLANE_MIN_COS = 0.35

PCF_PARAMS = (
    Param("kernel", 3, "int", 1, 9, "taps per side", False, source=SRC,
          doc="n of the n×n footprint: grid/gaussian tap n×n, Poisson patterns fill the disk of radius n/2 "
              "(1 = plain shadow map; 3, 5, 7 in the source)"),
    Param("softness", 1.0, "float", 0.25, 8.0, "texels", False, source=SRC,
          doc="spacing of the taps in shadow-map texels (the source's `softness`, Code A.4); scales every pattern"),
    Param("pattern", "grid", "choice", choices=PATTERNS, source=SRC,
          doc="kernel K: n×n grid with box weights, n×n grid with Gaussian weights, 16/32/64-point Poisson "
              "disk (dart throwing, fixed seed), or the Poisson disk rotated per point"),
    Param("sigma", 0.0, "float", 0.0, 8.0, "tap spacings", False, source=SRC,
          doc="σ of the `gaussian` weights exp(−(a²+b²)/(2σ²)) in tap spacings (σ·softness texels); 0 = n/4"),
    Param("rotated_samples", 16, "choice", units="taps", choices=(16, 32, 64), source=SRC,
          doc="size of the Poisson set `rotated_poisson` rotates"),
    Param("seed", 0, "int", 0, 1_000_000, "", False, source=SRC,
          doc="seed of `rotated_poisson`'s per-point angle 2π·hash(point index, seed)/2³²"),
    Param("receiver_plane", True, "bool", source="[Isidoro 2006]",
          doc="receiver plane depth bias: each tap compares against the receiver's tangent plane at the tap, not "
              "its depth at the centre (not in the source; removes most PCF acne on flat-shaded curved meshes); "
              "receivers lit at grazing angles (|cos| < RECEIVER_PLANE_MIN_COS) keep the plain test"),
    Param("bilinear", False, "bool", source=SRC,
          doc="each tap a hardware 2×2 bilinear PCF (four texel tests weighted by the bilinear fractions); "
              "an n×n grid at softness 1 then averages the n×n-texel square exactly, touching (n+1)×(n+1) texels"),
)


@register
class PCF(ShadowMapTechnique):
    """Percentage-closer filtering: grid, Gaussian, Poisson-disk and rotated Poisson-disk kernels
    of nearest-texel or bilinear (hardware 2×2) biased depth tests."""

    name = "pcf"
    title = "PCF (grid, Gaussian, Poisson disk, rotated; bilinear taps)"
    summary = ("percentage-closer filtering of biased depth tests: n×n grid (box or Gaussian weights), "
               "16/32/64-point Poisson disk, per-point rotated Poisson disk; nearest-texel or hardware-style "
               "2×2 bilinear taps")
    params = PCF_PARAMS + BIAS_PARAMS

    def fit_params(self, values):
        """No parameter is differentiable (taps are steps): ``fit`` searches the kernel and its softness."""
        return ("kernel", "softness")

    def filter(self, view, rec, bias, values):
        pattern = values["pattern"]
        bilinear = bool(values["bilinear"])
        off, w = _raw_taps(pattern, int(values["kernel"]), float(values["sigma"]), int(values["rotated_samples"]))
        table = (_table(off[:, 0]), _table(off[:, 1]), _table(w))
        count = dr.opaque(mi.UInt32, len(w))
        s = dr.opaque(mi.Float, float(values["softness"]))
        rot = None
        if pattern == "rotated_poisson":
            theta = rotation_angle(dr.width(rec["u"]), int(values["seed"]))
            rot = dr.sincos(theta)[::-1]                           # (cos θ, sin θ)
        g = receiver_plane_gradient(view, rec, rec["ng"], RECEIVER_PLANE_MIN_COS) if values["receiver_plane"] else None
        vis = _accumulate(view, rec, bias, table, count, s, rot, bilinear, g)
        return dr.clip(vis, 0.0, 1.0)

    def filter_variance(self, values: dict) -> float:
        """Σ wᵢ (softness·oᵢ,x)² over the taps plus one tap's own variance (a nearest test's box
        1/12, a bilinear tap's tent 1/6), texels² per axis (the grid's and Poisson sets' x and y agree)."""
        off, w = taps(values["pattern"], int(values["kernel"]), float(values["sigma"]), int(values["rotated_samples"]))
        s = float(values["softness"])
        spread = float(np.sum(w * (0.5 * (off[:, 0] ** 2 + off[:, 1] ** 2)) * s * s))
        return spread + (1.0 / 6.0 if values["bilinear"] else 1.0 / 12.0)

    def summarise(self, frame, values, ctx, lights):
        k = len(taps(values["pattern"], int(values["kernel"]), 0.0, int(values["rotated_samples"]))[1])
        return {**super().summarise(frame, values, ctx, lights), "taps_per_point": k,
                "depth_tests_per_point": 4 * k if values["bilinear"] else k}


__doc__ += "\n\nParameters of ``pcf`` (generated from the declaration):\n\n" + param_table_markdown(PCF)
