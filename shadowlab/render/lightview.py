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

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from ..scene import lights as lights_mod
from ..scene.build import surface_tau, transparent
from .camera import Camera

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
        """Light-space z -> NDC depth in [0, 1] (numpy or Dr.Jit) with this face's near / far."""
        n, f = self.near, self.far
        if self.ortho:
            return (z - n) / (f - n)
        return f / (f - n) * (1.0 - n / z)

    def linear_depth(self, d):
        """NDC depth -> light-space z (inverse of :meth:`ndc_depth`)."""
        n, f = self.near, self.far
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


def projection(light, scene, res: int | None = None, fit=None) -> Projection:
    """The light camera of ``light`` in ``scene`` for ``fit`` (None: :class:`SceneSphere`, the
    module table)."""
    res = int(res or light.shadow_map)
    fit = SceneSphere() if fit is None else fit
    if isinstance(fit, SceneSphere):
        return _scene_sphere(light, scene, res)
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
    cam = Camera.from_scene(scene)
    corners = cam.frustum_corners(fit.z0, fit.z1)
    d = np.array(lights_mod.forward(light))
    Rm = _frame(d, light.up)
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


def light_frame(light) -> np.ndarray:
    """Rows right, up, forward of a light's camera (forward = the direction it faces)."""
    return _frame(np.array(lights_mod.forward(light)), light.up)


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
    #: surfaces behind the first along each texel's ray, (L − 1, F, N, N) each, for the rasterizer's
    #: bias (every fragment biased, the smallest kept): their quantised NDC depth (1 = none) and slope
    layer_depth: np.ndarray | None = None
    layer_slope: np.ndarray | None = None
    #: translucent casters (``translucent=True``): (F, N, N, 3) τ product before the first opaque
    #: surface, and the map of the nearest translucent surfaces (a LightView; empty where none)
    trans_rgb: np.ndarray | None = None
    translucent: "LightView | None" = None
    _dr: dict = field(default_factory=dict, repr=False)

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
        return 1 if self.layer_depth is None else 1 + len(self.layer_depth)

    def dr(self, name: str):
        """Flat Dr.Jit Float of the map ``name`` ('depth', 'z', 'slope'), made once."""
        if name not in self._dr:
            self._dr[name] = mi.Float(np.ascontiguousarray(getattr(self, name), np.float32).ravel())
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
        if self.trans_rgb is None:
            return mi.Color3f(1.0)
        for c in range(3):  # one flat channel each, cached where :meth:`dr` looks first
            if f"trans_rgb{c}" not in self._dr:
                self._dr[f"trans_rgb{c}"] = mi.Float(np.ascontiguousarray(self.trans_rgb[..., c], np.float32).ravel())
        return mi.Color3f(*[self.fetch(f"trans_rgb{c}", face, ix, iy) for c in range(3)])

    def lookup(self, p):
        """Project world points ``p`` (mi.Point3f) into the light view (Dr.Jit).

        Returns a dict: ``face`` (UInt32), ``u``, ``v`` (continuous texel coordinates, texel
        centres at i + 0.5), ``z`` (light-space depth), ``d`` (NDC depth, unquantised),
        ``inside`` (in front of the camera and within the face), ``texel`` (world size of
        one texel at that depth).
        """
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
        uniform = self.proj.uniform
        if uniform:  # one set of planes for the map (every cube map): plain Python floats
            s, near, far, (sx, sy) = f0.scale, f0.near, f0.far, f0.shift
            shifted = f0.shift != (0.0, 0.0)
        else:        # each face its own: gathered per point
            if any(f.ortho != f0.ortho for f in faces):
                raise ValueError("a light view mixes orthographic and perspective faces")
            s, near, far, sx, sy = (
                self.proj.face_param(face, k) for k in ("scale", "near", "far", "shift_x", "shift_y")
            )
            shifted = True
        if f0.ortho:
            x, y = qx / s, qy / s
            texel = mi.Float(2.0 * s / N)
        else:
            inv = dr.rcp(dr.maximum(qz, 1e-12))
            x, y = qx * inv / s, qy * inv / s
            texel = 2.0 * s * qz / N
        if shifted:
            x, y = x - sx, y - sy
        u = (x + 1.0) * 0.5 * N
        v = (1.0 - y) * 0.5 * N
        inside = (qz > near) & (qz < far) & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0)
        d = self.proj.ndc_depth(dr.maximum(qz, 1e-12) if not f0.ortho else qz, face=None if uniform else face)
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
        Xs, Ys = (X, Y) if f.shift == (0.0, 0.0) else (X + f.shift[0], Y + f.shift[1])
        if f.ortho:
            local_o = np.stack([Xs * f.scale, Ys * f.scale, np.zeros_like(X)], -1).reshape(-1, 3)
            o = np.array(f.origin) + local_o @ R
            d = np.broadcast_to(R[2], o.shape)
        else:
            local_d = np.stack([Xs * f.scale, Ys * f.scale, np.ones_like(X)], -1).reshape(-1, 3)
            d = local_d @ R
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            o = np.broadcast_to(np.array(f.origin), d.shape)
        os_.append(o)
        ds_.append(d)
    return np.concatenate(os_), np.concatenate(ds_)


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
    """

    scene = scene.casters  # the map holds what casts shadows (``casts_shadows``)
    proj = projection(light, scene, res, fit)
    bits = int(bits or light.depth_bits)
    N, F = proj.res, len(proj.faces)
    o_np, d_np = texel_rays(proj)
    # start past the light's own surface: spheres at their radius, planar lights just in front
    start = light.radius * 1.001 if light.kind in ("sphere", "point") else 1e-5 * scene.radius
    clip = False
    if proj.faces[0].ortho:  # orthographic rays start on the near plane or at the light's position
        start = min(0.0, proj.faces[0].near)
        # a FrustumSlice whose near plane is the light's: rays start before the nearest caster, a plane
        # fixed in the world (from the near plane, which moves with the camera, hits would shift by
        # float rounding and stable cascades shimmer); "pancake" clamps a hit before the near plane
        # onto it (_texel_depths), "light" casts such a texel again from the near plane (clips it)
        clip = isinstance(proj.fit, FrustumSlice) and proj.fit.near_plane == "light"
        if isinstance(proj.fit, FrustumSlice) and proj.fit.near_plane != "caster":
            f0 = proj.faces[0]
            start = min(start, float(np.min((_corners(scene) - np.array(f0.origin)) @ np.array(f0.R[2])))
                        - 1e-3 * scene.radius)
    near_start = min(0.0, proj.faces[0].near)
    o_np = o_np + d_np * start
    ray = mi.Ray3f(mi.Point3f(*[o_np[:, k].astype(np.float32) for k in range(3)]),
                   mi.Vector3f(*[d_np[:, k].astype(np.float32) for k in range(3)]))
    own = scene.light_shapes.get(light.name)
    shapes = scene.mi_scene.shapes_dr()
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    alpha = bool(getattr(scene, "has_alpha", False))
    table = scene.translucency() if translucent and getattr(scene, "has_translucent", False) else None
    tr = {}
    if table is None:
        si = cast_first_hit(scene.mi_scene, ray, backface, own_ptr, alpha)
        if proj.faces[0].ortho and clip:
            si = _clip_near(scene, proj, si, o_np - d_np * start + d_np * near_start, d_np, backface, own_ptr, alpha)
    else:
        si, tau, first = _cast_translucent(scene.mi_scene, ray, backface, own_ptr, alpha, table)
        hf, sf, dqf, zf = _texel_depths(proj, first, bits)
        shp = (F, N, N)
        near = LightView(light=light, proj=proj, bits=bits, backface=backface, depth=dqf.reshape(shp),
                         z=zf.astype(np.float32).reshape(shp), slope=sf.astype(np.float32).reshape(shp),
                         hit=hf.reshape(shp))
        tr = {"trans_rgb": np.stack([np.asarray(c.numpy(), np.float32) for c in (tau.x, tau.y, tau.z)], -1)
              .reshape(F, N, N, 3), "translucent": near}
    h, slope, dq, zq = _texel_depths(proj, si, bits)
    extra, before = [], h
    for _ in range(layers - 1):  # a few layers, each one wavefront over every texel
        si = cast_first_hit(scene.mi_scene, si.spawn_ray(ray.d), backface, own_ptr, alpha)
        hk, sk, dk, _ = _texel_depths(proj, si, bits)
        hk &= before                 # a ray that already left the scene meets nothing more
        extra.append((np.where(hk, dk, 1.0).astype(np.float32), np.where(hk, sk, 0.0).astype(np.float32)))
        before = hk
    shp = (F, N, N)
    lay = {}
    if extra:
        lay = {"layer_depth": np.stack([e[0].reshape(shp) for e in extra]),
               "layer_slope": np.stack([e[1].reshape(shp) for e in extra])}
    return LightView(light=light, proj=proj, bits=bits, backface=backface, depth=dq.reshape(shp),
                     z=zq.astype(np.float32).reshape(shp), slope=slope.astype(np.float32).reshape(shp),
                     hit=h.reshape(shp), **lay, **tr)


def _clip_near(scene, proj, si, o_near, d_np, backface, own_ptr, alpha):
    """``si`` where its hit lies past the near plane of orthographic ``proj``; elsewhere the first
    hit of the texel's ray from the near plane (points ``o_near``): the casters nearer to the light
    are clipped, as a rasterizer's depth clip does."""
    f0 = proj.faces[0]
    o, d = mi.Point3f(*f0.origin), mi.Vector3f(*f0.R[2])
    before = si.is_valid() & (dr.dot(si.p - o, d) < f0.near)
    if not dr.any(before):
        return si
    ray = mi.Ray3f(mi.Point3f(*[o_near[:, k].astype(np.float32) for k in range(3)]),
                   mi.Vector3f(*[d_np[:, k].astype(np.float32) for k in range(3)]))
    return dr.select(before, cast_first_hit(scene.mi_scene, ray, backface, own_ptr, alpha), si)


