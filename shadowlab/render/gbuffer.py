"""G-buffer from the scene's own Mitsuba sensor (docs/ARCHITECTURE.md, GBuffer).

Camera rays go through pixel centres (or the centres of an s×s grid of sub-pixels), made by
``sensor.sample_ray`` so the G-buffer matches the ground-truth camera exactly. Point ``k`` of
the flat arrays is pixel ``(x, y) = ((k // s²) % W, (k // s²) // W)``, sub-pixel ``k % s²``:
reshaping any flat array to (H, W, s²) and averaging the last axis gives pixel values.

Alpha-tested casters ([Buljan 2020, §2.4]): in a scene with ``scene.has_alpha``
camera rays continue through transparent texels (alpha < cutoff), so a pixel shows what lies
behind a leaf card's holes; other scenes cast one ``ray_intersect`` as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scene.build import transparent
from .camera import Camera, pixel_uv


@dataclass
class GBuffer:
    """Per shading point: Dr.Jit arrays (``si`` is Mitsuba's SurfaceInteraction3f, kept for
    shading and shadow rays) plus numpy copies of what reports and metrics read."""

    width: int
    height: int
    ss: int
    si: object              # mi.SurfaceInteraction3f, flat, size W*H*ss²
    rays: object            # mi.Ray3f camera rays
    p: object               # mi.Point3f world position
    n: object               # mi.Normal3f shading normal (world)
    ng: object              # mi.Normal3f geometric normal (world), facing the camera
    valid: object           # mi.Bool: a non-emitting surface was hit
    view_depth: np.ndarray  # (H, W, ss²) distance from the camera position along the ray
    z_depth: np.ndarray     # (H, W, ss²) depth along the camera's forward axis
    albedo: np.ndarray      # (H, W, ss², 3)
    mask: np.ndarray        # (H, W, ss²) bool
    shape_id: np.ndarray    # (H, W, ss²) int32, -1 = miss
    view: object = None     # the scene's camera (spec) the rays came from

    @property
    def size(self) -> int:
        return self.width * self.height * self.ss * self.ss

    def to_image(self, flat) -> np.ndarray:
        """Flat per-point values (Dr.Jit or numpy, size N or N×C) -> pixel image (H, W[, C])
        averaged over sub-pixels."""
        a = np.asarray(flat.numpy() if hasattr(flat, "numpy") else flat, dtype=np.float32)
        if a.ndim == 2 and a.shape[0] != self.size:  # Dr.Jit vectors come as (C, N)
            a = a.T
        if a.shape[0] != self.size:
            raise ValueError(f"{a.shape[0]} values for a G-buffer of {self.size} points")
        a = a.reshape(self.height, self.width, self.ss * self.ss, *a.shape[1:])
        return a.mean(axis=2)


def vec_numpy(v) -> np.ndarray:
    """A Dr.Jit 3-vector array (which ``.numpy()`` gives as (3, N)) -> numpy (N, 3)."""
    return np.asarray(v.numpy()).T


def gbuffer(scene, ss: int = 1) -> GBuffer:
    """Cast camera rays through pixel (sub-)centres; see module docstring for the layout.

    >>> from shadowlab.scene import load
    >>> gb = gbuffer(load("contact", resolution=(8, 6)))
    >>> gb.mask.shape, gb.view_depth.shape          # images are (height, width, channels)
    ((6, 8, 1), (6, 8, 1))
    >>> bool(gb.mask.any())
    True
    """

    W, H = scene.resolution
    uv = pixel_uv(W, H, ss)
    film_uv = mi.Point2f(uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32))
    ray, _ = scene.sensor.sample_ray(0.0, 0.5, film_uv, mi.Point2f(0.5))
    si = scene.mi_scene.ray_intersect(ray)
    if getattr(scene, "has_alpha", False):
        si = _through_alpha(scene.mi_scene, si, ray)
    hit = si.is_valid()
    is_emitter = si.shape.is_emitter() if hasattr(si.shape, "is_emitter") else mi.Bool(False)
    valid = hit & ~is_emitter
    # geometric normal facing the camera (two-sided surfaces)
    ng = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray.d) > 0, -n, n)
    cam = Camera.from_scene(scene)
    cam_o = mi.Point3f(*[float(x) for x in cam.position])
    dist = dr.norm(si.p - cam_o)
    zd = dr.dot(si.p - cam_o, mi.Vector3f(*[float(x) for x in cam.forward]))
    bsdf = si.bsdf(ray)
    alb = bsdf.eval_diffuse_reflectance(si, valid) if hasattr(bsdf, "eval_diffuse_reflectance") else mi.Color3f(0.5)
    shapes = scene.mi_scene.shapes_dr()
    # shape index: compare the hit shape pointer against each shape (few shapes, fixed loop)
    sid = dr.full(mi.Int32, -1, dr.width(ray))
    for idx in range(len(scene.shape_names)):
        sid = dr.select(hit & (si.shape == dr.gather(type(shapes), shapes, idx)), idx, sid)
    dr.eval(si, valid, ng, n, dist, zd, alb, sid)
    shp = (H, W, ss * ss)
    mask = valid.numpy().reshape(shp)
    vd = np.where(mask, dist.numpy().reshape(shp), 0).astype(np.float32)
    zz = np.where(mask, zd.numpy().reshape(shp), 0).astype(np.float32)
    albedo = vec_numpy(alb).reshape(*shp, 3).astype(np.float32) * mask[..., None]
    return GBuffer(width=W, height=H, ss=ss, si=si, rays=ray, p=si.p, n=n, ng=ng, valid=valid,
                   view_depth=vd, z_depth=zz, albedo=albedo, mask=mask,
                   shape_id=sid.numpy().reshape(shp).astype(np.int32), view=scene.spec.camera)


MAX_ALPHA_LAYERS = 64  # transparent texels a camera ray may pass before it stops (then: a miss)


@dr.syntax
def _through_alpha(mi_scene, si, ray):
    """Continue camera rays through transparent texels of alpha-tested shapes (a symbolic loop,
    only for scenes that have them). ``si.t`` stays the distance from the camera ray's origin; a
    ray still on a transparent texel after MAX_ALPHA_LAYERS surfaces counts as a miss."""
    r = mi.Ray3f(ray)
    i = mi.UInt32(0)
    through = transparent(si)
    while dr.hint(through & (i < MAX_ALPHA_LAYERS), max_iterations=-1):
        r = si.spawn_ray(r.d)
        si = mi_scene.ray_intersect(r)
        through = transparent(si)
        i += 1
    si.t = dr.select(through, dr.inf, dr.select(si.is_valid(), dr.norm(si.p - ray.o), si.t))
    return si
