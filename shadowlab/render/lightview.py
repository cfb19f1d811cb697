"""Light views: one depth map per light, by casting one Mitsuba ray per texel (DESIGN.md, LightView).

Light cameras (003_b5589b67cce60746.txt §2.2, "Različite vrste svjetla"):

| light kind           | light camera                                                        |
|----------------------|---------------------------------------------------------------------|
| spot                 | perspective from the light's centre, field of view = 2·cone angle   |
| rect, disk           | perspective from the light's centre along its normal, fitted to the |
|                      | scene's bounding box (field of view at most 160°)                   |
| point, sphere        | six 90° perspective faces (a cube map), faces ±x, ±y, ±z            |
| directional          | orthographic, fitted to the scene's bounding sphere (p = c − λ d)   |

A face looks down its +z axis; light-space coordinates are q = (right·(p−o), up·(p−o),
forward·(p−o)). Texel (i, j) of an N×N face covers NDC x ∈ [2i/N − 1, 2(i+1)/N − 1], row j
counts from the top (y = +1). Stored per texel, like a GPU depth buffer:

* ``depth``: NDC depth d ∈ [0, 1] (perspective d = f/(f−n)·(1 − n/z), orthographic
  d = (z−n)/(f−n)), quantised to 16/24-bit UNORM or kept as fp32; 1 where nothing was hit;
* ``z``: the light-space z that the quantised d decodes to (linear depth for PCSS & co.);
* ``slope``: max(|∂d/∂x|, |∂d/∂y|) per texel of the caster's plane, for Direct3D's
  SlopeScaledDepthBias (computed from the hit's geometric normal, not by differencing).

Alpha-tested casters (003 §2.4, "Transparentni objekti"): a texel ray passes through texels of
an ``alpha_texture`` whose alpha is below the shape's ``alpha_cutoff`` (the depth pass's
``discard``), so the map stores the next surface behind a leaf card's holes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..scene import lights as lights_mod
from ..scene.build import transparent

MAX_HALF_FOV = math.radians(80.0)


@dataclass(frozen=True)
class Face:
    origin: tuple       # light camera position (world)
    R: tuple            # rows: right, up, forward (world unit vectors)
    ortho: bool
    scale: float        # tan(half fov) for perspective, half extent (world units) for orthographic
    near: float
    far: float

    def __post_init__(self):  # plain Python floats: Dr.Jit constructors refuse numpy scalars
        object.__setattr__(self, "origin", tuple(float(x) for x in self.origin))
        object.__setattr__(self, "R", tuple(tuple(float(x) for x in row) for row in self.R))
        for k in ("scale", "near", "far"):
            object.__setattr__(self, k, float(getattr(self, k)))


@dataclass(frozen=True)
class Projection:
    """A light camera: its faces and resolution. Pure geometry, no depth."""

    faces: tuple
    res: int
    cube: bool

    def ndc_depth(self, z):
        """Light-space z -> NDC depth in [0, 1] (numpy or Dr.Jit)."""
        f0 = self.faces[0]
        n, f = f0.near, f0.far
        if f0.ortho:
            return (z - n) / (f - n)
        return f / (f - n) * (1.0 - n / z)

    def linear_depth(self, d):
        """NDC depth -> light-space z (inverse of :meth:`ndc_depth`)."""
        f0 = self.faces[0]
        n, f = f0.near, f0.far
        if f0.ortho:
            return n + d * (f - n)
        return n / (1.0 - d * (f - n) / f)


def _frame(fwd, up):
    f = np.asarray(fwd, float)
    f /= np.linalg.norm(f)
    u = np.asarray(lights_mod._up_for(tuple(f), up), float)
    r = np.cross(f, u)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return np.stack([r, u, f])


def _corners(scene):
    """Corners of every non-emitting shape's bounding box (tighter than the scene's box)."""
    return np.array([[x, y, z] for lo, hi in scene.shape_boxes
                     for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _near_far(light, o, scene):
    c = _corners(scene)
    far = float(np.max(np.linalg.norm(c - o, axis=1))) * 1.01 + 1e-3
    lo, hi = np.array(scene.bbox_min), np.array(scene.bbox_max)
    gap = float(np.linalg.norm(np.maximum(0, np.maximum(lo - o, o - hi))))
    near = light.near or max(1e-3 * scene.radius, 0.5 * gap, 0.02 * scene.radius if gap == 0 else 0.0)
    return near, far


def projection(light, scene, res: int | None = None) -> Projection:
    """The light camera of ``light`` in ``scene`` (see the module table)."""
    res = int(res or light.shadow_map)
    kind = light.kind
    if kind == "directional":
        d = np.array(lights_mod.forward(light))
        c, R = np.array(scene.center), scene.radius
        o = c - 2.0 * R * d
        face = Face(tuple(o), tuple(map(tuple, _frame(d, light.up))), True, R, R, 3.0 * R)
        return Projection((face,), res, False)
    o = np.array(light.position, float)
    near, far = _near_far(light, o, scene)
    if kind in ("point", "sphere"):
        faces = []
        for axis in range(3):
            for sign in (1.0, -1.0):
                fwd = np.zeros(3)
                fwd[axis] = sign
                up = (0, 1, 0) if axis != 1 else (0, 0, 1)
                faces.append(Face(tuple(o), tuple(map(tuple, _frame(fwd, up))), False, 1.0, near, far))
        return Projection(tuple(faces), res, True)
    fwd = np.array(lights_mod.forward(light))
    Rm = _frame(fwd, light.up)
    if kind == "spot":
        t = math.tan(math.radians(light.angle))
    else:
        # geometry behind a one-sided area light receives no light from it: fit what is in front
        q = (_corners(scene) - o) @ Rm.T
        q = q[q[:, 2] > near]
        t = math.tan(MAX_HALF_FOV) if not len(q) else \
            min(float(np.max(np.maximum(np.abs(q[:, 0]), np.abs(q[:, 1])) / q[:, 2])) * 1.02, math.tan(MAX_HALF_FOV))
    return Projection((Face(tuple(o), tuple(map(tuple, Rm)), False, t, near, far),), res, False)


def quantise(d: np.ndarray, bits: int) -> np.ndarray:
    """Emulate a depth-buffer format: 16/24-bit UNORM (round to nearest) or 32-bit float."""
    d = np.clip(np.asarray(d, np.float64), 0.0, 1.0)
    if bits == 32:
        return d.astype(np.float32)
    m = float(2 ** bits - 1)
    return (np.round(d * m) / m).astype(np.float32)


@dataclass
class LightView:
    """A light's depth map (all faces) plus Dr.Jit copies for lookups in techniques."""

    light: object
    proj: Projection
    bits: int
    backface: bool
    depth: np.ndarray   # (F, N, N) quantised NDC depth, 1 = empty
    z: np.ndarray       # (F, N, N) decoded light-space depth (far where empty)
    slope: np.ndarray   # (F, N, N) max NDC depth slope per texel
    hit: np.ndarray     # (F, N, N) bool
    _dr: dict = field(default_factory=dict, repr=False)

    @property
    def res(self):
        return self.proj.res

    @property
    def nfaces(self):
        return len(self.proj.faces)

    def dr(self, name: str):
        """Flat Dr.Jit Float of the map ``name`` ('depth', 'z', 'slope'), made once."""
        import mitsuba as mi
        if name not in self._dr:
            self._dr[name] = mi.Float(np.ascontiguousarray(getattr(self, name), np.float32).ravel())
        return self._dr[name]

    def fetch(self, name: str, face, ix, iy):
        """Texel values at integer texel coordinates, clamped to the face (Dr.Jit)."""
        import drjit as dr
        import mitsuba as mi
        N = self.res
        ix = dr.clip(mi.Int32(ix), 0, N - 1)
        iy = dr.clip(mi.Int32(iy), 0, N - 1)
        idx = mi.UInt32(face) * (N * N) + mi.UInt32(iy * N + ix)
        return dr.gather(mi.Float, self.dr(name), idx)

    def lookup(self, p):
        """Project world points ``p`` (mi.Point3f) into the light view (Dr.Jit).

        Returns a dict: ``face`` (UInt32), ``u``, ``v`` (continuous texel coordinates, texel
        centres at i + 0.5), ``z`` (light-space depth), ``d`` (NDC depth, unquantised),
        ``inside`` (in front of the camera and within the face), ``texel`` (world size of
        one texel at that depth).
        """
        import drjit as dr
        import mitsuba as mi
        faces = self.proj.faces
        o = mi.Point3f(*faces[0].origin)
        rel = p - o
        if self.proj.cube:
            ax, ay, az = dr.abs(rel.x), dr.abs(rel.y), dr.abs(rel.z)
            fx = dr.select(rel.x >= 0, 0, 1)
            fy = dr.select(rel.y >= 0, 2, 3)
            fz = dr.select(rel.z >= 0, 4, 5)
            face = mi.UInt32(dr.select((ax >= ay) & (ax >= az), fx, dr.select(ay >= az, fy, fz)))
            Rf = mi.Float(np.asarray([f.R for f in faces], np.float32).ravel())
            row = [mi.Vector3f(*[dr.gather(mi.Float, Rf, face * 9 + 3 * r + c) for c in range(3)]) for r in range(3)]
        else:
            face = mi.UInt32(0)
            R = faces[0].R
            row = [mi.Vector3f(*R[r]) for r in range(3)]
        qx, qy, qz = dr.dot(rel, row[0]), dr.dot(rel, row[1]), dr.dot(rel, row[2])
        f0 = faces[0]
        N = self.res
        if f0.ortho:
            x, y = qx / f0.scale, qy / f0.scale
            texel = mi.Float(2.0 * f0.scale / N)
        else:
            inv = dr.rcp(dr.maximum(qz, 1e-12))
            x, y = qx * inv / f0.scale, qy * inv / f0.scale
            texel = 2.0 * f0.scale * qz / N
        u = (x + 1.0) * 0.5 * N
        v = (1.0 - y) * 0.5 * N
        inside = (qz > f0.near) & (qz < f0.far) & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0)
        d = self.proj.ndc_depth(dr.maximum(qz, 1e-12) if not f0.ortho else qz)
        return {"face": face, "u": u, "v": v, "z": qz, "d": d, "inside": inside, "texel": texel}


