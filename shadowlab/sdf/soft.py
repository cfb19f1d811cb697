"""Single-ray soft shadows of signed distance fields [Bán 2019, ch. 3–4].

The light is a sphere (centre ``c``, radius ``R``), the shading point carries the *surface
sphere* of [Bán 2019, §2.9] (centre ``p``, radius ``R0``), and the shadow is the fraction of the light
seen inside the cone tangent to both spheres ([Bán 2019, §3.2, Fig. 4.1]). Everything here is a
Dr.Jit symbolic loop over all points at once (LLVM); parameters that change between runs
(ε, i_max, radii) are opaque, so a new value reuses the compiled kernel.

**τ and τ⁻¹** ([Bán 2019, §4.1], §4.3.1). A straight occluder edge at relative distance ``r`` from the
centre of the unit disk leaves ``τ(r) = ½ + (r·√(1 − r²) + arcsin r)/π`` of it lit (clamped to
0 / 1 outside [−1, 1], the τ̂ of the thesis). ``τ⁻¹`` is bisection on [−1, 1]
(:data:`TAU_INV_ITERATIONS` = 22 halvings: |error in r| ≤ 2⁻²² < 1e-6; Newton fails at ±1 where
τ' = 0, as the thesis notes). :func:`tau` / :func:`tau_inv` take Dr.Jit arrays (any float type)
or numpy arrays (float64).

**The cone** (:func:`make_cone`). Its cross-section radius at distance ``t`` along the axis
from ``p`` is ``ρ(t) = R0^L + t·tanα^L`` with ``R0^L = R0`` (the surface sphere, as in the
thesis) and, at the light's centre (``t = d = |c − p|``), ``R1^L = R/cos α``, ``sin α = R/d``:
the radius of the light's silhouette there, i.e. of the cone from ``p`` tangent to the light
sphere (the thesis takes ``R1^L = R``, the small-angle form). ``tanα^L = (R1^L − R0^L)/d``.
Starting from ``R0^L = R0`` keeps a flat receiver at ``ϱ = 1`` where the march starts (a cone
tangent to both spheres would begin at ``R0/cos α`` and see the receiver as an occluder at
``ϱ = cos α``, a full level ε of ``discrete``).
Direction A marches from ``p`` to ``c``; direction B from ``c`` to ``p`` with ``R0^L`` and
``R1^L`` swapped ([Bán 2019, §4.3.2]). When the SDF is bounded the march is clipped to the segment
inside its bounding box grown by the largest cone radius (outside it ``f ≥ ρ``: nothing to find).

**The marching algorithms** (:func:`march`), with the relative distance
``ϱ(f; t) = f/ρ(t)`` (Def. 4.1.1) and the threshold / trace cones ``T`` and ``C`` of relative
radii ``R^T > R^C``:

* ``base`` — Algorithm 3: ``R^C = τ⁻¹(τ(R^T) − ε)``, stop when ``m = τ(R^T) ≤ ε``. On a
  detection ``R^T ← F/ρ(t)``, the relative size of Def. 4.1.1 (the L cone's radius); the printed
  ``F/(R_0^T + t·tanα^T)`` divides by T's own radius ``R^T·ρ(t)``, which gives ``ϱ/R^T_old``, not
  a relative distance (it can even exceed ``R^T_old``), and is read as a misprint;
* ``linear`` — Algorithm 4: ``R^C = R^T − e`` with ``e = επ/2`` (τ' ≤ 2/π), one τ at the end. The
  printed loop condition ``R^T > e`` would stop every march at half shadow (τ(e) ≈ ½); it is read
  as Algorithm 3's ``τ(R^T) > ε``, i.e. ``R^T > τ⁻¹(ε)`` with that constant computed once;
* ``discrete`` — Algorithm 5: on each detection ``R^T ← R^C``, ``m ← m − ε``,
  ``R^C ← τ⁻¹(m − ε)``: ``m`` walks down in steps of ε. The printed step can be negative right
  after a detection (``f < R^C·ρ``); it is clamped at 0, so the next iterations lower ``m`` at the
  same ``t`` until the trace cone clears the surface again (no backward steps);
* ``convex`` — Algorithm 4 with the convex-optimised step of §4.4.3 while ``R^C ≥ 0``: along the
  axis ``h_j(t) = f_j(s(t)) − ρ_C(t)`` is convex for every convex primitive ``j`` (the signed
  distance to a convex solid is convex, ρ_C is linear in t), so the secant through the previous
  and the current sample bounds it from below beyond ``t``: the C cone cannot touch primitive
  ``j`` before ``t + h_j/(−slope)`` (never, if the slope is ≥ 0). The step is the minimum over
  the primitives of max(that bound, the plain cone step); non-convex primitives take the plain
  step. (The thesis uses its engine's convex-optimised cone trace without specifying it; this is
  that idea in its gradient-free form. A primitive here is a leaf of :attr:`SDF.primitives`.)

Every step is the cone-trace step of the C cone, ``(f − ρ_C(t))/(1 + |tanα^C|)`` ([Bán 2019, §2.8]), the
loop runs while ``t < t_end`` and ``i < i_max``. The result of ``base``, ``linear`` and
``convex`` is ``τ̂(f_min/ρ(t_min))`` at the last detection (``t_min``, ``f_min``), recomputed
outside the loop from the detached ``t_min`` and ``f_min``: the same bits as the loop's own
value, and, when the light radius is a Dr.Jit variable with gradients, ``d/dR`` of the minimum
by the envelope theorem (the argmin does not move to first order) — the light radius is
differentiable without reverse-mode AD through the loop. ``discrete`` returns its level ``m``.

**Hard shadows** ([Bán 2019, §3.1]): :func:`shadowlab.sdf.trace.hard_visibility` — sphere tracing toward
the light's centre.
**Anti-aliased hard shadows** ([Bán 2019, §4.3.3]): the same single-ray algorithms with ``R = 0``; the
surface sphere keeps the cone open, so the shadow edge is a ramp about one pixel wide.

**Baseline** (:func:`quilez`): Quílez (2010) and Aaltonen's (2018) improved penumbra estimate:
sphere tracing toward the light centre, ``res = min(res, k·h/t)`` (Aaltonen: ``k·d/max(0, t − y)``
with ``y = h²/(2·h_prev)``, ``d = √(h² − y²)``), 0 on a hit. ``k`` is the light size: the cone
from the point to the light has ``tanα = R/√(d² − R²)``, so ``k = 1/tanα`` makes ``k·h/t`` the
relative distance ϱ of the thesis (``k = 0`` in the technique = this mapping, per point). The
result ``clamp(res, 0, 1)`` is 0 for ϱ ≤ 0: the inner half of the true penumbra (ϱ ∈ [−1, 0])
is umbra, the penumbra comes out about half as wide as the truth ([Bán 2019, §6.4, Fig. 6.16]a).

**Monte-Carlo reference in the cone** ([Bán 2019, §3.3], §3.3.1): :func:`mc_cone_visibility` — Halton
points (bases 2, 3) on the disk of the cone at the light, in polar coordinates either
``r = u`` weighted by ``r`` (``scheme="r_weighted"``) or ``r = √u`` (``scheme="sqrt"``), each one
sphere-traced shadow ray. Per point the Halton set is shifted by a Cranley–Patterson rotation
(a hash of the point index and the seed), so neighbouring pixels do not share one pattern.
``measure="disk"`` is the thesis' estimator (the fraction of the disk's area); the default
``"solid_angle"`` weighs each sample by ``cos³θ`` (θ to the axis: ``dω = cos³θ·dA/d²``), which
makes it the fraction of the light's solid angle, i.e. exactly the visible fraction Mitsuba's
sphere emitter samples (the truth's ``A``); ``cosine=True`` also weighs by ``max(0, n·ω)``,
the diffuse truth's ``V`` (= ∫ v cos / ∫ cos over the light).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

TAU_INV_ITERATIONS = 22           # bisection halvings of [−1, 1]: 2/2^23 < 1e-6 in r
VARIANTS = ("base", "linear", "discrete", "convex")
DIRECTIONS = ("A", "B")
SCHEMES = ("sqrt", "r_weighted")
MEASURES = ("solid_angle", "disk")
QUILEZ_VARIANTS = ("quilez2010", "aaltonen2018")
SIN_MAX = 0.999                   # |sin α| of a cone is clamped here (a light touching the point)
DETECT_TOL = 1e-4                 # a detection needs ϱ < R^T − this: float rounding of f at the start
                                  # (a flat receiver sits at ϱ = 1) must not cost ``discrete`` a level


# ----------------------------------------------------------------------------------------------
# τ and its inverse ([Bán 2019, §4.1], §4.3.1)

def tau(r):
    """Lit fraction of the unit disk behind a straight edge at signed relative distance ``r``
    ([Bán 2019, §4.1]): ``½ + (r√(1 − r²) + arcsin r)/π``, clamped to [0, 1] outside [−1, 1] (τ̂).

    >>> round(float(tau(np.array(0.0))), 6), float(tau(np.array(-1.0))), float(tau(np.array(2.0)))
    (0.5, 0.0, 1.0)
    """
    if isinstance(r, dr.ArrayBase):
        r = dr.clip(r, -1.0, 1.0)
        return 0.5 + (r * dr.sqrt(dr.maximum(1.0 - r * r, 0.0)) + dr.asin(r)) * (1.0 / math.pi)
    r = np.clip(np.asarray(r, dtype=np.float64), -1.0, 1.0)
    return 0.5 + (r * np.sqrt(np.maximum(1.0 - r * r, 0.0)) + np.arcsin(r)) / math.pi


def tau_inv(m, iterations: int = TAU_INV_ITERATIONS):
    """τ⁻¹ by bisection on [−1, 1] ([Bán 2019, §4.3.1]): ``iterations`` halvings (a fixed, unrolled
    loop); m ≤ 0 gives −1, m ≥ 1 gives 1.

    >>> abs(float(tau_inv(np.array(0.5)))) < 1e-6, round(float(tau_inv(tau(np.array(-0.3)))), 6)
    (True, -0.3)
    """
    jit = isinstance(m, dr.ArrayBase)
    if not jit:
        m = np.asarray(m, dtype=np.float64)
    lo = m * 0.0 - 1.0
    hi = m * 0.0 + 1.0
    sel = dr.select if jit else np.where
    for _ in range(int(iterations)):
        mid = 0.5 * (lo + hi)
        below = tau(mid) < m
        lo = sel(below, mid, lo)
        hi = sel(below, hi, mid)
    return sel(m <= 0.0, -1.0, sel(m >= 1.0, 1.0, 0.5 * (lo + hi)))


# ----------------------------------------------------------------------------------------------
# the cone between the surface sphere and the light sphere

@dataclass
class Cone:
    """Per point: the march's origin ``o`` and unit direction ``v``, the segment [t0, t1] to
    march, the cross-section radius ``rho0`` at t = 0 and its slope ``tan`` (ρ(t) = rho0 +
    t·tan), the end-point distance ``d`` and whether the march runs light → point (B)."""

    o: object
    v: object
    t0: object
    t1: object
    rho0: object
    tan: object
    d: object
    reverse: bool = False

    def rho(self, t):
        return self.rho0 + t * self.tan

    def detach(self) -> "Cone":
        return Cone(*(dr.detach(x) for x in (self.o, self.v, self.t0, self.t1, self.rho0, self.tan, self.d)),
                    reverse=self.reverse)


def _box_clip(o, v, lo, hi, grow):
    """[t_enter, t_exit] of the ray o + t·v in the box [lo − grow, hi + grow] (slab test)."""
    inv = 1.0 / mi.Vector3f(dr.select(dr.abs(v.x) > 1e-12, v.x, 1e-12), dr.select(dr.abs(v.y) > 1e-12, v.y, 1e-12),
                            dr.select(dr.abs(v.z) > 1e-12, v.z, 1e-12))
    a = (mi.Vector3f(*map(float, lo)) - grow - o) * inv
    b = (mi.Vector3f(*map(float, hi)) + grow - o) * inv
    t_in = dr.maximum(dr.maximum(dr.minimum(a.x, b.x), dr.minimum(a.y, b.y)), dr.minimum(a.z, b.z))
    t_out = dr.minimum(dr.minimum(dr.maximum(a.x, b.x), dr.maximum(a.y, b.y)), dr.maximum(a.z, b.z))
    return t_in, t_out


def bounds(sdf):
    """``(bbox_min, bbox_max)`` of a bounded SDF, the ``bbox`` of :func:`make_cone`; None if it is
    unbounded (a plane)."""
    return (sdf.bbox_min, sdf.bbox_max) if sdf.bounded else None


def make_cone(p, R0, center, R, direction: str = "A", bbox=None) -> Cone:
    """The cone from the surface sphere (``p``, ``R0``; per point) to the light sphere
    (``center``, ``R``), module docstring. ``R`` may be a Dr.Jit Float with gradients (width 1
    or per point); ``bbox = (lo, hi)`` clips the march to the SDF's bounds."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be A or B, not {direction!r}")
    p = mi.Vector3f(p)
    c = mi.Vector3f(center) if isinstance(center, dr.ArrayBase) else mi.Vector3f(*map(float, center))
    D = c - p
    d = dr.maximum(dr.norm(D), 1e-12)
    v = D / d
    s = dr.minimum(R / d, SIN_MAX)
    rho_p = R0 + 0.0 * d
    rho_c = R / dr.sqrt(1.0 - s * s)
    tan = (rho_c - rho_p) / d
    t0, t1 = dr.zeros(mi.Float, dr.width(d)), mi.Float(d)
    if direction == "A":
        o, rho0, slope = p, rho_p, tan
    else:
        o, v, rho0, slope = c + 0.0 * p, -v, rho_c, -tan
    if bbox is not None and np.all(np.isfinite(bbox[0])) and np.all(np.isfinite(bbox[1])):
        grow = dr.detach(dr.maximum(rho_p, rho_c)) * 1.0001 + 1e-6
        t_in, t_out = _box_clip(o, v, bbox[0], bbox[1], grow)
        t0 = dr.clip(t_in, 0.0, d)
        t1 = dr.clip(t_out, t0, d)
    return Cone(o=o, v=v, t0=t0, t1=t1, rho0=rho0 + 0.0 * d, tan=slope + 0.0 * d, d=d, reverse=direction == "B")


