"""Direct light from one emitter by stratified emitter sampling, with or without visibility.

One estimator serves both sides of a comparison, so they differ only in visibility:

* unshadowed radiance ``U_L`` at each shading point (no shadow rays), which a technique's
  visibility multiplies: ``shaded = Σ_L U_L · V_L``;
* the ground truth (``reference/truth.py``), which adds Mitsuba shadow rays and estimates
  ``V_L = ∫ f v / ∫ f`` (the ratio of shadowed to unshadowed direct light) and the plain
  visible fraction ``A_L`` (area for rect/disk lights, solid angle for spheres: Mitsuba's
  sphere emitter samples its visible cone uniformly).

Samples: a k×k jittered grid on the emitter's 2D sample domain per round, random numbers
from PCG32 seeded by (seed, round, point): same seed, same bits.

Light ranges. A point or spot light with a ``range`` R (the scene format's influence radius) has
its falloff windowed by

    w(d) = clamp(1 − (d/R)⁴, 0, 1)²,   d = |x_light − x|, x_light the light's position (its centre)

the windowing common in engines [Karis 2013] (Unreal Engine 4; Frostbite uses the same
window [Lagarde 2014]): 1 at the light, 0 from d = R on, smooth at both ends. It is applied
in one place, :func:`light_samples`, to every sample's contribution (``window`` = :func:`range_window`,
computed by :func:`sample_light` from the light's spec): ``U_L`` (:func:`unshadowed`) and every
caller of :func:`sample_light` get it. d is measured from the light's centre, not from the
sample on an area light, so w is one number per shading point: the truth's visibility ratio
``V_L = ∫ f v / ∫ f`` is unchanged by it wherever w > 0, and beyond the range (∫ f = 0) it
becomes the truth's "no light" value. Mitsuba's own ``direct`` integrator cannot window a light,
so its image ignores ranges (``Scene.mitsuba_notes``).

Shadow rays are Mitsuba's ``ray_test``, except in a scene with alpha-tested casters
(``scene.has_alpha``): ``ray_test`` ignores BSDF opacity, so there :func:`occluded_alpha`
intersects and continues through transparent texels (a symbolic loop; slower, so only there).

Translucent casters (``scene.has_translucent``): a shadow ray's visibility becomes RGB, the
straight-line transmittance of the segment (:func:`transmitted`): 0 when an opaque surface lies on
it, else the product of the τ of every translucent surface it crosses. This is the truth's model
of translucency, the one the screen-space technique assumes [Tamás 2015, §6.5]: no refraction, no
scattering inside the caster, no light reflected by it toward the receiver.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scene.build import surface_tau, transparent
from .gbuffer import vec_numpy


def seed_hash(*vals) -> int:
    """FNV-1a (32 bit) of the values' 8-byte little-endian bytes: the seed of every PCG32 stream
    (seed, round, ...) in shadowlab.

    >>> seed_hash(0) == seed_hash(0), seed_hash(0, 1) != seed_hash(1, 0)
    (True, True)
    """
    h = 2166136261
    for v in vals:
        for b in int(v).to_bytes(8, "little", signed=False):
            h = ((h ^ b) * 16777619) & 0xFFFFFFFF
    return h


def window(d, light_range):
    """The range window w(d) = clamp(1 − (d/R)⁴, 0, 1)² [Karis 2013] (module docstring), Dr.Jit
    or Python floats; ``light_range`` R > 0."""
    t = d / light_range
    t2 = t * t
    c = dr.clip(1.0 - t2 * t2, 0.0, 1.0)
    return c * c


def range_window(light, p):
    """w(|x_light − p|) of ``light`` (a LightSpec) at the points ``p`` (mi.Point3f), or None for a
    light without a range (no window). The range enters opaquely (one kernel for every range)."""
    rng = getattr(light, "range", None)
    if rng is None:
        return None
    c = mi.Point3f(*[float(x) for x in light.position])
    return window(dr.norm(mi.Point3f(p) - c), dr.opaque(mi.Float, float(rng)))


def _light_of(scene, emitter):
    """The LightSpec whose Mitsuba emitter is ``emitter`` (None if ``scene`` has no such light)."""
    spec = getattr(scene, "spec", None)
    for name, e in getattr(scene, "emitters", {}).items():
        if e is emitter and spec is not None:
            return spec.light(name)
    return None


def sample_light(scene, si, emitter, k: int, seed: int, rnd: int, shadow: bool, stratified: bool = True):
    """One round of k×k stratified samples of ``emitter`` at every interaction of ``si``
    (``stratified=False``: k² independent uniform samples, for comparison in the benchmark).

    Returns Dr.Jit arrays per point: ``f`` (Color3f, Σ of bsdf·Le·cos/pdf over the samples,
    i.e. k² times the unshadowed estimate), ``fv`` (Float, Σ |f|·v), ``fsum`` (Float, Σ |f|)
    and ``v`` (Float, number of unoccluded samples). Visibility is only traced when ``shadow``.
    A light with a ``range`` has every sample's contribution windowed (:func:`range_window`).
    """

    n = dr.width(si.p)
    idx = dr.arange(mi.UInt32, n)
    # opaque: a literal seed would be baked into the kernel and compile a new one every round
    rng = mi.PCG32(n, dr.opaque(mi.UInt64, seed_hash(seed, rnd)), mi.UInt64(idx))
    alpha = bool(shadow and getattr(scene, "has_alpha", False))
    light = _light_of(scene, emitter)
    win = range_window(light, si.p) if light is not None else None
    occluders = scene.casters.mi_scene if shadow else None  # what casts shadows (``casts_shadows``)
    return light_samples(occluders, si, emitter, rng, mi.UInt32(k), shadow, stratified, alpha, win)


MAX_ALPHA_LAYERS = 64  # transparent texels a shadow ray may pass; a ray still on one after that is blocked


@dr.syntax
def occluded_alpha(mi_scene, ray, active):
    """``scene.mi_scene.ray_test`` that sees through transparent texels of alpha-tested casters.

    Mitsuba's ``ray_test`` ignores BSDF opacity (a ``mask`` BSDF's holes block it), so: intersect
    (position, normal and uv only), and while the hit is a transparent texel spawn a new segment
    from it to the same end point. Returns mi.Bool: an opaque surface lies on the segment.
    Segments that ``ray_test`` finds empty are done at its cost (a pre-pass with the same result:
    one pass of 512² shadow rays on ``foliage`` took 14 ms instead of 16 ms; ``ray_test`` alone 2 ms)."""
    target = ray(ray.maxt)
    active = mi.Bool(active) & mi_scene.ray_test(ray, active)
    flags = mi.RayFlags.Minimal | mi.RayFlags.UV
    # the overload with flags is (ray, ray_flags, coherent, active): ``active`` third would be
    # taken for ``coherent``
    si = mi_scene.ray_intersect(ray, flags, False, active)
    through = transparent(si, active)
    i = mi.UInt32(0)
    while dr.hint(through & (i < MAX_ALPHA_LAYERS), max_iterations=-1):
        si = mi_scene.ray_intersect(si.spawn_ray_to(target), flags, False, through)
        through = transparent(si, through)
        i += 1
    return active & si.is_valid()


MAX_TRANSLUCENT_LAYERS = 16  # translucent surfaces a shadow ray may cross; a ray still on one after that is blocked


@dr.syntax
def transmitted(mi_scene, ray, active, table, alpha=False):
    """Straight-line transmittance (mi.Color3f) of the shadow segment ``ray`` (to ``ray.maxt``):
    1 where nothing lies on it, 0 where an opaque surface does, else the product of the τ of
    every translucent surface crossed (``table``: ``Scene.translucency()``; ``alpha``: also pass
    transparent texels of alpha-tested casters, with τ = 1). Segments that ``ray_test`` finds
    empty are done at its cost; the others intersect and continue through translucent hits (a
    symbolic loop)."""
    target = ray(ray.maxt)
    blocked = mi.Bool(active) & mi_scene.ray_test(ray, active)
    flags = mi.RayFlags.Minimal | mi.RayFlags.UV
    si = mi_scene.ray_intersect(ray, flags, False, blocked)
    through, tau_s = surface_tau(si, table, blocked)
    if alpha:
        through |= transparent(si, blocked)
    tau = mi.Color3f(1.0)
    i = mi.UInt32(0)
    while dr.hint(through & (i < MAX_TRANSLUCENT_LAYERS), max_iterations=-1):
        tau *= tau_s
        si = mi_scene.ray_intersect(si.spawn_ray_to(target), flags, False, through)
        through, tau_s = surface_tau(si, table, through)
        if alpha:
            through |= transparent(si, through)
        i += 1
    return dr.select(~blocked, mi.Color3f(1.0), dr.select(si.is_valid(), mi.Color3f(0.0), tau))


@dr.syntax
def light_samples(mi_scene, si, emitter, rng, k, shadow, stratified, alpha=False, win=None, radiance=True,
                  table=None):
    """k² samples of ``emitter`` at ``si`` (see :func:`sample_light`); ``win``: per-point range
    window (:func:`range_window`) multiplying every sample's contribution, None = none;
    ``radiance=False``: ``f`` is not summed (returned as zero; the truth needs only fv, fsum, v).

    ``table`` (``Scene.translucency()``, with ``shadow``): a sample's visibility is its segment's
    RGB transmittance τ (:func:`transmitted`) and ``v`` sums its channel mean; three more values
    come back: ``fv_rgb`` (Color3f, Σ |f|·τ per channel; ``fv`` is its channel mean), ``lit``
    and ``dark`` (Float, samples with τ = 1, resp. 0, in every channel: where either is k², the
    samples were unanimous). Without ``shadow`` the samples of a point off the surfaces or beyond
    the light's range (``win`` = 0) are skipped: their contributions are zero, and ``v`` is 0 there.

    Sample i's stratum is (i mod k, i div k), kept as two counters rather than divided out per
    sample (the same values; on the CPU, together with ``radiance=False``, the truth's samples
    without their shadow rays cost a fifth less)."""
    ctx = mi.BSDFContext()
    bsdf = si.bsdf()
    n = dr.width(si.p)
    f = mi.Color3f(0.0)
    fv = dr.zeros(mi.Float, n)
    fsum = dr.zeros(mi.Float, n)
    v = dr.zeros(mi.Float, n)
    coloured = shadow and table is not None
    fv_rgb = mi.Color3f(0.0) if coloured else None
    lit = dr.zeros(mi.Float, n) if coloured else None
    dark = dr.zeros(mi.Float, n) if coloured else None
    i = mi.UInt32(0)
    kk = k * k
    # without shadow rays a point off the surfaces or beyond the light's range sums only zeros:
    # its samples are not taken (the same bits)
    taken = kk
    if not shadow:
        reached = si.is_valid() if win is None else si.is_valid() & (win > 0)
        taken = dr.select(reached, kk, 0)
    sx = mi.UInt32(0)
    sy = mi.UInt32(0)
    while i < taken:
        if stratified:
            u = mi.Point2f((mi.Float(sx) + rng.next_float32()) / mi.Float(k),
                           (mi.Float(sy) + rng.next_float32()) / mi.Float(k))
            sx += 1
            wrap = sx == k
            sx = dr.select(wrap, 0, sx)
            sy = dr.select(wrap, sy + 1, sy)
        else:
            u = mi.Point2f(rng.next_float32(), rng.next_float32())
        ds, w = emitter.sample_direction(si, u, si.is_valid())
        wo = si.to_local(ds.d)
        fs = bsdf.eval(ctx, si, wo, si.is_valid())
        c = fs * w
        c = dr.select(si.is_valid() & (ds.pdf > 0), c, 0.0)
        if win is not None:
            c = c * win
        mag = c.x + c.y + c.z
        if coloured:
            tau = transmitted(mi_scene, si.spawn_ray_to(ds.p), si.is_valid() & (mag > 0), table, alpha)
            vis = (tau.x + tau.y + tau.z) / 3.0
            fv_rgb += mag * tau
            lit += dr.select((tau.x == 1.0) & (tau.y == 1.0) & (tau.z == 1.0), 1.0, 0.0)
            dark += dr.select((tau.x == 0.0) & (tau.y == 0.0) & (tau.z == 0.0), 1.0, 0.0)
        elif shadow:
            if not alpha:
                occluded = mi_scene.ray_test(si.spawn_ray_to(ds.p), si.is_valid() & (mag > 0))
            else:
                occluded = occluded_alpha(mi_scene, si.spawn_ray_to(ds.p), si.is_valid() & (mag > 0))
            vis = dr.select(occluded, 0.0, 1.0)
        else:
            vis = mi.Float(1.0)
        if radiance:
            f += c
        fv += mag * vis
        fsum += mag
        v += vis
        i += 1
    return (f, fv, fsum, v, fv_rgb, lit, dark) if coloured else (f, fv, fsum, v)


def unshadowed(scene, gbuffer, light_name: str, k: int = 16, seed: int = 0):
    """Unshadowed outgoing radiance U_L at every G-buffer point (flat mi.Color3f), estimated
    with k×k stratified emitter samples (a delta light needs and gets one); not evaluated
    (``make_frame`` evaluates every light's with the G-buffer)."""
    spec = scene.spec.light(light_name)
    k = 1 if spec.is_delta else k
    f, _, _, _ = sample_light(scene, gbuffer.si, scene.emitters[light_name], k, seed, 0xFFFF, False)
    return dr.select(gbuffer.valid, f / float(k * k), 0.0)


def compose(frame, visibility: dict, colour: dict | None = None) -> np.ndarray:
    """Shaded image (H, W, 3) = Σ_L U_L · V_L, averaged over sub-pixels.

    ``visibility`` maps light name -> flat per-point visibility (Dr.Jit Float or numpy);
    ``colour`` (optional) light name -> flat per-point RGB visibility (Dr.Jit Color3f or numpy
    (n, 3)), used instead for the lights it has (coloured shadows of translucent casters)."""
    out = None
    for name, U in frame.unshadowed.items():
        if colour and name in colour:
            V = colour[name]
            V = vec_numpy(V) if hasattr(V, "x") else np.asarray(V).reshape(-1, 3)
        else:
            V = visibility[name]
            V = (V.numpy() if hasattr(V, "numpy") else np.asarray(V)).reshape(-1, 1)
        c = vec_numpy(U) * V
        out = c if out is None else out + c
    return frame.gbuffer.to_image(out)
