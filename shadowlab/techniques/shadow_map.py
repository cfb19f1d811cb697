"""Plain shadow map (``hard``) with the bias variants of [Buljan 2020, §2.3].

Source: [Buljan 2020, §2.1] (principle: project the shaded point into the light's
clip space and compare its NDC depth with the stored one) and §2.3 "Nedostatci i poboljšanja"
(shadow acne and its fixes, light leaking / Peter Panning when the bias is too large).
The depth maps are :class:`~shadowlab.render.lightview.LightView` s (ray cast per texel centre,
quantised to the light's 16/24-bit UNORM or 32-bit float format).

Visibility of a shading point p with geometric normal n (1 lit, 0 shadowed):

1. *normal offset* (receiver side): p' = p + n · normal_offset · w(p), w(p) the world size of
   one shadow-map texel at p's light-space depth; n is the G-buffer's geometric normal facing
   the camera, i.e. the outward normal of every visible closed surface;
2. *receiver bias* (§2.3, Slika 2.8): z̃ = z(p') − constant_bias − min(ε·tan∠(n, l),
   max_slope_bias), ε = ``slope_bias``, l the direction to the light, d̃ = NDC depth of z̃;
3. *rasterizer bias* (§2.3, Direct3D ``D3D11_RASTERIZER_DESC``), added to the stored caster
   depth D of the texel as the rasterizer would have when it wrote the map::

       Bias = DepthBias · r + SlopeScaledDepthBias · max(|∂d/∂x|, |∂d/∂y|)
       r    = 2^(exponent(D) − 23)       (32-bit float depth; exponent of the texel's own depth,
                                           the closest we have to "max z in primitive")
       r    = 1 / (2^bits − 1)           (16/24-bit UNORM: "the minimum representable value > 0")
       DepthBiasClamp > 0: Bias = min(clamp, Bias);  < 0: Bias = max(clamp, Bias);  0: no clamp
       D'   = saturate(D + Bias)

   The map holds D = quantise(d), not the rasterizer's quantise(d + Bias); D + Bias has the same
   error distribution (Bias plus a rounding error uniform in ± half a step) and equals it exactly
   for a whole number of UNORM steps, whereas re-quantising D + Bias would drop any Bias below
   half a step;
   ``bias_mode`` = ``rasterizer``: Direct3D and OpenGL bias every fragment before the depth test,
   so a texel keeps the smallest biased depth among all surfaces along its ray; the map then holds
   the first :data:`RASTER_LAYERS` surfaces per texel and D' = min_k saturate(D_k + Bias_k). It
   differs from ``first_hit`` (the default: the cheaper single-surface map, bias on the first
   surface) where a steep caster's slope bias carries its depth past a surface close behind it;
4. *grazing receivers* (``grazing_slope_bias`` = k): a receiver facing the light with
   0 ≤ cos(n, l) < :data:`GRAZING_MAX_COS` is tested at texel t with
   d̃_t = d̃ − max(0, −k·(g_u·Δu + g_v·Δv)), g = its tangent plane's NDC depth gradient per texel
   (tan(n, l) capped at :data:`GRAZING_MAX_TAN`), Δ = t's centre − the receiver's texel position:
   min(its depth, its tangent plane's depth at t's centre) for k = 1 [Isidoro 2006] (not on the
   virtual maps' tiles, whose texels differ per tile and axis);
5. *test*: lit = H(D' − d̃) (nearest texel; empty texels are lit); ``backface`` uses the map
   of the first surfaces facing away from the light (front faces culled, §2.3 Slika 2.7).

Points outside the light camera or without a surface get visibility 1.

Defaults, chosen against exact point-light visibility (a Mitsuba shadow ray to the light
camera's centre) over the pixels facing that point; acne = over-darkening rate, leaks = leak
rate (Peter Panning), both from ``shadowlab.metrics``. On the floor + box + sphere scene under a
``point`` light of ``tests/test_techniques_shadow_map.py`` (512² cube map) the tests assert the
shape of the trade-off: with every bias 0 a large share of the lit pixels shows acne, the
defaults remove nearly all of it at a small leak rate, and a constant bias of one world unit
removes it too but lets a large share of the umbra leak (``test_bias_sweep_acne_then_peter_panning``);
each bias variant alone removes most of the acne (``test_each_bias_variant_removes_most_acne``);
16-bit depth shows more acne than 32-bit at the same small bias
(``test_16_bit_depth_has_more_acne_than_32_bit_at_the_same_small_bias``). The rates are
measured by those tests and not copied here.

* ``slope_scaled_depth_bias`` = 2: a planar caster's depth changes by at most 1× its slope
  between a texel centre and any point of the texel, so 1 suffices for ``hard``; 2 also keeps
  the default 3×3 ``pcf`` (taps one texel away) nearly free of acne for a small increase in
  leaks, and does not depend on the map resolution;
* ``depth_bias`` = 16 (16 ulp of fp32, 16 steps of UNORM): surfaces facing the light head-on have
  slope 0, and float32 rounding of D and d̃ alone gives acne on the point scene;
* receiver-side world-unit biases and ``normal_offset`` stay 0: they grow the leaks for no
  further acne reduction here, and world units do not scale with the scene or the map;
* ``depth_bias_clamp`` = 0: grazing casters need their large slope bias (a clamp of 1e-3 NDC
  brings acne back on ``contact``);
* ``grazing_slope_bias`` = 1: near a terminator the nearest texel (or a PCF tap's) holds a steeper
  part of the surface than the receiver. Along a convex surface the depth z(x) is convex, so the
  caster at a texel centre x_t lies no nearer the light than the receiver's tangent plane there,
  z(x_t) ≥ z(x) + z'(x)·(x_t − x): comparing with that plane (k = 1) is exact for convex
  terminators, and taking the min with the receiver's own depth never darkens. Raising the shared
  slope-scaled bias instead (to 4) made thin casters' shadows vanish on the outdoor scenes. The cut-off
  :data:`GRAZING_MAX_COS` equals ``pcf``'s receiver-plane cut-off (the taps the plane does not cover);
  the tan cap bounds the lift where the caster in front is another object (contact shadows of thin
  casters on grazing ground, faces nearly edge-on to the light inside another caster's shadow).

How the defaults scale with the texel size w (world size of one texel at the receiver) and the map
resolution N. A planar receiver tilted by θ from the light changes its light-space depth by w·tan θ
per texel, so the depth error between a receiver and the texel centre it reads is at most about
w·tan θ, and a 3×3 PCF tap one texel further away adds w·tan θ more. The caster's NDC slope per texel
(``slope``, max(|∂d/∂u|, |∂d/∂v|)) is that same w·tan θ measured in NDC: halving N doubles w and
doubles the stored slope, so ``slope_scaled_depth_bias`` (and ``grazing_slope_bias``, the
receiver's slope per texel) are counts of texels and hold at any resolution and scene size without
retuning. ``depth_bias`` is in steps of the depth format (1/(2^bits − 1), or 2^(e − 23) for fp32): it
covers the rounding of D and d̃, which depends on the format and the depth, not on w, so it neither
needs to grow with the texel nor is it enough for tilted receivers on its own. World-unit receiver
biases (``constant_bias``, ``slope_bias``) do not follow w: a value tuned at one resolution leaks at a
finer map and is too small at a coarser one, which is why they default to 0; ``normal_offset`` is in
texels at the receiver and so scales with w like the slope terms.

All parameters are piecewise constant in the visibility (a step function of every bias), so none
is ``differentiable``; fitting searches them without gradients. Every continuous value enters the
kernel through ``dr.opaque``: a new value reuses the compiled kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from ..render.frame import ViewKey
from ..render.lightview import face_rows, opaque_values
from ..render.tiles import TiledView
from .base import FromScene, LightResult, Param, Technique, needs_mitsuba_geometry, param_table_markdown, register

SOURCE = "[Buljan 2020, §2.3]"
RES_MIN, RES_MAX = 64, 8192

def largest_map(frame) -> int:
    """The largest ``shadow_map`` of ``frame``'s lights: one resolution that stands for
    ``resolution`` 0 (each light's own) where one number is needed (a fit's start)."""
    return int(max(l.shadow_map for l in frame.lights))


#: The shadow-map and bias parameters every shadow-map technique shares (hard, pcf, ...).
BIAS_PARAMS = (
    Param("resolution", 0, "int", 0, RES_MAX, "texels", False, source=SOURCE,
          doc="shadow-map side per face; 0 = the light's `shadow_map` from the scene, else 64…8192",
          from_scene=FromScene(0, largest_map, floor=RES_MIN)),
    Param("depth_bits", 0, "choice", units="bits", choices=(0, 16, 24, 32), source=SOURCE,
          doc="depth format: 16/24-bit UNORM or 32-bit float; 0 = the light's `depth_bits`"),
    Param(
        "depth_bias",
        16,
        "int",
        -1_000_000,
        1_000_000,
        "DepthBias units (r)",
        False,
        source=SOURCE,
        doc="Direct3D DepthBias: Bias += DepthBias·r, r = 2^(exponent(d)−23) (fp32) or 1/(2^bits−1) "
        "(UNORM), added to the stored caster depth",
    ),
    Param("slope_scaled_depth_bias", 2.0, "float", -64.0, 64.0, "× NDC depth slope per texel", False, source=SOURCE,
          doc="Direct3D SlopeScaledDepthBias: Bias += value × the caster's max NDC depth slope (∂d/∂x, ∂d/∂y)"),
    Param(
        "grazing_slope_bias",
        1.0,
        "float",
        0.0,
        64.0,
        "× receiver tangent-plane depth drop",
        False,
        source="[Isidoro 2006]",
        doc="receivers facing the light at grazing angles (0 ≤ cos(n, l) < GRAZING_MAX_COS) compare each texel "
        "with min(their depth, their tangent plane's depth at the texel's centre), the plane's slope × this "
        "value (tan capped at GRAZING_MAX_TAN): no acne on curved and flat-shaded terminators; 0 = off",
    ),
    Param("depth_bias_clamp", 0.0, "float", -1.0, 1.0, "NDC depth", False, source=SOURCE,
          doc="Direct3D DepthBiasClamp: > 0 Bias = min(clamp, Bias), < 0 Bias = max(clamp, Bias), 0 = none"),
    Param("constant_bias", 0.0, "float", 0.0, 10.0, "world units", False, source=SOURCE,
          doc="subtracted from the receiver's light-space z before the test"),
    Param("slope_bias", 0.0, "float", 0.0, 10.0, "world units", False, source=SOURCE,
          doc="ε of bias = ε·tan(angle(n, l)), subtracted from the receiver's light-space z"),
    Param("max_slope_bias", 0.05, "float", 0.0, 10.0, "world units", False, source=SOURCE,
          doc="upper bound of ε·tan(angle(n, l)) (tan grows without bound at grazing light)"),
    Param("normal_offset", 0.0, "float", 0.0, 8.0, "texels", False, source=SOURCE,
          doc="move the receiver along its geometric normal by this many texel widths (at its depth) "
              "before projecting"),
    Param("backface", False, "bool", source=SOURCE,
          doc="front-face culling: the map stores the first surface facing away from the light"),
    Param(
        "bias_mode",
        "first_hit",
        "choice",
        choices=("first_hit", "rasterizer"),
        source=SOURCE,
        doc="first_hit: the rasterizer bias is added to the first surface of a texel's ray; rasterizer: to "
        "every surface along it (RASTER_LAYERS of them), the smallest biased depth kept, as Direct3D and "
        "OpenGL bias every fragment before the depth test",
    ),
)

#: surfaces per texel ray the ``rasterizer`` bias mode considers
RASTER_LAYERS = 4

#: receivers facing the light with cos(n, l) below this get ``grazing_slope_bias`` (the same cut-off as
#: ``pcf.RECEIVER_PLANE_MIN_COS``: the receivers whose PCF taps keep the plain test)
GRAZING_MAX_COS = 0.35
#: tan(angle(n, l)) the grazing term uses at most (cos ≈ 0.32): an edge-on receiver's slope is unbounded, and
#: a larger cap lets grazing receivers leak under the casters just in front of them (``bench``'s legs inside
#: the seat's outline; thin casters on ``street``'s ground under the 12° sun, ``street/csm``'s leak gate)
GRAZING_MAX_TAN = 3.0


# ----------------------------------------------------------------------------------------------
# shared helpers (pcf and later shadow-map techniques reuse them)

def check_map_params(values: dict, technique: str) -> None:
    """Refuse resolutions 1…63 (the declared range [0, 8192] cannot say "0 or 64…8192")."""
    r = values.get("resolution", 0)
    if r != 0 and not RES_MIN <= r <= RES_MAX:
        raise InputError(f"{technique}.resolution={r} is out of range: allowed 0 (the light's shadow_map) "
                         f"or {RES_MIN}…{RES_MAX} texels")


def map_settings(frame, light_name: str, values: dict) -> tuple[int, int]:
    """(resolution, depth bits) of ``light_name``'s map: the parameter, or the light's own when 0."""
    spec = frame.scene.spec.light(light_name)
    res = int(values.get("resolution") or spec.shadow_map)
    bits = int(values.get("depth_bits") or spec.depth_bits)
    return res, bits


def view_for(frame, light_name: str, values: dict, translucent: bool = False, with_translucent: bool = False):
    """The (cached) LightView a shadow-map technique samples for ``light_name``; ``translucent``:
    the opaque casters' depth plus the translucent casters' colour and depth (in a scene with
    translucent shapes; the plain view elsewhere). Every light of the frame is cast with it, each
    with its own map settings, in one stage (the render asks for each of them next), and with
    ``with_translucent`` their translucent views too (a technique that reads both)."""
    backface, layers = bool(values.get("backface", False)), map_layers(values)
    own = ViewKey(light_name, *map_settings(frame, light_name, values), backface, None, layers, bool(translucent))
    if frame.has_view(own):
        return frame.views([own])[0]
    flags = dict.fromkeys((bool(translucent),) + ((True,) if with_translucent else ()))
    keys = [ViewKey(l.name, *map_settings(frame, l.name, values), backface, None, layers, flag)
            for flag in flags for l in frame.lights]
    views = frame.views(keys)
    return views[[k.name for k in keys].index(light_name)]


def map_layers(values: dict) -> int:
    """Surfaces per texel the light view keeps for ``bias_mode``: :data:`RASTER_LAYERS` or 1."""
    return RASTER_LAYERS if values.get("bias_mode", "first_hit") == "rasterizer" else 1


@dataclass
class Points:
    """The G-buffer arrays :func:`receiver` reads (``p``, ``ng``, ``valid``), for any set of points."""

    p: object
    ng: object
    valid: object


@dataclass
class SubFrame:
    """A frame whose G-buffer is a :class:`Points` (a subset of the points, or the points as
    another pass reconstructs them): what ``csm`` hands each cascade's family."""

    scene: object
    gbuffer: Points

    @property
    def lights(self):
        return self.scene.spec.lights


