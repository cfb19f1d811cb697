"""Percentage-closer soft shadows (``pcss``) [Buljan 2020, §3.6, Code A.9].

PCSS is PCF whose filter width follows the estimated penumbra. Per shading point with
light-space depth z̃ (the receiver's linear depth, ``LightView.lookup()['z']`` of the
normal-offset point) and the light size w_light (``light_scale`` × the light's own size, see
below), the three steps of §3.6:

1. *blocker search* (Računanje zaklonjenosti): over the square region of full width
   ``w_search = (z̃ − z_near)/z̃ · w_light`` (near-plane units, z_near = the light camera's near
   plane ``Face.near``; "from similar triangles", the cone from the receiver to the light cut
   by the near plane) take ``blocker_samples`` taps and average the linear depths z
   (``LightView.z``) of the texels that are closer than the receiver, closer by exactly the
   biased test of ``hard`` (all of ``BIAS_PARAMS``, §2.3; Code A.9 has a fixed 0.001 instead):
   a texel is a blocker iff its depth test says "shadowed". No blocker → the point is lit
   (visibility 1) and the PCF step is skipped for it;
2. *penumbra estimate* (Procjena širine penumbre), one planar blocker parallel to the light at
   z_avg: ``w_penumbra = (z̃ − z_avg)/z_avg · w_light`` (world units at the receiver's depth);
3. *filtering* (Filtriranje): PCF over the square of full width ``w_f = z_near/z̃ · w_penumbra``
   (near-plane units), ``w_f = max(w_f, w_fmin)`` with w_fmin = ``min_filter`` (texels), sampled
   by ``pcf_samples`` taps.

Units. The formulas are in light-view units on the near plane; world ↔ texels goes through the
near plane's size 2·z_near·tan(half fov) for N texels (``Face.scale`` = tan(half fov)), i.e. one
texel is 2·z_near·tan/N near-plane units. Hence w_search[texels] = w_search·N/(2·z_near·tan), and
w_f[texels] = (z_near/z̃)·w_penumbra·N/(2·z_near·tan) = w_penumbra/(2·z̃·tan/N): the penumbra's
world width over one texel's world width at the receiver's depth (``lookup()['texel']``).
A box filter of full width W over a straight shadow edge is a linear ramp of width W, which is
exactly the visible fraction of a square light of side w_light behind a straight edge parallel
to it (the closed form of ``parallel_planes``), so every width is a full width, not a radius
(Code A.9 multiplies unit-disk offsets by a "radius"). Cube maps (point, sphere lights) use the
same formulas per face; taps are clamped to the receiver's face (no seam crossing), so penumbrae
that straddle a cube edge are cut there.

Orthographic light cameras (directional lights) have no light position: the light is a source at
infinity of angular size w_light (radians), every depth is a distance along the light's
direction, and similar triangles with parallel rays give

    w_search   = (z̃ − z_near) · tan(w_light)      (world units = texels · 2·half_extent/N)
    w_penumbra = (z̃ − z_avg)  · tan(w_light)      (world units)
    w_f        = w_penumbra                        (no perspective division)

(z_near = the orthographic camera's near plane, which lies outside the scene's bounding sphere).

Light size. ``light_scale`` is the one light-size convention of every family
(:data:`~shadowlab.techniques.base.LIGHT_SCALE`): a multiplier of each light's own size, so
w_light = ``light_scale`` × :func:`scene_light_size` per light, in world units (radians for
directional lights), and one value fits every light of a scene in proportion to its size;
``light_scale`` 1 (the default) is the scene's light. A light's size is
``LightSpec.physical_size`` times a per-kind factor, the side of the square with the light's
area (for directional lights, with its angular area). PCSS models a square light (a square
filter), and a square of the same area has nearly the same edge ramp as the light:

| light kind | ``LightSpec.physical_size`` | × | w_light at ``light_scale`` = 1 |
|---|---|---|---|
| rect w × h | √(w·h) | 1 | √(w·h) (a square light exactly) |
| disk, spot, radius r | 2r (diameter) | √π/2 | √π·r ≈ 1.772 r |
| sphere, point, radius r | 2r (its silhouette is a disk of radius r) | √π/2 | √π·r |
| directional, angular diameter θ | θ (radians) | √π/2 | √π/2·θ ≈ 0.886 θ (radians) |

For a disk the equal-area square's 10–90 % edge ramp is 0.8·√π·r = 1.418 r against the disk's
1.374 r (a square of side 2r, the diameter, would give 1.6 r). For w ≠ h the true ramp is w or h
depending on the edge's direction; √(w·h) is their geometric mean. Delta lights (r = 0, θ = 0)
get 0 at any ``light_scale``: a hard shadow widened only by ``min_filter``.

Sampling patterns (fixed, part of the technique's definition; uploaded as data, so each count
compiles its own kernel once and nothing else does):

* blocker search (:data:`SEARCH_SETS`): 16, 25 or 32 Poisson-disk points in the unit square,
  Mitchell's best candidate (64 candidates per point from the counter-based splitmix64 stream of
  :mod:`shadowlab.techniques._random`, seed :data:`SEARCH_SEED`), then centred (mean 0) and scaled
  back into [−½, ½]² if centring moved a point out; offsets in units of w_search. 16–25 is the
  source's "usually enough" and Code A.9 uses 16; the default 32 is the declared maximum (the
  region is wide, because blockers at the near plane would be seen through all of it: 75 texels
  on ``parallel_planes``, 110–140 on ``contact`` for the 1 m lights);
* PCF (:func:`pcf_pattern`): a centred Hammersley set, x_k = (k + ½)/n, y_k = φ₂(k) + ½/n (φ₂ the
  base-2 radical inverse), minus ½: for n a power of two every row and every column of an n×n
  grid holds one tap, so a shadow edge along either axis of the map gets n levels instead of
  √n; n = 1 is one tap at the centre (hardware 2×2 PCF), weights 1/n.

Every tap (search and PCF) is a *bilinear* tap: the four texels around it are depth-tested
(nearest-texel biased tests, exactly ``hard``'s) and weighted by the bilinear fractions, like
hardware 2×2 PCF; in the search, a blocker's weight also weights its depth in z_avg (the
"blocker count" is the sum of those weights, 0 … ``blocker_samples``).

``receiver_plane`` (not in the source; [Isidoro 2006], "receiver plane depth bias", as in NVIDIA's
PCSS samples): each tap compares against the depth of the receiver's tangent plane (from the
G-buffer's geometric normal) at that tap instead of z̃ at the centre. NDC depth is linear in the
shadow-map coordinates over a plane, so the tap's reference is d̃ + ∂d/∂u·Δu + ∂d/∂v·Δv, exact
for planar receivers. Without it a receiver that is tilted in the light's view finds itself as a
"blocker" in the wide search region and in wide PCF footprints (PCSS acne): on ``contact`` 30 % of
the truly lit pixels come out below 0.9 (1.5 % with it), and the RMSE of the shaded image is 0.099
(0.028 with it; ``hard`` 0.058, ``pcf`` 0.046); ``cornell`` 0.0104 → 0.0057, ``two_lights``
0.037 → 0.019, ``analytic_sphere`` 0.018 → 0.013, ``parallel_planes`` unchanged (its receivers
face the light). Default on, a deliberate departure from [Buljan 2020, §3.6] (which compares with z̃): with
the source's comparison PCSS is worse than the plain shadow map on every tilted receiver, which
is a property of that comparison rather than of PCSS; ``--set pcss.receiver_plane=false``
gives the source's algorithm.

Differentiability. Through the bilinear weights the visibility is a continuous, piecewise smooth
function of the tap positions, hence of w_light: ``light_scale`` is ``differentiable``.
Pass it as a Dr.Jit ``mi.Float`` of width 1 with gradients enabled (the convention of every
family, :meth:`~shadowlab.techniques.base.Technique.resolve`): w_light = ``light_scale`` ×
:func:`scene_light_size` stays in the expression, and
``dr.backward`` of a loss on the visibility reaches it through both the search region and the
filter width (``tests/test_pcss.py`` compares it with central differences). As a plain number it
enters through ``dr.opaque``. ``min_filter`` (a ``max``) and the biases (steps) are not
differentiable; ``blocker_samples``, ``pcf_samples`` and ``receiver_plane`` are structural (one
kernel each).

Measured on ``parallel_planes`` (128², 1024² fp32 map, committed reference, defaults;
``tests/test_pcss.py``): penumbra RMSE of the shaded image 0.0092 (``hard`` 0.397, ``pcf``
default 3×3 0.341), of the visibility 0.0067; 10–90 % penumbra width on the floor 0.801 world
units against the prediction 0.8·w_penumbra = 0.800 (truth fit 0.78, closed form 0.8); with
``light_scale`` 0.5 / 1 / 1.5 (the light's side is 1) the widths are 0.400 / 0.801 / 1.200 and the visibility is within
RMSE ≤ 0.001 of the closed form for that light size. With ``light_scale`` → 0 the result equals
``hard`` at all but 0.8 % of the pixels (the one-texel bilinear ramp of ``min_filter``); with
``pcf_samples`` 1 and ``min_filter`` 0 on every pixel.

AOVs per light: ``<light>.penumbra_width`` (w_penumbra, world units at the receiver),
``<light>.penumbra_texels`` (the same in shadow-map texels, before ``min_filter``),
``<light>.filter_texels`` (w_f used, texels), ``<light>.blocker_depth`` (z_avg, light-space
depth; 0 where no blocker), ``<light>.blocker_count`` (weighted count of blocker taps),
``<light>.search_texels`` (w_search, texels), plus ``hard``'s ``texel``, ``receiver_bias`` and
``depth_bias``; all 0 where the point is inactive (no surface, outside the light camera). Stats:
``samples_per_pixel`` (mean taps per active point: the search's, plus the PCF's where a
blocker was found; each tap reads 2×2 texels), per light and pooled as ``all``.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from .base import (LightResult, Param, Pooled, device_count, light_scale_param, param_table_markdown, register,
                   scaled_size)
from .shadow_map import (BIAS_PARAMS, ShadowMapTechnique, map_entry, map_stats, receiver, receiver_plane_gradient,
                         stored_depth, texel_index)
from .blocker_search import (BLOCKER_COUNTS, PCF_COUNTS, pcf_arrays, pcf_loop, search_arrays,
                             penumbra_width, scene_light_size, search_loop, search_width)

SOURCE = "[Buljan 2020, §3.6]"

PCSS_PARAMS = (
    light_scale_param(SOURCE, doc="w_light = light_scale × the side of the light's equal-area square: rect √(w·h); "
                                  "disk/sphere/spot/point √π·r; directional √π/2·angular diameter (radians)"),
    Param("blocker_samples", 32, "choice", units="taps", choices=BLOCKER_COUNTS, source=SOURCE,
          doc="taps of the blocker search over the w_search square (fixed best-candidate Poisson set; bilinear "
              "taps; 16–25 in the source)"),
    Param("pcf_samples", 64, "choice", units="taps", choices=PCF_COUNTS, source=SOURCE,
          doc="taps of the PCF step over the w_f square (centred Hammersley set, box weights; bilinear taps; "
              "1 = one 2×2 bilinear tap)"),
    Param("min_filter", 1.0, "float", 0.0, 64.0, "texels", False, source=SOURCE,
          doc="w_fmin: the PCF footprint is at least this wide (full width), w_f = max(w_f, w_fmin)"),
    Param("receiver_plane", True, "bool", source="[Isidoro 2006]",
          doc="receiver plane depth bias: every tap compares against the receiver's tangent plane at that "
              "tap (not in the source; removes self-blocking of tilted receivers)"),
)


# ----------------------------------------------------------------------------------------------
# the technique

@register
class PCSS(ShadowMapTechnique):
    """Percentage-closer soft shadows: blocker search, penumbra estimate, variable-width PCF."""

    name = "pcss"
    title = "PCSS (percentage-closer soft shadows)"
    summary = ("blocker search, penumbra width from a planar blocker parallel to the light, then PCF of that "
               "width; bilinear taps, so the light size is differentiable")
    params = PCSS_PARAMS + BIAS_PARAMS

    def light_size(self, light, values: dict):
        """w_light of ``light`` as a Dr.Jit Float: ``light_scale`` × :func:`scene_light_size`
        (a Dr.Jit ``light_scale`` stays in the expression, a number enters opaquely)."""
        w, val = scaled_size(values["light_scale"], scene_light_size(light))
        if light.kind == "directional" and val >= 0.5 * math.pi:
            sc = values["light_scale"]
            sc = float(dr.detach(sc)[0]) if isinstance(sc, dr.ArrayBase) else float(sc)
            raise InputError(f"pcss.light_scale={sc:g} gives w_light = {val:g} rad for directional light "
                             f"{light.name!r}: an angular size must be below π/2 (the sun's disk is 0.0093 rad)")
        return w

    def pcss(self, frame, view, rec, bias, values, w_light):
        """The three steps of §3.6 for the receivers ``rec``; returns (visibility, dict of AOVs)."""
        f0 = view.proj.faces[0]
        N = view.res
        zr = rec["z"]
        for name in ("depth", "slope", "z"):  # upload before the symbolic loops record
            view.dr(name)
        g = receiver_plane_gradient(view, rec, rec["ng"]) if values["receiver_plane"] else None
        w_search = search_width(view, zr, w_light)
        # 1. blocker search
        nb = int(values["blocker_samples"])
        px, py = search_arrays(nb)
        cnt, zsum = search_loop(view, rec, g, bias, w_search, px, py, nb)
        found = rec["active"] & (cnt > 0.0)
        z_avg = dr.select(found, zsum / dr.maximum(cnt, 1e-20), zr)
        # 2. penumbra width (world units at the receiver), 3. filter width (texels)
        w_pen = penumbra_width(view, zr, z_avg, w_light)
        if f0.ortho:
            w_pen_tex = w_pen * (1.0 / (2.0 * f0.scale / N))
        else:
            w_pen_tex = w_pen / dr.maximum(rec["texel"], 1e-12)
        w_f = dr.maximum(w_pen_tex, dr.opaque(mi.Float, float(values["min_filter"])))
        npcf = int(values["pcf_samples"])
        px, py = pcf_arrays(npcf)
        dark = pcf_loop(view, rec, g, bias, w_f, px, py, npcf, found)
        vis = dr.select(found, dr.clip(1.0 - dark * (1.0 / npcf), 0.0, 1.0), 1.0)
        act = rec["active"]
        aovs = {"penumbra_width": dr.select(found, w_pen, 0.0), "penumbra_texels": dr.select(found, w_pen_tex, 0.0),
                "filter_texels": dr.select(found, w_f, 0.0), "blocker_depth": dr.select(found, z_avg, 0.0),
                "blocker_count": dr.select(act, cnt, 0.0), "search_texels": dr.select(act, w_search, 0.0)}
        return vis, aovs

    def filter(self, view, rec, bias, values):  # pragma: no cover - render_light() does the work
        raise NotImplementedError("pcss renders through PCSS.render_light (it needs the frame's normals)")

    def evaluate(self, frame, light, view, values, ctx):
        rec = receiver(frame, view, ctx.bias)
        w_light = self.light_size(light, values)
        v, extra = self.pcss(frame, view, rec, ctx.bias, values, w_light)
        _, _, b = stored_depth(view, rec["face"], texel_index(rec["u"]), texel_index(rec["v"]), ctx.bias)
        return LightResult(v, {"texel": rec["texel"], "receiver_bias": rec["zbias"], "depth_bias": b, **extra},
                           active=rec["active"], maps=[map_entry(view)],
                           stats={**map_stats(view), "light_size": dr.detach(w_light)},
                           counts={"active": device_count(rec["active"]),
                                   "found": device_count(rec["active"] & (extra["blocker_count"] > 0))})

    def light_stats(self, frame, light, values, ctx, result):
        """Taps per active point: the search's, plus the PCF's where a blocker was found (the
        points counted in the render's kernel)."""
        nb, npcf = int(values["blocker_samples"]), int(values["pcf_samples"])
        n_act, n_found = result.counts["active"], result.counts["found"]
        return {"samples_per_pixel": Pooled(float(nb * n_act + npcf * n_found), n_act)}

    def summarise(self, frame, values, ctx, lights):
        return {**super().summarise(frame, values, ctx, lights), "blocker_samples": int(values["blocker_samples"]),
                "pcf_samples": int(values["pcf_samples"]), "texels_per_sample": 4,
                "receiver_plane": bool(values["receiver_plane"])}


__doc__ += "\n\nParameters of ``pcss`` (generated from the declaration):\n\n" + param_table_markdown(PCSS)
