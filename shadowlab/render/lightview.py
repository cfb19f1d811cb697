"""Light views: one depth map per light, by casting one Mitsuba ray per texel (docs/ARCHITECTURE.md, LightView).

Light cameras ([Buljan 2020, §2.2], "Različite vrste svjetla"):

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

The whole shadow pass runs in Dr.Jit: texel rays generated from the texel index (per-face
camera values gathered, or opaque scalars for one face, so a moved light or cascade reuses the
compiled kernel), the casts (skipping, near-plane clipping, further layers, translucent casters)
and the post-processing (depth, format, decoded z, slope, layers, τ) are one kernel, evaluated
once when the view is made; :class:`LightView` holds the flat Dr.Jit arrays that techniques read
(``view.dr(name)``, no upload) and makes numpy copies only when asked (``view.depth`` …). Ray
directions, light space, slopes and depth conversions are computed in Float64 and rounded to
float32 once, as the earlier host-side (numpy float64) implementation did: every texel keeps its
bits (measured on the built-in scenes, every map and every shadow-map technique's visibility
equal), and a stored depth depends only on its float32 hit point. On GPUs whose FP64 rate is
low this post-processing is the place to move to float32 (a few ulp of depth, at UNORM
rounding boundaries one step).

Fits (which part of the scene a map covers) are explicit frozen dataclasses, part of the map's
identity (:meth:`shadowlab.render.frame.FrameContext.light_view` caches per fit):

* :class:`SceneSphere` (the default): the table above, the whole scene;
* :class:`FrustumSlice` (directional lights): the view-depth slice [z0, z1] of the camera's
  frustum, light position p = c − λd from the slice's bounding sphere (or box) centre
  [Buljan 2020, §2.2, §4.2], optionally snapped to whole texels (stable cascades);
* :class:`TileRect`: a square of another fit's NDC [−1, 1]², i.e. one tile of a larger virtual
  map at the same texel grid.

A light may have several maps (one per fit), each :class:`Face` with its own near, far, scale,
NDC shift and matrices (:attr:`Face.view_matrix`, :attr:`Face.proj_matrix`); depth conversions
and :meth:`LightView.lookup` read the face's own values.

Alpha-tested casters ([Buljan 2020, §2.4], "Transparentni objekti"): a texel ray passes through texels of
an ``alpha_texture`` whose alpha is below the shape's ``alpha_cutoff`` (the depth pass's
``discard``), so the map stores the next surface behind a leaf card's holes.

Translucent casters ([Tamás 2015, §6.5]; ``light_view(..., translucent=True)``, in a scene with
translucent shapes): the shadow map stores depth plus colour. ``depth`` is then the first *opaque*
surface (translucent ones are passed), ``trans_rgb`` the product of the τ of every translucent
surface the texel ray crossed before it (the shadow's colour; 1 where none) and ``translucent`` a
LightView of the nearest of them (depth, z, slope; empty where none): a receiver behind it, by the
same biased depth test as an opaque caster's, gets the colour.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from ..scene import lights as lights_mod
from ..scene.build import surface_tau, transparent
from .camera import Camera
from .replay import replayed, uploaded

MAX_HALF_FOV = math.radians(80.0)


@dataclass(frozen=True)
class SceneSphere:
    """The whole scene: the light cameras of the module table (perspective fitted to the shapes'
    boxes, orthographic to the scene's bounding sphere with p = c − 2R·d). The default fit."""


#: where a :class:`FrustumSlice` map's depth range starts (see there)
NEAR_PLANES = ("caster", "light", "pancake")


@dataclass(frozen=True)
class FrustumSlice:
    """The camera-frustum slice between view depths ``z0`` < ``z1`` (m), for a directional light
    [Buljan 2020, §2.2, §4.2, Code A.13].

    * ``bound="sphere"``: the slice's bounding sphere (centre c = mean of its 8 corners, radius r
      = the farthest corner, rounded up to 1/8 m as Code A.13 does), an orthographic square of half
      size r: invariant under camera rotation;
      ``bound="box"``: the square around the corners' light-space bounding rectangle (tighter,
      changes as the camera turns).
    * light position p = c − λd with λ = ``pull`` · r (Code A.13's DistanceFactor);
    * ``snap=True`` moves p across the light direction to whole texels (the map is one texel
      wider, half size r·N/(N − 1), so the slice stays inside), so a camera translation moves the
      map's texel grid only by whole texels: stable cascaded shadow maps.
    * depth range, ``near_plane``: ``"light"`` (Code A.13, §2.2): the view volume starts at the
      light position p (or at the slice's nearest corner where λ < 1 puts p inside the slice) and
      ends at the slice's far side; a caster nearer to the light is clipped (not in the map), so
      a λ too low loses casters and a λ too high spends depth precision;
      ``"pancake"``: the same planes, a caster nearer to the light is clamped onto the near plane
      (depth 0: depth clamping), so none is lost and λ sets only the depth precision;
      ``"caster"``: from the scene's nearest caster toward the light to the slice's far side
      (λ then moves p and both planes together and changes nothing).
    """

    z0: float
    z1: float
    pull: float = 2.0
    snap: bool = False
    bound: str = "sphere"
    near_plane: str = "caster"

    def __post_init__(self):
        for k in ("z0", "z1", "pull"):
            object.__setattr__(self, k, float(getattr(self, k)))
        if not (math.isfinite(self.z0) and math.isfinite(self.z1) and 0 < self.z0 < self.z1):
            raise InputError(f"FrustumSlice: expected view depths 0 < z0 < z1, got z0 = {self.z0}, z1 = {self.z1}")
        if not self.pull > 0:
            raise InputError(f"FrustumSlice: pull (λ in radii of the slice's sphere) must be > 0, got {self.pull}")
        if self.bound not in ("sphere", "box"):
            raise InputError(f"FrustumSlice: bound {self.bound!r}: expected 'sphere' or 'box'")
        if self.near_plane not in NEAR_PLANES:
            raise InputError(f"FrustumSlice: near_plane {self.near_plane!r}: expected one of {', '.join(NEAR_PLANES)}")
        object.__setattr__(self, "snap", bool(self.snap))


@dataclass(frozen=True)
class TileRect:
    """The square [x0, x1] × [y0, y1] of ``base``'s NDC [−1, 1]² (x right, y up) as a map of its
    own: one tile of a virtual map. Rendered at ``res`` texels per side, its texel centres are
    those of a ``base`` map of res · 2 / (x1 − x0) texels where the tile lies on that map's texel
    grid, so its depths equal that larger map's texels there."""

    x0: float
    y0: float
    x1: float
    y1: float
    base: object = SceneSphere()

    def __post_init__(self):
        for k in ("x0", "y0", "x1", "y1"):
            object.__setattr__(self, k, float(getattr(self, k)))
        if not (self.x0 < self.x1 and self.y0 < self.y1):
            raise InputError(f"TileRect: expected x0 < x1 and y0 < y1, got {self.x0, self.y0, self.x1, self.y1}")
        if abs((self.x1 - self.x0) - (self.y1 - self.y0)) > 1e-9 * (self.x1 - self.x0):
            raise InputError(f"TileRect: a tile is square (its map has square texels); got "
                             f"{self.x1 - self.x0} × {self.y1 - self.y0}")
        if not isinstance(self.base, (SceneSphere, FrustumSlice, TileRect, LightSquare)):
            raise InputError(f"TileRect: base {self.base!r} is not a fit (SceneSphere, FrustumSlice, TileRect, "
                             "LightSquare)")

    @property
    def center(self) -> tuple:
        return (0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1))

    @property
    def half(self) -> float:
        return 0.5 * (self.x1 - self.x0)


