"""The blocker search and penumbra estimate of percentage-closer soft shadows [Buljan 2020, §3.6,
Code A.9], shared by the families that search a shadow map for blockers: ``pcss`` (search, estimate,
variable-width PCF), ``ssss`` (the search feeds a screen-space blur, [Tamás 2015]) and ``dpsv``'s
``sm_dpsv_soft`` (the search's test on a grid, [Wang 2022, §1.4]).

What is here, with the units of :mod:`shadowlab.techniques.pcss`'s docstring (widths are full
widths, in texels or near-plane units):

- the tap patterns: the blocker-search point sets :data:`SEARCH_SETS` (Mitchell's best candidate,
  :func:`best_candidate`, a fixed seed: part of the technique's definition), the PCF pattern
  :func:`pcf_pattern` (the centred Hammersley set) and :func:`pattern_arrays`, a pattern as Dr.Jit
  arrays read by index inside symbolic loops;
- the light size at ``light_scale`` 1, :func:`scene_light_size` (the side of the light's
  equal-area square);
- the taps: :func:`blocked` (``hard``'s biased depth test of one texel: a blocker iff the test
  says "shadowed"), :func:`tap` (one bilinear tap), :func:`search_loop` (step 1, Σ of the weighted
  blocker count and depth over the search taps) and :func:`pcf_loop` (step 3's taps);
- :func:`search_width` (step 1's w_search) and :func:`penumbra_width` (step 2's w_penumbra).

>>> sorted(SEARCH_SETS) == list(BLOCKER_COUNTS)
True
>>> pcf_pattern(4).tolist()
[[-0.375, -0.375], [-0.125, 0.125], [0.125, -0.125], [0.375, 0.375]]
"""

from __future__ import annotations

import functools
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ._random import uniform as _uniform
from .shadow_map import stored_depth

BLOCKER_COUNTS = (16, 25, 32)
PCF_COUNTS = (1, 16, 32, 64)

# ----------------------------------------------------------------------------------------------
# sampling patterns

#: seed of the blocker-search point sets (fixed: the sets are part of the technique's definition)
SEARCH_SEED = 0x5EED_036


def best_candidate(count: int, seed: int = SEARCH_SEED, candidates: int = 64) -> np.ndarray:
    """``count`` well-spread points of the unit square as offsets in [−½, ½]²: Mitchell's best
    candidate (each new point is, of ``candidates`` uniform candidates, the one farthest from the
    points so far), then centred (mean 0, so the search is not shifted) and scaled back into
    [−½, ½]² if centring moved a point out. Deterministic (splitmix64 counter stream)."""
    u = _uniform(seed, 0, 2 * candidates * count).reshape(count, candidates, 2)
    pts = [u[0, 0]]
    for k in range(1, count):
        c = u[k]
        d = np.min(((c[:, None, :] - np.asarray(pts)[None]) ** 2).sum(-1), axis=1)
        pts.append(c[int(np.argmax(d))])
    p = np.asarray(pts) - 0.5
    p = p - p.mean(0)
    return p * min(1.0, 0.5 / float(np.max(np.abs(p))))


#: blocker-search offsets (units of w_search) by count
SEARCH_SETS = {n: best_candidate(n) for n in BLOCKER_COUNTS}


def radical_inverse2(k: int) -> float:
    """Base-2 radical inverse φ₂(k): the bits of k mirrored about the binary point."""
    r, f = 0.0, 0.5
    while k:
        r += f * (k & 1)
        k >>= 1
        f *= 0.5
    return r


def pcf_pattern(n: int) -> np.ndarray:
    """PCF offsets (units of w_f) in [−½, ½)²: the centred Hammersley set
    ((k + ½)/n, φ₂(k) + ½/n) − ½, k = 0 … n − 1."""
    return np.array([((k + 0.5) / n - 0.5, (radical_inverse2(k) + 0.5 / n) % 1.0 - 0.5) for k in range(n)])


def pattern_arrays(offsets: np.ndarray):
    """A tap pattern as two evaluated Dr.Jit Floats (x and y), read by index inside the loops."""
    x, y = (mi.Float(np.ascontiguousarray(offsets[:, i], np.float32)) for i in range(2))
    dr.make_opaque(x, y)
    return x, y


@functools.lru_cache(maxsize=None)
def search_arrays(count: int):
    """:data:`SEARCH_SETS` ``[count]`` as :func:`pattern_arrays`, uploaded once per process (the
    sets are fixed: a frame moves no pattern to the device)."""
    return pattern_arrays(SEARCH_SETS[count])


@functools.lru_cache(maxsize=None)
def pcf_arrays(count: int):
    """:func:`pcf_pattern` ``(count)`` as :func:`pattern_arrays`, uploaded once per process."""
    return pattern_arrays(pcf_pattern(count))


# ----------------------------------------------------------------------------------------------
# light size

