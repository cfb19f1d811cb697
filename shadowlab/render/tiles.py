"""Tiled light views: the tiles of one virtual shadow map, ray cast in one wavefront [Giegl 2007, §3, §4.6, §4.10].

A virtual shadow map is a one-face light camera ``base`` (a
:class:`~shadowlab.render.lightview.Projection`, e.g. the directional light's map focused on the
view by a :class:`~shadowlab.render.lightview.FrustumSlice`) whose NDC square [−1, 1]² is covered
by tiles. Tile k is the rectangle [x0, x1] × [y0, y1] of that square (x right, y up) rendered at
nx × ny texels: the per-axis sizes of [Giegl 2007, §4.10], so a tile's texels need not be square.
Texel (i, j) of a tile has its centre at x = x0 + (i + ½)(x1 − x0)/nx, y = y1 − (j + ½)(y1 − y0)/ny
(row 0 at the top, as in :mod:`~shadowlab.render.lightview`); a tile whose rectangle lies on the
texel grid of a base map of nx·2/(x1 − x0) texels holds that map's depths there.

Every tile's texels are cast in one Dr.Jit wavefront (a texel finds its tile by binary search
over the tiles' texel offsets; chunks of :func:`chunk_texels` texels bound the memory), with the
conventions of :func:`~shadowlab.render.lightview.light_view`: ``depth`` is the NDC depth,
quantised to 16/24-bit UNORM or kept as fp32, 1 where nothing was hit; ``slope`` the caster's
max NDC depth slope per texel, max(|∂d/∂x|·t_x, |∂d/∂y|·t_y) with the tile's own texel widths.

A :class:`TiledView` reads like a :class:`~shadowlab.render.lightview.LightView` for the
shadow-map families' receiver and depth-test code (``lookup``, ``fetch``, ``proj``, ``bits``):
its "face" is the tile. Which tile a point reads is decided beforehand by :func:`assign_tiles`
(the deferred shadowing of [Giegl 2007, §3.2]: a tile writes every pixel of its screen rectangle
whose point falls in the tile's texture; later tiles overwrite earlier ones).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from .lightview import Projection, cast_first_hit
from .replay import replayed, uploaded

#: texels per wavefront of :func:`render_tiles` on the CPU (Mitsuba's intersection record is ~100 B a
#: ray) and on a GPU (:func:`chunk_texels`)
CHUNK = 1 << 22
CHUNK_GPU = 1 << 26


def chunk_texels() -> int:
    """Texels per wavefront for the active variant: larger wavefronts on a GPU, where kernel
    launches, not memory, bound a frame of many small ones."""
    return CHUNK_GPU if mi.variant().startswith("cuda") else CHUNK


@dataclass(frozen=True)
class Tiles:
    """Tile rectangles in the base map's NDC and their texel counts, in the order they are
    applied (a later tile overwrites an earlier one where both hold a point). ``screen``:
    optional (T, 4) screen rectangles [x0, y0, x1, y1) in pixels that each tile shadows (None:
    the full screen)."""

    x0: np.ndarray
    y0: np.ndarray
    x1: np.ndarray
    y1: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    screen: np.ndarray | None = None

    def __post_init__(self):
        for k in ("x0", "y0", "x1", "y1"):
            object.__setattr__(self, k, np.asarray(getattr(self, k), np.float64).reshape(-1))
        for k in ("nx", "ny"):
            object.__setattr__(self, k, np.asarray(getattr(self, k), np.int64).reshape(-1))
        T = len(self.x0)
        if any(len(getattr(self, k)) != T for k in ("y0", "x1", "y1", "nx", "ny")):
            raise ValueError("Tiles: every field needs one value per tile")
        if T and (
            np.any(self.x1 <= self.x0) or np.any(self.y1 <= self.y0) or np.any(self.nx < 1) or np.any(self.ny < 1)
        ):
            raise ValueError("Tiles: expected x0 < x1, y0 < y1 and at least one texel per axis")
        if self.screen is not None:
            object.__setattr__(self, "screen", np.asarray(self.screen, np.float64).reshape(T, 4))

    def __len__(self) -> int:
        return len(self.x0)

    def subset(self, lo: int, hi: int) -> "Tiles":
        """Tiles lo … hi − 1."""
        return Tiles(self.x0[lo:hi], self.y0[lo:hi], self.x1[lo:hi], self.y1[lo:hi], self.nx[lo:hi], self.ny[lo:hi],
                     None if self.screen is None else self.screen[lo:hi])

    @property
    def offsets(self) -> np.ndarray:
        """(T + 1,) first texel of each tile in the concatenated texel array, then the total."""
        return np.concatenate([[0], np.cumsum(self.nx * self.ny)]).astype(np.int64)

    @property
    def texels(self) -> int:
        return int(np.sum(self.nx * self.ny))


def _opaque(*values, kind=None):
    """Python numbers as opaque Dr.Jit scalars (``mi.Float`` unless ``kind``)."""
    return [dr.opaque(kind or mi.Float, float(v)) for v in values]


def cells_of(x, y, n: int):
    """(column, row) of the n × n grid cell holding NDC (x, y), row 0 at the top, clamped to the
    grid (numpy int64, or Dr.Jit Int32 for Dr.Jit inputs)."""
    if isinstance(x, dr.ArrayBase):
        return (mi.Int32(dr.clip(dr.floor((x + 1.0) * 0.5 * n), 0, n - 1)),
                mi.Int32(dr.clip(dr.floor((1.0 - y) * 0.5 * n), 0, n - 1)))
    cx = np.clip(np.floor((np.asarray(x) + 1.0) * 0.5 * n), 0, n - 1).astype(np.int64)
    cy = np.clip(np.floor((1.0 - np.asarray(y)) * 0.5 * n), 0, n - 1).astype(np.int64)
    return cx, cy


@dataclass(frozen=True)
class Warp:
    """The light-space perspective warp of LiSPSM [Wimmer 2004, §4–5] in the plane of an
    orthographic map: base NDC (x, y) → warped NDC (X, Y), the square the tiles cut.

    With the perspective's axis e = (ex, ey) (the view direction projected into the light's
    plane), along = e·(x, y), lat = e⊥·(x, y) (e⊥ = (−ey, ex)), the perspective's centre
    ``n`` before the body's nearest point ``b_min`` along e and at lateral ``a0`` (the eye's):
    u = along − b_min, b = n + u, a = lat − a0, and

        X = 2·(a/b − p0)/(p1 − p0) − 1,   Y = 2·t − 1,  t = (n + d)·u / (b·d)

    (t: the perspective depth of a frustum from n to n + d, 0 at the body's near end, 1 at its
    far end; [p0, p1]: the body's range of a/b). Light rays stay parallel through it (the axis
    is perpendicular to the light), so a texel's depth is the orthographic map's. The density
    of texels along e is dY/db = 2n(n + d)/(d·b²): (1 + d/n)² times more at the near end than
    at the far end; n → ∞ tends to the orthographic (affine) fit of the body. Lengths are in
    base NDC units (world lengths / the map's half extent)."""

    ex: float
    ey: float
    a0: float
    b_min: float
    n: float
    d: float
    p0: float
    p1: float

    def __post_init__(self):
        for k in ("ex", "ey", "a0", "b_min", "n", "d", "p0", "p1"):
            object.__setattr__(self, k, float(getattr(self, k)))
        if not (self.n > 0 and self.d > 0 and self.p1 > self.p0):
            raise ValueError(f"Warp: expected n > 0, d > 0 and p0 < p1, got {self}")

    def _consts(self, kind):
        if kind is np:
            return (self.ex, self.ey, self.a0, self.b_min, self.n, self.d, self.p0, self.p1)
        return _opaque(self.ex, self.ey, self.a0, self.b_min, self.n, self.d, self.p0, self.p1, kind=kind)

    def apply(self, x, y):
        """Base NDC -> (X, Y) (numpy or Dr.Jit); points at or behind the centre (b ≤ 0) map
        outside the square (X = Y = 4)."""
        dj = isinstance(x, dr.ArrayBase)
        ex, ey, a0, bmin, n, d, p0, p1 = self._consts(type(x) if dj else np)
        u = ex * x + ey * y - bmin
        b = n + u
        a = -ey * x + ex * y - a0
        safe = dr.select(b > 0, b, 1.0) if dj else np.where(b > 0, b, 1.0)
        X = 2.0 * (a / safe - p0) / (p1 - p0) - 1.0
        Y = 2.0 * ((n + d) / d) * (u / safe) - 1.0
        if dj:
            return dr.select(b > 0, X, 4.0), dr.select(b > 0, Y, 4.0)
        return np.where(b > 0, X, 4.0), np.where(b > 0, Y, 4.0)

    def _ab(self, X, Y, c):
        ex, ey, a0, bmin, n, d, p0, p1 = c
        t = 0.5 * (Y + 1.0)
        b = n * (n + d) / ((n + d) - t * d)
        p = p0 + 0.5 * (X + 1.0) * (p1 - p0)
        return p, b, c

    def invert(self, X, Y):
        """Warped NDC -> base NDC (x, y) (numpy or Dr.Jit, any float type)."""
        dj = isinstance(X, dr.ArrayBase)
        p, b, (ex, ey, a0, bmin, n, d, p0, p1) = self._ab(X, Y, self._consts(type(X) if dj else np))
        along, lat = b - n + bmin, p * b + a0
        return ex * along - ey * lat, ey * along + ex * lat

    def jacobian(self, X, Y):
        """∂(x, y)/∂(X, Y) at warped NDC (X, Y): (x_X, y_X, x_Y, y_Y), base NDC per warped NDC."""
        dj = isinstance(X, dr.ArrayBase)
        p, b, (ex, ey, a0, bmin, n, d, p0, p1) = self._ab(X, Y, self._consts(type(X) if dj else np))
        b_Y = b * b * d / (2.0 * n * (n + d))
        a_X, a_Y = 0.5 * b * (p1 - p0), p * b_Y
        return -ey * a_X, ex * a_X, ex * b_Y - ey * a_Y, ey * b_Y + ex * a_Y


def face_ndc(face, p, warp: Warp | None = None):
    """World points (Dr.Jit) -> (x, y, light-space z): NDC of the light camera ``face``, (x, y)
    through ``warp`` where given. The camera's position, scale and shift enter the kernel
    opaquely: a focus that follows the view changes them every frame without compiling a new
    kernel."""
    o = _opaque(*face.origin)
    s, sx, sy = _opaque(face.scale, *face.shift)
    rel = p - mi.Point3f(*o)
    qx, qy, qz = (dr.dot(rel, mi.Vector3f(*face.R[r])) for r in range(3))
    if face.ortho:
        x, y = qx / s, qy / s
    else:
        inv = dr.rcp(dr.maximum(qz, 1e-12)) / s
        x, y = qx * inv, qy * inv
    x, y = x - sx, y - sy
    if warp is not None:
        x, y = warp.apply(x, y)
    return x, y, qz


@dataclass
class TiledView:
    """The rendered tiles of a virtual map (see the module docstring)."""

    layers = 1                # one surface per texel (the first_hit bias mode)

    light: object
    proj: Projection          # the base map (one face): near, far, matrices of every tile
    bits: int
    backface: bool
    tiles: Tiles
    depth: object             # mi.Float, concatenated tiles, row-major per tile
    slope: object             # mi.Float
    hit_texels: int
    point_tile: object = None  # mi.UInt32 per point (see bind)
    point_has: object = None   # mi.Bool per point: some tile holds it
    warp: Warp | None = None   # the tiles cut the warped square (LiSPSM), not the base map's

    def _tab(self, name):
        cache = self.__dict__.setdefault("_tabs", {})
        if name not in cache:
            t = self.tiles
            if name in ("nx", "ny", "off"):
                a = {"nx": t.nx, "ny": t.ny, "off": t.offsets[:-1]}[name]
                cache[name] = mi.UInt32(np.asarray(a, np.uint32))
            else:
                f0 = self.proj.faces[0]
                a = {"x0": t.x0, "y0": t.y0, "x1": t.x1, "y1": t.y1,
                     "sx": t.nx / (t.x1 - t.x0), "sy": t.ny / (t.y1 - t.y0),
                     "texel": np.maximum((t.x1 - t.x0) / t.nx, (t.y1 - t.y0) / t.ny) * f0.scale}[name]
                cache[name] = mi.Float(np.asarray(a, np.float32))
        return cache[name]

    def ndc(self, p):
        """World points -> (x, y, light-space z) in the base map's NDC, warped (Dr.Jit)."""
        return face_ndc(self.proj.faces[0], p, self.warp)

    def bind(self, tile) -> "TiledView":
        """This view bound to the tile each point reads (``tile``: Int32 per point, −1 none, as
        :func:`assign_tiles` gives, indices into this view's tiles)."""
        tile = mi.Int32(tile)
        return replace(self, point_tile=mi.UInt32(dr.maximum(tile, 0)), point_has=tile >= 0)

    def lookup(self, p):
        """:meth:`LightView.lookup` for the points :meth:`bind` bound: ``face`` is the point's
        tile, ``u``, ``v`` its continuous texel coordinates in that tile, ``inside`` False where no
        tile holds the point, ``texel`` the world size of the tile's larger texel side (with a
        warp, of the texel at the point: the warp's Jacobian times the texel's sides)."""
        if self.point_tile is None:
            raise ValueError("TiledView.lookup needs the points' tiles: call bind(assign_tiles(...)) first")
        f0 = self.proj.faces[0]
        x, y, qz = self.ndc(p)
        t = self.point_tile
        g = lambda name: dr.gather(mi.Float, self._tab(name), t)  # noqa: E731
        u = (x - g("x0")) * g("sx")
        v = (g("y1") - y) * g("sy")
        texel = g("texel") if f0.ortho else g("texel") * qz
        if self.warp is not None:
            xX, yX, xY, yY = self.warp.jacobian(x, y)
            wx, wy = dr.rcp(g("sx")), dr.rcp(g("sy"))      # the tile's texel sides in warped NDC
            texel = dr.maximum(dr.sqrt(xX * xX + yX * yX) * wx, dr.sqrt(xY * xY + yY * yY) * wy) * f0.scale
        near, far = _opaque(f0.near, f0.far)
        inside = self.point_has & (qz > near) & (qz < far) & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0)
        d = f0.ndc_depth(qz if f0.ortho else dr.maximum(qz, 1e-12))
        return {"face": t, "u": u, "v": v, "z": qz, "d": d, "inside": inside, "texel": texel}

    def fetch(self, name: str, face, ix, iy):
        """Texel values of tile ``face`` at integer texel coordinates, clamped to the tile."""
        face = mi.UInt32(face)
        nx = dr.gather(mi.UInt32, self._tab("nx"), face)
        ny = dr.gather(mi.UInt32, self._tab("ny"), face)
        ix = mi.UInt32(dr.clip(mi.Int32(ix), 0, mi.Int32(nx) - 1))
        iy = mi.UInt32(dr.clip(mi.Int32(iy), 0, mi.Int32(ny) - 1))
        idx = dr.gather(mi.UInt32, self._tab("off"), face) + iy * nx + ix
        return dr.gather(mi.Float, getattr(self, name), idx)


