"""Screen-space access: the G-buffer as Dr.Jit arrays on the pixel grid, with the camera's projection.

A technique that works in screen space (neighbour gathers, separable blurs with depth rejection,
screen ↔ world) reads ``frame.screen`` (a :class:`Screen`, made once per frame) and stays in
Dr.Jit: no numpy round trip between passes.

Layout. Values are flat Dr.Jit arrays in the **G-buffer's point order** (what techniques compute
per shading point): point k is pixel ((k // s²) % W, (k // s²) // W), sub-pixel k % s²
(:func:`shadowlab.render.camera.pixel_uv`). The screen's grid is the sub-pixel grid:
``width`` = W·s, ``height`` = H·s columns and rows, grid pixel (X, Y) = (x·s + k % s,
y·s + k // s), its centre at continuous grid coordinates (X + ½, Y + ½) (y down from the top
row); with s = 1 it is the image. :meth:`Screen.index` maps grid coordinates to points.

Fields (per point): ``depth`` (view depth, camera-space z along the camera's forward axis, 0 where
no surface), ``normal`` (shading normal facing the camera), ``position`` (world), ``valid``.
:meth:`Screen.texture` gives any of them (or any per-point array) as an ``mi.Texture2f`` over the
grid for bilinear lookups at film uv.

>>> from shadowlab import backend
>>> _ = backend.init()
>>> import numpy as np
>>> from shadowlab.render.camera import Camera
>>> scr = Screen.from_depth(Camera((0, 0, 5), (0, 0, 0), fov=60, width=8, height=6), np.full((6, 8), 5.0))
>>> v = scr.blur(scr.depth, 3, "x", depth_sigma=0.05)
>>> bool(np.allclose(v.numpy(), 5.0))
True
"""

from __future__ import annotations


import drjit as dr
import mitsuba as mi
import numpy as np

from .camera import Camera

__all__ = ["Screen"]

FIELDS = ("depth", "normal", "position", "valid")


