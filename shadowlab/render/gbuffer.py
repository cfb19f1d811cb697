"""G-buffer from the scene's own Mitsuba sensor (docs/ARCHITECTURE.md, GBuffer).

Camera rays go through pixel centres (or the centres of an s×s grid of sub-pixels), made by
``sensor.sample_ray`` so the G-buffer matches the ground-truth camera exactly. Point ``k`` of
the flat arrays is pixel ``(x, y) = ((k // s²) % W, (k // s²) // W)``, sub-pixel ``k % s²``:
reshaping any flat array to (H, W, s²) and averaging the last axis gives pixel values.

Alpha-tested casters ([Buljan 2020, §2.4]): in a scene with ``scene.has_alpha``
camera rays continue through transparent texels (alpha < cutoff), so a pixel shows what lies
behind a leaf card's holes; other scenes cast one ``ray_intersect`` as before.

No host round trip: the film coordinates are made on the device (:func:`film_uv`) and every
field stays a Dr.Jit array; the numpy images that reports and metrics read (``mask``,
``view_depth``, ``z_depth``, ``albedo``, ``shape_id``) are read back on first use, outside a
frame's own work.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scene.build import transparent
from .camera import Camera


@dataclass
class GBuffer:
    """Per shading point, flat Dr.Jit arrays (``si`` is Mitsuba's SurfaceInteraction3f, kept for
    shading and shadow rays); the numpy images (H, W, ss²[, 3]) reports and metrics read are
    properties, read back once when first asked for."""

    width: int
    height: int
    ss: int
    si: object              # mi.SurfaceInteraction3f, flat, size W*H*ss²
    rays: object            # mi.Ray3f camera rays
    p: object               # mi.Point3f world position
    n: object               # mi.Normal3f shading normal (world)
    ng: object              # mi.Normal3f geometric normal (world), facing the camera
    valid: object           # mi.Bool: a non-emitting surface was hit
    distance: object        # mi.Float distance from the camera position along the ray, 0 where not valid
    forward_depth: object   # mi.Float depth along the camera's forward axis, 0 where not valid
    reflectance: object     # mi.Color3f diffuse albedo, 0 where not valid
    shape: object           # mi.Int32 index into the scene's shapes, -1 = miss
    view: object = None     # the scene's camera (spec) the rays came from

    def _image(self, a, dtype, channels: int = 0) -> np.ndarray:
        a = np.asarray(a.numpy(), dtype)
        if channels:
            return np.ascontiguousarray(a.T).reshape(self.height, self.width, self.ss * self.ss, channels)
        return a.reshape(self.height, self.width, self.ss * self.ss)

    @cached_property
    def mask(self) -> np.ndarray:
        """(H, W, ss²) bool: ``valid``."""
        return self._image(self.valid, bool)

    @cached_property
    def view_depth(self) -> np.ndarray:
        """(H, W, ss²) float32: ``distance``."""
        return self._image(self.distance, np.float32)

    @cached_property
    def z_depth(self) -> np.ndarray:
        """(H, W, ss²) float32: ``forward_depth``."""
        return self._image(self.forward_depth, np.float32)

    @cached_property
    def albedo(self) -> np.ndarray:
        """(H, W, ss², 3) float32: ``reflectance``."""
        return self._image(self.reflectance, np.float32, 3)

    @cached_property
    def shape_id(self) -> np.ndarray:
        """(H, W, ss²) int32: ``shape``."""
        return self._image(self.shape, np.int32)

    #: the evaluated Dr.Jit fields (what :meth:`arrays` gives and :meth:`of` takes); ``rays`` stay lazy
    ARRAYS = ("si", "p", "n", "ng", "valid", "distance", "forward_depth", "reflectance", "shape")

    def arrays(self) -> dict:
        """The evaluated Dr.Jit fields by name (:data:`ARRAYS`)."""
        return {k: getattr(self, k) for k in self.ARRAYS}

    @classmethod
    def of(cls, scene, ss: int, arrays: dict, rays=None) -> "GBuffer":
        """The G-buffer of ``scene``'s camera with the Dr.Jit fields ``arrays`` (:meth:`arrays`) and
        the camera rays ``rays`` (None: :func:`camera_rays`, traced anew and left lazy)."""
        W, H = scene.resolution
        rays = camera_rays(scene, ss) if rays is None else rays
        return cls(width=W, height=H, ss=ss, view=scene.spec.camera, rays=rays, **arrays)

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


def gbuffer(scene, ss: int = 1, *, evaluated: bool = True) -> GBuffer:
    """Cast camera rays through pixel (sub-)centres; see module docstring for the layout.
    ``evaluated=False`` leaves the arrays lazy for a caller that evaluates them together with
    more work (:func:`evaluate`) while ``scene`` is alive: the kernel calls Mitsuba's ray tracer
    of the scene, which the lazy arrays do not keep alive.

    >>> from shadowlab.scene import load
    >>> gb = gbuffer(load("contact", resolution=(8, 6)))
    >>> gb.mask.shape, gb.view_depth.shape          # images are (height, width, channels)
    ((6, 8, 1), (6, 8, 1))
    >>> bool(gb.mask.any())
    True
    """

    ray = camera_rays(scene, ss)
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
    dist = dr.select(valid, dr.norm(si.p - cam_o), 0.0)
    zd = dr.select(valid, dr.dot(si.p - cam_o, mi.Vector3f(*[float(x) for x in cam.forward])), 0.0)
    bsdf = si.bsdf(ray)
    alb = bsdf.eval_diffuse_reflectance(si, valid) if hasattr(bsdf, "eval_diffuse_reflectance") else mi.Color3f(0.5)
    alb = dr.select(valid, alb, 0.0)
    sid = dr.select(hit, dr.gather(mi.Int32, scene.shape_index, dr.reinterpret_array(mi.UInt32, si.shape), hit), -1)
    arrays = {"si": si, "p": si.p, "n": n, "ng": ng, "valid": valid, "distance": dist, "forward_depth": zd,
              "reflectance": alb, "shape": sid}
    gb = GBuffer.of(scene, ss, rays=ray, arrays=arrays)
    if evaluated:
        evaluate(gb)
    return gb


def camera_rays(scene, ss: int = 1):
    """The camera rays through the pixel (sub-)centres (mi.Ray3f, lazy), in the G-buffer's point order."""
    W, H = scene.resolution
    return scene.sensor.sample_ray(0.0, 0.5, film_uv(W, H, ss), mi.Point2f(0.5))[0]