def texel_rays(proj: Projection):
    """World-space rays through every texel centre of every face, as numpy (origins, dirs),
    each (F·N·N, 3), in (face, row, column) order."""
    N = proj.res
    c = (np.arange(N) + 0.5) / N * 2.0 - 1.0
    X, Y = np.meshgrid(c, -c, indexing="xy")
    os_, ds_ = [], []
    for f in proj.faces:
        R = np.array(f.R)
        if f.ortho:
            local_o = np.stack([X * f.scale, Y * f.scale, np.zeros_like(X)], -1).reshape(-1, 3)
            o = np.array(f.origin) + local_o @ R
            d = np.broadcast_to(R[2], o.shape)
        else:
            local_d = np.stack([X * f.scale, Y * f.scale, np.ones_like(X)], -1).reshape(-1, 3)
            d = local_d @ R
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            o = np.broadcast_to(np.array(f.origin), d.shape)
        os_.append(o)
        ds_.append(d)
    return np.concatenate(os_), np.concatenate(ds_)


def light_view(scene, light, res: int | None = None, bits: int | None = None, backface: bool = False) -> LightView:
    """Render ``light``'s depth map by ray casting (module docstring has the conventions).

    ``backface=True`` keeps the first surface facing away from the light (front-face culling,
    003_b5589b67cce60746.txt §2.3). The light's own emitter shape never occludes.
    """
    import drjit as dr
    import mitsuba as mi

    proj = projection(light, scene, res)
    bits = int(bits or light.depth_bits)
    N, F = proj.res, len(proj.faces)
    o_np, d_np = texel_rays(proj)
    # start past the light's own surface: spheres at their radius, planar lights just in front
    start = light.radius * 1.001 if light.kind in ("sphere", "point") else 1e-5 * scene.radius
    if proj.faces[0].ortho:
        start = 0.0
    o_np = o_np + d_np * start
    ray = mi.Ray3f(mi.Point3f(*[o_np[:, k].astype(np.float32) for k in range(3)]),
                   mi.Vector3f(*[d_np[:, k].astype(np.float32) for k in range(3)]))
    own = scene.light_shapes.get(light.name)
    shapes = scene.mi_scene.shapes_dr()
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    si = _cast(scene.mi_scene, ray, backface, own_ptr, bool(getattr(scene, "has_alpha", False)))
    hit = si.is_valid()
    # light-space z and the caster's plane in light space
    face_idx = np.repeat(np.arange(F), N * N)
    Rs = np.array([f.R for f in proj.faces])[face_idx]  # (M, 3, 3)
    p = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], 1).astype(np.float64)
    ng = np.stack([si.n.x.numpy(), si.n.y.numpy(), si.n.z.numpy()], 1).astype(np.float64)
    h = hit.numpy()
    f0 = proj.faces[0]
    origins = np.array([f.origin for f in proj.faces])[face_idx]
    rel = p - origins
    q = np.einsum("mij,mj->mi", Rs, rel)
    nl = np.einsum("mij,mj->mi", Rs, ng)
    z = np.where(h, q[:, 2], f0.far)
    n_, f_ = f0.near, f0.far
    with np.errstate(divide="ignore", invalid="ignore"):
        if f0.ortho:
            slope = 2.0 / N * f0.scale * np.maximum(np.abs(nl[:, 0]), np.abs(nl[:, 1])) / (np.abs(nl[:, 2]) * (f_ - n_))
        else:
            B = f_ * n_ / (f_ - n_)
            D = np.abs(np.einsum("mi,mi->m", nl, q))
            slope = 2.0 / N * B * f0.scale * np.maximum(np.abs(nl[:, 0]), np.abs(nl[:, 1])) / D
    slope = np.where(h & np.isfinite(slope), np.minimum(slope, 1.0), 0.0)
    d = np.where(h, proj.ndc_depth(np.clip(z, n_, f_)), 1.0)
    dq = quantise(d, bits)
    zq = np.where(h, proj.linear_depth(dq.astype(np.float64)), f_)
    shp = (F, N, N)
    return LightView(light=light, proj=proj, bits=bits, backface=backface, depth=dq.reshape(shp),
                     z=zq.astype(np.float32).reshape(shp), slope=slope.astype(np.float32).reshape(shp),
                     hit=h.reshape(shp))