def _texel_depths(proj, si, bits):
    """(hit, slope, quantised NDC depth, decoded light-space z) of every texel's hit ``si``."""
    N, F = proj.res, len(proj.faces)
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
    if proj.uniform:  # the map's own planes (shared by every face)
        n_, f_, sc, fi = f0.near, f0.far, f0.scale, None
    else:             # each face its own planes
        if any(f.ortho != f0.ortho for f in proj.faces):
            raise ValueError("a light view mixes orthographic and perspective faces")
        n_, f_, sc = (proj.face_param(face_idx, k) for k in ("near", "far", "scale"))
        fi = face_idx
    z = np.where(h, q[:, 2], f_)
    with np.errstate(divide="ignore", invalid="ignore"):
        if f0.ortho:
            slope = 2.0 / N * sc * np.maximum(np.abs(nl[:, 0]), np.abs(nl[:, 1])) / (np.abs(nl[:, 2]) * (f_ - n_))
        else:
            B = f_ * n_ / (f_ - n_)
            D = np.abs(np.einsum("mi,mi->m", nl, q))
            slope = 2.0 / N * B * sc * np.maximum(np.abs(nl[:, 0]), np.abs(nl[:, 1])) / D
    slope = np.where(h & np.isfinite(slope), np.minimum(slope, 1.0), 0.0)
    d = np.where(h, proj.ndc_depth(np.clip(z, n_, f_), face=fi), 1.0)
    dq = quantise(d, bits)
    zq = np.where(h, proj.linear_depth(dq.astype(np.float64), face=fi), f_)
    return h, slope, dq, zq