@dataclass(frozen=True)
class LightSquare:
    """An orthographic map of a directional light over the square of half size ``half`` centred at
    (``cx``, ``cy``) in the light's frame (x right, y up, about the world origin), its depth range
    from the scene's nearest caster toward the light to light-space depth ``z1`` (what it must
    shadow): a focus on the part of the scene the view sees [Giegl 2007, §4.8]."""

    cx: float
    cy: float
    half: float
    z1: float

    def __post_init__(self):
        for k in ("cx", "cy", "half", "z1"):
            object.__setattr__(self, k, float(getattr(self, k)))
        if not (all(math.isfinite(getattr(self, k)) for k in ("cx", "cy", "half", "z1")) and self.half > 0):
            raise InputError(f"LightSquare: expected finite values and half > 0, got {self}")


FITS = (SceneSphere, FrustumSlice, TileRect, LightSquare)


def opaque_values(kind, *values):
    """Python floats as opaque Dr.Jit scalars of type ``kind`` (its scalar type for vectors): they
    enter a kernel as data, so a light camera that moves reuses the compiled kernel. Each equals
    the literal it replaces, and a division by one is written ``x * dr.rcp(v)``, which is what
    Dr.Jit makes of a division by a literal: the results keep their bits. The scalars are made
    once per value (each ``dr.opaque`` is a device write: about 50 per light and render before)."""
    kind = dr.value_t(kind) if dr.depth_v(kind) > 1 else kind
    return [_opaque(kind, float(v)) for v in values]


@functools.lru_cache(maxsize=4096)
def _opaque(kind, value: float):
    return dr.opaque(kind, value)


def face_rows(proj, face):
    """Rows right, up, forward (3 mi.Vector3f) of each point's ``face`` (UInt32): the one face's
    as opaque values, a cube map's gathered from a table of its faces."""
    faces = proj.faces
    if len(faces) == 1:
        return [mi.Vector3f(*opaque_values(mi.Float, *faces[0].R[r])) for r in range(3)]
    table = mi.Float([x for f in faces for row in f.R for x in row])
    return [mi.Vector3f(*[dr.gather(mi.Float, table, face * 9 + 3 * r + c) for c in range(3)]) for r in range(3)]


@dataclass(frozen=True)
class Face:
    origin: tuple       # light camera position (world)
    R: tuple            # rows: right, up, forward (world unit vectors)
    ortho: bool
    scale: float        # tan(half fov) for perspective, half extent (world units) for orthographic
    near: float
    far: float
    shift: tuple = (0.0, 0.0)  # NDC offset: ndc = (x/z or x)/scale − shift (a tile of a larger map)

    def __post_init__(self):  # plain Python floats: Dr.Jit constructors refuse numpy scalars
        object.__setattr__(self, "origin", tuple(float(x) for x in self.origin))
        object.__setattr__(self, "R", tuple(tuple(float(x) for x in row) for row in self.R))
        for k in ("scale", "near", "far"):
            object.__setattr__(self, k, float(getattr(self, k)))
        object.__setattr__(self, "shift", tuple(float(x) for x in self.shift))

    def ndc_depth(self, z):
        """Light-space z -> NDC depth in [0, 1] (numpy or Dr.Jit) with this face's near / far.
        Dr.Jit: the planes enter the kernel opaquely (:func:`opaque_values`)."""
        n, f = self.near, self.far
        if isinstance(z, dr.ArrayBase):
            if self.ortho:
                n_, w = opaque_values(type(z), n, f - n)
                return (z - n_) * dr.rcp(w)
            a, n_ = opaque_values(type(z), f / (f - n), n)
            return a * (1.0 - n_ / z)
        if self.ortho:
            return (z - n) / (f - n)
        return f / (f - n) * (1.0 - n / z)

    def linear_depth(self, d):
        """NDC depth -> light-space z (inverse of :meth:`ndc_depth`)."""
        n, f = self.near, self.far
        if isinstance(d, dr.ArrayBase):
            n_, w, f_ = opaque_values(type(d), n, f - n, f)
            if self.ortho:
                return n_ + d * w
            return n_ / (1.0 - d * w * dr.rcp(f_))
        if self.ortho:
            return n + d * (f - n)
        return n / (1.0 - d * (f - n) / f)

    @property
    def view_matrix(self) -> np.ndarray:
        """World -> light space (x right, y up, looking down +z; q = R (p − o)), 4×4."""
        R = np.array(self.R)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, -R @ np.array(self.origin)
        return M

    @property
    def proj_matrix(self) -> np.ndarray:
        """Light space -> clip, 4×4 (Direct3D depth range): ndc = clip[:3] / clip[3] gives NDC
        x, y ∈ [−1, 1] over the face (y up, texel row 0 at y = +1) and z = :meth:`ndc_depth`."""
        s, (sx, sy), n, f = self.scale, self.shift, self.near, self.far
        if self.ortho:
            return np.array([[1 / s, 0, 0, -sx], [0, 1 / s, 0, -sy],
                             [0, 0, 1 / (f - n), -n / (f - n)], [0, 0, 0, 1]], np.float64)
        return np.array([[1 / s, 0, -sx, 0], [0, 1 / s, -sy, 0],
                         [0, 0, f / (f - n), -f * n / (f - n)], [0, 0, 1, 0]], np.float64)

    @property
    def world_to_clip(self) -> np.ndarray:
        return self.proj_matrix @ self.view_matrix

    @property
    def projection_key(self) -> tuple:
        """What two faces must share to be one projection: kind, scale, near, far and shift."""
        return (self.ortho, self.scale, self.near, self.far, self.shift)