def film_uv(width: int, height: int, ss: int = 1):
    """Film coordinates of pixel (sub-)centres in the G-buffer's point order (mi.Point2f), made on
    the device: the values of :func:`shadowlab.render.camera.pixel_uv` rounded to float32,
    computed as one correctly rounded division (2·(x·s + i) + 1) / (2·W·s) of exact integers. The
    division is done in float64 and rounded to float32 once, which is the correctly rounded float32
    quotient (53 ≥ 2·24 + 2 bits) on every backend: CUDA's float32 division is approximate, and
    Dr.Jit turns a division by a literal into a product with its reciprocal (the divisors are
    opaque)."""
    s = int(ss)
    f64 = dr.float64_array_t(mi.Float)
    k = dr.arange(mi.UInt32, width * height * s * s)
    pix, sub = k // (s * s), k % (s * s)
    u = f64(2 * ((pix % width) * s + sub % s) + 1)
    v = f64(2 * ((pix // width) * s + sub // s) + 1)
    return mi.Point2f(mi.Float(u / dr.opaque(f64, 2 * width * s)), mi.Float(v / dr.opaque(f64, 2 * height * s)))


def evaluate(gb: GBuffer, *more) -> None:
    """Evaluate the G-buffer's arrays (and ``more``, e.g. the unshadowed light, in the same
    kernel): the frame's one stage boundary."""
    dr.eval(gb.si, gb.valid, gb.ng, gb.n, gb.distance, gb.forward_depth, gb.reflectance, gb.shape, *more)


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
