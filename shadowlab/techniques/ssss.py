"""Layered screen-space soft shadows (``ssss``) [Tamás 2015], extending [Gumbau 2010].

Per frame:

1. **Layers** [Tamás 2015, §5]: the lights' lit volumes, their intersection graph and its greedy
   colouring by ascending degree, suns on layers of their own, an optional bound k
   (``max_layers``): :mod:`shadowlab.scene.light_layers`, which also says what happens to the
   lights that do not fit (they share the least-conflicting layer; ``layer_conflicts`` counts the
   edges inside a layer). Recomputed at every render (lights may move between frames).
2. **Hard shadows** per light from ``hard``'s machinery (:func:`~shadowlab.techniques.shadow_map.receiver`,
   :func:`~shadowlab.techniques.shadow_map.depth_test` with all of ``BIAS_PARAMS``): 1 lit, 0
   shadowed, 1 outside the light camera.
3. **Penumbra map** per layer [Tamás 2015, §6.2–6.3]: the penumbra size, world units at the
   receiver, w = (d_receiver − d_blocker)·w_light/d_blocker with linear light-space depths
   (the source reconstructs them from the depth buffer; ``blocker_search.penumbra_width``, an
   orthographic map (sun): (d_r − d_b)·tan w_light), d_blocker from
   ``penumbra`` = ``blocker_search``: ``pcss``'s search (the mean depth of the blockers over the
   w_search square, ``blocker_samples`` bilinear taps, receiver-plane test), or
   ``min_filter``: a separable min filter of the light's linear-depth map at 1/:data:`MIN_FILTER_DOWNSAMPLE`
   resolution (min of 4×4 blocks, then a min along rows and along columns over the w_search
   square of the farthest receiver), read at the receiver's texel: a blocker where that minimum
   is nearer than the receiver's biased depth. The *penumbra mask* is folded into the size:
   0 where no blocker was found, and 0 means "no blur". ``w_light`` = ``light_scale`` ×
   ``blocker_search.scene_light_size`` (the side of the light's equal-area square). Where two lights of a
   layer light one point (only after a k-bound overflow) the layer keeps the larger size.
   Stored per layer at ``penumbra_bits`` 16 (IEEE half float, what an RGBA16F texel holds, 4
   layers per texel) or 8 (UNORM over [0, the layer's largest size], the banding the source
   warns of, §6.2).
4. **Layered shadow map** [Tamás 2015, §6.4]: ``layer_packing`` = ``binary``: one bit per layer,
   32 layers per 32-bit word (R32U), bit l of word l // 32 = the layer's hard visibility;
   ``exponential``: per layer exp(−k(z − d)) (k = ``exp_k`` in 1/m, z the receiver's linear light
   depth less the receiver bias, d the occluder's at the receiver's texel; 1 where the hard test
   says lit), clamped to [0, 1] and stored as floor(255·v) (the source's ``float_to_r8``), four
   layers per 32-bit word as RGBA8 (layer 4j in the high byte, as ``rgba8_to_uint``). Both are
   packed into ``UInt32`` words and unpacked again (:func:`pack_binary`, :func:`unpack_binary`,
   :func:`pack_rgba8`, :func:`unpack_rgba8`), so their quantisation is the emulated hardware's
   exactly. Where two lights of one layer light a point, the layer holds the product of their
   values (binary: both bits lit).
5. **Blur** [Tamás 2015, §7], [Geusebroek 2003]: per layer a separable Gaussian in screen space,
   a pass along x then one along y, each of ``kernel`` taps (5, 11 (the source's typical) or 23).
   The filter size at a pixel is the source's
   ``light_size · sqrt(max(dot((0, 0, 1), n_view), 0.25)) / depth`` with light_size·(…) the
   stored penumbra size (which carries w_light): F = w·sqrt(max(n_z, 0.25))·P/z pixels, P = the
   screen's pixels per world unit at view depth 1 (W/(2 tan(fov_x/2))), n_z the view-space normal's
   component toward the camera, z the view depth; the viewing-angle term is the source's one
   scalar per pixel (the kernel stays isotropic and separable). F is the penumbra's full width;
   the Gaussian's σ = F/√12 (the variance of a box of width F: a linear ramp of width F has that
   variance). Tap i = −R … R (R = (kernel − 1)/2) sits at i·3σ/R pixels with weight exp(−½(3i/R)²),
   read bilinearly between the two pixels around it; a pixel whose view depth differs from the
   centre's by more than ``depth_threshold`` × the centre's depth is rejected (the source's 0.03;
   its depth is normalised, shadowlab's relative threshold is its scale-free reading;
   ``depth_scale`` = ``normalised`` multiplies the threshold by the view depths the scene spans
   instead, and ``depth_plane`` = False compares with the centre's own depth as the source does:
   on the built-in scenes the defaults are the closer to the truth on the whole,
   ``docs/families/ssss.md``). A pixel of
   size 0 keeps its own value (no blur), so with every size 0 ``ssss`` is ``hard`` bit for bit.
   ``half_resolution``: the layer is blurred on a half-resolution grid whose pixels are the
   4-tap gather (mean) of the 2×2 full-resolution hard shadows below them (depth: their mean,
   σ: the largest of theirs, halved), and read back at full resolution bilinearly with the same
   depth rejection (the nearest half pixel where every one is rejected).
6. **Lighting**: light L reads its layer's blurred value once per pixel inside its lit volume;
   outside it, where the range window is 0, its visibility is 1 (the light does not shade there).
7. **Translucent casters** [Tamás 2015, §6.5, §7] (a scene with translucent shapes): the hard
   shadows and the exponential values come from the light views of the *opaque* casters, and a
   light's tint is the colour of the translucent casters in front of the receiver
   (:meth:`~shadowlab.render.lightview.LightView.tint`: their τ product where the receiver lies
   behind the nearest of them, by the same biased depth test as the hard shadows', against the
   map of the nearest translucent surfaces, so a pane does not tint itself). The penumbra size still comes from every
   caster (the plain
   views), so a pane's shadow edge is blurred too. Per layer the tint (the members' product per
   channel) and its coverage (1 where tinted) are the layered translucency map: one RGBA8 word
   per layer (:func:`pack_rgba8`, R in the high byte; floor(255·v), as the source's
   ``float_to_r8``), unpacked with the source's ``uint_to_rgba8`` and blurred channel by channel
   like the hard shadows. The light's RGB visibility is the blurred hard value times the blurred
   tint (``ShadowResult.colour``); its scalar visibility is that product's channel mean.

Where the work happens: a layer's value is the product of its member lights' values, packed
with the other layers into the layered shadow map and blurred once, so the blur needs every
member light before any of them has a visibility. ``prepare`` therefore runs each light's own
steps 2–4 (:meth:`SSSS.light_inputs`) and the layers' steps 3–5 once per render; ``render_light``
does step 6, the light's read of its layer.

AOVs per light: ``layer`` (its layer index), ``penumbra_size`` (its layer's stored size at its
points, world units), ``filter_px`` (F, pixels), ``hard`` (its hard shadow), and with translucent
casters ``tinted`` (1 where its layer's unblurred tint has coverage). Stats: ``layers_used``,
``max_degree``, ``layer_conflicts``, ``layer_edges``, ``words_per_pixel`` (32-bit words of the
layered shadow map), ``translucency_words_per_pixel`` (of the layered translucency map: one per
layer, 0 without translucent casters), and per light ``layer``.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from ..render.replay import replayed
from ..scene.light_layers import colour, lit_volume
from .base import LightResult, Param, light_scale_param, param_table_markdown, register, scaled_size
from .blocker_search import (BLOCKER_COUNTS, penumbra_width, scene_light_size, search_arrays,
                             search_loop, search_width)
from .shadow_map import (BIAS_PARAMS, ShadowMapTechnique, depth_test, map_entry, map_stats, receiver,
                         receiver_plane_gradient, texel_index, view_for)

SOURCE = "[Tamás 2015]"
KERNELS = (5, 11, 23)
#: the min filter's low resolution: the map is reduced by this factor (min of B×B blocks)
MIN_FILTER_DOWNSAMPLE = 4
#: the filter-size floor of the viewing-angle term [Tamás 2015, §7]
NZ_FLOOR = 0.25

SSSS_PARAMS = (
    light_scale_param(SOURCE, differentiable=False,
                      doc="w_light = light_scale × the side of the light's equal-area square (as pcss); the "
                          "source's light_size, chosen there by eye"),
    Param("penumbra", "blocker_search", "choice", choices=("blocker_search", "min_filter"),
          source="[Tamás 2015, §6.2]",
          doc="d_blocker from pcss's blocker search (mean blocker depth) or from a separable low-resolution "
              "min filter of the shadow map (nearest depth in the search square)"),
    Param("blocker_samples", 16, "choice", units="taps", choices=BLOCKER_COUNTS, source="[Tamás 2015, §6.2]",
          doc="taps of the blocker search (penumbra = blocker_search); bilinear, pcss's point sets"),
    Param("penumbra_bits", 16, "choice", units="bits", choices=(16, 8), source="[Tamás 2015, §6.2]",
          doc="penumbra map storage: 16-bit half float, or 8-bit UNORM over the layer's largest size (banding)"),
    Param("layer_packing", "binary", "choice", choices=("binary", "exponential"), source="[Tamás 2015, §6.4]",
          doc="layered shadow map: one bit per layer (32 per word) or exp(−k(z − d)) in 8 bits (4 per word)"),
    Param("exp_k", 80.0, "float", 1.0, 1000.0, "1/m", False, source="[Tamás 2015, §6.4]",
          doc="k of the exponential layers, exp(−k(z − d)) with linear light depths in metres"),
    Param("kernel", 11, "choice", units="taps", choices=KERNELS, source="[Tamás 2015, §7]",
          doc="taps per pass of the separable Gaussian (5, 11 typical, 23)"),
    Param("depth_threshold", 0.03, "float", 0.0, 1000.0, "× centre view depth", False, source="[Tamás 2015, §7]",
          doc="a tap whose view depth differs from the centre's by more than this × the centre's is rejected"),
    Param("depth_scale", "relative", "choice", choices=("relative", "normalised"), source="[Tamás 2015, §7]",
          doc="what the threshold multiplies: the centre's view depth (relative, scale-free) or the view depths "
              "the scene spans (normalised: the source's threshold on a [0, 1] depth)"),
    Param("depth_plane", True, "bool", source="[Tamás 2015, §7]",
          doc="compare a tap's depth with the centre's tangent plane at the tap (not in the source) instead of "
              "the centre's depth: a tilted receiver keeps its taps, a depth discontinuity still rejects them"),
    Param("half_resolution", False, "bool", source="[Tamás 2015, §7]",
          doc="blur at half resolution from a 4-tap gather of the full-resolution hard shadows"),
    Param("max_layers", 0, "int", 0, 4096, "layers", False, source="[Tamás 2015, §5]",
          doc="bound k on the layers (k-colouring); 0 = unbounded; lights that do not fit share the "
              "least-conflicting layer (stat layer_conflicts)"),
)


# ----------------------------------------------------------------------------------------------
# packing (exact emulation of the layered textures)

def pack_binary(bits: list) -> list:
    """Layer values (Dr.Jit Floats/Bools, lit = 1) -> UInt32 words, bit l % 32 of word l // 32."""
    words = []
    for j in range(0, len(bits), 32):
        w = dr.zeros(mi.UInt32, dr.width(bits[0]))
        for l, b in enumerate(bits[j:j + 32]):          # layers, not pixels
            w = w | dr.select(b > 0.5, mi.UInt32(1 << l), mi.UInt32(0))
        words.append(w)
    return words


