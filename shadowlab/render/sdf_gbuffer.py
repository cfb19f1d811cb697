"""The cone-traced G-buffer of an SDF scene [Bán 2019, §2.9] and its unshadowed light.

Camera rays are the same as the Mitsuba G-buffer's (``sensor.sample_ray`` at pixel (sub-)centres,
:func:`shadowlab.render.camera.pixel_uv` order), each traced as the *pixel-covering cone* of
[Bán 2019, §2.9]: apex at the camera, half-angle ``α`` with ``tanα`` = half the diagonal of a (sub-)pixel
at unit distance. :func:`shadowlab.sdf.trace.cone_trace` stops at the *surface point* ``p``: the
ball of radius ``f(p)`` around it (``radius``) does not cross the surface and covers the pixel, so
thin objects cannot fall between pixel centres, and rays started from it do not crawl along the
surface ([Bán 2019, §2.9]). It is the shading point, as in the thesis: normals ``n`` are the normalised
gradient there, depths are measured to it, and the soft-shadow cone starts from its ball.

Measured on the Mandelbulb, shadow rays from points on the fractal itself (sphere traced to
``f < 1e-4``) are blocked by its sub-pixel pores: 35 % of the bulb's pixels came out in umbra
(speckle), 10 % from the surface points. The centre ray's own hit, sphere traced on from ``p`` for
at most four cone radii, is kept as ``p_surface`` / ``n_surface`` (``p`` where there is none:
the cone grazed a silhouette); on the twins it lies within 4e-4 of Mitsuba's hit
(tests/test_sdf_trace.py). Albedo and shape id come from the primitive nearest to ``p_surface``
(``shape_id`` indexes ``sdf.primitives``).

Which G-buffer is used: for scenes whose every object has a Mitsuba twin, techniques use the
Mitsuba G-buffer (so they are evaluated at the ground truth's own points); this cone-traced one is
the G-buffer of scenes with SDF-only content (``[[sdf]]``, e.g. the Mandelbulb), which Mitsuba
cannot see (:func:`shadowlab.render.frame.make_frame` chooses).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..sdf.trace import cone_trace, sphere_trace
from .camera import Camera
from .gbuffer import GBuffer, film_uv
from .shading import seed_hash


@dataclass
class SDFGBuffer(GBuffer):
    """A :class:`GBuffer` from cone tracing (``p`` = the surface points of [Bán 2019, §2.9]), plus their
    balls and the centre rays' own hits."""

    radius: object = None       # mi.Float f(p): radius of the surface point's empty ball, covering the pixel
    t: object = None            # mi.Float distance of p along the camera ray
    p_surface: object = None    # mi.Point3f the centre ray's hit near p (p where none: a grazed silhouette)
    n_surface: object = None    # mi.Normal3f normalised gradient at p_surface
    iterations: object = None   # mi.UInt32 cone-trace steps
    tan_alpha: float = 0.0      # the pixel cone's tan(half-angle)


def pixel_tan_alpha(camera, ss: int = 1) -> float:
    """The pixel cone's tan(half-angle) for a scene's camera spec: :meth:`Camera.pixel_tan_alpha`."""
    return Camera.from_spec(camera).pixel_tan_alpha(ss)