@dataclass(frozen=True)
class Projection:
    """A light camera: its faces and resolution. Pure geometry, no depth."""

    faces: tuple
    res: int
    cube: bool
    fit: object = SceneSphere()

    @property
    def uniform(self) -> bool:
        """All faces share projection kind, near, far, scale and shift (every cube map does)."""
        k = self.faces[0].projection_key
        return all(f.projection_key == k for f in self.faces[1:])

    def ndc_depth(self, z, face=None):
        """Light-space z -> NDC depth in [0, 1] (numpy or Dr.Jit) with the near / far of
        ``face`` (an index, a per-point Dr.Jit UInt32 or numpy array of face indices; None: the
        map's planes, which every face shares unless :attr:`uniform` is False)."""
        return self._per_face(face, "ndc_depth", z)

    def linear_depth(self, d, face=None):
        """NDC depth -> light-space z (inverse of :meth:`ndc_depth`)."""
        return self._per_face(face, "linear_depth", d)

    def _per_face(self, face, fn, x):
        if face is None:
            if not self.uniform:
                raise ValueError("this map's faces have different near / far planes: pass face=")
            return getattr(self.faces[0], fn)(x)
        if isinstance(face, (int, np.integer)):
            return getattr(self.faces[int(face)], fn)(x)
        if self.uniform:
            return getattr(self.faces[0], fn)(x)
        n, f, o = (self.face_param(face, k) for k in ("near", "far", "ortho"))
        if isinstance(face, np.ndarray):
            o = o.astype(bool)
            if fn == "ndc_depth":
                with np.errstate(divide="ignore", invalid="ignore"):
                    return np.where(o, (x - n) / (f - n), f / (f - n) * (1.0 - n / x))
            return np.where(o, n + x * (f - n), n / (1.0 - x * (f - n) / f))
        if fn == "ndc_depth":
            return dr.select(o > 0.5, (x - n) / (f - n), f / (f - n) * (1.0 - n / x))
        return dr.select(o > 0.5, n + x * (f - n), n / (1.0 - x * (f - n) / f))

    def face_param(self, face, name: str):
        """Per-point value of a face parameter (``near``, ``far``, ``scale``, ``ortho``,
        ``shift_x``, ``shift_y``) for face indices ``face`` (numpy array or Dr.Jit UInt32)."""
        vals = [float(f.shift[0] if name == "shift_x" else f.shift[1] if name == "shift_y" else getattr(f, name))
                for f in self.faces]
        if isinstance(face, np.ndarray):
            return np.asarray(vals, np.float64)[face]
        return dr.gather(mi.Float, mi.Float(vals), mi.UInt32(face))

    def matrices(self, face: int = 0) -> tuple:
        """(world -> light view, light view -> clip) 4×4 matrices of ``face``."""
        f = self.faces[face]
        return f.view_matrix, f.proj_matrix


def _frame(fwd, up):
    f = np.asarray(fwd, float)
    f /= np.linalg.norm(f)
    u = np.asarray(lights_mod.up_for(tuple(f), up), float)
    r = np.cross(f, u)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return np.stack([r, u, f])


#: which of a box's (min, max) each of its 8 corners takes per axis, x slowest
_CORNER = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)])


def _corners(scene):
    """Corners of every non-emitting shape's bounding box (tighter than the scene's box), (8·S, 3),
    made once per scene (in ``scene.derived``, where it has one; read-only).

    >>> from types import SimpleNamespace
    >>> _corners(SimpleNamespace(shape_boxes=[((0, 0, 0), (1, 2, 3))]))[[0, 1, 7]].tolist()
    [[0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [1.0, 2.0, 3.0]]
    """
    memo = getattr(scene, "derived", None)
    if memo is not None and "shape_corners" in memo:
        return memo["shape_corners"]
    boxes = np.asarray(scene.shape_boxes, np.float64).reshape(-1, 2, 3)
    c = boxes[:, _CORNER, np.arange(3)].reshape(-1, 3)
    c.flags.writeable = False
    if memo is not None:
        memo["shape_corners"] = c
    return c


def _near_far(light, o, scene):
    c = _corners(scene)
    far = float(np.max(np.linalg.norm(c - o, axis=1))) * 1.01 + 1e-3
    lo, hi = np.array(scene.bbox_min), np.array(scene.bbox_max)
    gap = float(np.linalg.norm(np.maximum(0, np.maximum(lo - o, o - hi))))
    near = light.near or max(1e-3 * scene.radius, 0.5 * gap, 0.02 * scene.radius if gap == 0 else 0.0)
    return near, far


def projection(light, scene, res: int | None = None, fit=None) -> Projection:
    """The light camera of ``light`` in ``scene`` for ``fit`` (None: :class:`SceneSphere`, the
    module table)."""
    res = int(res or light.shadow_map)
    fit = SceneSphere() if fit is None else fit
    if isinstance(fit, SceneSphere):  # the geometry's alone: made once per scene (every frame casts it)
        memo = getattr(scene, "derived", None)
        if memo is None:
            return _scene_sphere(light, scene, res)
        key = ("scene_sphere", light, res)
        if key not in memo:
            memo[key] = _scene_sphere(light, scene, res)
        return memo[key]
    if isinstance(fit, FrustumSlice):
        return _frustum_slice(light, scene, res, fit)
    if isinstance(fit, TileRect):
        return _tile(light, scene, res, fit)
    if isinstance(fit, LightSquare):
        return _light_square(light, scene, res, fit)
    raise InputError(f"light view fit {fit!r}: expected one of {', '.join(f.__name__ for f in FITS)}")