MAX_SKIPS = 16         # surfaces a texel ray may skip (the light's own shape, back faces)
MAX_SKIPS_ALPHA = 64   # … in a scene with alpha-tested casters (foliage stacks many cards)


def cast_first_hit(mi_scene, ray, backface: bool, own_ptr, alpha: bool = False):
    """First hit along ``ray`` that is not the light's own shape, (with ``backface``) that faces
    away from the ray origin and (``alpha``: the scene has alpha-tested casters) that is not a
    transparent texel. A symbolic loop: at most MAX_SKIPS (MAX_SKIPS_ALPHA) surfaces are
    skipped."""
    return _cast_loop(mi_scene, ray, backface, own_ptr, alpha)


@dr.syntax
def _cast_loop(mi_scene, ray, backface, own_ptr, alpha=False):
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


@dr.syntax
def _cast_translucent(mi_scene, ray, backface, own_ptr, alpha, table):
    """:func:`cast_first_hit` passing translucent surfaces too: (first opaque hit, τ product of
    the translucent surfaces crossed before it (mi.Color3f), the first translucent hit as a
    :class:`_Hit` (not valid where there was none))."""
    si = mi_scene.ray_intersect(ray)
    n = dr.width(si.p)
    first_p, first_n, found = dr.zeros(mi.Point3f, n), dr.zeros(mi.Vector3f, n), dr.zeros(mi.Bool, n)
    tau = mi.Color3f(1.0)
    i = mi.UInt32(0)
    trans, tau_s = surface_tau(si, table)
    own = _skip(si, ray, backface, own_ptr, alpha) & ~trans
    while dr.hint((own | trans) & (i < MAX_SKIPS_ALPHA), max_iterations=-1):
        tau = dr.select(trans, tau * tau_s, tau)
        new = trans & ~found
        first_p = dr.select(new, si.p, first_p)
        first_n = dr.select(new, si.n, first_n)
        found |= trans
        ray = si.spawn_ray(ray.d)
        si = mi_scene.ray_intersect(ray)
        trans, tau_s = surface_tau(si, table)
        own = _skip(si, ray, backface, own_ptr, alpha) & ~trans
        i += 1
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