@dataclass
class Bias:
    """The bias parameters as opaque Dr.Jit scalars: new values reuse the compiled kernel."""

    depth_bias: object
    slope_scaled: object
    clamp: object
    constant: object
    slope: object
    max_slope: object
    normal_offset: object
    grazing: object


def opaque_bias(values: dict) -> Bias:
    o = lambda k: dr.opaque(mi.Float, float(values[k]))  # noqa: E731
    return Bias(depth_bias=o("depth_bias"), slope_scaled=o("slope_scaled_depth_bias"),
                clamp=o("depth_bias_clamp"), constant=o("constant_bias"), slope=o("slope_bias"),
                max_slope=o("max_slope_bias"), normal_offset=o("normal_offset"),
                grazing=dr.opaque(mi.Float, float(values.get("grazing_slope_bias", 0.0))))  # absent: no grazing term


def to_light(view, p):
    """Unit direction from ``p`` to the light (the light camera's centre, or −forward)."""
    f0 = view.proj.faces[0]
    if f0.ortho:
        return mi.Vector3f(*opaque_values(mi.Float, *[-x for x in f0.R[2]]))
    return dr.normalize(mi.Point3f(*opaque_values(mi.Float, *f0.origin)) - p)


def receiver(frame, view, bias: Bias) -> dict:
    """Project the G-buffer points into ``view`` with the receiver-side biases of §2.3.

    Returns the dict of :meth:`LightView.lookup` for the normal-offset point, plus ``dt``
    (biased receiver NDC depth d̃), ``zbias`` (world units subtracted from z), ``active``
    (valid G-buffer point inside the light camera), ``ng`` (the points' geometric normals).
    """
    gb = frame.gbuffer
    p = gb.p
    ng = mi.Vector3f(gb.ng)
    first = view.lookup(p)
    p_off = mi.Point3f(p + ng * (bias.normal_offset * first["texel"]))
    rec = view.lookup(p_off)
    cs = dr.dot(ng, to_light(view, p))
    c = dr.abs(cs)
    tan = dr.safe_sqrt(1.0 - c * c) / dr.maximum(c, 1e-6)
    zbias = bias.constant + dr.minimum(bias.slope * tan, bias.max_slope)
    zt = rec["z"] - zbias
    f0 = view.proj.faces[0]
    rec["dt"] = view.proj.ndc_depth(zt if f0.ortho else dr.maximum(zt, 1e-12))
    rec["zbias"] = zbias
    rec["active"] = gb.valid & rec["inside"]
    rec["ng"] = ng
    if not isinstance(view, TiledView):   # tiles have texel sizes of their own per axis: no grazing term there
        rec["rslope"] = grazing_slope(view, rec, ng, cs, tan, bias)
    return rec