def cone_gbuffer(scene, sdf, ss: int = 1, *, eps: float = 1e-4, i_max: int = 512,
                 evaluated: bool = True) -> SDFGBuffer:
    """Cone-traced G-buffer of ``sdf`` seen by ``scene``'s camera (see the module docstring);
    ``evaluated=False``: lazy, for a caller that evaluates it with more work (:func:`evaluate`)."""

    W, H = scene.resolution
    cam = Camera.from_scene(scene)
    ray, _ = scene.sensor.sample_ray(0.0, 0.5, film_uv(W, H, ss), mi.Point2f(0.5))
    t_max = float(np.linalg.norm(cam.position - np.asarray(scene.center)) + scene.radius) * 1.01 + 1e-3
    ta = cam.pixel_tan_alpha(ss)
    o, d = mi.Vector3f(ray.o), mi.Vector3f(ray.d)
    hit, t, its = cone_trace(sdf, o, d, t_max, ta, eps=eps, i_max=i_max)
    p = o + d * t
    radius = sdf.distance(p)
    n = sdf.gradient(p)
    n = dr.select(dr.dot(n, d) > 0, -n, n)
    # the centre ray's own hit: sphere tracing on from the cone's stop, at most a few cone radii
    # (where it finds none, the cone grazed a silhouette: it stays where the cone stopped)
    reach = t + 4.0 * (radius + t * ta) + 10 * eps
    on, t_on, _ = sphere_trace(sdf, o, d, reach, eps=eps, i_max=256, t_min=t)
    p_s = o + d * dr.select(hit & on, t_on, t)
    n_s = sdf.gradient(p_s)
    n_s = dr.select(dr.dot(n_s, d) > 0, -n_s, n_s)
    # the primitive nearest to the surface point gives albedo and shape id (a few fixed taps)
    prims = sdf.primitives
    best = dr.full(mi.Float, dr.inf, dr.width(p))
    sid = dr.full(mi.Int32, -1, dr.width(p))
    alb = mi.Color3f(0.0)
    for k, prim in enumerate(prims):
        dk = prim.distance(p_s)
        closer = hit & (dk < best)
        best = dr.select(closer, dk, best)
        sid = dr.select(closer, k, sid)
        alb = dr.select(closer, mi.Color3f(*prim.albedo), alb)
    cam_p = mi.Vector3f(*(float(x) for x in cam.position))
    fwd = mi.Vector3f(*(float(x) for x in cam.forward))
    dist = dr.select(hit, dr.norm(p - cam_p), 0.0)
    zd = dr.select(hit, dr.dot(p - cam_p, fwd), 0.0)
    alb = dr.select(hit, alb, 0.0)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(p))
    si.p = mi.Point3f(p)
    si.n = mi.Normal3f(n)
    si.sh_frame = mi.Frame3f(n)
    si.t = dr.select(hit, t, dr.inf)
    si.wi = si.to_local(-d)
    p_s, n_s = mi.Point3f(p_s), mi.Normal3f(n_s)
    gb = SDFGBuffer(width=W, height=H, ss=ss, si=si, rays=ray, p=si.p, n=si.n, ng=si.n, valid=hit,
                    distance=dist, forward_depth=zd, reflectance=alb, shape=sid,
                    radius=radius, t=t, p_surface=p_s, n_surface=n_s, iterations=its, tan_alpha=ta)
    if evaluated:
        evaluate(gb)
    return gb


def evaluate(gb: SDFGBuffer, *more) -> None:
    """Evaluate the cone-traced G-buffer's arrays (and ``more`` in the same kernel)."""
    dr.eval(gb.si, gb.valid, gb.radius, gb.t, gb.p_surface, gb.n_surface, gb.shape, gb.reflectance, gb.distance,
            gb.forward_depth, gb.iterations, *more)


def unshadowed(scene, gb: SDFGBuffer, light_name: str, k: int = 16, seed: int = 0):
    """Unshadowed radiance U_L at the points of a cone-traced G-buffer (flat mi.Color3f): the
    estimator of :func:`shadowlab.render.shading.unshadowed` (k×k stratified emitter samples,
    PCG32 seeded by (seed, 0xFFFF, point)) with the diffuse BSDF written out, albedo/π·cos, since
    the surface points belong to no Mitsuba shape."""
    spec = scene.spec.light(light_name)
    k = 1 if spec.is_delta else int(k)
    n = gb.size
    idx = dr.arange(mi.UInt32, n)
    rng = mi.PCG32(n, dr.opaque(mi.UInt64, seed_hash(seed, 0xFFFF)), mi.UInt64(idx))
    U = _unshadowed_loop(scene.emitters[light_name], gb.si, gb.valid, gb.reflectance, rng, mi.UInt32(k))
    return dr.select(gb.valid, U / float(k * k), 0.0)


@dr.syntax
def _unshadowed_loop(emitter, si, valid, albedo, rng, k):
    f = mi.Color3f(0.0)
    i = mi.UInt32(0)
    while i < k * k:
        u = mi.Point2f((mi.Float(i % k) + rng.next_float32()) / mi.Float(k),
                       (mi.Float(i // k) + rng.next_float32()) / mi.Float(k))
        ds, w = emitter.sample_direction(si, u, valid)
        cos = dr.maximum(dr.dot(si.n, ds.d), 0.0)
        f += dr.select(valid & (ds.pdf > 0), albedo * dr.inv_pi * cos * w, 0.0)
        i += 1
    return f
