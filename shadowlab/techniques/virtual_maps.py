"""Virtual shadow maps: the brute-force virtual tiled shadow map (``vtsm``) and fitted virtual
shadow maps (``fvsm``) [Giegl 2007, §3–4], with orthographic or LiSPSM focusing [Wimmer 2004].

Both cover one *virtual* shadow map of a directional light, the light's orthographic map focused
on the visible part of the view (``focus`` [Giegl 2007, §4.8]: ``visible``, the light-space square
around the G-buffer's surface points, :func:`visible_square`; the bounding sphere or box of the
camera frustum between the shadowed range's view depths, the fits of ``csm``'s cascades
[Buljan 2020, §4.2]; or the whole scene), with tiles: rectangles of its NDC square, each
rendered as a texture of its own (:mod:`shadowlab.render.tiles`, one ray per texel) and applied by
deferred shadowing into a one-byte *shadow result texture* (§3.2): a tile writes the hard,
biased depth test of ``hard`` ([Buljan 2020, §2.3], the same code) for every pixel whose point
falls in its texture; a later tile overwrites an earlier one. A pixel no tile writes keeps the
texture's clear value, lit (``unshadowed_fraction``), in the source; ``uncovered`` = ``fallback``
(the default) gives it the tile whose texture holds it, else one coarse tile of the whole map
(:meth:`VirtualMap.cover`), so no pixel is left without a tile.

Eq. (1) of §3.2 (:meth:`shadowlab.render.camera.Camera.eye_unproject`) reconstructs a pixel's
point from the eye-space depth buffer; it gives the G-buffer's points (to float precision, a
test), and the pass reads the G-buffer's points so that the technique is evaluated where the
truth is, also along a camera path (frame 0's points seen by frame t's camera). What depends on
the view itself, the demand and the ``visible`` focus, reads the frame's own view
(:attr:`~shadowlab.render.frame.FrameContext.own_gbuffer`): along a path each frame has its tiles.

**vtsm** (§3): the virtual map cut into ``grid`` × ``grid`` equal tiles, every one rendered at
``t_max`` × ``t_max`` (16 × 16 tiles of 4096² in [Giegl 2007]; 8 × 1024² by default here, 67 M rays a frame).

**fvsm** (§4): only the tiles the view needs, at the resolution it needs:

1. *SMTMM* (§4.3, the shadow map tile mapping map): per pixel of the frame, its position in
   the virtual map and the virtual map resolution each axis needs there. The pixel's footprint
   is the parallelogram of its two screen neighbours: along x the neighbour (left or right) of
   smaller |Δz| in view depth (the other way round across a silhouette), along y likewise;
   projected into the map's NDC, its bounding box has half extents Δ_x, Δ_y, and a map of 1/Δ
   texels across [−1, 1] gives that pixel one texel. The demand level is
   L = round(−log2 Δ + ½) (rounding half up: floor(−log2 Δ + 1), the byte [Giegl 2007] stores as L/256),
   so 2^L > 1/Δ. The source prints −log2(round(Δ + (0.5, 0.5)))/256, which cannot be meant as
   written (a Δ below 1 rounds to 0 or 1, whose logarithm is −∞ or 0, for every pixel); with the
   rounding around the logarithm, as here, the level is the smallest whose map has more than 1/Δ
   texels across, so every pixel gets at least one texel (§4.3's sub-pixel accuracy), where
   round(−log2 Δ) would let a texel grow to √2 pixels. The SMTMM samples every ``smtmm_scale``-th
   pixel (the pixel at each block's centre): 256² for a 1024² frame at the default 4 (§5).
2. *SMTG* (§4.4, the tile grid): ``grid`` × ``grid`` cells over the map; per cell and axis the
   maximum level, the screen rectangle of its SMTMM pixels, and a histogram of pixel counts per
   level with every level below η0 in one bucket and every level above η1 in another
   (η0 = 17, η1 = 22, §5). The discard rule: the ``discard`` fraction of a cell's pixels with
   the highest demands may go unmet; the cell's demand is then the level of the highest bucket
   whose count from the top exceeds that many pixels (a level; the cell's maximum for the top
   bucket; the highest level below η0 for the bottom one). ``discard`` = 0 keeps the maximum.
3. *Pyramid* (§4.5): the maximum demand and the merged screen rectangle of every block of
   2^a × 2^b cells, so every node of the kd-tree below (2 × 2 maxima on the diagonal a = b).
4. *Traversal* (§4.6), top-down from the whole map, an implicit kd-tree: a node of 2^−p_x ×
   2^−p_y of the map needs 2^(L − p) texels along an axis; it splits along each axis where
   L − ξ − p > log2 t_max (in 2 or 4), else it is a tile of min(2^(L − p), t_max) texels per axis
   ([Giegl 2007, §4.10]: the size it needs), extended by ``overlap`` texels on every side; nodes
   without pixels make no tile. ξ (§4.9) lowers every demand by 2^ξ when deciding to refine: a
   large ξ stops at the root, one ordinary focused map of min(2^L, t_max) texels per axis.
   At the ``grid`` level a node cannot split further and takes t_max (its demand unmet).
   Tiles are applied in traversal order (breadth first), each to its screen rectangle
   (``apply`` = ``rect``, §5 Fig. 6) or to the whole screen (``full``).

**Tile texture modes** (``tile_mode``, §4.10), which change only the memory the tiles take
(every mode renders a tile at its own w × h texels; these are the textures they are drawn into,
reused by later tiles as tiles are drawn one after another), 4 bytes a texel (one float):

* ``subrect``: a sub-rectangle of one S × S texture, S = t_max + 2·overlap: S²;
* ``pow2``: a sub-rectangle of the smallest texture of the series S_k = t_max/2^k + 2·overlap
  that holds the tile: Σ S_k² over the k used (≤ 4/3·t_max² without overlap);
* ``exact``: a texture of exactly w × h per shape used: Σ w·h over the distinct shapes
  (2·4/3·t_max² in [Giegl 2007, §4.10]'s count, which assumes aspect ratios of at most 2).

Stats per light: ``tiles``, ``texels`` (rays cast), ``memory_bytes`` (the chosen mode) and
``memory_modes`` (all three; with the coarse tile of ``uncovered`` its texture in each),
``traversal_depth`` (the deepest pyramid level a tile sits on, max(p_x, p_y)), ``demand`` (the
root's demand levels [L_x, L_y]: the virtual map 2^L a sub-pixel result needs), ``smtmm`` (its
size), ``discarded_pixels`` and ``unshadowed_fraction``.
AOVs: ``tile`` (the tile a pixel reads, −1 none), ``demand_x``, ``demand_y`` (L per pixel),
``provided_x``, ``provided_y`` (log2 of the virtual resolution its tile gives), ``cell`` (the
SMTG cell, for the grid overlay); −1 where there is no surface or it lies outside the map. Every parameter steps the
result (none is differentiable).

**LiSPSM** (``warp`` = ``lispsm``; [Giegl 2007, §5] ran every result with it, [Wimmer 2004, §4–5];
the default is ``ortho``: LiSPSM's lower error per frame comes with shadows that crawl as the view
moves, see the family's page):
the focused orthographic map's plane is warped by a perspective whose axis is the view direction
projected into the light's plane (:class:`~shadowlab.render.tiles.Warp`, :func:`lispsm_warp`): its
centre sits n = ``lispsm_n`` · n_opt before the focused body's nearest point, in line with the eye,
n_opt = (z_n + √(z_n·z_f))/sin γ (γ: the angle between the view and the light; z_n … z_f: the
visible points' view depths for ``focus`` = ``visible``, the shadowed range's for the others),
and the warped body's bounding box becomes the square. The tiles, the demand (step 1's
footprints), the tile each point reads, its texel coordinates and texel size (the normal offset)
and the casters' slope bias (the depth's slope per warped texel) are all taken in the warped
square; depths stay the orthographic map's (the warp keeps light rays parallel). The body is
the visible points (``visible``) or the base map's square (the other foci); ``snap`` steadies
the base map only (the warp follows the view). Stats: ``lispsm`` = n and the body's depth d in
metres and the near/far texel density ratio (1 + d/n)².

Not done: semitransparent receivers ([Giegl 2007, §4.11] shadows them with one ordinary map):
no built-in scene has them.

>>> demand_level(np.array([0.5, 0.25, 0.3, 1e-4])).tolist()
[2, 3, 2, 14]
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from ..io.png import NO_DATA
from ..render.gbuffer import vec_numpy
from ..render.lightview import FrustumSlice, LightSquare, SceneSphere, light_frame, projection
from ..render.tiles import Tiles, Warp, assign_tiles, cells_of, face_ndc, render_tiles, tile_groups
from .base import LightResult, Panel, Param, Technique, get, needs_mitsuba_geometry, param_table_markdown, register
from .cascades import CSM_PARAMS, shadow_range
from .shadow_map import (BIAS_PARAMS, Points, SubFrame, depth_test, map_settings, opaque_bias, receiver,
                         texel_index)

SOURCE = "[Giegl 2007]"
GRIDS = (1, 2, 4, 8, 16, 32)
T_MAX_LIMIT = 16384
LEVEL_MAX = 255
TILE_MODES = ("subrect", "pow2", "exact")
#: texels across the coarse tile of ``uncovered`` = ``fallback`` (at most t_max)
COARSE = 128
FOCI = ("visible", "sphere", "box", "scene")
WARPS = ("ortho", "lispsm")
_CSM = {p.name: p for p in CSM_PARAMS}


def _focus_params(default: str) -> tuple:
    return (
        Param(
            "focus",
            default,
            "choice",
            choices=FOCI,
            source="[Giegl 2007, §4.8]",
            doc="the virtual map's light camera: the light-space square around the points the view sees (visible), "
            "the view frustum between the shadowed range's depths (its bounding sphere or light-space box, "
            "csm's fits), or the whole scene",
        ),
        Param(
            "warp",
            "ortho",
            "choice",
            choices=WARPS,
            source="[Giegl 2007, §5], [Wimmer 2004, §4–5]",
            doc="the virtual map's parameterisation: the focused orthographic map (ortho), or LiSPSM's perspective "
            "warp of it along the view direction projected into the light's plane (lispsm, what [Giegl 2007] ran "
            "every result with): more texels near the viewer, through the lookup, the tiles, the demand and the slope "
            "bias",
        ),
        Param(
            "lispsm_n",
            1.0,
            "float",
            0.05,
            100.0,
            "× n_opt",
            False,
            source="[Wimmer 2004, §5]",
            doc="LiSPSM's n (the perspective centre's distance before the focused body) as a multiple of "
            "n_opt = (z_n + √(z_n·z_f))/sin γ; smaller = a stronger warp (more texels near the viewer), larger = "
            "nearer the orthographic map (warp = lispsm only)",
        ),
        replace(
            _CSM["snap"],
            doc="move the focused light across its direction by whole texels of the finest "
            "possible virtual map (grid × t_max), so its texel grid holds still under small camera "
            "moves; with focus = visible the square's side also steps by powers of two",
        ),
        replace(
            _CSM["pull"],
            doc="pull-back of the focused light from the frustum's centre, in radii of its bounding sphere",
        ),
        replace(
            _CSM["shadow_near"],
            doc="near end of the focused range (view depth); 0 = the camera's near clip within the scene",
        ),
        replace(
            _CSM["shadow_far"],
            doc="far end of the focused range (view depth); 0 = the camera's far clip within the scene",
        ),
    )


def _tile_params(grid_default: int, grid_doc: str) -> tuple:
    return (
        Param(
            "t_max",
            1024,
            "int",
            1,
            T_MAX_LIMIT,
            "texels",
            False,
            source="[Giegl 2007, §3]",
            doc="largest tile texture side, a power of two ≤ 16384 (4096 in [Giegl 2007]; 1024 is under a second of "
                "rays "
            "on 2 CPU cores)",
        ),
        Param("grid", grid_default, "choice", units="tiles per axis", choices=GRIDS, source="[Giegl 2007, §3, §4.4]",
              doc=grid_doc),
    )


#: the bias parameters of ``hard``; a tile's size comes from the tiling, not ``resolution``, and
#: tiles keep the first surface per texel only (``bias_mode`` first_hit)
TILE_BIAS_PARAMS = tuple(p for p in BIAS_PARAMS if p.name not in ("resolution", "bias_mode", "grazing_slope_bias"))

VTSM_PARAMS = _tile_params(8, "n: the virtual map is n × n tiles of t_max² each (16 in [Giegl 2007])") + _focus_params(
    "visible"
)

FVSM_PARAMS = (
    _tile_params(16, "n: the SMTG has n × n cells, the finest tiles (16 or 32 in [Giegl 2007])")
    + (
        Param(
            "xi",
            0,
            "int",
            0,
            16,
            "log2 levels",
            False,
            source="[Giegl 2007, §4.9]",
            doc="ξ: subtracted from the log2 demand when deciding to refine (0 … 5 in [Giegl 2007]; large = one "
                "ordinary map)",
        ),
        Param(
            "smtmm_scale",
            4,
            "int",
            1,
            16,
            "pixels",
            False,
            source="[Giegl 2007, §4.3, §5]",
            doc="frame pixels per SMTMM pixel along each axis (4: a 256² SMTMM for a 1024² frame, as in [Giegl 2007])",
        ),
        Param("eta0", 17, "int", 0, LEVEL_MAX, "log2 texels", False, source="[Giegl 2007, §4.4, §5]",
              doc="η0: demand levels below it share the histogram's lowest bucket"),
        Param("eta1", 22, "int", 0, LEVEL_MAX, "log2 texels", False, source="[Giegl 2007, §4.4, §5]",
              doc="η1: demand levels above it share the histogram's highest bucket (η0 < η1)"),
        Param("discard", 0.0, "float", 0.0, 0.5, "fraction of a cell's pixels", False, source="[Giegl 2007, §4.4]",
              doc="the share of a cell's SMTMM pixels with the highest demands that may go unmet (0 = none)"),
        Param(
            "tile_mode",
            "pow2",
            "choice",
            choices=TILE_MODES,
            source="[Giegl 2007, §4.10]",
            doc="tile textures: sub-rectangles of one t_max² texture, of a power-of-two series (recommended), or of "
            "the exact per-axis size (memory only: every mode renders the same texels)",
        ),
        Param("overlap", 1, "int", 0, 8, "texels", False, source="[Giegl 2007, §5]",
              doc="texels each tile extends beyond its rectangle on every side (tiles overlap slightly)"),
        Param("apply", "rect", "choice", choices=("rect", "full"), source="[Giegl 2007, §4.5, §5]",
              doc="a tile shadows the screen rectangle of its pixels (rect) or the whole screen (full)"),
        Param("uncovered", "fallback", "choice", choices=("fallback", "lit"), source="[Giegl 2007, §3.2]",
              doc="a pixel no tile writes: read the tile whose texture holds it, else one coarse tile of the whole "
                  "map (fallback), or keep the shadow result texture's clear value, lit (lit: the source)"),
    )
    + _focus_params("visible")
)


# ----------------------------------------------------------------------------------------------
# the demand (SMTMM, §4.3)

def demand_level(delta):
    """Quantised demand L = round(−log2 Δ + ½), half up (= floor(−log2 Δ + 1)), in 0 … 255, of
    a footprint half extent Δ in the map's NDC (numpy or Dr.Jit); Δ ≤ 0 demands 255."""
    if isinstance(delta, dr.ArrayBase):
        L = dr.floor(-dr.log2(dr.maximum(delta, 1e-30)) + 1.0)
        return dr.clip(dr.select(delta > 0, L, LEVEL_MAX), 0, LEVEL_MAX)
    d = np.asarray(delta, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.floor(-np.log2(np.where(d > 0, d, 1.0)) + 1.0)
    return np.clip(np.where(d > 0, L, LEVEL_MAX), 0, LEVEL_MAX).astype(np.int64)


def footprint(screen, face, warp: Warp | None = None):
    """Per point (Dr.Jit, G-buffer order): the NDC half extents (Δ_x, Δ_y) of the pixel's
    footprint in the map ``face`` (see the module docstring, step 1) and its NDC (x, y), both
    in the warped square where ``warp`` is given."""
    P = screen.position
    x, y, _ = face_ndc(face, P, warp)
    axes = []
    for dx, dy, n in ((1, 0, screen.width), (0, 1, screen.height)):
        coord = screen.x if dx else screen.y
        z = screen.depth
        zm, zp = screen.gather("depth", -dx, -dy), screen.gather("depth", dx, dy)
        vm = screen.gather("valid", -dx, -dy) & (coord > 0)
        vp = screen.gather("valid", dx, dy) & (coord < n - 1)
        use_p = vp & (~vm | (dr.abs(zp - z) <= dr.abs(zm - z)))
        Pm, Pp = screen.gather("position", -dx, -dy), screen.gather("position", dx, dy)
        e = dr.select(use_p, Pp - P, P - Pm)
        # no neighbour on this surface: the pixel's own width at its depth, facing the camera
        cam = screen.camera
        axis = cam.right if dx else -cam.up
        w = z * (2.0 * (cam.tan_x if dx else cam.tan_y) / n)
        e = dr.select(vm | vp, e, mi.Vector3f(*[float(c) for c in axis]) * w)
        axes.append(e)
    xe, ye, _ = face_ndc(face, P + axes[0], warp)
    xf, yf, _ = face_ndc(face, P + axes[1], warp)
    ax, ay, bx, by = xe - x, ye - y, xf - x, yf - y
    return 0.5 * (dr.abs(ax) + dr.abs(bx)), 0.5 * (dr.abs(ay) + dr.abs(by)), x, y


@dataclass
class SMTMM:
    """The sampled demand: per SMTMM pixel (numpy, flat, row-major over ``shape`` = (h, w)) its
    map NDC (x, y), levels (lx, ly) and whether it holds a surface inside the map (``ok``)."""

    shape: tuple
    scale: int
    x: np.ndarray
    y: np.ndarray
    lx: np.ndarray
    ly: np.ndarray
    ok: np.ndarray


@dataclass
class DeviceSMTMM:
    """:class:`SMTMM` left on the device (Dr.Jit arrays: x, y Float64, lx, ly Int32, ok Bool), as a
    frame samples it: :func:`tile_grid` accumulates it there and reads back only the grid."""

    shape: tuple
    scale: int
    x: object
    y: object
    lx: object
    ly: object
    ok: object

    def numpy(self) -> SMTMM:
        """The same samples as a numpy :class:`SMTMM`."""
        return SMTMM(self.shape, self.scale, self.x.numpy().astype(np.float64), self.y.numpy().astype(np.float64),
                     self.lx.numpy().astype(np.int64), self.ly.numpy().astype(np.int64), self.ok.numpy().astype(bool))


def sample_smtmm(screen, x, y, lx, ly, scale: int) -> DeviceSMTMM:
    """Every ``scale``-th grid pixel (each scale × scale block's centre) of the per-point maps, on
    the device."""
    W, H = screen.width, screen.height
    w, h = -(-W // scale), -(-H // scale)
    k = dr.arange(mi.Int32, w * h)
    row, col = k // w, k % w
    idx = screen.index(dr.minimum(col * scale + scale // 2, W - 1), dr.minimum(row * scale + scale // 2, H - 1))
    X, Y = mi.Float64(dr.gather(mi.Float, x, idx)), mi.Float64(dr.gather(mi.Float, y, idx))
    ok = dr.gather(mi.Bool, screen.valid, idx) & (dr.abs(X) <= 1.0) & (dr.abs(Y) <= 1.0)
    return DeviceSMTMM((h, w), int(scale), X, Y, mi.Int32(dr.gather(type(lx), lx, idx)),
                       mi.Int32(dr.gather(type(ly), ly, idx)), ok)


# ----------------------------------------------------------------------------------------------
# the tile grid (SMTG, §4.4), the discard rule and the pyramid (§4.5)

def bucket(levels, eta0: int, eta1: int):
    """Histogram bucket of demand levels: 0 below η0, L − η0 + 1 for η0 ≤ L ≤ η1, η1 − η0 + 2 above η1
    (numpy int64, or Dr.Jit for Dr.Jit levels)."""
    if isinstance(levels, dr.ArrayBase):
        return dr.clip(levels - eta0 + 1, 0, eta1 - eta0 + 2)
    return np.clip(np.asarray(levels, np.int64) - eta0 + 1, 0, eta1 - eta0 + 2)


@dataclass
class Grid:
    """The SMTG: per cell (arrays (n, n), [row, column]) and axis a = x, y: ``count`` of pixels,
    ``max`` level (−1 empty), ``hist`` (n, n, buckets), ``lo_max`` (highest level below η0, −1
    none), ``rect`` (n, n, 4) screen rectangle [x0, y0, x1, y1] in SMTMM pixels (inclusive)."""

    n: int
    eta0: int
    eta1: int
    count: np.ndarray
    max: dict
    hist: dict
    lo_max: dict
    rect: np.ndarray


def _per_cell(ufunc, groups, values, size: int, fill: int) -> np.ndarray:
    """``ufunc`` (np.maximum / np.minimum) of ``values`` over each cell of ``groups`` (cells' order, the
    first entry of each run, the cells present), folded with ``fill``, which empty cells keep: what
    ``ufunc.at`` onto a ``fill`` array gives, from one sort instead of one scattered update per pixel."""
    order, starts, present = groups
    out = np.full(size, fill, np.int64)
    if len(order):
        out[present] = ufunc(ufunc.reduceat(np.asarray(values, np.int64)[order], starts), fill)
    return out


def tile_grid(sm, n: int, eta0: int, eta1: int) -> Grid:
    """Accumulate the SMTMM pixels into the n × n SMTG: a :class:`DeviceSMTMM` on the device
    (:func:`_device_grid`), a numpy :class:`SMTMM` in numpy (no loop over pixels); the same grid."""
    if isinstance(sm, DeviceSMTMM):
        return _device_grid(sm, n, eta0, eta1)
    ok = sm.ok
    cx, cy = cells_of(sm.x[ok], sm.y[ok], n)
    cell = cy * n + cx
    count = np.bincount(cell, minlength=n * n).reshape(n, n)
    order = np.argsort(cell, kind="stable")
    sc = cell[order]
    starts = np.flatnonzero(np.r_[True, sc[1:] != sc[:-1]]) if len(sc) else np.zeros(0, np.int64)
    groups = (order, starts, sc[starts])
    nb = eta1 - eta0 + 3
    mx, hist, lo = {}, {}, {}
    for a, L in (("x", sm.lx[ok]), ("y", sm.ly[ok])):
        mx[a] = _per_cell(np.maximum, groups, L, n * n, -1).reshape(n, n)
        hist[a] = np.bincount(cell * nb + bucket(L, eta0, eta1), minlength=n * n * nb).reshape(n, n, nb)
        lo[a] = _per_cell(np.maximum, groups, np.where(L < eta0, L, -1), n * n, -1).reshape(n, n)
    pix = np.flatnonzero(ok)
    px, py = pix % sm.shape[1], pix // sm.shape[1]
    big = np.iinfo(np.int64).max
    rect = np.stack([_per_cell(np.minimum, groups, px, n * n, big), _per_cell(np.minimum, groups, py, n * n, big),
                     _per_cell(np.maximum, groups, px, n * n, -1), _per_cell(np.maximum, groups, py, n * n, -1)], -1)
    return Grid(n, eta0, eta1, count, mx, hist, lo, rect.reshape(n, n, 4))


def _device_grid(sm: DeviceSMTMM, n: int, eta0: int, eta1: int) -> Grid:
    """:func:`tile_grid` of SMTMM pixels on the device: every count, maximum, minimum and histogram
    bin an integer scatter-reduction over the pixels (one kernel; integer atomics, so the grid does
    not depend on their order), the n × n grid read back once."""
    I32, U32 = mi.Int32, mi.UInt32
    ok = sm.ok
    cx, cy = cells_of(sm.x, sm.y, n)
    cell = U32(cy * n + cx)
    nb = eta1 - eta0 + 3
    big = 2 ** 31 - 1
    k = dr.arange(I32, dr.width(ok))
    px, py = k % sm.shape[1], k // sm.shape[1]
    count = dr.zeros(I32, n * n)
    dr.scatter_reduce(dr.ReduceOp.Add, count, I32(1), cell, ok)
    parts = [count]
    for L in (sm.lx, sm.ly):
        mx, lo, hist = dr.full(I32, -1, n * n), dr.full(I32, -1, n * n), dr.zeros(I32, n * n * nb)
        dr.scatter_reduce(dr.ReduceOp.Max, mx, L, cell, ok)
        dr.scatter_reduce(dr.ReduceOp.Max, lo, L, cell, ok & (L < eta0))
        dr.scatter_reduce(dr.ReduceOp.Add, hist, I32(1), cell * nb + U32(bucket(L, eta0, eta1)), ok)
        parts += [mx, lo, hist]
    rect = [dr.full(I32, big, n * n), dr.full(I32, big, n * n), dr.full(I32, -1, n * n), dr.full(I32, -1, n * n)]
    for r, v, op in zip(rect, (px, py, px, py), (dr.ReduceOp.Min, dr.ReduceOp.Min, dr.ReduceOp.Max, dr.ReduceOp.Max)):
        dr.scatter_reduce(op, r, v, cell, ok)
    host = dr.concat(parts + rect).numpy().astype(np.int64)     # the grid's one read
    sizes = [n * n] + [n * n, n * n, n * n * nb] * 2 + [n * n] * 4
    count, mxx, lox, hx, mxy, loy, hy, *rc = np.split(host, np.cumsum(sizes)[:-1])
    rect = np.stack(rc, -1)
    rect[rect == big] = np.iinfo(np.int64).max                 # an empty cell's minimum, as numpy's fill
    return Grid(n, eta0, eta1, count.reshape(n, n), {"x": mxx.reshape(n, n), "y": mxy.reshape(n, n)},
                {"x": hx.reshape(n, n, nb), "y": hy.reshape(n, n, nb)},
                {"x": lox.reshape(n, n), "y": loy.reshape(n, n)}, rect.reshape(n, n, 4))


def cell_demand(g: Grid, fraction: float) -> tuple:
    """(demand x, demand y, discarded pixels per cell) under the discard rule (module docstring,
    step 2); −1 where a cell is empty."""
    allowed = np.floor(float(fraction) * g.count).astype(np.int64)
    out, dropped = {}, np.zeros_like(g.count)
    for a in ("x", "y"):
        h = g.hist[a]
        nb = h.shape[-1]
        above = np.cumsum(h[..., ::-1], axis=-1)[..., ::-1]        # pixels in bucket b or higher
        keep = above > allowed[..., None]
        b = np.where(keep.any(-1), nb - 1 - np.argmax(keep[..., ::-1], axis=-1), 0)
        lvl = np.where(b == nb - 1, g.max[a], np.where(b == 0, g.lo_max[a], g.eta0 + b - 1))
        out[a] = np.where(g.count > 0, lvl, -1)
        nxt = np.concatenate([above[..., 1:], np.zeros_like(above[..., :1])], axis=-1)
        dropped = np.maximum(dropped, np.take_along_axis(nxt, b[..., None], -1)[..., 0] * (g.count > 0))
    return out["x"], out["y"], dropped


@dataclass
class Pyramid:
    """Per level pair (a, b) (2^a columns, 2^b rows of blocks): the maximum demand per axis, the
    pixel count and the merged screen rectangle of every block of the n × n grid."""

    K: int
    lx: dict
    ly: dict
    count: dict
    rect: dict


def pyramid(dx: np.ndarray, dy: np.ndarray, count: np.ndarray, rect: np.ndarray) -> Pyramid:
    """Block maxima of the cell demands over every 2^(K−a) × 2^(K−b) block (numpy reductions: one
    maximum per block for the demands and the rectangle together, whose minima are the maxima of the
    negated corners, and one sum for the counts)."""
    n = dx.shape[0]
    K = int(round(math.log2(n)))
    signs = np.array([1, 1, -1, -1, 1, 1], np.int64)
    both = np.concatenate([np.stack([dx, dy], -1).astype(np.int64), np.asarray(rect, np.int64)], -1) * signs
    lx, ly, cnt, rc = {}, {}, {}, {}
    for a in range(K + 1):
        for b in range(K + 1):
            sh = (2 ** b, n >> b, 2 ** a, n >> a)
            m = both.reshape(*sh, 6).max(axis=(1, 3)) * signs
            lx[a, b], ly[a, b], rc[a, b] = m[..., 0], m[..., 1], m[..., 2:]
            cnt[a, b] = count.reshape(sh).sum(axis=(1, 3))
    return Pyramid(K, lx, ly, cnt, rc)


# ----------------------------------------------------------------------------------------------
# the traversal (§4.6, §4.9, §4.10)

@dataclass
class Leaves:
    """The tiles of a traversal in the order they are applied: node (ix, iy) at pyramid levels
    (px, py), demands (lx, ly), texels (w, h) without the overlap, screen rectangles (SMTMM
    pixels, inclusive); ``depth``: traversal iterations."""

    ix: np.ndarray
    iy: np.ndarray
    px: np.ndarray
    py: np.ndarray
    lx: np.ndarray
    ly: np.ndarray
    w: np.ndarray
    h: np.ndarray
    rect: np.ndarray

    def __len__(self) -> int:
        return len(self.ix)


def traverse(pyr: Pyramid, xi: int, t_max: int) -> Leaves:
    """Breadth-first refinement of the pyramid into tiles (vectorised per level of the tree)."""
    K, lt = pyr.K, int(round(math.log2(t_max)))
    ix = iy = px = py = np.zeros(1, np.int64)
    out = {k: [] for k in ("ix", "iy", "px", "py", "lx", "ly", "rect")}
    while len(ix):
        lx = np.empty(len(ix), np.int64)
        ly, cnt = np.empty_like(lx), np.empty_like(lx)
        rect = np.empty((len(ix), 4), np.int64)
        for a, b in set(zip(px.tolist(), py.tolist())):   # the (≤ (K+1)²) levels present
            m = (px == a) & (py == b)
            lx[m], ly[m] = pyr.lx[a, b][iy[m], ix[m]], pyr.ly[a, b][iy[m], ix[m]]
            cnt[m], rect[m] = pyr.count[a, b][iy[m], ix[m]], pyr.rect[a, b][iy[m], ix[m]]
        live = cnt > 0
        ex = live & (lx - xi - px > lt) & (px < K)
        ey = live & (ly - xi - py > lt) & (py < K)
        leaf = live & ~ex & ~ey
        for k, v in (("ix", ix), ("iy", iy), ("px", px), ("py", py), ("lx", lx), ("ly", ly), ("rect", rect)):
            out[k].append(v[leaf])
        split = ex | ey
        kids = []
        for ddx in (0, 1):
            for ddy in (0, 1):
                m = split & ((ddx == 0) | ex) & ((ddy == 0) | ey)
                kids.append((np.where(ex, 2 * ix + ddx, ix)[m], np.where(ey, 2 * iy + ddy, iy)[m],
                             (px + ex)[m], (py + ey)[m]))
        ix, iy, px, py = (np.concatenate([c[i] for c in kids]) for i in range(4))
    cat = {k: np.concatenate(v) if v else np.zeros((0, 4) if k == "rect" else 0, np.int64) for k, v in out.items()}
    w = 2 ** np.clip(cat["lx"] - cat["px"], 0, lt)
    h = 2 ** np.clip(cat["ly"] - cat["py"], 0, lt)
    return Leaves(cat["ix"], cat["iy"], cat["px"], cat["py"], cat["lx"], cat["ly"], w, h, cat["rect"].reshape(-1, 4))


def leaf_cells(lv: Leaves, n: int) -> np.ndarray:
    """(n, n) index of the tile whose rectangle holds each grid cell, −1 none."""
    out = np.full((n, n), -1, np.int64)
    for a, b in set(zip(lv.px.tolist(), lv.py.tolist())):
        m = np.flatnonzero((lv.px == a) & (lv.py == b))
        lvl = np.full((2 ** b, 2 ** a), -1, np.int64)
        lvl[lv.iy[m], lv.ix[m]] = m
        out = np.maximum(out, np.repeat(np.repeat(lvl, n >> b, axis=0), n >> a, axis=1))
    return out


def tile_rects(lv: Leaves, overlap: int, screen_scale: int | None = None, screen_size=None) -> Tiles:
    """The leaves as :class:`~shadowlab.render.tiles.Tiles`: NDC rectangles extended by
    ``overlap`` texels, (w + 2·overlap) × (h + 2·overlap) texels, and (``screen_scale``: SMTMM
    pixel size) screen rectangles in grid pixels."""
    wx, wy = 2.0 / 2.0 ** lv.px, 2.0 / 2.0 ** lv.py
    x0 = -1.0 + lv.ix * wx
    y1 = 1.0 - lv.iy * wy
    ox, oy = overlap * wx / lv.w, overlap * wy / lv.h
    screen = None
    if screen_scale is not None:
        s = int(screen_scale)
        W, H = screen_size
        # an SMTMM pixel stands for its s × s block; a pixel of a neighbouring block may still fall
        # in the tile, so the rectangle takes one more block on every side
        screen = np.stack([np.maximum(lv.rect[:, 0] - 1, 0) * s, np.maximum(lv.rect[:, 1] - 1, 0) * s,
                           np.minimum((lv.rect[:, 2] + 2) * s, W), np.minimum((lv.rect[:, 3] + 2) * s, H)], -1)
    return Tiles(x0 - ox, y1 - wy - oy, x0 + wx + ox, y1 + oy, lv.w + 2 * overlap, lv.h + 2 * overlap, screen)


def memory_texels(w, h, t_max: int, overlap: int = 0) -> dict:
    """Texels of the tile textures each mode allocates for tiles of w × h texels (module docstring)."""
    w, h = np.asarray(w, np.int64), np.asarray(h, np.int64)
    if not len(w):
        return {m: 0 for m in TILE_MODES}
    o2 = 2 * int(overlap)
    k = np.round(np.log2(t_max / np.maximum(w, h))).astype(np.int64)
    series = {int(x) for x in k.tolist()}
    shapes = {(int(a), int(b)) for a, b in zip(w.tolist(), h.tolist())}
    return {"subrect": (t_max + o2) ** 2,
            "pow2": sum((t_max // 2 ** x + o2) ** 2 for x in series),
            "exact": sum((a + o2) * (b + o2) for a, b in shapes)}


# ----------------------------------------------------------------------------------------------
# focusing (§4.8)

def visible_square(frame, light, res: int, snap: bool) -> LightSquare:
    """The light-space square around the G-buffer's surface points (the part of the scene the view
    sees), to the deepest of them; ``snap``: its half size rounded up to a power of two (metres)
    and its centre to whole texels of a ``res``-texel map, so small camera moves leave the texel
    grid where it was."""
    gb = frame.own_gbuffer
    R = light_frame(light)
    lo, hi = light_bounds(gb.p, gb.valid, R)
    if not np.all(np.isfinite(lo)):          # no point seen: the scene's sphere
        c = np.asarray(frame.scene.center, np.float64)
        q = np.stack([c - frame.scene.radius, c + frame.scene.radius]) @ R.T
        lo, hi = q.min(axis=0), q.max(axis=0)
    cx, cy = 0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])
    half = 0.5 * float(max(hi[0] - lo[0], hi[1] - lo[1])) * 1.001 + 1e-6 * frame.scene.radius
    if snap:   # one texel wider, as FrustumSlice's snap: the rounded centre moves by up to half a texel
        half = 2.0 ** math.ceil(math.log2(half)) * max(res, 2) / (max(res, 2) - 1.0)
        t = 2.0 * half / res
        cx, cy = round(cx / t) * t, round(cy / t) * t
    return LightSquare(cx, cy, half, float(hi[2]) + 1e-3 * frame.scene.radius)


def light_bounds(p, valid, R) -> tuple:
    """(min, max) over the points ``p`` where ``valid`` (Dr.Jit) of their light-space coordinates
    q = R·p, as numpy computes them (``P @ R.T`` in float64; ±inf without points), without reading
    every point back (2 M at 1080p): the device's Float64 extremes (which may differ from numpy's
    in the last bit: another order of the products) pick the few points within 1e-9 of them, and
    numpy's extremes of those are the extremes of all."""
    F = mi.Float64
    P = [F(p[c]) for c in range(3)]
    q = [P[0] * float(R[r][0]) + P[1] * float(R[r][1]) + P[2] * float(R[r][2]) for r in range(3)]
    ext = [dr.min(dr.select(valid, a, math.inf)) for a in q] + [dr.max(dr.select(valid, a, -math.inf)) for a in q]
    dr.eval(ext)
    e = np.array([x[0] for x in ext], np.float64)
    if not np.all(np.isfinite(e)):
        return e[:3], e[3:]
    tol = 1e-9 * (np.abs(e) + 1.0)
    near = mi.Bool(False)
    for k in range(6):
        near |= dr.abs(q[k % 3] - float(e[k])) <= float(tol[k])
    idx = dr.compress(valid & near)
    qn = vec_numpy(dr.gather(mi.Point3f, p, idx)) @ np.asarray(R, np.float64).T
    return qn.min(axis=0), qn.max(axis=0)


def base_ndc(face, P) -> np.ndarray:
    """World points (numpy (N, 3)) -> (N, 2) NDC (x, y) of the orthographic ``face``."""
    q = (np.asarray(P, np.float64).reshape(-1, 3) - np.asarray(face.origin)) @ np.asarray(face.R)[:2].T
    return q / face.scale - np.asarray(face.shift)


def n_opt(z_near: float, z_far: float, sin_gamma: float) -> float:
    """LiSPSM's n_opt = (z_n + √(z_n·z_f))/sin γ [Wimmer 2004, §5]: at γ = 90° the n whose
    warp spreads the aliasing error evenly over the view depths z_n … z_f; as the light turns
    toward the view direction (γ → 0) n grows without bound and the warp becomes orthographic."""
    return (z_near + math.sqrt(z_near * z_far)) / sin_gamma


def _lo_hi(a) -> tuple:
    """(min, max) of a numpy or Dr.Jit array, as Python floats."""
    if isinstance(a, dr.ArrayBase):
        return float(dr.min(a)[0]), float(dr.max(a)[0])
    return float(np.min(a)), float(np.max(a))


def lispsm_warp(face, camera, body, z_near: float, z_far: float, n_scale: float = 1.0) -> Warp | None:
    """The LiSPSM warp [Wimmer 2004, §4–5] of the orthographic map ``face`` for a view from
    ``camera`` over ``body`` ((x, y): base NDC of the points that must stay in the square, numpy
    or Dr.Jit arrays): the axis is the view direction projected into the light's plane, the
    centre sits n = ``n_scale``·n_opt (:func:`n_opt` of the view depths z_n … z_f and the angle γ
    between view and light) before the body's nearest point, in line with the eye, and the warped
    body's bounding box is the new square. None where the view looks along the light (sin γ = 0:
    nothing to warp) or the body is empty."""
    R = np.asarray(face.R, np.float64)
    v = np.asarray(camera.forward, np.float64)
    e = np.array([v @ R[0], v @ R[1]])
    sin_g = float(np.linalg.norm(e))          # |v × l|: R's rows are orthonormal
    bx, by = body
    if sin_g < 1e-9 or not (dr.width(bx) if isinstance(bx, dr.ArrayBase) else np.size(bx)):
        return None
    e /= sin_g
    ex, ey = float(e[0]), float(e[1])
    n = float(n_scale) * n_opt(float(z_near), float(z_far), sin_g) / face.scale
    along, lat = ex * bx + ey * by, -ey * bx + ex * by
    eye = base_ndc(face, camera.position)[0]
    a0 = float(-ey * eye[0] + ex * eye[1])
    lo, hi = _lo_hi(along)
    d = hi - lo
    pad = 1e-4 * max(d, 1e-6)                   # the body's extremes land inside the square, not on its edge
    b_min, d = lo - pad, d + 2.0 * pad
    p0, p1 = _lo_hi((lat - a0) / (n + along - b_min))
    pp = 1e-4 * max(p1 - p0, 1e-9 * max(abs(p0), abs(p1), 1e-30))
    return Warp(ex, ey, a0, b_min, n, d, p0 - pp, p1 + pp)


# ----------------------------------------------------------------------------------------------
# the techniques

def _check_tiling(values: dict, name: str) -> None:
    t = int(values["t_max"])
    if t < 1 or t & (t - 1) or t > T_MAX_LIMIT:
        raise InputError(f"{name}.t_max={t}: expected a power of two from 1 to {T_MAX_LIMIT} "
                         f"(e.g. 256, 1024, 4096)")
    if "eta0" in values and not int(values["eta0"]) < int(values["eta1"]):
        raise InputError(f"{name}: eta0={values['eta0']} must be below eta1={values['eta1']} "
                         "(η0 = 17, η1 = 22 in [Giegl 2007, §5])")


# ----------------------------------------------------------------------------------------------
# the report's images

#: tile colours (sRGB 8-bit): Kelly's 22 colours of maximum contrast without white, black and grey
TILE_COLOURS = np.array([[243, 195, 0], [135, 86, 146], [243, 132, 0], [161, 202, 241], [190, 0, 50],
                         [194, 178, 128], [0, 136, 86], [230, 143, 172], [0, 103, 165], [249, 147, 121],
                         [96, 78, 151], [246, 166, 0], [179, 68, 108], [220, 211, 0], [136, 45, 23],
                         [141, 182, 0], [101, 69, 34], [226, 88, 34], [43, 61, 38]], np.uint8)
_LINE = (255, 255, 255)


def _labels(a) -> np.ndarray:
    """A label AOV (H×W or H×W×1, float) -> int64 H×W, −1 where negative or not finite."""
    x = np.asarray(a, np.float64)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[:, :, 0]
    if x.ndim != 2:
        raise InputError(f"expected an H×W label image, got shape {x.shape}")
    ok = np.isfinite(x) & (x >= -0.5)
    return np.where(ok, np.rint(np.where(ok, x, -1.0)), -1).astype(np.int64)


def cell_edges(cell) -> np.ndarray:
    """bool H×W: the pixels whose right or lower neighbour lies in another SMTG cell
    ([Giegl 2007, §4.4]); pixels of no cell (−1) draw no line and end none.

    >>> cell_edges(np.array([[0, 0, 1], [2, 2, 3], [2, 2, 3]])).astype(int).tolist()
    [[1, 1, 1], [0, 1, 0], [0, 1, 0]]
    """
    c = _labels(cell)
    has = c >= 0
    out = np.zeros(c.shape, bool)
    out[:, :-1] |= (c[:, :-1] != c[:, 1:]) & has[:, :-1] & has[:, 1:]
    out[:-1] |= (c[:-1] != c[1:]) & has[:-1] & has[1:]
    return out


def tile_colours(tile, cell=None, visibility=None, *, line=_LINE) -> np.ndarray:
    """H×W×3 uint8 image of a tile index AOV ([Giegl 2007, §3, §4.10]): ``TILE_COLOURS[id mod 19]``,
    grey where −1 (no tile wrote the pixel); ``visibility`` multiplies the colour (as
    :func:`cascade_colours`); ``cell``: the SMTG cell AOV, drawn as ``line``-coloured lines where
    it changes between neighbouring pixels (:func:`cell_edges`, [Giegl 2007, §4.4]).

    >>> tile_colours(np.array([[0, 1, -1]])).tolist()
    [[[243, 195, 0], [135, 86, 146], [128, 128, 128]]]
    >>> tile_colours(np.array([[0, 0]]), cell=np.array([[3, 4]]), visibility=np.array([[0.5, 0.5]])).tolist()
    [[[255, 255, 255], [122, 98, 0]]]
    """
    idx = _labels(tile)
    a = TILE_COLOURS[np.maximum(idx, 0) % len(TILE_COLOURS)].astype(np.float64)
    if visibility is not None:
        a = a * np.clip(np.asarray(visibility, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
    a = np.where((idx < 0)[..., None], NO_DATA.astype(np.float64), a)
    if cell is not None:
        a = np.where(cell_edges(np.asarray(cell).reshape(idx.shape))[..., None], np.asarray(line, np.float64), a)
    return np.round(a).astype(np.uint8)


def undersampling(demand, provided) -> np.ndarray:
    """Per pixel max(demand − provided, 0) in log₂ levels ([Giegl 2007, §4.3, §4.10]): 0 = the
    pixel's tile gives at least the virtual resolution it needs, k = 2^k times too coarse; NaN
    where either level is missing (−1 or NaN).

    >>> undersampling(np.array([[12.0, 9.0, 12.0]]), np.array([[10.0, 10.0, -1.0]])).tolist()
    [[2.0, 0.0, nan]]
    """
    d, p = (np.where(np.isfinite(x) & (x >= 0), x, np.nan)
            for x in (np.asarray(demand, np.float64), np.asarray(provided, np.float64).reshape(np.shape(demand))))
    return np.maximum(d - p, 0.0)


class VirtualMap(Technique):
    """The shared part: the focused light camera, the tiles' render and the deferred pass."""

    source = SOURCE
    panels = (
        Panel("colour", "tiles", (("tile", ""),), "tiles",
              note=f"a colour per tile id (the palette repeats every {len(TILE_COLOURS)} ids), grey = no tile wrote "
                   "the pixel, × visibility; white lines (where the technique has a cell AOV: fvsm): the SMTG grid "
                   "cells [Giegl 2007, §4.4]"),
        Panel("levels", "required resolution per axis (demand L, SMTMM [Giegl 2007, §4.3]): log₂ texels of the "
                        "virtual shadow map across it that give the pixel one texel; grey = no surface",
              (("demand_x", "x"), ("demand_y", "y")), "demand", legend="log₂ texels across the virtual map"),
        Panel("excess_levels", "undersampling per axis: max(demand − provided, 0), log₂ levels by which the pixel's "
                               "tile is coarser than it needs [Giegl 2007, §4.10]; white (0) = the tile meets the "
                               "pixel's demand; grey = no surface or no tile",
              (("under_x", "x"), ("under_y", "y")), "undersampling", legend="log₂ levels too coarse"),
    )

    def report_images(self, frame, result, mask, vis):
        """[Giegl 2007, §4]: "tile": the tile colours × visibility (:func:`tile_colours`) with the
        SMTG grid of the ``cell`` AOV on the surface pixels ``mask``; "demand_x", "demand_y": the
        demand levels, −1 off the surface; "under_x", "under_y": :func:`undersampling` of the
        demand and the tile's provided levels, −1 off the surface or where no tile wrote the pixel."""
        out = {}
        for l in frame.lights:
            a = {k: result.aovs[f"{l.name}.{k}"] for k in ("tile", "cell", "demand_x", "demand_y", "provided_x",
                                                           "provided_y") if f"{l.name}.{k}" in result.aovs}
            if "tile" not in a:
                continue
            cell = np.where(mask, a["cell"], -1) if "cell" in a else None
            out.setdefault("tile", {})[l.name] = tile_colours(a["tile"], cell, vis[l.name]) / 255.0
            has_tile = mask & (a["tile"] >= 0)
            for ax in "xy":
                if f"demand_{ax}" not in a:
                    continue
                d = np.where(mask, a[f"demand_{ax}"], -1.0)
                out.setdefault(f"demand_{ax}", {})[l.name] = d
                if f"provided_{ax}" in a:
                    u = undersampling(d, np.where(has_tile, a[f"provided_{ax}"], -1.0))
                    out.setdefault(f"under_{ax}", {})[l.name] = np.where(np.isnan(u), -1.0, u)
        return out

    def unsupported(self, spec) -> str | None:
        if why := needs_mitsuba_geometry(self.name, spec):
            return why
        for l in spec.lights:
            if l.kind != "directional":
                return (f"{self.name}: light {l.name!r} is a {l.kind} light; this virtual shadow map tiles the "
                        "orthographic map of a directional light focused on the view (the sun of [Giegl 2007, §5]): "
                        "use hard, pcf, pcss, … for this scene")
        return None

    def resolve(self, overrides=None):
        values = super().resolve(overrides)
        _check_tiling(values, self.name)
        return values

    def prepare(self, frame, values, ctx):
        ctx.bias = opaque_bias(values)

    def fit_params(self, values: dict) -> tuple:
        """``shadowlab fit``'s default parameters: ``hard``'s (the biases of the test every tile
        applies), searched without gradients."""
        return tuple(get("hard").fit_params(values))

    @property
    def fit_loss(self) -> str:
        """``hard``'s loss: every tile applies its test."""
        return get("hard").fit_loss

    def base(self, frame, light, values):
        """The virtual map's light camera (one orthographic face)."""
        res = int(values["grid"]) * int(values["t_max"])
        if values["focus"] == "scene":
            fit = SceneSphere()
        elif values["focus"] == "visible":
            fit = visible_square(frame, light, res, bool(values["snap"]))
        else:
            n, f = shadow_range(frame.camera, frame.scene, values)
            fit = FrustumSlice(n, f, float(values["pull"]), bool(values["snap"]), values["focus"])
        # snapping steps by a texel of the finest virtual map the tiles can make
        return projection(light, frame.scene, res, fit)

    @staticmethod
    def warp(frame, values, base) -> Warp | None:
        """``warp`` = ``lispsm``: :func:`lispsm_warp` of the base map for the frame's own view,
        its body the visible points (``focus`` = ``visible``, their view depths z_n … z_f) or the
        base map's square (the other foci, the shadowed range's depths); None for ``ortho``."""
        if values.get("warp", "ortho") != "lispsm":
            return None
        f0, cam = base.faces[0], frame.camera
        gb = frame.own_gbuffer
        if values["focus"] == "visible" and dr.any(gb.valid):   # reduced on the device: no point leaves it
            x, y, _ = face_ndc(f0, gb.p)
            inside = dr.compress(gb.valid & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0))
            body = (dr.gather(mi.Float, x, inside), dr.gather(mi.Float, y, inside))
            z = dr.dot(gb.p - mi.Point3f(*map(float, cam.position)), mi.Vector3f(*map(float, cam.forward)))
            zn, zf = _lo_hi(dr.gather(mi.Float, z, dr.compress(gb.valid)))
            zn = max(zn, cam.near)
        else:
            body = (np.array([-1.0, 1.0, 1.0, -1.0]), np.array([-1.0, -1.0, 1.0, 1.0]))
            zn, zf = shadow_range(cam, frame.scene, values)
        return lispsm_warp(f0, cam, body, zn, max(zf, zn), float(values["lispsm_n"]))

    @staticmethod
    def cover(base, tiles, tile, gb, cells, values, warp=None) -> tuple:
        """``uncovered`` = ``fallback``: a point no tile writes (outside every screen rectangle
        that would hold it, or in a cell no tile covers) reads the last tile whose texture holds
        it, as if that tile's rectangle reached it; a point no tile's texture holds reads one
        coarse tile of the whole map, min(t_max, :data:`COARSE`) texels across, appended last
        and written only where nothing else is. Returns (tiles, tile per point)."""
        f0 = base.faces[0]
        if tiles.screen is not None:
            anyt = assign_tiles(f0, tiles, gb.p, None, None, cells, int(values["grid"]), warp)
            tile = dr.select(tile < 0, anyt, tile)
        x, y, _ = face_ndc(f0, gb.p, warp)
        left = gb.valid & (tile < 0) & (dr.abs(x) <= 1.0) & (dr.abs(y) <= 1.0)
        if not dr.any(left):
            return tiles, tile
        c = min(int(values["t_max"]), COARSE)
        scr = None if tiles.screen is None else np.vstack([tiles.screen, [[-np.inf, -np.inf, np.inf, np.inf]]])
        more = Tiles(np.append(tiles.x0, -1.0), np.append(tiles.y0, -1.0), np.append(tiles.x1, 1.0),
                     np.append(tiles.y1, 1.0), np.append(tiles.nx, c), np.append(tiles.ny, c), scr)
        tile = dr.select(left, mi.Int32(len(tiles)), tile)
        dr.eval(tile)
        return more, tile

    def plan(self, frame, light, values, base, warp) -> tuple:  # pragma: no cover - interface
        """(Tiles, cells table or None, stats, per-point AOVs): the tiles of the (``warp`` ed)
        square to render."""
        raise NotImplementedError

    def render_light(self, frame, light, values, ctx):
        frame.require_mitsuba_geometry()
        base = self.base(frame, light, values)
        warp = self.warp(frame, values, base)
        tiles, cells, stats, aovs = self.plan(frame, light, values, base, warp)
        _, bits = map_settings(frame, light.name, values)
        gb = frame.gbuffer
        npts = dr.width(gb.valid)
        if frame.own_gbuffer is gb:           # pixel centres
            px, py = mi.Float(frame.screen.x) + 0.5, mi.Float(frame.screen.y) + 0.5
        else:                                 # the points where this frame's camera sees them
            px, py, _ = frame.own_screen.project(gb.p)
        tile = assign_tiles(base.faces[0], tiles, gb.p, px, py, cells, int(values["grid"]), warp)
        if values.get("uncovered") == "fallback":
            n_before = len(tiles)
            tiles, tile = self.cover(base, tiles, tile, gb, cells, values, warp)
            if len(tiles) > n_before and "memory_modes" in stats:   # the coarse tile's texture, in every mode
                extra = 4 * int(tiles.nx[-1] * tiles.ny[-1])
                stats = {**stats, "memory_bytes": stats["memory_bytes"] + extra,
                         "memory_modes": {k: v + extra for k, v in stats["memory_modes"].items()}}
        pts = SubFrame(frame.scene, Points(gb.p, gb.ng, gb.valid))
        v, active, texel = dr.full(mi.Float, 1.0, npts), dr.full(mi.Bool, False, npts), dr.zeros(mi.Float, npts)
        hits = 0
        # tiles are applied one after another: a wavefront of tiles at a time, then its texels are freed
        for lo, hi in tile_groups(tiles):
            tv = render_tiles(frame.scene, light, base, tiles.subset(lo, hi), bits, bool(values["backface"]), warp)
            tv = tv.bind(dr.select((tile >= lo) & (tile < hi), tile - lo, -1))
            rec = receiver(pts, tv, ctx.bias)
            test = depth_test(tv, rec, texel_index(rec["u"]), texel_index(rec["v"]), ctx.bias)
            v = dr.select(rec["active"], test, v)
            texel = dr.select(rec["active"], rec["texel"], texel)
            active |= rec["active"]
            dr.eval(v, texel, active)
            hits += tv.hit_texels
        v = dr.round(v * 255.0) * (1.0 / 255.0)                    # the one-byte shadow result texture
        t = tiles
        if len(t):
            prov = lambda size, lo, hi: mi.Float(np.log2(size * 2.0 / (hi - lo)).astype(np.float32))  # noqa: E731
            k = mi.UInt32(dr.maximum(tile, 0))
            px, py = (dr.select(tile >= 0, dr.gather(mi.Float, prov(a, lo, hi), k), 0.0)
                      for a, lo, hi in ((t.nx, t.x0, t.x1), (t.ny, t.y0, t.y1)))
        else:
            px = py = dr.zeros(mi.Float, npts)
        aovs = {**aovs, "tile": dr.select(active, mi.Float(tile), -1.0), "provided_x": px, "provided_y": py,
                "texel": texel}
        f0 = base.faces[0]
        entry = {"resolution": int(max(t.nx.max(initial=0), t.ny.max(initial=0))), "depth_bits": int(bits), "faces": 1,
                 "tiles": len(t), "texels": t.texels, "near": float(f0.near), "far": float(f0.far),
                 "projection": "orthographic", "virtual_extent": 2.0 * float(f0.scale),
                 "warp": "lispsm" if warp is not None else "ortho"}
        nvalid = max(int(dr.count(gb.valid)[0]), 1)
        stats = {**stats, "tiles": len(t), "texels": t.texels, "hit_texels": hits,
                 "unshadowed_fraction": int(dr.count(gb.valid & ~active)[0]) / nvalid}
        if warp is not None:   # LiSPSM's n in metres and the near/far texel density ratio (1 + d/n)²
            stats["lispsm"] = {"n": warp.n * float(f0.scale), "depth": warp.d * float(f0.scale),
                               "density_ratio": (1.0 + warp.d / warp.n) ** 2}
        return LightResult(v, aovs, stats=stats, maps=[entry])

    def summarise(self, frame, values, ctx, lights):
        return {"shadow_map_texels": sum(st.get("texels", 0) for st in lights.values())}


@register
class VTSM(VirtualMap):
    """Brute-force virtual tiled shadow map: grid × grid tiles of t_max², applied one after another."""

    name = "vtsm"
    title = "Virtual tiled shadow map (brute force)"
    summary = ("the focused map of a directional light as n × n tiles of t_max² texels each, every tile rendered "
               "and applied by deferred shadowing (the brute-force baseline of fitted virtual shadow maps)")
    params = VTSM_PARAMS + TILE_BIAS_PARAMS

    def plan(self, frame, light, values, base, warp):
        n, t = int(values["grid"]), int(values["t_max"])
        iy, ix = np.divmod(np.arange(n * n), n)
        w = 2.0 / n
        tiles = Tiles(-1.0 + ix * w, 1.0 - (iy + 1) * w, -1.0 + (ix + 1) * w, 1.0 - iy * w,
                      np.full(n * n, t), np.full(n * n, t))
        mem = 4 * t * t
        stats = {
            "memory_bytes": mem,
            "memory_modes": {m: mem for m in TILE_MODES},
            "traversal_depth": int(round(math.log2(n))),
        }
        return tiles, np.arange(n * n).reshape(n, n), stats, {}


@register
class FVSM(VirtualMap):
    """Fitted virtual shadow maps: SMTMM -> SMTG -> pyramid -> kd traversal -> tiles of the needed size."""

    name = "fvsm"
    title = "Fitted virtual shadow maps"
    summary = ("per-pixel shadow-map resolution demand (SMTMM) gathered into a tile grid with histograms (SMTG), "
               "a max pyramid and a kd-tree traversal that renders only the tiles the view needs at the size it "
               "needs, ξ trading quality for speed down to one ordinary focused map")
    params = FVSM_PARAMS + TILE_BIAS_PARAMS

    def demand(self, frame, base, values, warp=None) -> dict:
        """The per-point demand (Dr.Jit, at :attr:`~shadowlab.render.frame.FrameContext.own_screen`'s
        points) and the SMTMM, SMTG, pyramid and tiles of one light, in the square of ``warp``
        (None: the one ``values`` ask for, :meth:`warp`)."""
        warp = warp if warp is not None else self.warp(frame, values, base)
        scr = frame.own_screen
        f0 = base.faces[0]
        dx, dy, x, y = footprint(scr, f0, warp)
        lx, ly = demand_level(dx), demand_level(dy)
        dr.eval(lx, ly, x, y)
        n = int(values["grid"])
        sm = sample_smtmm(scr, x, y, lx, ly, int(values["smtmm_scale"]))
        g = tile_grid(sm, n, int(values["eta0"]), int(values["eta1"]))
        cdx, cdy, dropped = cell_demand(g, float(values["discard"]))
        pyr = pyramid(cdx, cdy, g.count, g.rect)
        lv = traverse(pyr, int(values["xi"]), int(values["t_max"]))
        return {"lx": lx, "ly": ly, "x": x, "y": y, "smtmm": sm, "grid": g, "dropped": dropped, "pyramid": pyr,
                "leaves": lv}

    def plan(self, frame, light, values, base, warp):
        d = self.demand(frame, base, values, warp)
        lv, n, scr = d["leaves"], int(values["grid"]), frame.screen
        o = int(values["overlap"])
        rect_scale = d["smtmm"].scale if values["apply"] == "rect" else None
        tiles = tile_rects(lv, o, rect_scale, (scr.width, scr.height))
        mem = {m: 4 * v for m, v in memory_texels(lv.w, lv.h, int(values["t_max"]), o).items()}
        root = d["pyramid"]
        stats = {"memory_bytes": mem[values["tile_mode"]], "memory_modes": mem,
                 "traversal_depth": int(np.max(np.maximum(lv.px, lv.py))) if len(lv) else 0,
                 "demand": [int(root.lx[0, 0][0, 0]), int(root.ly[0, 0][0, 0])],
                 "smtmm": [int(d["smtmm"].shape[1]), int(d["smtmm"].shape[0])],
                 "discarded_pixels": int(d["dropped"].sum())}
        cx, cy = cells_of(d["x"], d["y"], n)
        ok = frame.own_gbuffer.valid & (dr.abs(d["x"]) <= 1.0) & (dr.abs(d["y"]) <= 1.0)
        aovs = {"demand_x": dr.select(ok, mi.Float(d["lx"]), -1.0), "demand_y": dr.select(ok, mi.Float(d["ly"]), -1.0),
                "cell": dr.select(ok, mi.Float(cy * n + cx), -1.0)}
        return tiles, leaf_cells(lv, n), stats, aovs


__doc__ += ("\n\nParameters of ``vtsm`` (generated from the declaration):\n\n" + param_table_markdown(VTSM)
            + "\n\nParameters of ``fvsm`` (generated from the declaration):\n\n" + param_table_markdown(FVSM))