def grazing_slope(view, rec, ng, cos, tan, bias: Bias):
    """The receiver's tangent-plane depth gradient (∂d/∂u, ∂d/∂v) per texel
    (:func:`receiver_plane_gradient`) × ``grazing_slope_bias``, for receivers facing the light with
    0 ≤ cos(n, l) < :data:`GRAZING_MAX_COS`, (0, 0) for the others. The gradient grows like
    tan(angle(n, l)); it is scaled down to tan = :data:`GRAZING_MAX_TAN` where tan is larger (an
    edge-on face's slope is unbounded). :func:`depth_test` lowers the receiver's depth by the
    plane's depth drop toward the tested texel's centre (never raises it)."""
    gx, gy = receiver_plane_gradient(view, rec, ng)
    k = bias.grazing * dr.minimum(1.0, GRAZING_MAX_TAN / dr.maximum(tan, 1e-6))
    grazing = (cos >= 0.0) & (cos < GRAZING_MAX_COS)
    return dr.select(grazing, k * gx, 0.0), dr.select(grazing, k * gy, 0.0)


def grazing_drop(rec, ix, iy):
    """max(0, −(g_u·Δu + g_v·Δv)): how far the grazing receiver's scaled tangent plane
    (:func:`grazing_slope`) lies nearer the light at the centre of texel (ix, iy) than at the
    receiver (Δ = texel centre − receiver, in texels); 0 for non-grazing receivers."""
    gx, gy = rec["rslope"]
    return dr.maximum(0.0, -(gx * (mi.Float(ix) + 0.5 - rec["u"]) + gy * (mi.Float(iy) + 0.5 - rec["v"])))