MAX_SKIPS = 16         # surfaces a texel ray may skip (the light's own shape, back faces)
MAX_SKIPS_ALPHA = 64   # … in a scene with alpha-tested casters (foliage stacks many cards)


def _cast(mi_scene, ray, backface: bool, own_ptr, alpha: bool = False):
    """First hit along ``ray`` that is not the light's own shape, (with ``backface``) that faces
    away from the ray origin and (``alpha``: the scene has alpha-tested casters) that is not a
    transparent texel. A symbolic loop: at most MAX_SKIPS (MAX_SKIPS_ALPHA) surfaces are
    skipped."""
    return _cast_loop(mi_scene, ray, backface, own_ptr, alpha)


@__import__("drjit").syntax
def _cast_loop(mi_scene, ray, backface, own_ptr, alpha=False):
    import drjit as dr
    import mitsuba as mi
    max_skips = MAX_SKIPS_ALPHA if alpha else MAX_SKIPS
    si = mi_scene.ray_intersect(ray)
    i = mi.UInt32(0)
    skip = _skip(si, ray, backface, own_ptr, alpha)
    while dr.hint(skip & (i < max_skips), max_iterations=-1):
        ray = si.spawn_ray(ray.d)
        si = mi_scene.ray_intersect(ray)
        skip = _skip(si, ray, backface, own_ptr, alpha)
        i += 1
    return si


def _skip(si, ray, backface, own_ptr, alpha=False):
    """Hits a light-view ray passes: the light's own shape; with ``backface`` surfaces facing the
    light (front-face culling); with ``alpha`` transparent texels of alpha-tested
    casters: the fragment shader's ``discard`` of texels with alpha < cutoff (003 §2.4)."""
    import drjit as dr
    import mitsuba as mi
    skip = mi.Bool(False)
    if own_ptr is not None:
        skip |= si.is_valid() & (si.shape == own_ptr)
    if backface:
        skip |= si.is_valid() & (dr.dot(si.n, ray.d) < 0)
    if alpha:
        skip |= transparent(si)
    return skip