def _frustum_slice(light, scene, res: int, fit: FrustumSlice) -> Projection:
    """Orthographic map of the camera-frustum slice (see :class:`FrustumSlice`)."""
    if light.kind != "directional":
        raise InputError(f"light {light.name!r} is a {light.kind} light: a FrustumSlice fit (an orthographic map "
                         "of a camera-frustum slice) is for directional lights; fit the others with SceneSphere() "
                         "or a TileRect of it")
    corners = Camera.from_scene(scene).frustum_corners(fit.z0, fit.z1)
    Rm = light_frame(light)
    c = corners.mean(axis=0)
    r = float(np.max(np.linalg.norm(corners - c, axis=1)))
    r = math.ceil(r * 8.0) / 8.0                     # Code A.13: radius in steps of 1/8
    q = corners @ Rm.T                               # light-space (about the world origin)
    if fit.bound == "sphere":
        cx, cy, half = float(Rm[0] @ c), float(Rm[1] @ c), r
    else:
        lo, hi = q.min(axis=0), q.max(axis=0)
        cx, cy = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
        half = 0.5 * float(max(hi[0] - lo[0], hi[1] - lo[1])) * 1.0001
    if fit.snap:  # whole-texel steps across the light direction; the centre moves by at most half a
        half *= res / (res - 1.0)  # texel, so the map grows by one texel to keep the slice inside
        t = 2.0 * half / res
        cx, cy = round(cx / t) * t, round(cy / t) * t
    lam = fit.pull * r
    cz = float(Rm[2] @ c) - lam                      # the light position's coordinate along d
    o = Rm[0] * cx + Rm[1] * cy + Rm[2] * cz
    zs = (_corners(scene) - o) @ Rm[2]               # casters toward the light still shadow the slice
    zq = q[:, 2] - cz
    margin = 1e-3 * scene.radius
    if fit.near_plane == "caster":
        near = min(float(zq.min()), float(zs.min())) - margin
    else:                                            # the light's position p, or the slice's nearest corner
        near = min(0.0, float(zq.min())) - margin
    far = float(zq.max()) + margin
    return Projection((Face(tuple(o), tuple(map(tuple, Rm)), True, half, near, far),), res, False, fit)


@functools.lru_cache(maxsize=256)
def light_frame(light) -> np.ndarray:
    """Rows right, up, forward of a light's camera (forward = the direction it faces); read-only,
    made once per light."""
    R = _frame(np.array(lights_mod.forward(light)), light.up)
    R.flags.writeable = False
    return R


def _light_square(light, scene, res: int, fit: LightSquare) -> Projection:
    """Orthographic map of a light-space square (see :class:`LightSquare`)."""
    if light.kind != "directional":
        raise InputError(f"light {light.name!r} is a {light.kind} light: a LightSquare fit (an orthographic map "
                         "of a light-space square) is for directional lights")
    Rm = light_frame(light)
    zs = _corners(scene) @ Rm[2]
    margin = 1e-3 * scene.radius
    cz = float(zs.min()) - margin                    # the light's plane: before every caster
    o = Rm[0] * fit.cx + Rm[1] * fit.cy + Rm[2] * cz
    far = max(fit.z1 - cz, 0.0) + margin
    return Projection((Face(tuple(o), tuple(map(tuple, Rm)), True, fit.half, margin, far),), res, False, fit)


def _tile(light, scene, res: int, fit: TileRect) -> Projection:
    """The square ``fit`` of its base fit's NDC as a map of its own (see :class:`TileRect`)."""
    base = projection(light, scene, res, fit.base)
    (xc, yc), h = fit.center, fit.half
    faces = tuple(Face(f.origin, f.R, f.ortho, f.scale * h, f.near, f.far,
                       ((f.shift[0] + xc) / h, (f.shift[1] + yc) / h)) for f in base.faces)
    return Projection(faces, res, base.cube, fit)


def _scene_sphere(light, scene, res: int) -> Projection:
    """The :class:`SceneSphere` light camera (the module table)."""
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


def quantise(d, bits: int):
    """Emulate a depth-buffer format on NDC depths ``d`` (Dr.Jit Float64 or Float): 16/24-bit
    UNORM (round to nearest, ties to even) or 32-bit float; mi.Float out."""
    d = dr.clip(d, 0.0, 1.0)
    if bits != 32:
        m = float(2 ** bits - 1)
        d = dr.round(d * m) / m
    return mi.Float(d)


#: the per-face values :class:`FaceConstants` holds, in this order
FACE_FIELDS = ("ox", "oy", "oz", "r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22",
               "scale", "near", "far", "shift_x", "shift_y")


class FaceConstants:
    """A light camera's per-face values as Dr.Jit Float64 that enter kernels as data, not literals:
    one opaque scalar each for a one-face map, a table gathered by face index for a cube map. A
    moved light (or a cascade that follows the camera) reuses the compiled light-view kernel."""

    def __init__(self, proj: Projection):
        rows = [[*f.origin, *f.R[0], *f.R[1], *f.R[2], f.scale, f.near, f.far, *f.shift] for f in proj.faces]
        self.ortho = proj.faces[0].ortho
        if any(f.ortho != self.ortho for f in proj.faces):
            raise ValueError("a light view mixes orthographic and perspective faces")
        self._one = [dr.opaque(mi.Float64, v) for v in rows[0]] if len(rows) == 1 else None
        self._table = None if self._one else uploaded(mi.Float64, rows)
        self._cache = {}

    @property
    def data(self):
        """The Dr.Jit arrays the values are read from (the inputs of a kernel that reads them)."""
        return self._one if self._one is not None else self._table

    def get(self, face, name: str):
        """The value ``name`` (a :data:`FACE_FIELDS` entry) of each texel's ``face`` (UInt32)."""
        k = FACE_FIELDS.index(name)
        if self._one is not None:
            return self._one[k]
        if name not in self._cache:
            self._cache[name] = dr.gather(mi.Float64, self._table, face * len(FACE_FIELDS) + k)
        return self._cache[name]

    def origin(self, face):
        return [self.get(face, n) for n in ("ox", "oy", "oz")]

    def rows(self, face):
        """Rows right, up, forward of each texel's face (world unit vectors, 3 × 3 Float64)."""
        return [[self.get(face, f"r{r}{c}") for c in range(3)] for r in range(3)]


def texel_grid(proj: Projection):
    """(face, NDC x, NDC y) of every texel centre of every face, in (face, row, column) order: one
    Dr.Jit wavefront (UInt32, Float64, Float64), NDC shifted by the face's ``shift``."""
    N, F = proj.res, len(proj.faces)
    k = dr.arange(mi.UInt32, F * N * N)
    face = k // (N * N)
    rem = k - face * (N * N)
    row = rem // N
    col = rem - row * N
    c = lambda i: (mi.Float64(i) + 0.5) / N * 2.0 - 1.0  # noqa: E731 - texel centre in NDC
    return face, c(col), -c(row)


