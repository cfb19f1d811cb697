"""Sphere tracing and cone tracing of signed distance fields ([Bán 2019, §2.7–2.9], §3.1).

* :func:`sphere_trace` — Hart's sphere tracing ([Bán 2019, §2.7], Algorithm 2): step by ``f``; a hit
  when ``f < eps``.
* :func:`cone_trace` — the cone trace of [Bán 2019, §2.8]: sphere tracing of the offset field
  ``F(x) = (f(x) − R0 − t·tanα) / (1 + |tanα|)``, stopping when the cone of radius
  ``R0 + t·tanα`` touches the surface (``f`` within ``(1 + κ)`` of the cone radius). With the
  pixel-covering cone of a camera ray ([Bán 2019, §2.9]) the stop point is the *surface point* of the
  thesis: the ball of radius ``f`` around it does not cross the surface and covers the pixel.
* :func:`hard_visibility` — hard shadows ([Bán 2019, §3.1]): sphere trace from a surface point towards
  a light position.

All three are Dr.Jit symbolic loops (``@dr.syntax``) over every lane at once; ``eps``, ``t_max``
and the cone parameters are opaque, so new values reuse the compiled kernel.

>>> import mitsuba as mi
>>> from shadowlab.sdf.field import Sphere
>>> hit, t, n = sphere_trace(Sphere((0, 0, 5), 1.0), mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, 1), mi.Float(10))
>>> bool(hit[0]), round(float(t[0]), 3)
(True, 4.0)
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

CONE_KAPPA = 0.25  # cone_trace stops when f < (1 + κ)·(R0 + t·tanα) + eps


def _f(v):
    return v if isinstance(v, mi.Float) else dr.opaque(mi.Float, float(v))


def sphere_trace(sdf, o, d, t_max, *, eps=1e-4, i_max=256, t_min=0.0):
    """Sphere-trace ``sdf`` along rays ``o + t·d`` (``d`` unit length) from ``t_min`` ([Bán 2019, §2.7]).

    Returns ``(hit, t, iterations)``: ``hit`` (mi.Bool) where ``f < eps`` was reached before
    ``t_max`` and ``i_max`` steps; ``t`` (mi.Float) the stop distance (``t_max`` for a miss);
    ``iterations`` (mi.UInt32) the number of distance evaluations.
    """
    o, d = mi.Vector3f(o), mi.Vector3f(d)
    t0 = dr.zeros(mi.Float, dr.width(o)) + _f(t_min)
    return _sphere_loop(sdf, o, d, t0, _f(t_max), _f(eps), dr.opaque(mi.UInt32, int(i_max)))


@dr.syntax
def _sphere_loop(sdf, o, d, t, t_max, eps, imax):
    i = mi.UInt32(0)
    hit = mi.Bool(False)
    active = t < t_max
    while dr.hint(active, max_iterations=-1, label="sphere_trace"):
        f = sdf.distance(o + d * t)
        hit = f < eps
        t = dr.select(hit, t, t + f)
        i += 1
        active = ~hit & (t < t_max) & (i < imax)
    return hit, dr.select(hit, t, dr.minimum(t, t_max)), i


def cone_trace(sdf, o, d, t_max, tan_alpha, *, r0=0.0, eps=1e-4, i_max=256, kappa=CONE_KAPPA):
    """Cone-trace ``sdf`` with cones of apex radius ``r0`` and half-angle ``atan(tan_alpha)``
    around rays ``o + t·d`` ([Bán 2019, §2.8]): sphere tracing of ``(f − r0 − t·tanα) / (1 + |tanα|)``.

    Returns ``(hit, t, iterations)``; a hit where ``f(o + t·d) < (1 + κ)·(r0 + t·tanα) + eps``.
    """
    o, d = mi.Vector3f(o), mi.Vector3f(d)
    return _cone_loop(sdf, o, d, _f(t_max), _f(tan_alpha), _f(r0), _f(eps), 1.0 + _f(kappa),
                      dr.opaque(mi.UInt32, int(i_max)))


@dr.syntax
def _cone_loop(sdf, o, d, t_max, ta, r0, eps, k1, imax):
    t = dr.zeros(mi.Float, dr.width(o))
    i = mi.UInt32(0)
    hit = mi.Bool(False)
    active = mi.Bool(True)
    while dr.hint(active, max_iterations=-1, label="cone_trace"):
        f = sdf.distance(o + d * t)
        radius = r0 + t * ta
        hit = f < k1 * radius + eps
        t = dr.select(hit, t, t + dr.maximum(f - radius, eps) / (1.0 + dr.abs(ta)))
        i += 1
        active = ~hit & (t < t_max) & (i < imax)
    return hit, dr.select(hit, t, dr.minimum(t, t_max)), i


def hard_visibility(sdf, p, n, target, *, eps=1e-4, i_max=256, offset=None, return_iterations=False):
    """Hard shadow of a point light at ``target`` ([Bán 2019, §3.1]): 1 where the sphere trace from
    ``p`` (moved off the surface along the normal ``n`` by ``offset``, default 4·eps; ``n=None``:
    ``p`` is already off the surface) reaches ``target`` without a hit, else 0 (mi.Float), and
    the SDF evaluations per lane with ``return_iterations``. ``target`` may be one point or one
    per lane (a 3-sequence or a Dr.Jit vector)."""
    p = mi.Vector3f(p)
    target = mi.Vector3f(target) if isinstance(target, dr.ArrayBase) else mi.Vector3f(*map(float, target))
    o = p if n is None else p + mi.Vector3f(n) * float(4 * eps if offset is None else offset)
    to = target - o
    dist = dr.maximum(dr.norm(to), 1e-12)
    hit, _, its = sphere_trace(sdf, o, to / dist, dist, eps=eps, i_max=i_max)
    v = dr.select(hit, 0.0, 1.0)
    return (v, its) if return_iterations else v