def assign_tiles(face, tiles: Tiles, p, px=None, py=None, cells=None, n: int = 1, warp: Warp | None = None):
    """The tile each point reads (Int32, −1 none): the last tile (in application order) whose
    texture holds the point's NDC position in the map ``face`` and, where tiles have screen
    rectangles, whose rectangle holds the point's pixel (``px``, ``py``: continuous pixel
    coordinates).

    ``cells``: (n, n) int table of the tile that holds each cell of an n×n grid over the NDC
    square (−1 none); the point's cell and its 8 neighbours' tiles are the candidates (a tile's
    overlap reaches at most into the adjacent cells). None: every tile is tried (a loop over
    the tiles; for tests and small tile counts). ``warp``: the tiles cut the warped square."""
    x, y, _ = face_ndc(face, p, warp)
    T = len(tiles)
    if T == 0:
        return dr.full(mi.Int32, -1, dr.width(x))
    best = mi.Int32(-1)
    if cells is None:
        cand = [mi.Int32(k) for k in range(T)]
    else:
        tab = mi.Int32(np.asarray(cells, np.int32).ravel())
        cx, cy = cells_of(x, y, n)
        cand = []
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                ok = (cx + dx >= 0) & (cx + dx < n) & (cy + dy >= 0) & (cy + dy < n)
                k = dr.gather(mi.Int32, tab, mi.UInt32(dr.clip((cy + dy) * n + cx + dx, 0, n * n - 1)))
                cand.append(dr.select(ok, k, -1))
    rect = [mi.Float(np.asarray(a, np.float32)) for a in (tiles.x0, tiles.y0, tiles.x1, tiles.y1)]
    scr = tiles.screen
    st = [mi.Float(np.asarray(scr[:, c], np.float32)) for c in range(4)] if scr is not None and px is not None else None
    for k in cand:
        kk = mi.UInt32(dr.maximum(k, 0))
        x0, y0, x1, y1 = (dr.gather(mi.Float, a, kk) for a in rect)
        inside = (k >= 0) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        if st is not None:
            sg = [dr.gather(mi.Float, a, kk) for a in st]
            inside &= (px >= sg[0]) & (px < sg[2]) & (py >= sg[1]) & (py < sg[3])
        best = dr.select(inside & (k > best), k, best)
    dr.eval(best)
    return best