def _texel_rays(proj: Projection, consts: FaceConstants):
    """(face, origins, unit directions) of every texel's ray (Float64 lists, origins on the face's
    camera: the light's position, or its plane for orthographic faces)."""
    face, x, y = texel_grid(proj)
    x, y = x + consts.get(face, "shift_x"), y + consts.get(face, "shift_y")
    s = consts.get(face, "scale")
    R, org = consts.rows(face), consts.origin(face)
    xs, ys = x * s, y * s
    if consts.ortho:
        return face, [org[c] + (xs * R[0][c] + ys * R[1][c]) for c in range(3)], R[2]
    d = [xs * R[0][c] + ys * R[1][c] + R[2][c] for c in range(3)]
    norm = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return face, org, [d[c] / norm for c in range(3)]


def texel_rays(proj: Projection):
    """World-space rays through every texel centre of every face, as numpy (origins, dirs),
    each (F·N·N, 3) float64, in (face, row, column) order (what :func:`light_view` casts, before it
    moves the origins along the rays past the light's own surface)."""
    face, o, d = _texel_rays(proj, FaceConstants(proj))
    n = dr.width(face)
    return tuple(np.stack([np.broadcast_to(np.asarray(a.numpy(), np.float64), n) for a in v], 1) for v in (o, d))


@dataclass(eq=False)
class LightView:
    """A light's depth map (all faces) as flat Dr.Jit arrays in (layer,) face, row, column order,
    evaluated once when the view is made; numpy copies of them (same names) are made on demand."""

    light: object
    proj: Projection
    bits: int
    backface: bool
    #: ``depth`` (quantised NDC depth, 1 = empty), ``z`` (decoded light-space depth, far where
    #: empty), ``slope`` (max NDC depth slope per texel): mi.Float; ``hit``: mi.Bool; with layers,
    #: ``layer_depth`` / ``layer_slope`` ((L − 1)·F·N·N: the surfaces behind the first along each
    #: texel's ray, for the rasterizer's bias; depth 1 = none); with translucent casters
    #: ``trans_rgb0`` … ``trans_rgb2`` (the τ product before the first opaque surface)
    maps: dict
    #: translucent casters: the map of the nearest translucent surfaces (a LightView; empty where none)
    translucent: "LightView | None" = None
    _dr: dict = field(default_factory=dict, repr=False)
    _np: dict = field(default_factory=dict, repr=False)

    @property
    def res(self):
        return self.proj.res

    @property
    def fit(self):
        """The fit this map was made for (:class:`SceneSphere`, :class:`FrustumSlice`, :class:`TileRect`)."""
        return self.proj.fit

    @property
    def nfaces(self):
        return len(self.proj.faces)

    @property
    def layers(self) -> int:
        """Surfaces kept per texel: 1, or 1 + the layers behind the first."""
        if "layer_depth" not in self.maps:
            return 1
        return 1 + dr.width(self.maps["layer_depth"]) // (self.nfaces * self.res * self.res)

    def numpy(self, name: str):
        """A map as numpy, (F, N, N) (``layer_depth`` / ``layer_slope``: (L − 1, F, N, N);
        ``trans_rgb``: (F, N, N, 3)), read back once; None where the view has no such map."""
        if name not in self._np:
            shp = (self.nfaces, self.res, self.res)
            if name == "trans_rgb":
                if "trans_rgb0" not in self.maps:
                    return None
                a = np.stack([self.maps[f"trans_rgb{c}"].numpy() for c in range(3)], -1).reshape(*shp, 3)
            elif name not in self.maps:
                return None
            else:
                a = self.maps[name].numpy().reshape(-1, *shp)
                a = a if name.startswith("layer_") else a[0]
            self._np[name] = a
        return self._np[name]

    depth = property(lambda self: self.numpy("depth"), doc="(F, N, N) quantised NDC depth, 1 = empty (numpy)")
    z = property(lambda self: self.numpy("z"), doc="(F, N, N) decoded light-space depth, far where empty (numpy)")
    slope = property(lambda self: self.numpy("slope"), doc="(F, N, N) max NDC depth slope per texel (numpy)")
    hit = property(lambda self: self.numpy("hit"), doc="(F, N, N) bool: the texel's ray met a caster (numpy)")
    layer_depth = property(lambda self: self.numpy("layer_depth"),
                           doc="(L − 1, F, N, N) NDC depth of the surfaces behind the first (1 = none; numpy)")
    layer_slope = property(lambda self: self.numpy("layer_slope"), doc="(L − 1, F, N, N) their slopes (numpy)")
    trans_rgb = property(lambda self: self.numpy("trans_rgb"),
                         doc="(F, N, N, 3) τ product of the translucent casters before the first opaque one (numpy)")

    def dr(self, name: str):
        """The flat Dr.Jit array of the map ``name`` ('depth', 'z', 'slope', 'hit', ...; no upload)
        or of an array :meth:`derived` made."""
        if name in self.maps:
            return self.maps[name]
        return self._dr[name]

    def derived(self, key: str, make):
        """A Dr.Jit array a technique derives from this map (e.g. a filtered depth), made once by
        ``make(self)`` and kept with the map's own arrays under ``key``."""
        if key not in self._dr:
            self._dr[key] = make(self)
        return self._dr[key]

    def fetch(self, name: str, face, ix, iy, layer: int = 0):
        """Texel values at integer texel coordinates, clamped to the face (Dr.Jit); ``layer`` k ≥ 1
        of ``layer_depth`` / ``layer_slope`` is the k-th surface behind the first."""
        N = self.res
        ix = dr.clip(mi.Int32(ix), 0, N - 1)
        iy = dr.clip(mi.Int32(iy), 0, N - 1)
        idx = (mi.UInt32(face) + (layer - 1 if layer else 0) * self.nfaces) * (N * N) + mi.UInt32(iy * N + ix)
        return dr.gather(mi.Float, self.dr(name), idx)

    def tint(self, face, ix, iy):
        """The colour ``trans_rgb`` of texel (ix, iy) of ``face`` (mi.Color3f, clamped like
        :meth:`fetch`; 1 in a view without translucency). Whether a receiver lies behind the
        translucent caster is the biased depth test against :attr:`translucent`
        (``shadow_map.depth_test``), which the caller makes."""
        if "trans_rgb0" not in self.maps:
            return mi.Color3f(1.0)
        return mi.Color3f(*[self.fetch(f"trans_rgb{c}", face, ix, iy) for c in range(3)])

    def lookup(self, p):
        """Project world points ``p`` (mi.Point3f) into the light view (Dr.Jit).

        Returns a dict: ``face`` (UInt32), ``u``, ``v`` (continuous texel coordinates, texel
        centres at i + 0.5), ``z`` (light-space depth), ``d`` (NDC depth, unquantised),
        ``inside`` (in front of the camera and within the face), ``texel`` (world size of
        one texel at that depth).
        """
        faces = self.proj.faces
        f0 = faces[0]
        o = mi.Point3f(*opaque_values(mi.Float, *f0.origin))
        rel = p - o
        if self.proj.cube:
            ax, ay, az = dr.abs(rel.x), dr.abs(rel.y), dr.abs(rel.z)
            fx = dr.select(rel.x >= 0, 0, 1)
            fy = dr.select(rel.y >= 0, 2, 3)
            fz = dr.select(rel.z >= 0, 4, 5)
            face = mi.UInt32(dr.select((ax >= ay) & (ax >= az), fx, dr.select(ay >= az, fy, fz)))
        else:
            face = mi.UInt32(0)
        row = face_rows(self.proj, face)
        qx, qy, qz = dr.dot(rel, row[0]), dr.dot(rel, row[1]), dr.dot(rel, row[2])
        N = self.res
        uniform = self.proj.uniform
        if uniform:  # one set of planes for the map (every cube map): opaque scalars
            shifted = f0.shift != (0.0, 0.0)
            s, near, far, sx, sy = opaque_values(mi.Float, f0.scale, f0.near, f0.far, *f0.shift)
            texel_k = opaque_values(mi.Float, 2.0 * f0.scale / N if f0.ortho else 2.0 * f0.scale)[0]
        else:        # each face its own: gathered per point
            if any(f.ortho != f0.ortho for f in faces):
                raise ValueError("a light view mixes orthographic and perspective faces")
            s, near, far, sx, sy = (
                self.proj.face_param(face, k) for k in ("scale", "near", "far", "shift_x", "shift_y")
            )
            texel_k = 2.0 * s / N if f0.ortho else 2.0 * s
            shifted = True
        over_s = (lambda a: a * dr.rcp(s)) if uniform else (lambda a: a / s)  # noqa: E731 - as a literal divides
        if f0.ortho:
            x, y = over_s(qx), over_s(qy)
            texel = mi.Float(texel_k)
        else:
            inv = dr.rcp(dr.maximum(qz, 1e-12))
            x, y = over_s(qx * inv), over_s(qy * inv)
            texel = texel_k * qz / N
        if shifted:
            x, y = x - sx, y - sy
        u = (x + 1.0) * 0.5 * N
        v = (1.0 - y) * 0.5 * N
        inside = (qz > near) & (qz < far) & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0)
        d = self.proj.ndc_depth(dr.maximum(qz, 1e-12) if not f0.ortho else qz, face=None if uniform else face)
        return {"face": face, "u": u, "v": v, "z": qz, "d": d, "inside": inside, "texel": texel}