def _light_space(view, rec, vec):
    """World vector ``vec`` in the light space of each receiver's face (rows right, up, forward)."""
    return [dr.dot(vec, r) for r in face_rows(view.proj, rec["face"])]


def receiver_plane_gradient(view, rec, ng, min_cos: float = 0.0):
    """(∂d/∂u, ∂d/∂v): NDC depth per texel of the receiver's tangent plane (normal ``ng``) in the
    shadow map. Over a plane n·X = c (light space), 1/z (perspective) or z (orthographic) is
    linear in the NDC coordinates x' = 2u/N − 1, y' = 1 − 2v/N, so d is linear in (u, v):

        perspective  ∂d/∂x' = −f·n_near/(f − n_near) · n_x·tan/c,  c = n·q
        orthographic ∂d/∂x' = −n_x·half_extent/(n_z·(f − n_near))
    (y' likewise with n_y), ∂/∂u = 2/N·∂/∂x', ∂/∂v = −2/N·∂/∂y'. Grazing planes (c or n_z → 0)
    are kept finite (|denominator| ≥ 1e-6·scale); with ``min_cos`` > 0 a receiver whose normal makes
    |cos| < ``min_cos`` with the direction to the light gets (0, 0): its plane, extrapolated across
    the taps, would reach far past the surfaces next to it."""
    f0 = view.proj.faces[0]
    N = view.res
    near, s = opaque_values(mi.Float, f0.near, f0.scale)
    nx, ny, nz = _light_space(view, rec, mi.Vector3f(ng))
    x = 2.0 * rec["u"] / N - 1.0
    y = 1.0 - 2.0 * rec["v"] / N

    def safe(c, eps):
        return dr.select(dr.abs(c) < eps, dr.select(c < 0, -eps, eps), c)

    if f0.ortho:
        den = safe(nz, 1e-6) * opaque_values(mi.Float, f0.far - f0.near)[0]
        gx, gy = -nx * s / den, -ny * s / den
    else:
        z = rec["z"]
        c = safe(nx * x * s * z + ny * y * s * z + nz * z, 1e-6 * dr.maximum(dr.abs(z), near))
        k = opaque_values(mi.Float, -f0.far * f0.near / (f0.far - f0.near) * f0.scale)[0]
        gx, gy = k * nx / c, k * ny / c
    if min_cos > 0.0:
        if f0.ortho:
            cos = dr.abs(nz)
        else:
            to_light = dr.normalize(mi.Vector3f(x * s, y * s, 1.0))
            cos = dr.abs(nx * to_light.x + ny * to_light.y + nz * to_light.z)
        grazing = cos < min_cos
        gx, gy = dr.select(grazing, 0.0, gx), dr.select(grazing, 0.0, gy)
    return gx * (2.0 / N), gy * (-2.0 / N)