def tile_groups(tiles: Tiles, chunk: int | None = None) -> list:
    """Consecutive tile ranges [lo, hi) of at most ``chunk`` texels each (a larger tile alone):
    the wavefronts a frame's tiles are rendered and applied in."""
    chunk = chunk_texels() if chunk is None else int(chunk)
    off = tiles.offsets
    out, lo = [], 0
    while lo < len(tiles):
        hi = int(np.searchsorted(off, off[lo] + chunk, side="right")) - 1
        hi = max(hi, lo + 1)
        out.append((lo, min(hi, len(tiles))))
        lo = out[-1][1]
    return out


def render_tiles(scene, light, base: Projection, tiles: Tiles, bits: int, backface: bool = False,
                 warp: Warp | None = None) -> TiledView:
    """Cast one ray per texel of every tile (one wavefront per :func:`chunk_texels` texels).
    ``warp`` (an orthographic ``base`` only): the tiles cut the warped square; a texel's ray
    starts at its centre's inverse warp, and its slope is the depth's per warped texel."""
    if len(base.faces) != 1:
        raise InputError(f"light {light.name!r}: a virtual tiled map needs a one-face light camera "
                         f"(directional or spot), not a {len(base.faces)}-face map")
    f0 = base.faces[0]
    if warp is not None and not f0.ortho:
        raise InputError(f"light {light.name!r}: the LiSPSM warp is built for a directional light's orthographic "
                         "map; use warp = ortho for this light")
    T, total = len(tiles), tiles.texels
    if T == 0:
        return TiledView(light, base, int(bits), bool(backface), tiles, mi.Float(), mi.Float(), 0, warp=warp)
    off = tiles.offsets
    off_dr = uploaded(mi.UInt32, off)
    tab = lambda a: uploaded(mi.Float, a)  # noqa: E731
    tab64 = lambda a: uploaded(mi.Float64, a)  # noqa: E731
    X0, Y1 = tab64(tiles.x0), tab64(tiles.y1)
    DX, DY = tab64((tiles.x1 - tiles.x0) / tiles.nx), tab64((tiles.y1 - tiles.y0) / tiles.ny)
    NX = uploaded(mi.UInt32, tiles.nx)
    TX, TY = tab((tiles.x1 - tiles.x0) / tiles.nx * f0.scale), tab((tiles.y1 - tiles.y0) / tiles.ny * f0.scale)
    owner, scene = scene, scene.casters  # the tiles hold what casts shadows (``casts_shadows``)
    own = scene.light_shapes.get(light.name)
    shapes = scene.mi_scene.shapes_dr()
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    alpha = bool(getattr(scene, "has_alpha", False))
    # the light camera's placement enters the kernel opaquely (the focus follows the view)
    n_, f_ = _opaque(f0.near, f0.far)
    ortho_d = _opaque(f0.near, f0.far - f0.near)              # d = (z − n)/(f − n), as Face.ndc_depth
    persp_d = _opaque(f0.far / (f0.far - f0.near), f0.near)   # d = f/(f − n)·(1 − n/z)
    org64 = _opaque(*f0.origin, kind=mi.Float64)
    scale64, shx, shy = _opaque(f0.scale, *f0.shift, kind=mi.Float64)
    start = _opaque(min(0.0, f0.near) if f0.ortho else 1e-5 * scene.radius, kind=mi.Float64)[0]
    tables = (off_dr, X0, Y1, DX, DY, NX, TX, TY)
    camera = (n_, f_, ortho_d, persp_d, org64, scale64, shx, shy, start)
    depth, slope, hits = [], [], []
    step = chunk_texels()
    for k0 in range(0, total, step):
        n, k0_dr = min(total, k0 + step) - k0, dr.opaque(mi.UInt32, k0)

        def stage(*_inputs, n=n, k0_dr=k0_dr):  # the arrays it reads are the inputs; the rest is the key's
            return _cast_tiles(scene, f0, T, n, k0_dr, tables, camera, own_ptr, alpha, backface, warp, bits)

        # the light's axes and the warp are literals of the kernel: part of the key with the sizes
        key = (T, n, int(bits), bool(backface), own is not None, alpha, f0.ortho, tuple(map(tuple, f0.R)), warp)
        dn, s, hit = replayed("tiles", key, stage, owner, scene.mi_scene, tables, camera, k0_dr, own_ptr)
        depth.append(dn)
        slope.append(s)
        hits.append(dr.count(hit))        # a reduction, outside the stage: a recording cannot dry-run one
    hits = sum(int(h[0]) for h in hits)   # read once, after every wavefront
    # several wavefronts: one array again, on the device
    return TiledView(light, base, int(bits), bool(backface), tiles, dr.concat(depth), dr.concat(slope), hits,
                     warp=warp)