def light_view(scene, light, res: int | None = None, bits: int | None = None, backface: bool = False,
               fit=None, layers: int = 1, translucent: bool = False) -> LightView:
    """Render ``light``'s depth map by ray casting (module docstring has the conventions).

    ``backface=True`` keeps the first surface facing away from the light (front-face culling,
    [Buljan 2020, §2.3]). The light's own emitter shape never occludes, nor does a surface that
    casts no shadow (``casts_shadows``: the rays are cast in :attr:`Scene.casters`).
    ``fit``: which part of the scene the map covers (None: :class:`SceneSphere`).
    ``layers`` > 1 also keeps the next ``layers`` − 1 surfaces along each texel's ray (same
    skipping rules), so that a rasterizer's bias, added to every fragment before the depth test,
    can be emulated (:func:`shadowlab.techniques.shadow_map.stored_depth`).
    ``translucent`` (a scene with translucent shapes): the depth of the first opaque surface, the
    translucent casters' colour in ``trans_rgb`` and a view of the nearest of them in
    ``translucent`` (module docstring).

    One Dr.Jit wavefront over every texel of every face (and layer): rays, casts and depth
    formats are traced into one kernel and evaluated once, when the view is returned.
    """

    return light_views(scene, light, [fit], res=res, bits=bits, backface=backface, layers=layers,
                       translucent=translucent)[0]


@dataclass
class _Cast:
    """What one light view's kernel reads (a camera of ``projection``) and the Python values its
    trace depends on (``key``)."""

    proj: Projection
    consts: FaceConstants
    t0: object
    clip_plane: object
    own_ptr: object
    bits: int
    key: tuple


def light_views(scene, light, fits, res: int | None = None, bits: int | None = None, backface: bool = False,
                layers: int = 1, translucent: bool = False) -> list:
    """:func:`light_view` for each fit of ``fits`` (None: :class:`SceneSphere`) of ``light`` (a
    LightSpec, or a list of them, one per fit), cast together (:func:`cast_views`)."""
    lights = list(light) if isinstance(light, (list, tuple)) else [light] * len(fits)
    return cast_views(scene, [ViewRequest(l, f, res, bits, backface, layers, translucent)
                              for l, f in zip(lights, fits)])


@dataclass(frozen=True)
class ViewRequest:
    """One light view to cast: :func:`light_view`'s arguments (``light`` a LightSpec)."""

    light: object
    fit: object = None
    res: int | None = None
    bits: int | None = None
    backface: bool = False
    layers: int = 1
    translucent: bool = False


def cast_views(scene, requests) -> list:
    """The light views of ``requests`` (:class:`ViewRequest`), cast in one stage: one evaluation and
    one replay, which walks the scene's arrays once for every light, fit, map size and depth format
    (what differs between the views is in the stage's key; views of one size share a kernel)."""
    owner, scene = scene, scene.casters  # the map holds what casts shadows (``casts_shadows``)
    shapes = scene.mi_scene.shapes_dr()
    alpha = bool(getattr(scene, "has_alpha", False))
    table = scene.translucency() if getattr(scene, "has_translucent", False) else None
    tables = [table if q.translucent else None for q in requests]
    casts = [_prepare(scene, q.light, projection(q.light, scene, q.res, q.fit), int(q.bits or q.light.depth_bits),
                      shapes) for q in requests]

    def stage(*_inputs):  # the arrays it reads are the inputs; the rest is the key's
        views = [_cast_view(scene, c.proj, c.consts, c.bits, c.t0, bool(q.backface), c.own_ptr, alpha, tb,
                            c.clip_plane, int(q.layers)) for c, q, tb in zip(casts, requests, tables)]
        dr.eval(views)  # the light views are a stage boundary: one evaluation of every map
        return views

    # the lights and their cameras are inputs (t0, consts, clip_plane, own panel): moved lights replay
    key = tuple(c.key + (bool(q.backface), alpha, tb is not None, int(q.layers))
                for c, q, tb in zip(casts, requests, tables))
    views = replayed("light_view", key, stage, owner, scene.mi_scene, [c.consts.data for c in casts],
                     [c.t0 for c in casts], [c.own_ptr for c in casts], table if any(t is not None for t in tables)
                     else None, [c.clip_plane for c in casts])
    out = []
    for q, c, (maps, near) in zip(requests, casts, views):
        near = None if near is None else LightView(light=q.light, proj=c.proj, bits=c.bits, backface=q.backface,
                                                   maps=near)
        out.append(LightView(light=q.light, proj=c.proj, bits=c.bits, backface=q.backface, maps=maps,
                             translucent=near))
    return out