def texel_index(u):
    """Nearest texel of a continuous texel coordinate (centres at i + 0.5)."""
    return mi.Int32(dr.floor(u))


def rasterizer_bias(view, D, slope, bias: Bias):
    """Direct3D's depth bias of a texel with stored depth ``D`` and caster slope ``slope``."""
    if view.bits == 32:
        # r = 2^(exponent(D) - 23): keep D's exponent bits, subtract 23 from the exponent
        e = dr.reinterpret_array(mi.UInt32, D) & 0x7F800000
        r = dr.select(e > (23 << 23), dr.reinterpret_array(mi.Float, e - (23 << 23)), 0.0)
    else:
        r = mi.Float(1.0 / (2 ** view.bits - 1))
    b = bias.depth_bias * r + bias.slope_scaled * slope
    b = dr.select(bias.clamp > 0, dr.minimum(bias.clamp, b), dr.select(bias.clamp < 0, dr.maximum(bias.clamp, b), b))
    return b


def stored_depth(view, face, ix, iy, bias: Bias):
    """(biased stored depth D', empty, Bias) of texel (ix, iy) of ``face`` (clamped to the face).

    A view with layers (``bias_mode = "rasterizer"``) holds the surfaces behind the first too:
    D' = min over them of saturate(D_k + Bias(D_k, slope_k)), what a rasterizer's depth test keeps
    when every fragment is biased; Bias is then D' − D_0."""
    D = view.fetch("depth", face, ix, iy)
    S = view.fetch("slope", face, ix, iy)
    b = rasterizer_bias(view, D, S, bias)
    Db = dr.clip(D + b, 0.0, 1.0)
    layers = view.layers
    for k in range(1, layers):
        Dk = view.fetch("layer_depth", face, ix, iy, layer=k)
        Sk = view.fetch("layer_slope", face, ix, iy, layer=k)
        Db = dr.select(Dk < 1.0, dr.minimum(Db, dr.clip(Dk + rasterizer_bias(view, Dk, Sk, bias), 0.0, 1.0)), Db)
    if layers > 1:
        b = Db - D
    return Db, D >= 1.0, b