# ----------------------------------------------------------------------------------------------
# the marching algorithms ([Bán 2019, §4.3–4.4])

@dataclass
class March:
    """Result of :func:`march` per point: ``visibility`` (mi.Float), ``t_min`` / ``f_min`` (axis
    distance and SDF value at the last detection), ``found`` (a detection happened),
    ``r_min`` (= f_min/ρ(t_min), 1 where nothing was found), ``iterations`` (SDF evaluations of
    the march), ``complete`` (the march reached the end of the segment rather than stopping at
    τ ≤ ε or ``i_max``), ``cone`` (the cone marched)."""

    visibility: object
    t_min: object
    f_min: object
    found: object
    r_min: object
    iterations: object
    complete: object
    cone: Cone


def _opaque(v, kind="float"):
    if isinstance(v, dr.ArrayBase):
        return v
    return dr.opaque(mi.Float if kind == "float" else mi.UInt32, float(v) if kind == "float" else int(v))


def _state(cone):
    n = dr.width(cone.d)
    return (mi.Float(cone.t0), dr.full(mi.Float, 1.0, n), mi.Float(cone.t0), dr.full(mi.Float, dr.inf, n),
            dr.full(mi.Bool, False, n), dr.zeros(mi.UInt32, n))


def _step(F, RC, cone, t):
    """Cone-trace step of the C cone ([Bán 2019, §2.8]): (f − R^C·ρ(t)) / (1 + |R^C·tanα|)."""
    return (F - RC * cone.rho(t)) / (1.0 + dr.abs(RC * cone.tan))