def _prepare(scene, light, proj, bits: int, shapes) -> _Cast:
    """The inputs of ``light``'s cast through ``proj``: its camera values, where its rays start, its
    clipping plane, its own panel among ``shapes`` (the scene's shape pointers; None without one)."""
    f0 = proj.faces[0]
    # start past the light's own surface: spheres at their radius, planar lights just in front
    start = light.radius * 1.001 if light.kind in ("sphere", "point") else 1e-5 * scene.radius
    clip = False
    if f0.ortho:  # orthographic rays start on the near plane or at the light's position
        start = min(0.0, f0.near)
        # a FrustumSlice whose near plane is the light's: rays start before the nearest caster, a plane
        # fixed in the world (from the near plane, which moves with the camera, hits would shift by
        # float rounding and stable cascades shimmer); "pancake" clamps a hit before the near plane
        # onto it (_texel_depths), "light" casts such a texel again from the near plane (clips it)
        clip = isinstance(proj.fit, FrustumSlice) and proj.fit.near_plane == "light"
        if isinstance(proj.fit, FrustumSlice) and proj.fit.near_plane != "caster":
            start = min(start, float(np.min((_corners(scene) - np.array(f0.origin)) @ np.array(f0.R[2])))
                        - 1e-3 * scene.radius)
    own = scene.light_shapes.get(light.name)
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    return _Cast(proj, FaceConstants(proj), dr.opaque(mi.Float64, start), _clip_plane(f0) if clip else None,
                 own_ptr, bits, (proj.res, len(proj.faces), f0.ortho, clip, bits, own is not None))


def _cast_view(scene, proj, consts, bits, t0, backface, own_ptr, alpha, table, clip_plane, layers):
    """One light view's maps and the nearest translucent casters' maps (or None), not evaluated."""
    face, o64, d64 = _texel_rays(proj, consts)
    d = mi.Vector3f(*[mi.Float(a) for a in d64])
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o64[c] + d64[c] * t0) for c in range(3)]), d)
    maps, near = {}, None
    if table is None:
        si = cast_first_hit(scene.mi_scene, ray, backface, own_ptr, alpha,
                            near_clip=_near_clip(o64, d64, d, clip_plane) if clip_plane else None)
    else:
        si, tau, first = cast_translucent(scene.mi_scene, ray, backface, own_ptr, alpha, table)
        h, s, dq, zq = _texel_depths(proj, consts, face, first, bits)
        near = {"depth": dq, "z": zq, "slope": s, "hit": h}
        maps.update({f"trans_rgb{c}": mi.Float(tau[c]) for c in range(3)})
    h, s, dq, zq = _texel_depths(proj, consts, face, si, bits)
    maps.update({"depth": dq, "z": zq, "slope": s, "hit": h})
    ld, ls, before = [], [], h
    for _ in range(layers - 1):  # each layer continues the previous one's rays, in the same kernel
        si = cast_first_hit(scene.mi_scene, si.spawn_ray(ray.d), backface, own_ptr, alpha)
        hk, sk, dk, _ = _texel_depths(proj, consts, face, si, bits)
        hk &= before                 # a ray that already left the scene meets nothing more
        ld.append(dr.select(hk, dk, 1.0))
        ls.append(dr.select(hk, sk, 0.0))
        before = hk
    if ld:
        maps.update({"layer_depth": dr.concat(ld), "layer_slope": dr.concat(ls)})
    return maps, near


def _clip_plane(f0):
    """The near plane of an orthographic face as opaque data: (ray start along the texel rays, the
    camera's position, forward axis, near distance)."""
    return (dr.opaque(mi.Float64, min(0.0, f0.near)), mi.Point3f(*[dr.opaque(mi.Float, x) for x in f0.origin]),
            mi.Vector3f(*[dr.opaque(mi.Float, x) for x in f0.R[2]]), dr.opaque(mi.Float, f0.near))


def _near_clip(o64, d64, d, clip_plane):
    """:func:`cast_first_hit`'s ``near_clip`` for an orthographic face: each texel's ray from the
    near plane, and the plane (:func:`_clip_plane`)."""
    t_near, origin, forward, near = clip_plane
    o_near = mi.Point3f(*[mi.Float(o64[c] + d64[c] * t_near) for c in range(3)])
    return (mi.Ray3f(o_near, d), origin, forward, near)


def _texel_depths(proj, consts: FaceConstants, face, si, bits):
    """(hit, slope, quantised NDC depth, decoded light-space z) of every texel's hit ``si``
    (hit: mi.Bool, the others mi.Float). Light space, slopes and depth conversions run in Float64
    (rounded to float32 once, at the end), as a host-side reference would: a texel's stored depth
    then depends only on its float32 hit point."""
    N = proj.res
    hit = si.is_valid()
    F64 = mi.Float64
    p, ng = [F64(si.p[c]) for c in range(3)], [F64(si.n[c]) for c in range(3)]
    R, org = consts.rows(face), consts.origin(face)
    rel = [p[c] - org[c] for c in range(3)]
    q = [R[r][0] * rel[0] + R[r][1] * rel[1] + R[r][2] * rel[2] for r in range(3)]
    nl = [R[r][0] * ng[0] + R[r][1] * ng[1] + R[r][2] * ng[2] for r in range(3)]
    n_, f_, sc = (consts.get(face, k) for k in ("near", "far", "scale"))
    z = dr.select(hit, q[2], f_)
    m = dr.maximum(dr.abs(nl[0]), dr.abs(nl[1]))
    if consts.ortho:
        slope = 2.0 / N * sc * m / (dr.abs(nl[2]) * (f_ - n_))
    else:
        B = f_ * n_ / (f_ - n_)
        slope = 2.0 / N * B * sc * m / dr.abs(nl[0] * q[0] + nl[1] * q[1] + nl[2] * q[2])
    slope = dr.select(hit & dr.isfinite(slope), dr.minimum(slope, 1.0), 0.0)
    zc = dr.clip(z, n_, f_)
    if consts.ortho:
        d = (zc - n_) / (f_ - n_)
    else:
        d = f_ / (f_ - n_) * (1.0 - n_ / zc)
    dq = quantise(dr.select(hit, d, 1.0), bits)
    dq64 = F64(dq)
    zq = n_ + dq64 * (f_ - n_) if consts.ortho else n_ / (1.0 - dq64 * (f_ - n_) / f_)
    return hit, mi.Float(slope), dq, mi.Float(dr.select(hit, zq, f_))