def depth_test(view, rec: dict, ix, iy, bias: Bias):
    """H(z(t_i) − z̃) at one texel: 1.0 lit, 0.0 shadowed (empty texels are lit)."""
    Db, empty, _ = stored_depth(view, rec["face"], ix, iy, bias)
    dt = rec["dt"] - grazing_drop(rec, ix, iy) if "rslope" in rec else rec["dt"]
    return dr.select(empty | (Db >= dt), 1.0, 0.0)


class ShadowMapTechnique(Technique):
    """A technique that samples each light's shadow map. Its per-light part chooses the
    light's map (:meth:`view`) and :meth:`evaluate` s it: builds the receivers and calls
    :meth:`filter` (the one thing ``hard`` and ``pcf`` implement; ``pcss`` and the prefiltered
    families override :meth:`evaluate`); ``texel``, ``receiver_bias`` and ``depth_bias`` AOVs and
    the map's stats (``maps``: resolution, depth bits, faces, texels, near, far) come with it."""

    source = "[Buljan 2020]"

    def resolve(self, overrides: dict | None = None) -> dict:
        values = super().resolve(overrides)
        check_map_params(values, self.name)
        return values

    def unsupported(self, spec) -> str | None:
        return needs_mitsuba_geometry(self.name, spec)

    def filter(self, view, rec: dict, bias: Bias, values: dict):  # pragma: no cover - interface
        raise NotImplementedError

    def bias_values(self, values: dict) -> dict:
        """The values :func:`opaque_bias` reads (all of ``BIAS_PARAMS``)."""
        return values

    def filter_variance(self, values: dict) -> float:
        """Per-axis variance (texels²) of the footprint whose depth tests one point averages: one
        nearest-texel test is a box one texel wide, 1/12 (what a transfer to an engine's filter matches)."""
        return 1.0 / 12.0

    def prepare(self, frame, values, ctx):
        ctx.bias = opaque_bias(self.bias_values(values))

    def view(self, frame, light, values, ctx):
        """The LightView the technique samples for ``light`` (one map per light)."""
        return view_for(frame, light.name, values)

    def render_light(self, frame, light, values, ctx):
        return self.evaluate(frame, light, self.view(frame, light, values, ctx), values, ctx)

    def evaluate(self, frame, light, view, values, ctx) -> LightResult:
        """Visibility, AOVs and stats of ``light`` at ``frame``'s G-buffer points from the given
        map ``view`` (what :meth:`render_light` does after choosing the view). ``csm`` calls it
        once per cascade, with the cascade's map and the points that cascade selects."""
        rec = receiver(frame, view, ctx.bias)
        v = self.filter(view, rec, ctx.bias, values)
        _, _, b = stored_depth(view, rec["face"], texel_index(rec["u"]), texel_index(rec["v"]), ctx.bias)
        return LightResult(v, {"texel": rec["texel"], "receiver_bias": rec["zbias"], "depth_bias": b},
                           active=rec["active"], stats=map_stats(view), maps=[map_entry(view)])

    def summarise(self, frame, values, ctx, lights):
        return {"shadow_map_texels": sum(m["texels"] for st in lights.values() for m in st.get("maps", ()))}