def _point(cone, t):
    return mi.Point3f(cone.o + cone.v * t)


@dr.syntax
def _march_linear(sdf, cone, e, r_stop, i_max):
    t, RT, t_min, f_min, found, i = _state(cone)
    RC = RT - e
    while (t < cone.t1) & (RT > r_stop) & (i < i_max):
        F = sdf.distance(_point(cone, t))
        rho = cone.rho(t)
        hit = F < (RT - DETECT_TOL) * rho
        RT = dr.select(hit, F / dr.maximum(rho, 1e-30), RT)
        t_min = dr.select(hit, t, t_min)
        f_min = dr.select(hit, F, f_min)
        found |= hit
        RC = RT - e
        t = t + _step(F, RC, cone, t)
        i += 1
    return t_min, f_min, found, i, RT, t


@dr.syntax
def _march_base(sdf, cone, eps, rc1, i_max):
    t, RT, t_min, f_min, found, i = _state(cone)
    m = dr.full(type(t), 1.0, dr.width(t))
    RC = rc1 + 0.0 * t
    while (t < cone.t1) & (m > eps) & (i < i_max):
        F = sdf.distance(_point(cone, t))
        rho = cone.rho(t)
        hit = F < (RT - DETECT_TOL) * rho
        RT = dr.select(hit, F / dr.maximum(rho, 1e-30), RT)
        m = dr.select(hit, tau(RT), m)
        RC = dr.select(hit, tau_inv(m - eps), RC)
        t_min = dr.select(hit, t, t_min)
        f_min = dr.select(hit, F, f_min)
        found |= hit
        t = t + _step(F, RC, cone, t)
        i += 1
    return t_min, f_min, found, i, m, t