def _cast_tiles(scene, f0, T, n, k0, tables, camera, own_ptr, alpha, backface, warp, bits):
    """One wavefront of :func:`render_tiles`: texels k0 .. k0 + n − 1 of the tiles, cast; returns the
    quantised depth, the slope and whether each texel hit, evaluated."""
    off_dr, X0, Y1, DX, DY, NX, TX, TY = tables
    n_, f_, ortho_d, persp_d, org64, scale64, shx, shy, start = camera
    R = [mi.Vector3f(*f0.R[r]) for r in range(3)]
    k = dr.arange(mi.UInt32, n) + k0
    t = dr.binary_search(0, T - 1, lambda i: dr.gather(mi.UInt32, off_dr, i + 1) <= k)
    j = k - dr.gather(mi.UInt32, off_dr, t)
    nx = dr.maximum(dr.gather(mi.UInt32, NX, t), 1)   # the LLVM packet's unused lanes gather 0: no x/0 there
    col, row = j % nx, j // nx
    # texel centres and ray origins in double precision, rounded once: the same world texel gets the
    # same float32 ray wherever the (snapped) light camera sits, so a still texel grid casts the same rays
    F = mi.Float64
    xb = dr.gather(F, X0, t) + (F(col) + 0.5) * dr.gather(F, DX, t)
    yb = dr.gather(F, Y1, t) - (F(row) + 0.5) * dr.gather(F, DY, t)
    tx, ty = dr.gather(mi.Float, TX, t), dr.gather(mi.Float, TY, t)
    jac = None
    if warp is not None:
        Xc, Yc = xb, yb
        xb, yb = warp.invert(Xc, Yc)
        jac = [mi.Float(j) for j in warp.jacobian(Xc, Yc)]
    xb, yb = xb + shx, yb + shy
    xs, ys = xb * scale64, yb * scale64
    Rr = f0.R
    if f0.ortho:
        d = R[2]
        org = mi.Point3f(*[mi.Float(org64[c] + Rr[0][c] * xs + Rr[1][c] * ys + Rr[2][c] * start) for c in range(3)])
    else:
        dd = [Rr[0][c] * xs + Rr[1][c] * ys + Rr[2][c] for c in range(3)]
        inv = dr.rsqrt(dd[0] * dd[0] + dd[1] * dd[1] + dd[2] * dd[2])
        d = mi.Vector3f(*[mi.Float(a * inv) for a in dd])
        org = mi.Point3f(*[mi.Float(org64[c] + dd[c] * inv * start) for c in range(3)])
    ray = mi.Ray3f(mi.Point3f(org), mi.Vector3f(d))
    si = cast_first_hit(scene.mi_scene, ray, backface, own_ptr, alpha)
    hit = si.is_valid()
    rel = [mi.Float64(si.p[c]) - org64[c] for c in range(3)]          # light space in double, as light_view
    q = [mi.Float(rel[0] * Rr[r][0] + rel[1] * Rr[r][1] + rel[2] * Rr[r][2]) for r in range(3)]
    nl = [dr.dot(mi.Vector3f(si.n), R[r]) for r in range(3)]
    if jac is None:
        m = dr.maximum(dr.abs(nl[0]) * tx, dr.abs(nl[1]) * ty)
    else:   # the caster plane's depth slope per warped texel: ∇d along the warp's columns
        xX, yX, xY, yY = jac
        m = dr.maximum(dr.abs(nl[0] * xX + nl[1] * yX) * tx, dr.abs(nl[0] * xY + nl[1] * yY) * ty)
    if f0.ortho:
        s = m / (dr.abs(nl[2]) * (f_ - n_))
    else:
        s = (f_ * n_ / (f_ - n_)) * m / dr.abs(nl[0] * q[0] + nl[1] * q[1] + nl[2] * q[2])
    s = dr.select(hit & dr.isfinite(s), dr.minimum(s, 1.0), 0.0)
    z = dr.clip(dr.select(hit, q[2], f_), n_, f_)
    if f0.ortho:
        dn = (z - ortho_d[0]) / ortho_d[1]
    else:
        dn = persp_d[0] * (1.0 - persp_d[1] / z)
    dn = dr.select(hit, dn, 1.0)
    dn = dr.clip(dn, 0.0, 1.0)
    if int(bits) != 32:
        mq = float(2 ** int(bits) - 1)
        dn = dr.round(dn * mq) / mq
    dr.eval(dn, s, hit)
    return dn, s, hit