def map_stats(view) -> dict:
    """The per-light map stats readers use (``stats["resolution"][light]`` ...)."""
    return {"resolution": view.res, "depth_bits": view.bits, "faces": view.nfaces}


def map_entry(view) -> dict:
    """One map's entry of ``stats["lights"][light]["maps"]``: its format and its own projection."""
    f0 = view.proj.faces[0]
    return {"resolution": view.res, "depth_bits": view.bits, "faces": view.nfaces,
            "texels": view.nfaces * view.res * view.res, "near": float(f0.near), "far": float(f0.far),
            "projection": "orthographic" if f0.ortho else "perspective"}


@register
class HardShadowMap(ShadowMapTechnique):
    """Plain shadow map: one nearest-texel biased depth test per point (§2.1, §2.3)."""

    name = "hard"
    title = "Shadow map (hard, biased)"
    summary = ("shadow map with Direct3D depth bias, receiver constant/slope bias, normal offset "
               "and back-face depth")
    params = BIAS_PARAMS
    #: the biases trade acne in the lit area against Peter Panning at contacts, and the penumbra
    #: mask sees neither (fitted there, the slope bias runs negative for a 0.5 % gain)
    fit_loss = "rmse"

    def fit_params(self, values):
        """No parameter is differentiable (the test is a step): ``fit`` searches the two biases."""
        return ("slope_scaled_depth_bias", "depth_bias")

    def filter(self, view, rec, bias, values):
        return depth_test(view, rec, texel_index(rec["u"]), texel_index(rec["v"]), bias)


__doc__ += "\n\nParameters of ``hard`` (generated from the declaration):\n\n" + param_table_markdown(HardShadowMap)