MAX_SKIPS = 16         # surfaces a texel ray may skip (the light's own shape, back faces)
MAX_SKIPS_ALPHA = 64   # … in a scene with alpha-tested casters (foliage stacks many cards)


def cast_first_hit(mi_scene, ray, backface: bool, own_ptr, alpha: bool = False, *, active=True, near_clip=None):
    """First hit along ``ray`` that is not the light's own shape, (with ``backface``) that faces
    away from the ray origin and (``alpha``: the scene has alpha-tested casters) that is not a
    transparent texel. A symbolic loop: at most MAX_SKIPS (MAX_SKIPS_ALPHA) surfaces are
    skipped. Rays where ``active`` is False are not cast (no hit).

    ``near_clip`` = (ray_near, origin, forward, near): a first hit whose light-space depth
    (forward·(p − origin)) lies before ``near`` is cast again along ``ray_near`` (from the near
    plane, with a fresh skip budget): the casters nearer to the light are clipped, as a
    rasterizer's depth clip does; in the same loop, so a clipped map costs no second wavefront."""
    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):  # one trace of the loop body (Mitsuba's
        if near_clip is None:                                     # intersection over every shape), not two
            return _cast_loop(mi_scene, ray, backface, own_ptr, alpha, mi.Bool(active))
        return _cast_clipped(mi_scene, ray, backface, own_ptr, alpha, mi.Bool(active), *near_clip)


def cast_flags(alpha: bool):
    """What a cast computes of each hit: position, geometric normal, shape (and its uv where
    alpha-tested casters read their texture); the rest of a SurfaceInteraction is not needed."""
    return mi.RayFlags.Minimal | mi.RayFlags.UV if alpha else mi.RayFlags.Minimal


@dr.syntax
def _cast_loop(mi_scene, ray, backface, own_ptr, alpha, active):
    max_skips = MAX_SKIPS_ALPHA if alpha else MAX_SKIPS
    flags = cast_flags(alpha)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray))
    first = mi.Bool(active)      # the first intersection is the loop's first step (traced once)
    skip = mi.Bool(False)
    i = mi.UInt32(0)
    while dr.hint(first | (skip & (i < max_skips)), max_iterations=-1):
        ray = dr.select(first, ray, si.spawn_ray(ray.d))
        i = dr.select(first, i, i + 1)
        first = mi.Bool(False)
        si = mi_scene.ray_intersect(ray, flags, False, True)
        skip = _skip(si, ray, backface, own_ptr, alpha)
    return si


@dr.syntax
def _cast_clipped(mi_scene, ray, backface, own_ptr, alpha, active, ray_near, origin, forward, near):
    max_skips = MAX_SKIPS_ALPHA if alpha else MAX_SKIPS
    flags = cast_flags(alpha)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray))
    first = mi.Bool(active)
    skip, redo, clipped = mi.Bool(False), mi.Bool(False), mi.Bool(False)
    i = mi.UInt32(0)
    while dr.hint(first | ((skip | redo) & (i < max_skips)), max_iterations=-1):
        ray = dr.select(first, ray, dr.select(redo, ray_near, si.spawn_ray(ray.d)))
        i = dr.select(first | redo, 0, i + 1)
        clipped |= redo
        first = mi.Bool(False)
        si = mi_scene.ray_intersect(ray, flags, False, True)
        skip = _skip(si, ray, backface, own_ptr, alpha)
        redo = ~skip & ~clipped & si.is_valid() & (dr.dot(si.p - origin, forward) < near)
    return si


def cast_translucent(mi_scene, ray, backface, own_ptr, alpha, table):
    """:func:`cast_first_hit` passing translucent surfaces too: (first opaque hit, τ product of
    the translucent surfaces crossed before it (mi.Color3f), the first translucent hit as a
    :class:`_Hit` (not valid where there was none)). One trace of the loop (see there)."""
    with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, False):
        return _cast_translucent(mi_scene, ray, backface, own_ptr, alpha, table)


@dr.syntax
def _cast_translucent(mi_scene, ray, backface, own_ptr, alpha, table):
    flags = cast_flags(alpha)
    n = dr.width(ray)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    first_p, first_n, found = dr.zeros(mi.Point3f, n), dr.zeros(mi.Vector3f, n), dr.zeros(mi.Bool, n)
    tau, tau_s = mi.Color3f(1.0), mi.Color3f(1.0)
    i = mi.UInt32(0)
    first = mi.Bool(True)        # the first intersection is the loop's first step (traced once)
    trans, own = mi.Bool(False), mi.Bool(False)
    while dr.hint(first | ((own | trans) & (i < MAX_SKIPS_ALPHA)), max_iterations=-1):
        tau = dr.select(trans, tau * tau_s, tau)
        new = trans & ~found
        first_p = dr.select(new, si.p, first_p)
        first_n = dr.select(new, si.n, first_n)
        found |= trans
        ray = dr.select(first, ray, si.spawn_ray(ray.d))
        i = dr.select(first, i, i + 1)
        first = mi.Bool(False)
        si = mi_scene.ray_intersect(ray, flags, False, True)
        trans, tau_s = surface_tau(si, table)
        own = _skip(si, ray, backface, own_ptr, alpha) & ~trans
    return si, tau, _Hit(first_p, first_n, found)


@dataclass
class _Hit:
    """The fields of a hit that :func:`_texel_depths` reads."""

    p: object
    n: object
    valid: object

    def is_valid(self):
        return self.valid


def _skip(si, ray, backface, own_ptr, alpha=False):
    """Hits a light-view ray passes: the light's own shape; with ``backface`` surfaces facing the
    light (front-face culling); with ``alpha`` transparent texels of alpha-tested
    casters: the fragment shader's ``discard`` of texels with alpha < cutoff ([Buljan 2020, §2.4])."""
    skip = mi.Bool(False)
    if own_ptr is not None:
        skip |= si.is_valid() & (si.shape == own_ptr)
    if backface:
        skip |= si.is_valid() & (dr.dot(si.n, ray.d) < 0)
    if alpha:
        skip |= transparent(si)
    return skip