SIZE_FACTOR = {"rect": 1.0, "disk": math.sqrt(math.pi) / 2, "spot": math.sqrt(math.pi) / 2,
               "sphere": math.sqrt(math.pi) / 2, "point": math.sqrt(math.pi) / 2,
               "directional": math.sqrt(math.pi) / 2}


def scene_light_size(light) -> float:
    """w_light of a light at ``light_scale`` 1: ``physical_size`` × the factor of its kind
    (the module docstring's table: the side of the equal-area square)."""
    return SIZE_FACTOR[light.kind] * light.physical_size


# ----------------------------------------------------------------------------------------------
# taps

def bilinear_corners(u, v):
    """The four texels around a continuous texel coordinate and their bilinear weights."""
    x, y = u - 0.5, v - 0.5
    x0, y0 = dr.floor(x), dr.floor(y)
    fx, fy = x - x0, y - y0
    ix, iy = mi.Int32(dr.detach(x0)), mi.Int32(dr.detach(y0))
    return ((ix, iy, (1.0 - fx) * (1.0 - fy)), (ix + 1, iy, fx * (1.0 - fy)),
            (ix, iy + 1, (1.0 - fx) * fy), (ix + 1, iy + 1, fx * fy))


def blocked(view, face, ix, iy, dt, bias):
    """``hard``'s biased test of texel (ix, iy) against the reference NDC depth ``dt``:
    True where the texel is a blocker (shadowed)."""
    Db, empty, _ = stored_depth(view, face, ix, iy, bias)
    return ~empty & (Db < dt)


def tap(view, rec, g, u, v, du, dv, bias):
    """One bilinear tap at (u + du, v + dv): (weighted shadowed fraction, weighted blocker z)."""
    dt = rec["dt"] if g is None else rec["dt"] + g[0] * du + g[1] * dv
    n = z = None
    for ix, iy, w in bilinear_corners(u + du, v + dv):
        b = dr.select(blocked(view, rec["face"], ix, iy, dt, bias), w, 0.0)
        bz = b * view.fetch("z", rec["face"], ix, iy)
        n = b if n is None else n + b
        z = bz if z is None else z + bz
    return n, z


def search_loop(view, rec, g, bias, w, px, py, n: int):
    """Σ over the ``n`` search taps of (weighted blocker count, weighted blocker depth), only at
    the active receivers (``rec["active"]``; 0 elsewhere, where no caller reads them): a symbolic
    loop (an unrolled one takes long to compile)."""
    u, v, run = rec["u"], rec["v"], rec["active"]

    def body(k, cnt, zsum):
        c, z = tap(view, rec, g, u, v, dr.gather(mi.Float, px, k) * w, dr.gather(mi.Float, py, k) * w, bias)
        return k + 1, cnt + c, zsum + z

    m = dr.width(u)
    _, cnt, zsum = dr.while_loop((dr.zeros(mi.UInt32, m), dr.zeros(mi.Float, m), dr.zeros(mi.Float, m)),
                                 lambda k, c, z: run & (k < n), body, labels=("k", "count", "zsum"),
                                 label="pcss_blocker_search", max_iterations=n)
    return cnt, zsum


def pcf_loop(view, rec, g, bias, w, px, py, n: int, run):
    """Σ over the ``n`` PCF taps of the shadowed fraction of each bilinear tap, only where
    ``run`` (a blocker was found): a symbolic loop."""
    u, v = rec["u"], rec["v"]

    def body(k, dark):
        c, _ = tap(view, rec, g, u, v, dr.gather(mi.Float, px, k) * w, dr.gather(mi.Float, py, k) * w, bias)
        return k + 1, dark + c

    m = dr.width(u)
    _, dark = dr.while_loop((dr.zeros(mi.UInt32, m), dr.zeros(mi.Float, m)), lambda k, d: run & (k < n), body,
                            labels=("k", "dark"), label="pcss_pcf", max_iterations=n)
    return dark


def search_width(view, zr, w_light):
    """Step 1's w_search in texels at receiver depth ``zr`` (the module docstring's units):
    (z̃ − z_near)/z̃ · w_light on the near plane, or (z̃ − z_near)·tan w_light for an orthographic map."""
    f0 = view.proj.faces[0]
    N, near = view.res, f0.near
    if f0.ortho:
        return dr.maximum(zr - near, 0.0) * dr.tan(w_light) * (1.0 / (2.0 * f0.scale / N))
    zs = dr.maximum(zr, near)
    return (zs - near) / zs * w_light * (N / (2.0 * near * f0.scale))


def penumbra_width(view, zr, z_avg, w_light):
    """Step 2's w_penumbra, world units at the receiver: (z̃ − z_avg)/z_avg · w_light, or
    (z̃ − z_avg)·tan w_light for an orthographic map."""
    if view.proj.faces[0].ortho:
        return dr.maximum(zr - z_avg, 0.0) * dr.tan(w_light)
    return dr.maximum(zr - z_avg, 0.0) / dr.maximum(z_avg, 1e-6) * w_light