class Screen:
    """Per-point G-buffer fields as Dr.Jit arrays on the (sub-)pixel grid of ``camera``."""

    def __init__(self, camera: Camera, ss: int, position, normal, valid):
        self.camera = camera
        self.ss = int(ss)
        self.width, self.height = camera.width * self.ss, camera.height * self.ss
        self.position = mi.Point3f(position)
        self.normal = mi.Vector3f(normal)
        self.valid = mi.Bool(valid)
        o = mi.Point3f(*[float(x) for x in camera.position])
        fwd = mi.Vector3f(*[float(x) for x in camera.forward])
        self.depth = dr.select(self.valid, dr.dot(self.position - o, fwd), 0.0)
        if dr.width(self.depth) != self.width * self.height:
            raise ValueError(f"{dr.width(self.depth)} points for a {self.width}×{self.height} screen")
        dr.eval(self.position, self.normal, self.valid, self.depth)
        self._tex = {}
        # grid coordinates of every point (G-buffer order)
        s, W = self.ss, camera.width
        k = dr.arange(mi.UInt32, self.width * self.height)
        pix, sub = k // (s * s), k % (s * s)
        self.x = mi.Int32((pix % W) * s + sub % s)
        self.y = mi.Int32((pix // W) * s + sub // s)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_frame(cls, frame) -> "Screen":
        """The screen of a :class:`~shadowlab.render.frame.FrameContext`'s G-buffer (Mitsuba or
        cone traced): ``frame.screen`` caches it."""
        gb = frame.gbuffer
        return cls(frame.camera, gb.ss, gb.p, gb.n, gb.valid)

    @classmethod
    def from_depth(cls, camera: Camera, depth, normal=None) -> "Screen":
        """A screen from a view-depth image (H, W) (numpy; 0 or non-finite = no surface) and
        optional normals (H, W, 3): positions are unprojected pixel centres. For tests and for
        depth that does not come from a G-buffer."""
        z = np.asarray(depth, np.float64)
        H, W = z.shape
        if (W, H) != camera.resolution:
            raise ValueError(f"depth image {W}×{H} for a {camera.width}×{camera.height} camera")
        ok = np.isfinite(z) & (z > 0)
        py, px = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
        p = camera.unproject(px.ravel(), py.ravel(), np.where(ok, z, 1.0).ravel())
        n = (
            np.broadcast_to(-camera.forward, p.shape)
            if normal is None
            else np.asarray(normal, np.float64).reshape(-1, 3)
        )
        f32 = lambda a: [np.ascontiguousarray(a[:, i], np.float32) for i in range(3)]  # noqa: E731
        return cls(camera, 1, mi.Point3f(*f32(p)), mi.Vector3f(*f32(n)), mi.Bool(ok.ravel()))

    # -- indexing ----------------------------------------------------------------------------
    def index(self, x, y):
        """Point index (G-buffer order) of grid pixel (x, y), both clamped to the grid (Dr.Jit)."""
        s, W = self.ss, self.camera.width
        x = mi.UInt32(dr.clip(mi.Int32(x), 0, self.width - 1))
        y = mi.UInt32(dr.clip(mi.Int32(y), 0, self.height - 1))
        return ((y // s) * W + x // s) * (s * s) + (y % s) * s + x % s

    def field(self, f):
        """A field by name (``depth``, ``normal``, ``position``, ``valid``) or a per-point array as is."""
        if isinstance(f, str):
            if f not in FIELDS:
                raise ValueError(f"screen field {f!r}: expected one of {', '.join(FIELDS)} or a per-point array")
            return getattr(self, f)
        return f

    def gather(self, f, dx, dy):
        """The value of ``f`` (a field name or per-point array) at each point's grid neighbour
        (x + dx, y + dy), clamped to the grid; ``dx``, ``dy`` ints or per-point Int32."""
        v = self.field(f)
        return dr.gather(type(v), v, self.index(self.x + dx, self.y + dy))

    def blur(self, values, radius_px: int, axis: str, *, sigma: float | None = None,
             depth_sigma: float | None = None, normal_power: float | None = None):
        """One pass of a separable Gaussian along ``axis`` (``"x"`` or ``"y"``) over the grid.

        Taps k = −radius … radius (grid pixels, clamped at the border) weigh
        exp(−k² / 2σ²) (``sigma`` default radius / 2); points without a surface take no part.
        ``depth_sigma`` rejects taps across depth discontinuities: a tap at view depth z_k
        seen from a point at z weighs exp(−½ ((z_k − z) / (depth_sigma · z))²) more (a relative
        depth tolerance); ``normal_power`` multiplies by max(0, n·n_k)^power. A point whose taps
        all vanish keeps its value. Returns an array like ``values``, G-buffer order."""
        r = int(radius_px)
        if r < 0:
            raise ValueError(f"blur radius {radius_px!r}: expected a non-negative number of pixels")
        if axis not in ("x", "y"):
            raise ValueError(f"blur axis {axis!r}: expected 'x' or 'y'")
        v = self.field(values)
        if r == 0:
            return type(v)(v)
        sg = float(sigma) if sigma is not None else max(r / 2.0, 1e-6)
        # the settings enter the kernel opaquely: a new sigma or tolerance reuses the compiled kernel
        inv_s2 = dr.opaque(mi.Float, 1.0 / (sg * sg))
        inv_dz = dr.opaque(mi.Float, 1.0 / float(depth_sigma)) if depth_sigma is not None else None
        npow = dr.opaque(mi.Float, float(normal_power)) if normal_power is not None else None
        z0, n0 = self.depth, self.normal
        acc, wsum = dr.zeros(type(v), dr.width(v)), dr.zeros(type(z0), dr.width(z0))
        for k in range(-r, r + 1):  # a loop over kernel taps (a fixed, small kernel), not over pixels
            idx = self.index(self.x + (k if axis == "x" else 0), self.y + (k if axis == "y" else 0))
            w = dr.select(dr.gather(type(self.valid), self.valid, idx), dr.exp(-0.5 * (k * k) * inv_s2), 0.0)
            if inv_dz is not None:
                zk = dr.gather(type(z0), z0, idx)
                t = (zk - z0) * inv_dz / dr.maximum(z0, 1e-12)
                w = w * dr.exp(-0.5 * t * t)
            if npow is not None:
                nk = dr.gather(type(n0), n0, idx)
                w = w * dr.power(dr.maximum(dr.dot(n0, nk), 0.0), npow)
            acc += dr.gather(type(v), v, idx) * w
            wsum += w
        keep = self.valid & (wsum > 0)
        return dr.select(keep, acc / dr.select(keep, wsum, 1.0), v)

    def texture(self, f):
        """``f`` (a field name or per-point array) as an ``mi.Texture2f`` over the grid (H, W, C),
        bilinear, clamped; look it up at film uv with ``tex.eval(mi.Point2f(u, v))``. Named
        fields are made once."""
        if isinstance(f, str) and f in self._tex:
            return self._tex[f]
        v = self.field(f)
        chans = [v[c] for c in range(len(v))] if dr.is_array_v(v) and dr.size_v(v) > 1 else [v]
        C, N = len(chans), self.width * self.height
        buf = dr.zeros(mi.Float, N * C)
        texel = mi.UInt32(self.y * self.width + self.x) * C
        for c, vc in enumerate(chans):                         # channels, not pixels
            dr.scatter(buf, mi.Float(vc), texel + c)
        tex = mi.Texture2f(mi.TensorXf(buf, (self.height, self.width, C)), filter_mode=dr.FilterMode.Linear,
                           wrap_mode=dr.WrapMode.Clamp)
        if isinstance(f, str):
            self._tex[f] = tex
        return tex

    def to_image(self, values) -> np.ndarray:
        """Per-point values -> numpy grid image (height, width[, C])."""
        a = np.asarray(values.numpy() if hasattr(values, "numpy") else values)
        a = a.T if a.ndim == 2 and a.shape[0] != self.width * self.height else a
        img = np.empty((self.height, self.width) + a.shape[1:], a.dtype)
        img[self.y.numpy(), self.x.numpy()] = a
        return img

    # -- screen <-> world --------------------------------------------------------------------
    def project(self, p):
        """World points (mi.Point3f) -> (px, py, view depth) in continuous grid coordinates (pixel
        centres at i + ½, y down) (Dr.Jit)."""
        c = self.camera
        rel = p - mi.Point3f(*[float(x) for x in c.position])
        z = dr.dot(rel, mi.Vector3f(*[float(x) for x in c.forward]))
        x = dr.dot(rel, mi.Vector3f(*[float(x) for x in c.right])) / (z * c.tan_x)
        y = dr.dot(rel, mi.Vector3f(*[float(x) for x in c.up])) / (z * c.tan_y)
        return (x + 1.0) * (0.5 * self.width), (1.0 - y) * (0.5 * self.height), z

    def unproject(self, px, py, depth):
        """Continuous grid coordinates + view depth -> world points (mi.Point3f) (Dr.Jit)."""
        c = self.camera
        x = (2.0 * mi.Float(px) / self.width - 1.0) * c.tan_x * depth
        y = (1.0 - 2.0 * mi.Float(py) / self.height) * c.tan_y * depth
        v = lambda a: mi.Vector3f(*[float(t) for t in a])  # noqa: E731
        return mi.Point3f(*[float(t) for t in c.position]) + v(c.forward) * depth + v(c.right) * x + v(c.up) * y

    def film_uv(self, px, py):
        """Continuous grid coordinates -> film uv (the texture's coordinates)."""
        return mi.Point2f(mi.Float(px) / self.width, mi.Float(py) / self.height)