@dr.syntax
def _march_discrete(sdf, cone, eps, rc1, i_max):
    t, RT, t_min, f_min, found, i = _state(cone)
    m = dr.full(type(t), 1.0, dr.width(t))
    RC = rc1 + 0.0 * t
    while (t < cone.t1) & (m > eps) & (i < i_max):
        F = sdf.distance(_point(cone, t))
        rho = cone.rho(t)
        hit = F < (RT - DETECT_TOL) * rho
        RT = dr.select(hit, RC, RT)
        m = dr.select(hit, m - eps, m)
        RC = dr.select(hit, tau_inv(m - eps), RC)
        t_min = dr.select(hit, t, t_min)
        f_min = dr.select(hit, F, f_min)
        found |= hit
        t = t + dr.maximum(_step(F, RC, cone, t), 0.0)
        i += 1
    return t_min, f_min, found, i, dr.maximum(m, 0.0), t


@dr.syntax
def _march_convex(sdf, prims, convex, cone, e, r_stop, i_max):
    t, RT, t_min, f_min, found, i = _state(cone)
    RC = RT - e
    n = dr.width(t)
    f_prev = [dr.full(mi.Float, dr.nan, n) for _ in prims]
    t_prev = mi.Float(t)
    while (t < cone.t1) & (RT > r_stop) & (i < i_max):
        x = _point(cone, t)
        fs = [pr.distance(x) for pr in prims]
        F = fs[0]
        for fj in fs[1:]:
            F = dr.minimum(F, fj)
        rho = cone.rho(t)
        hit = F < (RT - DETECT_TOL) * rho
        RT = dr.select(hit, F / dr.maximum(rho, 1e-30), RT)
        t_min = dr.select(hit, t, t_min)
        f_min = dr.select(hit, F, f_min)
        found |= hit
        RC = RT - e
        rc = RC * rho
        k1 = 1.0 + dr.abs(RC * cone.tan)
        rc_prev = RC * cone.rho(t_prev)
        dt = dr.maximum(t - t_prev, 1e-20)
        step = _convex_step(fs, f_prev, convex, RC, rc, rc_prev, k1, dt, t, t_prev)
        f_prev = fs
        t_prev = mi.Float(t)
        t = t + dr.minimum(step, cone.t1 - t + 1e-6)
        i += 1
    return t_min, f_min, found, i, RT, t