def unpack_binary(words: list, n_layers: int) -> list:
    """UInt32 words -> layer values as Floats (0 or 1), the source's ``unpack_shadow``."""
    return [mi.Float((words[l // 32] >> (l % 32)) & 1) for l in range(n_layers)]


def to_r8(v):
    """The source's ``float_to_r8``: floor(255·v) of v clamped to [0, 1] (UInt32)."""
    return mi.UInt32(dr.floor(255.0 * dr.clip(v, 0.0, 1.0)))


def pack_rgba8(values: list) -> list:
    """Layer values in [0, 1] -> UInt32 words of four 8-bit channels, layer 4j + c in bits
    24 − 8c … 31 − 8c of word j (R in the high byte, the source's ``rgba8_to_uint``)."""
    words = []
    for j in range(0, len(values), 4):
        w = dr.zeros(mi.UInt32, dr.width(values[0]))
        for c, v in enumerate(values[j:j + 4]):
            w = w | (to_r8(v) << (24 - 8 * c))
        words.append(w)
    return words


def unpack_rgba8(words: list, n_layers: int) -> list:
    """UInt32 words -> layer values code/255 (Floats)."""
    return [mi.Float((words[l // 4] >> (24 - 8 * (l % 4))) & 0xFF) * (1.0 / 255.0) for l in range(n_layers)]


def store_penumbra(size, bits: int):
    """The penumbra size as the penumbra map stores it: IEEE half float (16; the cast rounds to
    nearest even, as the hardware's) or 8-bit UNORM over [0, max size] (8; the maximum is reduced
    on the device, codes round half to even), without leaving the device."""
    s = mi.Float(size)
    if bits == 16:
        return mi.Float(dr.float16_array_t(mi.Float)(s))
    m = dr.max(s)
    # divisions in float64, rounded to float32 once: the correctly rounded float32 quotient on every
    # backend (CUDA's float32 division is approximate); 255 opaque, or Dr.Jit multiplies by 1/255
    f64 = dr.float64_array_t(mi.Float)
    m64 = f64(m)
    code = dr.round(dr.clip(mi.Float(f64(s) / m64), 0.0, 1.0) * 255.0)
    return dr.select(m > 0.0, code * mi.Float(m64 / dr.opaque(f64, 255.0)), 0.0)


# ----------------------------------------------------------------------------------------------
# lit volumes at points

def in_volume(light, p):
    """Bool per point: ``p`` lies in the light's lit volume (exact shape, not the graph's bound)."""
    vol = lit_volume(light)
    if vol.everything:
        return dr.full(mi.Bool, True, dr.width(p))
    rel = mi.Point3f(p) - mi.Point3f(*vol.apex)
    d = dr.norm(rel)
    inside = d < dr.opaque(mi.Float, vol.reach)
    if vol.cos_half > -1.0:
        inside &= dr.dot(rel, mi.Vector3f(*vol.axis)) >= dr.opaque(mi.Float, vol.cos_half) * d
    return inside


# ----------------------------------------------------------------------------------------------
# the blur

class Grid:
    """A pixel grid for the blur: ``width`` × ``height`` pixels of the camera's film, per-pixel
    arrays ``x``, ``y`` (Int32), ``z`` (view depth), ``ok`` (a surface), the tangent plane n·X = c
    of each pixel's surface (camera-relative: ``pn`` (n) and ``pc`` (n·(p − o)), for
    ``depth_plane``) and ``index(x, y)`` (clamped integer coordinates -> array index)."""

    def __init__(self, camera, width, height, x, y, z, ok, pn, pc, index):
        self.camera, self.width, self.height = camera, width, height
        self.x, self.y, self.z, self.ok, self.pn, self.pc, self.index = x, y, z, ok, pn, pc, index

    def plane_depth(self, px, py):
        """View depth of each pixel's tangent plane along the ray through grid point (px, py)
        (continuous coordinates); ``None`` where the plane is edge-on or behind the camera."""
        c = self.camera
        v = lambda a: mi.Vector3f(*[float(t) for t in a])  # noqa: E731
        d = (v(c.forward) + v(c.right) * ((2.0 * px / self.width - 1.0) * c.tan_x)
             + v(c.up) * ((1.0 - 2.0 * py / self.height) * c.tan_y))
        den = dr.dot(self.pn, d)
        zp = self.pc / dr.select(dr.abs(den) > 1e-6, den, 1e-6)
        return dr.select((dr.abs(den) > 1e-6) & (zp > 0), zp, self.z)


def _blur_pass(v, sigma, g: Grid, axis: str, kernel: int, thr, plane: bool, span=None):
    """One separable pass on grid ``g``: taps at i·3σ/R pixels along ``axis`` (bilinear between the
    two pixels around each), weights exp(−½(3i/R)²), a tap rejected where its view depth differs
    by more than thr·z from the centre's (``plane``: from the centre's tangent plane at the tap;
    ``span``: by more than thr·span, the source's threshold on normalised depth).
    Pixels with σ = 0 (or no accepted tap) keep their value."""
    R = (kernel - 1) // 2
    x, y, z = g.x, g.y, g.z
    pos = mi.Float(x if axis == "x" else y)
    acc = dr.zeros(mi.Float, dr.width(v))
    wsum = dr.zeros(mi.Float, dr.width(v))
    step = sigma * (3.0 / R)
    tol = thr * (z if span is None else span)
    for i in range(-R, R + 1):      # the kernel's fixed taps, unrolled (not a loop over pixels)
        wi = math.exp(-0.5 * (3.0 * i / R) ** 2)
        t = pos + step * i
        t0 = dr.floor(t)
        f = t - t0
        for tt, fw in ((t0, 1.0 - f), (t0 + 1.0, f)):
            ti = mi.Int32(tt)
            idx = g.index(ti, y) if axis == "x" else g.index(x, ti)
            zk = dr.gather(mi.Float, z, idx)
            if plane:
                zc = (g.plane_depth(tt + 0.5, mi.Float(y) + 0.5) if axis == "x"
                      else g.plane_depth(mi.Float(x) + 0.5, tt + 0.5))
            else:
                zc = z
            take = dr.gather(mi.Bool, g.ok, idx) & (dr.abs(zk - zc) <= tol)
            w = dr.select(take, wi * fw, 0.0)
            acc += w * dr.gather(mi.Float, v, idx)
            wsum += w
    blur = g.ok & (sigma > 0) & (wsum > 0)
    return dr.select(blur, acc / dr.select(blur, wsum, 1.0), v)


def _plane(camera, p, n):
    o = mi.Point3f(*[float(t) for t in camera.position])
    n = mi.Vector3f(n)
    return n, dr.dot(n, mi.Point3f(p) - o)


class _Blurs:
    """The owner of the blur stages' recordings (:func:`~shadowlab.render.replay.replayed`): they read
    the screen's arrays and the layers, no Mitsuba object."""


_BLURS = _Blurs()


def blur_full(screen, values: list, sigmas: list, kernel: int, thr, plane: bool, span=None) -> list:
    """The two passes on the screen's (sub-)pixel grid, G-buffer order, of every layer of
    ``values`` (with its ``sigmas``): each pass of every layer in one stage, the pair replayed
    once recorded (the camera, whose axes the tangent planes' depths compile in, is in its key)."""
    c = screen.camera
    key = (len(values), int(kernel), bool(plane), span is None, screen.width, screen.height, screen.ss, c.width,
           tuple(map(float, c.position)), tuple(map(float, c.forward)), tuple(map(float, c.right)),
           tuple(map(float, c.up)), float(c.tan_x), float(c.tan_y))

    def stage(values, sigmas, thr, span, x, y, depth, valid, position, normal):
        pn, pc = _plane(c, position, normal)
        g = Grid(c, screen.width, screen.height, x, y, depth, valid, pn, pc, screen.index)
        for axis in ("x", "y"):
            values = [_blur_pass(v, sg, g, axis, kernel, thr, plane, span) for v, sg in zip(values, sigmas)]
            dr.eval(*values)
        return values

    return list(replayed("ssss_blur", key, stage, _BLURS, list(values), list(sigmas), thr, span, screen.x,
                         screen.y, screen.depth, screen.valid, screen.position, screen.normal))


def blur_half(screen, values: list, sigmas: list, kernel: int, thr, plane: bool, span=None) -> list:
    """Blur on the half-resolution grid (4-tap gather down, depth-aware bilinear up) of every
    layer of ``values`` (with its ``sigmas``); the module docstring, step 5."""
    Wh, Hh = (screen.width + 1) // 2, (screen.height + 1) // 2
    k = dr.arange(mi.UInt32, Wh * Hh)
    X, Y = mi.Int32(k % Wh), mi.Int32(k // Wh)

    def hindex(ix, iy):
        return mi.UInt32(dr.clip(mi.Int32(iy), 0, Hh - 1) * Wh + dr.clip(mi.Int32(ix), 0, Wh - 1))

    n = len(values)
    vs, zs, ns = [0.0] * n, 0.0, 0.0
    ps, nsum, sg = mi.Point3f(0.0), mi.Vector3f(0.0), [dr.zeros(mi.Float, Wh * Hh) for _ in range(n)]
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):   # the 4-tap gather
        idx = screen.index(2 * X + dx, 2 * Y + dy)
        okk = dr.gather(mi.Bool, screen.valid, idx)
        for i in range(n):                            # layers, not pixels
            vs[i] = vs[i] + dr.select(okk, dr.gather(mi.Float, values[i], idx), 0.0)
            sg[i] = dr.maximum(sg[i], dr.select(okk, dr.gather(mi.Float, sigmas[i], idx), 0.0))
        zs = zs + dr.select(okk, dr.gather(mi.Float, screen.depth, idx), 0.0)
        ps = ps + dr.select(okk, dr.gather(mi.Point3f, screen.position, idx), 0.0)
        nsum = nsum + dr.select(okk, dr.gather(mi.Vector3f, screen.normal, idx), 0.0)
        ns = ns + dr.select(okk, 1.0, 0.0)
    hok = ns > 0
    inv = 1.0 / dr.maximum(ns, 1.0)
    hv = [dr.select(hok, v * inv, 1.0) for v in vs]
    hz = dr.select(hok, zs * inv, 0.0)
    hn = dr.normalize(dr.select(dr.norm(nsum) > 0, nsum, mi.Vector3f(0, 0, 1)))
    pn, pc = _plane(screen.camera, ps * inv, hn)
    hs = [x * 0.5 for x in sg]
    dr.eval(*hv, hz, hok, *hs, pn, pc)
    g = Grid(screen.camera, Wh, Hh, X, Y, hz, hok, pn, pc, hindex)
    for axis in ("x", "y"):
        hv = [_blur_pass(h, s, g, axis, kernel, thr, plane, span) for h, s in zip(hv, hs)]
        dr.eval(*hv)
    # up: bilinear over the 2×2 half pixels around the full pixel's centre, with depth rejection
    fx = (mi.Float(screen.x) + 0.5) * 0.5 - 0.5
    fy = (mi.Float(screen.y) + 0.5) * 0.5 - 0.5
    x0, y0 = dr.floor(fx), dr.floor(fy)
    ax, ay = fx - x0, fy - y0
    z = screen.depth
    acc = [dr.zeros(mi.Float, dr.width(z)) for _ in range(n)]
    wsum = dr.zeros(mi.Float, dr.width(z))
    for dx, dy, w in ((0, 0, (1 - ax) * (1 - ay)), (1, 0, ax * (1 - ay)), (0, 1, (1 - ax) * ay), (1, 1, ax * ay)):
        idx = hindex(mi.Int32(x0) + dx, mi.Int32(y0) + dy)
        zk = dr.gather(mi.Float, hz, idx)
        take = dr.gather(mi.Bool, hok, idx) & (dr.abs(zk - z) <= thr * (z if span is None else span))
        w = dr.select(take, w, 0.0)
        for i in range(n):
            acc[i] += w * dr.gather(mi.Float, hv[i], idx)
        wsum += w
    out = []
    for i in range(n):
        near = dr.gather(mi.Float, hv[i], hindex(screen.x // 2, screen.y // 2))
        up = dr.select(wsum > 0, acc[i] / dr.select(wsum > 0, wsum, 1.0), near)
        out.append(dr.select(screen.valid & (sigmas[i] > 0), up, values[i]))
    dr.eval(*out)
    return out


def _hit_depth(view):
    """The map's linear depth z where the texel hit something, else +inf (evaluated)."""
    zi = dr.select(view.dr("hit"), view.dr("z"), dr.inf)
    dr.eval(zi)
    return zi


def min_filter_map(view, r):
    """The min filter of ``view``'s linear depth (module docstring, step 3) as a flat ``mi.Float``
    of F × Nl × Nl low-resolution texels (face, row, column), Nl = ⌈N/B⌉, B =
    :data:`MIN_FILTER_DOWNSAMPLE`: the min of each B×B block (+inf for texels that hit nothing and
    those past the map's edge), then a min over ±``r`` low-resolution texels along x and then along
    y, clamped at the face's borders (scipy ``minimum_filter1d``'s ``mode="nearest"``). Three Dr.Jit
    passes over all low-resolution texels of all faces; N, Nl and r enter them as opaque values,
    so a new radius or map size reuses the compiled kernels; ``r`` may be a Dr.Jit Int32 of width
    1 (a radius computed on the device)."""
    B = MIN_FILTER_DOWNSAMPLE
    F, N = view.nfaces, view.res
    Nl = -(-N // B)
    z = view.derived("z_min_filter", _hit_depth)
    n_o, nl_o = dr.opaque(mi.Int32, N), dr.opaque(mi.Int32, Nl)
    # r ≥ Nl − 1 already spans a whole row
    r_o = dr.clip(r, 0, Nl) if isinstance(r, dr.ArrayBase) else dr.opaque(mi.Int32, min(max(int(r), 0), Nl))
    idx = dr.arange(mi.Int32, F * Nl * Nl)
    # block min, B×B taps unrolled
    lx = idx % nl_o
    t = idx // nl_o
    ly = t % nl_o
    face = t // nl_o
    low = dr.full(mi.Float, dr.inf, F * Nl * Nl)
    for by in range(B):
        y = ly * B + by
        for bx in range(B):
            x = lx * B + bx
            ok = (x < n_o) & (y < n_o)
            src = (face * n_o + dr.minimum(y, n_o - 1)) * n_o + dr.minimum(x, n_o - 1)
            low = dr.minimum(low, dr.select(ok, dr.gather(mi.Float, z, mi.UInt32(src)), dr.inf))
    dr.eval(low)

    def run(src, start, lo, hi, step):   # min of src[start + j·step], j = lo … hi: one symbolic loop
        def body(j, m):
            return j + 1, dr.minimum(m, dr.gather(mi.Float, src, mi.UInt32(start + dr.minimum(j, hi) * step)))
        return dr.while_loop((lo + 1, dr.gather(mi.Float, src, mi.UInt32(start + lo * step))),
                             lambda j, m: j <= hi, body, labels=("j", "m"), label="ssss_min_filter")[1]

    # along x (columns of a row), then along y (rows of a column), clamped at the borders
    top = nl_o - 1
    low = run(low, idx - lx, dr.maximum(lx - r_o, 0), dr.minimum(lx + r_o, top), 1)
    dr.eval(low)
    low = run(low, idx - ly * nl_o, dr.maximum(ly - r_o, 0), dr.minimum(ly + r_o, top), nl_o)
    dr.eval(low)
    return low


# ----------------------------------------------------------------------------------------------
# the technique

@register
class SSSS(ShadowMapTechnique):
    """Layered screen-space soft shadows: lights coloured into layers, one penumbra map and one
    packed hard-shadow layer per colour, an anisotropic separable screen-space blur per layer."""

    name = "ssss"
    title = "Layered screen-space soft shadows (SSSS)"
    summary = ("lights coloured into layers by their lit volumes; per layer a penumbra map and packed hard "
               "shadows, blurred in screen space with depth rejection; each light reads its layer")
    source = SOURCE
    params = SSSS_PARAMS + BIAS_PARAMS

    # -- penumbra size per light ----------------------------------------------------------------
    def penumbra_size(self, frame, light, view, rec, values, ctx):
        """w (world units at the receiver) per point, 0 where no blocker (the folded mask)."""
        w, val = scaled_size(values["light_scale"], scene_light_size(light))
        if light.kind == "directional" and val >= 0.5 * math.pi:
            raise InputError(f"ssss.light_scale={values['light_scale']:g} gives w_light = {val:g} rad for "
                             f"directional light {light.name!r}: an angular size must be below π/2")
        zr = rec["z"]
        act = rec["active"]
        w_search = search_width(view, zr, w)
        if values["penumbra"] == "blocker_search":
            for name in ("depth", "slope", "z"):  # upload before the symbolic loop records
                view.dr(name)
            g = receiver_plane_gradient(view, rec, rec["ng"])
            nb = int(values["blocker_samples"])
            px, py = search_arrays(nb)
            cnt, zsum = search_loop(view, rec, g, ctx.bias, w_search, px, py, nb)
            found = act & (cnt > 0.0)
            z_b = dr.select(found, zsum / dr.maximum(cnt, 1e-20), zr)
        else:
            zmin = self._min_filtered(view, rec, w_search, act)
            found = act & (zmin < zr - rec["zbias"])
            z_b = dr.select(found, zmin, zr)
        return dr.select(found, penumbra_width(view, zr, z_b, w), 0.0)

    def _min_filtered(self, view, rec, w_search, act):
        """The min filter's nearest depth at each receiver's texel (module docstring, step 3)."""
        B = MIN_FILTER_DOWNSAMPLE
        Nl = -(-view.res // B)
        # the radius, ⌈max w_search / 2B⌉ low-resolution texels, stays on the device (exact: ×1/8)
        r = mi.Int32(dr.ceil(dr.max(dr.select(act, w_search, 0.0)) * (0.5 / B)))
        low = min_filter_map(view, r)
        tex = dr.select(dr.isfinite(low), low, 3.0e38)
        ix = dr.clip(mi.Int32(dr.floor(rec["u"])) // B, 0, Nl - 1)
        iy = dr.clip(mi.Int32(dr.floor(rec["v"])) // B, 0, Nl - 1)
        return dr.gather(mi.Float, tex, (mi.UInt32(rec["face"]) * Nl + mi.UInt32(iy)) * Nl + mi.UInt32(ix))

    # -- per light: what its layer needs --------------------------------------------------------
    def light_inputs(self, frame, light, values, ctx) -> dict:
        """Light ``light``'s contribution to its layer (steps 2–4 of the module docstring, its own
        work): its map, hard shadow, penumbra size, lit-volume membership, layer value (binary:
        the hard shadow; exponential: exp(−k(z − d)) where shadowed) and, with translucent
        casters, its tint. Evaluated: a kernel per light (its search reads the light's map; one kernel
        for every light loses the caches, as ``Technique.render`` says), not waited for."""
        gb = frame.gbuffer
        coloured = frame.scene.has_translucent
        view = view_for(frame, light.name, values, with_translucent=True)  # both views of every light: one stage
        opaque = view_for(frame, light.name, values, translucent=True)  # ``view`` itself without translucency
        rec = receiver(frame, view, ctx.bias)
        hard = dr.select(rec["active"], depth_test(opaque, rec, texel_index(rec["u"]), texel_index(rec["v"]),
                                                   ctx.bias), 1.0)
        size = self.penumbra_size(frame, light, view, rec, values, ctx)
        member = gb.valid & in_volume(light, gb.p)
        if values["layer_packing"] == "exponential":
            zocc = opaque.fetch("z", rec["face"], texel_index(rec["u"]), texel_index(rec["v"]))
            zrec = rec["z"] - rec["zbias"]
            e = dr.clip(dr.exp(-dr.opaque(mi.Float, float(values["exp_k"])) * (zrec - zocc)), 0.0, 1.0)
            val = dr.select(hard > 0.5, 1.0, e)
        else:
            val = hard
        tint = None
        if coloured:  # behind the nearest translucent caster, by the hard shadows' biased test
            ix, iy = texel_index(rec["u"]), texel_index(rec["v"])
            behind = depth_test(opaque.translucent, rec, ix, iy, ctx.bias) < 0.5
            tint = dr.select(rec["active"] & behind, opaque.tint(rec["face"], ix, iy), mi.Color3f(1.0))
        dr.eval(hard, size, member, val, *([tint] if coloured else []))
        return dict(view=view, hard=hard, size=size, member=member, val=val, tint=tint)

    # -- what the lights share, once per render ---------------------------------------------------
    def prepare(self, frame, values, ctx):
        """The layers and their blur (steps 1, 3–5), which every light of a layer shares: a
        layer's value is the product of its members' values, packed with the other layers into
        the layered shadow map, and blurred once, so no light's visibility exists before every
        member of its layer has contributed (:meth:`light_inputs`). :meth:`render_light` then
        reads its layer."""
        super().prepare(frame, values, ctx)
        lights = list(frame.lights)
        k = int(values["max_layers"])
        if k > len(lights):
            raise InputError(f"ssss.max_layers={k}: more layers than the scene's {len(lights)} "
                             f"light{'s' * (len(lights) != 1)}; allowed 1…{len(lights)} (0 = unbounded)")
        lay = colour(lights, max_layers=k or None, key="ssss.max_layers")
        gb = frame.gbuffer
        scr = frame.screen
        n_layers = max(lay.layer.values()) + 1
        coloured = frame.scene.has_translucent
        per = {light.name: self.light_inputs(frame, light, values, ctx) for light in lights}
        # per layer: combine the members (product of values and of tints, largest size)
        lv, ls, lt = [], [], []
        for L in range(n_layers):
            v, s = dr.full(mi.Float, 1.0, gb.size), dr.zeros(mi.Float, gb.size)
            t = mi.Color3f(1.0) if coloured else None
            for name in lay.members(L):
                q = per[name]
                v = v * dr.select(q["member"], q["val"], 1.0)
                s = dr.maximum(s, dr.select(q["member"], q["size"], 0.0))
                if coloured:
                    t = t * dr.select(q["member"], q["tint"], mi.Color3f(1.0))
            lv.append(v)
            ls.append(s)
            lt.append(t)
        # an 8-bit penumbra map is scaled by its layer's largest size: the sizes are a stage of their own
        if int(values["penumbra_bits"]) == 8:
            dr.eval(*ls)
        ls = [store_penumbra(s, int(values["penumbra_bits"])) for s in ls]
        tw = []
        if coloured:  # the layered translucency map: one RGBA8 word per layer (RGB tint, A coverage)
            tw = [pack_rgba8([t.x, t.y, t.z, dr.select((t.x < 1.0) | (t.y < 1.0) | (t.z < 1.0), 1.0, 0.0)])[0]
                  for t in lt]
        words = pack_binary(lv) if values["layer_packing"] == "binary" else pack_rgba8(lv)
        # the packed layers and the stored penumbrae: one stage for all the layers
        dr.eval(*words, *tw, *ls)
        lv = unpack_binary(words, n_layers) if values["layer_packing"] == "binary" else unpack_rgba8(words, n_layers)
        lt = [unpack_rgba8([w], 4) for w in tw]
        # blur per layer, every layer's pass in one stage
        P = scr.width / (2.0 * scr.camera.tan_x)
        fwd = mi.Vector3f(*[float(x) for x in scr.camera.forward])
        nz = dr.maximum(dr.dot(scr.normal, -fwd), NZ_FLOOR)
        thr = dr.opaque(mi.Float, float(values["depth_threshold"]))
        span = None
        if values["depth_scale"] == "normalised":   # the view depths the scene spans, as a depth buffer's [0, 1]
            z0, z1 = scr.camera.depth_range(frame.scene.center, frame.scene.radius)
            span = dr.opaque(mi.Float, float(z1 - z0))
        kernel = int(values["kernel"])
        fpx = [dr.select(scr.valid, ls[L] * dr.sqrt(nz) * P / dr.maximum(scr.depth, 1e-12), 0.0)
               for L in range(n_layers)]
        sig = [F * (1.0 / math.sqrt(12.0)) for F in fpx]
        chans = [lv[L] for L in range(n_layers)] + [c for L in range(n_layers) for c in (lt[L][:3] if coloured else ())]
        csig = sig + [sig[L] for L in range(n_layers) for _ in (range(3) if coloured else ())]
        dr.eval(*fpx, *sig, *chans, *(t[3] for t in lt))
        fn = blur_half if values["half_resolution"] else blur_full
        out = fn(scr, chans, csig, kernel, thr, bool(values["depth_plane"]), span)
        blurred = out[:n_layers]
        tints = [mi.Color3f(*out[n_layers + 3 * L:n_layers + 3 * L + 3]) for L in range(n_layers)] if coloured else []
        ctx.layering = lay
        ctx.words = len(words)
        ctx.twords = n_layers if coloured else 0
        ctx.per, ctx.sizes, ctx.blurred, ctx.filter_px = per, ls, blurred, fpx
        ctx.tints, ctx.coverage = tints, [t[3] for t in lt] if coloured else []

    # -- per light: read its layer ----------------------------------------------------------------
    def render_light(self, frame, light, values, ctx):
        """Step 6: the light's visibility is its layer's blurred value inside its lit volume (1
        outside), times the layer's blurred tint with translucent casters; its AOVs."""
        gb = frame.gbuffer
        q, L = ctx.per[light.name], ctx.layering.layer[light.name]
        vis = dr.select(q["member"], ctx.blurred[L], 1.0)
        aovs = {"layer": dr.full(mi.Float, float(L), gb.size),
                "penumbra_size": dr.select(q["member"], ctx.sizes[L], 0.0),
                "filter_px": dr.select(q["member"], ctx.filter_px[L], 0.0), "hard": q["hard"]}
        rgb = None
        if ctx.tints:
            rgb = dr.select(q["member"], ctx.blurred[L] * ctx.tints[L], mi.Color3f(1.0))
            vis = (rgb.x + rgb.y + rgb.z) * (1.0 / 3.0)
            aovs["tinted"] = dr.select(q["member"], ctx.coverage[L], 0.0)
        return LightResult(vis, aovs=aovs, active=gb.valid, colour=rgb,
                           stats={**map_stats(q["view"]), "layer": L}, maps=[map_entry(q["view"])])

    def summarise(self, frame, values, ctx, lights):
        lay = ctx.layering
        return {
            **super().summarise(frame, values, ctx, lights),
            "layers_used": lay.layers_used,
            "max_degree": lay.max_degree,
            "layer_conflicts": lay.conflicts,
            "layer_edges": lay.edges,
            "words_per_pixel": ctx.words,
            "translucency_words_per_pixel": ctx.twords,
            "kernel": int(values["kernel"]),
            "penumbra": values["penumbra"],
            "layer_packing": values["layer_packing"],
        }


__doc__ += "\n\nParameters of ``ssss`` (generated from the declaration):\n\n" + param_table_markdown(SSSS)