def _convex_step(fs, f_prev, convex, RC, rc, rc_prev, k1, dt, t, t_prev):
    """The convex-optimised step (module docstring): min over primitives of max(secant bound,
    plain cone step); the plain step alone for non-convex primitives, on the first sample, after
    a detection moved nothing forward, and while R^C < 0."""
    step = None
    for j, fj in enumerate(fs):
        h = fj - rc
        sj = h / k1
        if convex[j]:
            slope = (h - (f_prev[j] - rc_prev)) / dt
            sec = dr.select(slope < 0.0, h / dr.maximum(-slope, 1e-30), dr.inf)
            sec = dr.select(dr.isnan(slope) | (RC < 0.0) | (t <= t_prev), sj, sec)
            sj = dr.maximum(sj, sec)
        step = sj if step is None else dr.minimum(step, sj)
    return step


def _tables(eps: float):
    """Host constants of ε: τ⁻¹(1 − ε) (the first R^C of Algorithms 3 and 5) and τ⁻¹(ε) (the
    stop threshold of Algorithm 4)."""
    return float(tau_inv(np.array(1.0 - eps))), float(tau_inv(np.array(eps)))


def march(sdf, cone: Cone, variant: str = "linear", *, eps: float = 1.0 / 30, i_max: int = 256) -> March:
    """Run one of the single-ray algorithms (module docstring) on ``cone``; returns a
    :class:`March`. ``cone`` may carry gradients (light radius): the loop runs on its detached
    copy and the result is recomputed from it (envelope theorem)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, not {variant!r}")
    if not (0.0 < eps < 1.0):
        raise ValueError(f"eps must be in (0, 1), got {eps}")
    cd = cone.detach()
    rc1, r_stop = _tables(eps)
    E = _opaque(eps)
    imax = _opaque(i_max, "uint")
    with dr.suspend_grad():
        if variant == "linear":
            t_min, f_min, found, its, _, t_end = _march_linear(sdf, cd, E * (math.pi / 2), _opaque(r_stop), imax)
        elif variant == "base":
            t_min, f_min, found, its, _, t_end = _march_base(sdf, cd, E, _opaque(rc1), imax)
        elif variant == "discrete":
            t_min, f_min, found, its, m, t_end = _march_discrete(sdf, cd, E, _opaque(rc1), imax)
        else:
            prims = list(getattr(sdf, "primitives", None) or [sdf])
            convex = [bool(getattr(pr, "convex", False)) for pr in prims]
            t_min, f_min, found, its, _, t_end = _march_convex(sdf, prims, convex, cd, E * (math.pi / 2),
                                                        _opaque(r_stop), imax)
    r = dr.select(found, f_min / dr.maximum(cone.rho(t_min), 1e-30), 1.0)
    # only a march that reached the end found the minimum (the envelope theorem's premise); one that
    # stopped at τ ≤ ε or at i_max reports a value that does not move with the radius to first order
    complete = t_end >= cd.t1
    r = dr.select(complete, r, dr.detach(r))
    vis = dr.select(found, tau(r), 1.0) if variant != "discrete" else mi.Float(m)
    return March(visibility=vis, t_min=t_min, f_min=f_min, found=found, r_min=dr.detach(r), iterations=its,
                 complete=complete, cone=cone)


def plane_residual(sdf, m: March):
    """How far the occluder at the minimum is from the thesis' single-plane model ([Bán 2019, §4.1],
    Fig. 4.4): at x = s(t_min), with ρ = ρ(t_min), g the unit SDF gradient projected across the
    axis and e ⟂ g, v, the plane predicts f(x ± ρg) = f_min ± ρ and f(x ± ρe) = f_min; returns
    max |f − prediction| / ρ over the four probes (0 for a plane parallel to the axis; 1 where
    nothing was found). Ten SDF evaluations per point."""
    c = m.cone.detach()
    x = mi.Vector3f(c.o + c.v * m.t_min)
    rho = dr.maximum(c.rho(m.t_min), 1e-12)
    g = mi.Vector3f(sdf.gradient(x))
    g = g - c.v * dr.dot(g, c.v)
    g = dr.normalize(dr.select(dr.norm(g) > 1e-9, g, mi.coordinate_system(c.v)[0]))
    e = dr.cross(c.v, g)
    res = mi.Float(0.0)
    for s in (1.0, -1.0):
        res = dr.maximum(res, dr.abs(sdf.distance(x + g * (s * rho)) - (m.f_min + s * rho)))
        res = dr.maximum(res, dr.abs(sdf.distance(x + e * (s * rho)) - m.f_min))
    return dr.select(m.found, res / rho, 1.0)


def edge_line(sdf, m: March):
    """The occluder's edge in the cross-section at the minimum ([Bán 2019, §5.3.1]): returns
    (x_min, unit direction g⊥ across the axis pointing *away* from the occluder, f_min): a ray
    crossing that plane at y is blocked iff ⟨y − x_min, g⊥⟩ ≤ −f_min."""
    c = m.cone.detach()
    x = mi.Vector3f(c.o + c.v * m.t_min)
    g = mi.Vector3f(sdf.gradient(x))
    g = g - c.v * dr.dot(g, c.v)
    g = dr.normalize(dr.select(dr.norm(g) > 1e-9, g, mi.coordinate_system(c.v)[0]))
    return x, g, m.f_min


# ----------------------------------------------------------------------------------------------
# the Quílez / Aaltonen baseline

def _quilez_ratio(h, ph, t, improved: bool):
    """h/t ([Quílez 2010]) or d/max(0, t − y), y = h²/(2·h_prev), d = √(h² − y²) ([Aaltonen 2018]);
    the estimate is k times its minimum along the ray."""
    if improved:
        y = h * h / (2.0 * ph)
        dd = dr.sqrt(dr.maximum(h * h - y * y, 0.0))
        # y ≥ h (the distance more than doubled: no closer approach between the two spheres) makes
        # the shader's sqrt NaN, which min() then ignores: skip the sample likewise
        return dr.select(y < h, dd / dr.maximum(t - y, 1e-20), dr.inf)
    return h / dr.maximum(t, 1e-20)


@dr.syntax
def _quilez_loop(sdf, o, v, t_end, eps, i_max, improved):
    n = dr.width(t_end)
    t = dr.zeros(mi.Float, n)
    q = dr.full(mi.Float, dr.inf, n)
    ph = dr.full(mi.Float, 1e20, n)
    i = dr.zeros(mi.UInt32, n)
    hit = dr.full(mi.Bool, False, n)
    while (t < t_end) & (i < i_max) & ~hit:
        h = sdf.distance(mi.Point3f(o + v * t))
        hit = h < eps
        q = dr.minimum(q, _quilez_ratio(h, ph, t, improved))
        ph = h
        t = t + h
        i += 1
    return hit, q, i


def quilez(sdf, p, center, R, *, k=None, variant: str = "quilez2010", eps: float = 1e-4, i_max: int = 256):
    """Quílez (2010) / Aaltonen (2018) soft shadow toward the centre of the light sphere
    (``center``, ``R``) from ``p`` (already off the surface); module docstring. ``k=None``
    maps the light size per point: k = √(d² − R²)/R. The loop keeps min h/t (resp. Aaltonen's
    ratio) and the result ``clamp(k·min, 0, 1)`` is formed outside it, so it is differentiable
    in a Dr.Jit ``R``. Returns (visibility, iterations)."""
    if variant not in QUILEZ_VARIANTS:
        raise ValueError(f"variant must be one of {QUILEZ_VARIANTS}, not {variant!r}")
    p = mi.Vector3f(p)
    c = mi.Vector3f(*map(float, center))
    D = c - p
    d = dr.maximum(dr.norm(D), 1e-12)
    Rf = _opaque(R)
    if k is None:
        kk = dr.sqrt(dr.maximum(d * d - Rf * Rf, 1e-20)) / dr.maximum(Rf, 1e-20)
    else:
        kk = _opaque(k) + 0.0 * d
    with dr.suspend_grad():
        hit, q, its = _quilez_loop(sdf, p, D / d, dr.detach(dr.maximum(d - Rf, 0.0)), _opaque(eps),
                                   _opaque(i_max, "uint"), variant == "aaltonen2018")
    return dr.select(hit, 0.0, dr.clip(kk * q, 0.0, 1.0)), its


# ----------------------------------------------------------------------------------------------
# Monte-Carlo reference inside the cone ([Bán 2019, §3.3], §3.3.1)

def halton(n: int, base: int) -> np.ndarray:
    """The first ``n`` points (indices 1 … n) of the radical inverse in ``base`` (float64)."""
    i = np.arange(1, int(n) + 1, dtype=np.int64)
    out = np.zeros(len(i))
    f = 1.0
    while np.any(i > 0):
        f /= base
        out += f * (i % base)
        i //= base
    return out


_HALTON = {}


def _halton_arrays(n: int):
    key = (int(n), mi.variant())
    if key not in _HALTON:
        _HALTON[key] = (mi.Float(halton(n, 2).astype(np.float32)), mi.Float(halton(n, 3).astype(np.float32)))
    return _HALTON[key]


def fnv32(*vals) -> int:
    """FNV-1a over the 8 little-endian bytes of each value: the seed hash of every Monte-Carlo
    stream in shadowlab (the same function as ``shadowlab.render.shading.seed_hash``, written here
    because this package imports nothing of shadowlab; a test checks they agree)."""
    h = 2166136261
    for v in vals:
        for b in int(v).to_bytes(8, "little", signed=False):
            h = ((h ^ b) * 16777619) & 0xFFFFFFFF
    return h


def _hash_u32(seed: int) -> int:
    return fnv32(0x5DF, seed)


def _disk_ray(j, h2, h3, off1, off2, nmax, o, v, e1, e2, c, dc, R, rho_d, nrm, sqrt_scheme, solid):
    """Direction, trace length, weight (disk or solid-angle measure) and cosine factor
    max(0, n·ω) of Halton sample ``j`` (module docstring)."""
    jj = dr.minimum(j, nmax - 1)
    u1 = dr.gather(mi.Float, h2, jj) + off1
    u2 = dr.gather(mi.Float, h3, jj) + off2
    u1 = u1 - dr.floor(u1)
    u2 = u2 - dr.floor(u2)
    phi = u1 * (2.0 * math.pi)
    if sqrt_scheme:
        r, w = dr.sqrt(u2), mi.Float(1.0)
    else:
        r, w = u2, u2
    s, co = dr.sincos(phi)
    q = v * dc + (e1 * co + e2 * s) * (rho_d * r)
    omega = dr.normalize(q)
    ct = dr.dot(omega, v)
    if solid:
        w = w * ct * ct * ct
    # distance to the light sphere along omega (first intersection)
    b = dr.dot(omega, c - o)
    disc = b * b - (dc * dc - R * R)
    tmax = b - dr.sqrt(dr.maximum(disc, 0.0))
    return omega, dr.maximum(tmax, 0.0), w, dr.maximum(dr.dot(nrm, omega), 0.0)


@dr.syntax
def _mc_loop(sdf, o, v, e1, e2, c, dc, R, rho_d, nrm, h2, h3, off1, off2, n, eps, i_max, sqrt_scheme, solid):
    """One sphere-traced ray per Halton sample; returns (Σw·v/Σw, Σw·cos·v/Σw·cos, SDF evaluations):
    both measures from the same rays."""
    N = dr.width(dc)
    j = dr.zeros(mi.UInt32, N)
    omega, tmax, w, cw = _disk_ray(j, h2, h3, off1, off2, n, o, v, e1, e2, c, dc, R, rho_d, nrm, sqrt_scheme, solid)
    t = dr.zeros(mi.Float, N)
    k = dr.zeros(mi.UInt32, N)
    sw = dr.zeros(mi.Float, N)
    swv = dr.zeros(mi.Float, N)
    sc = dr.zeros(mi.Float, N)
    scv = dr.zeros(mi.Float, N)
    its = dr.zeros(mi.UInt32, N)
    while j < n:
        f = sdf.distance(mi.Point3f(o + omega * t))
        hit = f < eps
        t = dr.select(hit, t, t + f)
        k += 1
        its += 1
        done = hit | (t >= tmax) | (k >= i_max)
        vis = dr.select(hit | (t < tmax), 0.0, 1.0)
        wd = dr.select(done, w, 0.0)
        sw += wd
        swv += wd * vis
        sc += wd * cw
        scv += wd * cw * vis
        j = dr.select(done, j + 1, j)
        om2, tm2, w2, cw2 = _disk_ray(j, h2, h3, off1, off2, n, o, v, e1, e2, c, dc, R, rho_d, nrm, sqrt_scheme,
                                      solid)
        omega = dr.select(done, om2, omega)
        tmax = dr.select(done, tm2, tmax)
        w = dr.select(done, w2, w)
        cw = dr.select(done, cw2, cw)
        t = dr.select(done, 0.0, t)
        k = dr.select(done, 0, k)
    return (dr.select(sw > 0.0, swv / dr.maximum(sw, 1e-30), 1.0),
            dr.select(sc > 0.0, scv / dr.maximum(sc, 1e-30), 1.0), its)


def start_points(sdf, points, normals, clearance: float):
    """``points`` moved along ``normals`` until they are ``clearance`` off the SDF's surface
    (points already farther away stay): the start of shadow rays."""
    p = mi.Vector3f(points)
    n = mi.Vector3f(normals)
    f = sdf.distance(mi.Point3f(p))
    return p + n * dr.maximum(clearance - f, 0.0)


def mc_cone_visibility(sdf, points, normals, light, n: int = 256, *, scheme: str = "sqrt",
                       measure: str = "solid_angle", cosine: bool | str = False, seed: int = 0, eps: float = 1e-4,
                       i_max: int = 512, clearance: float | None = None, radius: float | None = None,
                       return_iterations: bool = False):
    """Monte-Carlo visibility of a spherical light inside the cone from each point ([Bán 2019, §3.3.1]).

    ``light``: the light's sphere, a ``(centre, radius)`` pair (a scene light's sphere:
    :func:`shadowlab.scene.lights.light_sphere`); ``radius`` overrides the radius.
    ``n`` Halton samples per point (``scheme``: ``"sqrt"`` r = √u, or ``"r_weighted"`` r = u
    weighted by r), each one sphere-traced shadow ray from the point moved ``clearance`` off
    the surface along its normal (default 10·eps) to the light sphere; a ray still marching
    after ``i_max`` steps counts as blocked. ``measure`` / ``cosine``: module docstring.
    Returns mi.Float per point (and the SDF evaluations per point with ``return_iterations``);
    ``cosine="both"`` returns the pair (plain, cosine-weighted) from the same rays."""
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {SCHEMES}, not {scheme!r}")
    if measure not in MEASURES:
        raise ValueError(f"measure must be one of {MEASURES}, not {measure!r}")
    if cosine not in (False, True, "both"):
        raise ValueError(f"cosine must be False, True or 'both', not {cosine!r}")
    n = int(n)
    if n < 1:
        raise ValueError("n must be at least 1")
    if not (isinstance(light, (tuple, list)) and len(light) == 2):
        raise TypeError(f"light must be a (centre, radius) pair, not {light!r}")
    center, R = np.asarray(light[0], dtype=np.float64), float(light[1])
    if radius is not None:
        R = radius
    o = start_points(sdf, points, normals, 10 * eps if clearance is None else clearance)
    nrm = mi.Vector3f(normals)
    c = mi.Vector3f(*map(float, center))
    D = c - o
    dc = dr.maximum(dr.norm(D), 1e-12)
    v = D / dc
    Rf = _opaque(R)
    s = dr.minimum(Rf / dc, SIN_MAX)
    rho_d = dc * s / dr.sqrt(1.0 - s * s)            # tangent cone's radius at the light's centre
    e1, e2 = mi.coordinate_system(v)
    N = dr.width(dc)
    idx = dr.arange(mi.UInt32, N)
    rng = mi.PCG32(N, dr.opaque(mi.UInt64, _hash_u32(seed)), mi.UInt64(idx))
    off1, off2 = rng.next_float32(), rng.next_float32()
    h2, h3 = _halton_arrays(n)
    plain, cos, its = _mc_loop(sdf, o, v, e1, e2, c, dc, Rf, rho_d, nrm, h2, h3, off1, off2, _opaque(n, "uint"),
                               _opaque(eps), _opaque(i_max, "uint"), scheme == "sqrt", measure == "solid_angle")
    vis = (plain, cos) if cosine == "both" else cos if cosine else plain
    return (vis, its) if return_iterations else vis
