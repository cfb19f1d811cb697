"""Soft shadows of signed distance fields: single-ray cone marching and its references
([Bán 2019, ch. 3–5]; algorithms in :mod:`shadowlab.sdf.soft`, chapter 5 in
:mod:`shadowlab.techniques._sdf_shading`).

| technique | what it is | source |
|---|---|---|
| ``sdf_hard`` | sphere tracing toward the light's centre: a point light's hard shadow | [Bán 2019, §3.1] |
| ``sdf_aa_hard`` | the single-ray algorithm with light radius 0: hard shadow, edge anti-aliased by the surface sphere | [Bán 2019, §4.3.3] |
| ``sdf_base`` | Algorithm 3: threshold / trace cones kept ε apart in τ, τ⁻¹ by bisection | [Bán 2019, §4.3] |
| ``sdf_linear`` | Algorithm 4: trace cone e = επ/2 below in r, one τ at the end (the thesis' recommendation) | [Bán 2019, §4.4.1] |
| ``sdf_discrete`` | Algorithm 5: the lit fraction walks down in steps of ε | [Bán 2019, §4.4.2] |
| ``sdf_convex`` | Algorithm 4 with convex-optimised steps while R^C ≥ 0 | [Bán 2019, §4.4.3] |
| ``sdf_quilez`` | [Quílez 2010] / [Aaltonen 2018] penumbra estimate, k from the light size | [Bán 2019, §6.4] |
| ``sdf_mc`` | Monte-Carlo in the cone: Halton points, r-weighted or r = √u polar sampling | [Bán 2019, §3.3.1] |
| ``sdf_edge_mc`` | chapter 5: Eq. 5.1 by light sampling with visibility from the single ray's edge line (5.3.1), sphere-traced (5.1), or the separable Eq. 5.2 | [Bán 2019, §5.2–5.4] |

Every ``sdf_*`` technique needs the scene's signed distance field (``frame.sdf``; scenes made
of rectangles, disks, cubes, spheres and capped cylinders have one, as have ``[[sdf]]`` scenes);
on a scene with meshes or alpha-tested shapes it raises an InputError.

**Shading points.** With the Mitsuba G-buffer (every scene whose objects have Mitsuba twins) a
point p on the surface gets the surface sphere of [Bán 2019, §2.9], radius ``R0 = surface_radius`` ×
the width of one pixel at p's distance from the camera (``|p − camera|·2·tan(fov/2)/(W·s)``),
and the march starts from its centre ``p + R0·n`` (n the geometric normal facing the camera).
With the cone-traced G-buffer of ``[[sdf]]`` scenes the point already is the centre of its
surface sphere (radius ``f(p)``, :mod:`shadowlab.render.sdf_gbuffer`); ``surface_radius`` is then unused.

**Light size mapping.** The single-ray techniques, ``sdf_quilez`` and ``sdf_mc`` model every light
as a sphere (centre, radius R) by :func:`shadowlab.scene.lights.light_sphere` (``fit="equal_area"``):
sphere / point lights exactly, disks and spots by their radius, a w × h rectangle by the disk of
equal area (R = √(w·h/π)), a directional light by the sun disk the ground truth renders; the
radius used is ``light_scale`` × R (``light_scale`` 1 = the scene's light; fitting moves it; 0 =
a point light). ``sdf_edge_mc`` samples the actual emitter and bounds it by its sphere
(``fit="bounding"``, [Bán 2019, §5.4]). ``sdf_hard`` and ``sdf_aa_hard`` use the centre only.

**Differentiability.** ``light_scale`` of ``sdf_base``, ``sdf_linear``, ``sdf_convex`` and
``sdf_quilez`` is differentiable: the marches run detached and the result is recomputed from the
minimum they found (τ̂(f_min/ρ(t_min)), resp. clamp(k·min h/t)), whose derivative in the light
radius is that of the minimum (envelope theorem); pass a Dr.Jit Float of width 1 with gradients
enabled (the convention of every family, :meth:`Technique.resolve`). ``sdf_discrete`` is piecewise constant.

AOVs per light: ``<light>.iterations`` (SDF evaluations per point), and for the single-ray
techniques ``<light>.r_min`` (the relative distance found, 1 where the cone was clear) and
``<light>.t_min`` (distance along the march of the minimum). Stats: ``sdf_evals_per_point`` (mean
over the shaded points, per light and ``all``), ``at_i_max`` (fraction of points stopped by
``i_max``) and ``light_radius`` per light.
"""  # noqa: E501

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..errors import InputError
from ..scene.lights import light_sphere
from ..sdf import soft
from ..sdf.trace import hard_visibility
from . import _sdf_shading as sdf_shading
from .base import (LightResult, Param, Pooled, Technique, device_count, device_total, light_scale_param, needs_sdf,
                   param_table_markdown, register, scaled_size)

SOURCE = "[Bán 2019]"

EPSILON = Param("epsilon", 0.03125, "float", 1.0 / 256, 0.5, "lit fraction", source="[Bán 2019, §4.2]",
                doc="sensitivity ε: the smallest change of the lit fraction the march is sure to notice, i.e. its "
                    "maximal error (1/256 … 1/10 in the thesis, no visible gain below 1/30; 1/32 here)")
DIRECTION = Param("direction", "A", "choice", choices=soft.DIRECTIONS, source="[Bán 2019, §4.3.2]",
                  doc="A: march from the surface point to the light; B: from the light to the point (same cone)")
I_MAX = Param("i_max", 256, "int", 1, 8192, "steps", source="[Bán 2019, Alg. 3]",
              doc="the march stops after this many SDF evaluations and keeps what it found")
_SPHERE = ("radius of the light sphere = light_scale × the scene light's radius R (sphere/point/disk/spot r; "
           "rect √(w·h/π); directional: the sun disk)")
LIGHT_SCALE = light_scale_param("[Bán 2019, §3.2]", True, _SPHERE)
LIGHT_SCALE_ND = light_scale_param(
    "[Bán 2019, §3.2]", False, _SPHERE + " (not differentiable: the result is piecewise constant)"
)
SURFACE_RADIUS = Param("surface_radius", 0.1, "float", 0.01, 8.0, "pixels", source="[Bán 2019, §2.9]",
                       doc="radius R0 of the surface sphere around a Mitsuba G-buffer point, in pixel widths at its "
                           "distance; the march starts from p + R0·n (cone-traced G-buffers bring their own)")
AA_SURFACE_RADIUS = Param("surface_radius", 0.5, "float", 0.01, 8.0, "pixels", source="[Bán 2019, §4.3.3]",
                          doc="radius R0 of the surface sphere (pixel widths at the point's distance): the shadow "
                              "edge becomes a ramp 2·R0 wide on the receiver; 0.5 = one pixel")
HIT_EPS = Param("hit_eps", 1e-4, "float", 1e-7, 1e-1, "world units", source="[Bán 2019, Alg. 2]",
                doc="sphere tracing reports a hit where f < hit_eps")


def require_sdf(frame, technique: str):
    """``frame.sdf`` or an InputError naming the scene and what to use instead."""
    sdf = getattr(frame, "sdf", None)
    if sdf is None:
        raise InputError(
            f"technique {technique!r} needs a signed distance field, and scene {frame.scene.name!r} has none "
            "(meshes or alpha-tested shapes have no SDF twin); run it on a scene made of rectangles, disks, cubes, "
            "spheres and capped cylinders or with [[sdf]] objects, e.g. sdf_simple, sdf_composite, contact, "
            "mandelbulb (`shadowlab scenes`)")
    return sdf


def surface_points(frame, surface_radius):
    """(start points, surface-sphere radius R0) of the frame's shading points (module docstring)."""
    gb = frame.gbuffer
    radius = getattr(gb, "radius", None)
    if radius is not None:
        return mi.Vector3f(gb.p), dr.maximum(mi.Float(radius), 1e-6)
    cam = frame.scene.spec.camera
    W = cam.resolution[0]
    per_unit = 2.0 * math.tan(math.radians(cam.fov) / 2.0) / (W * gb.ss)
    dist = dr.norm(mi.Vector3f(gb.p) - mi.Vector3f(gb.rays.o))
    s = surface_radius if isinstance(surface_radius, dr.ArrayBase) else dr.opaque(mi.Float, float(surface_radius))
    R0 = dr.maximum(dist * per_unit * s, 1e-6)
    return mi.Vector3f(gb.p) + mi.Vector3f(gb.ng) * R0, R0


class SDFTechnique(Technique):
    """The SDF family's per-light part: :meth:`light_visibility` gives per-point Dr.Jit
    visibility, AOVs (``iterations``: SDF evaluations per point) and the light radius used."""

    source = SOURCE

    def light_radius(self, frame, light, values):
        """(centre, radius as a Dr.Jit Float of width 1, its value) of the light's sphere:
        ``light_scale`` × the sphere's radius R (:func:`~shadowlab.techniques.base.scaled_size`)."""
        center, R = light_sphere(frame.scene, light)
        r, rv = scaled_size(values.get("light_scale", 1.0), R)
        return center, r, rv

    def light_visibility(self, frame, sdf, light, o, R0, values):  # pragma: no cover - interface
        raise NotImplementedError

    def unsupported(self, spec) -> str | None:
        return needs_sdf(self.name, spec)

    def prepare(self, frame, values, ctx):
        ctx.sdf = require_sdf(frame, self.name)
        ctx.o, ctx.R0 = surface_points(frame, values.get("surface_radius", SURFACE_RADIUS.default))

    def render_light(self, frame, light, values, ctx):
        v, extra, radius = self.light_visibility(frame, ctx.sdf, light, ctx.o, ctx.R0, values)
        mask = frame.gbuffer.valid
        counts = {"points": device_count(mask)}
        if "iterations" in extra:   # SDF evaluations, counted in the render's kernel (float64: exact)
            its = dr.detach(extra["iterations"])
            counts["evals"] = device_total(dr.select(mask, its, 0.0))
            if values.get("i_max"):
                counts["stopped"] = device_count(mask & (its >= values["i_max"]))
        return LightResult(v, extra, active=mask, stats={"light_radius": radius}, counts=counts)

    def light_stats(self, frame, light, values, ctx, result):
        """SDF evaluations per shaded point and the share of points stopped by ``i_max``."""
        c = result.counts
        n, total = c["points"], c.get("evals", 0.0)
        at = c["stopped"] / n if n and "stopped" in c and self.name not in ("sdf_mc", "sdf_edge_mc") else 0.0
        return {"sdf_evals_per_point": Pooled(total, n, total / n if n else 0.0), "at_i_max": at}


@register
class SDFHard(SDFTechnique):
    name = "sdf_hard"
    title = "SDF hard shadow (sphere tracing toward the light)"
    summary = "point-light hard shadow: sphere tracing from the surface point toward the light's centre [Hart 1996]"
    params = (I_MAX, HIT_EPS, SURFACE_RADIUS)

    def light_visibility(self, frame, sdf, light, o, R0, values):
        center, _ = light_sphere(frame.scene, light)
        v, its = hard_visibility(sdf, o, None, center, eps=values["hit_eps"], i_max=values["i_max"],
                                 return_iterations=True)
        return v, {"iterations": mi.Float(its)}, 0.0


class SingleRay(SDFTechnique):
    """Algorithms 3–5 and the convex variant (:func:`shadowlab.sdf.soft.march`)."""

    variant = "linear"

    def radius_for(self, frame, light, values):
        return self.light_radius(frame, light, values)

    def light_visibility(self, frame, sdf, light, o, R0, values):
        center, R, Rv = self.radius_for(frame, light, values)
        variant = values.get("variant", self.variant)
        cone = soft.make_cone(o, R0, center, R, values["direction"], bbox=soft.bounds(sdf))
        m = soft.march(sdf, cone, variant, eps=values["epsilon"], i_max=values["i_max"])
        return m.visibility, {"iterations": mi.Float(m.iterations), "r_min": m.r_min, "t_min": m.t_min}, Rv


SINGLE_RAY_PARAMS = (EPSILON, DIRECTION, I_MAX, LIGHT_SCALE, SURFACE_RADIUS)


@register
class SDFAAHard(SingleRay):
    name = "sdf_aa_hard"
    title = "SDF anti-aliased hard shadow (single ray, light radius 0)"
    summary = (
        "the single-ray algorithm with a point light ([Bán 2019, §4.3.3]): the cone from the surface sphere to the "
        "light's centre gives a hard shadow whose edge is a ramp about one pixel wide"
    )
    params = (Param("variant", "linear", "choice", choices=("linear", "base"), source="[Bán 2019, §4.3.3]",
                    doc="the single-ray algorithm used (Algorithm 4 or 3)"),
              EPSILON, DIRECTION, I_MAX, AA_SURFACE_RADIUS)

    def radius_for(self, frame, light, values):
        center, _ = light_sphere(frame.scene, light)
        return center, dr.opaque(mi.Float, 0.0), 0.0


@register
class SDFBase(SingleRay):
    name = "sdf_base"
    title = "SDF single-ray soft shadow, base algorithm (Algorithm 3)"
    summary = ("cone march keeping the threshold cone T at the smallest relative distance found and the trace cone "
               "C at τ⁻¹(τ(R^T) − ε) (τ⁻¹ by bisection); result τ(R^T)")
    variant = "base"
    params = SINGLE_RAY_PARAMS


@register
class SDFLinear(SingleRay):
    name = "sdf_linear"
    title = "SDF single-ray soft shadow, linearized (Algorithm 4)"
    summary = "as sdf_base with the trace cone e = επ/2 below T in r (τ' ≤ 2/π) and one τ at the end; recommended"
    variant = "linear"
    params = SINGLE_RAY_PARAMS


@register
class SDFDiscrete(SingleRay):
    name = "sdf_discrete"
    title = "SDF single-ray soft shadow, discrete (Algorithm 5)"
    summary = "each detection lowers the lit fraction by exactly ε; output levels 1, 1 − ε, 1 − 2ε, …"
    variant = "discrete"
    params = (EPSILON, DIRECTION, I_MAX, LIGHT_SCALE_ND, SURFACE_RADIUS)


@register
class SDFConvex(SingleRay):
    name = "sdf_convex"
    title = "SDF single-ray soft shadow, convex-optimised"
    summary = ("Algorithm 4 with longer steps past convex primitives while R^C ≥ 0 (a secant bound: the distance "
               "to a convex solid is convex along the axis)")
    variant = "convex"
    params = SINGLE_RAY_PARAMS


@register
class SDFQuilez(SDFTechnique):
    name = "sdf_quilez"
    title = "SDF penumbra estimate of Quílez (2010) / Aaltonen (2018)"
    summary = ("sphere tracing toward the light's centre keeping min k·h/t (Aaltonen: the improved closest-approach "
               "estimate); k = 1/tanα of the light cone; the inner half of the penumbra comes out as umbra")
    params = (Param("variant", "quilez2010", "choice", choices=soft.QUILEZ_VARIANTS, source="[Bán 2019, §6.4]",
                    doc="quilez2010: res = min(k·h/t); aaltonen2018: res = min(k·d/max(0, t − y)), y = h²/(2h_prev)"),
              Param("k", 0.0, "float", 0.0, 1000.0, "", source="[Bán 2019, §6.4]",
                    doc="penumbra sharpness k; 0 = from the light size per point, k = √(d² − R²)/R = 1/tanα "
                        "(then k·h/t is the relative distance of the thesis)"),
              LIGHT_SCALE, I_MAX, HIT_EPS, SURFACE_RADIUS)

    def light_visibility(self, frame, sdf, light, o, R0, values):
        center, R, Rv = self.light_radius(frame, light, values)
        k = None if float(values["k"]) == 0.0 else float(values["k"])
        v, its = soft.quilez(sdf, o, center, R, k=k, variant=values["variant"], eps=values["hit_eps"],
                             i_max=values["i_max"])
        return v, {"iterations": mi.Float(its)}, Rv


@register
class SDFMC(SDFTechnique):
    name = "sdf_mc"
    title = "SDF Monte-Carlo visibility in the cone (Halton points)"
    summary = ("n sphere-traced shadow rays per point toward Halton points on the light's disk (polar: r-weighted or "
               "r = √u), Cranley–Patterson rotated per point; the thesis' reference method")
    params = (Param("samples", 64, "int", 1, 4096, "rays per point", source="[Bán 2019, §3.3.1]",
                    doc="Halton points per shading point (64 in Fig. 6.3, 512 in Fig. 6.6)"),
              Param("scheme", "sqrt", "choice", choices=soft.SCHEMES, source="[Bán 2019, §3.3.1]",
                    doc="polar sampling of the disk: r = √u (uniform) or r = u with weight r"),
              Param("measure", "disk", "choice", choices=soft.MEASURES, source="[Bán 2019, §3.3.1]",
                    doc="disk: fraction of the disk's area (the thesis); solid_angle: weight cos³θ, the fraction of "
                        "the light's solid angle (Mitsuba's A)"),
              Param("cosine", False, "bool", source="[Bán 2019, §5.1]",
                    doc="also weight by max(0, n·ω): the ratio ∫v cos/∫cos of Eq. 5.1 (the truth's V for diffuse "
                        "surfaces)"),
              Param("seed", 0, "int", 0, 1_000_000, source="[Bán 2019, §3.3]",
                    doc="seed of the per-point Cranley–Patterson rotation of the Halton set"),
              LIGHT_SCALE_ND, Param("i_max", 512, "int", 1, 8192, "steps", source="[Bán 2019, Alg. 2]",
                                    doc="steps per shadow ray; a ray still marching after them counts as blocked"),
              HIT_EPS, SURFACE_RADIUS)

    def light_visibility(self, frame, sdf, light, o, R0, values):
        center, R, Rv = self.light_radius(frame, light, values)
        v, its = soft.mc_cone_visibility(sdf, o, frame.gbuffer.n, (center, 0.0), int(values["samples"]),
                                         scheme=values["scheme"], measure=values["measure"],
                                         cosine=bool(values["cosine"]), seed=int(values["seed"]),
                                         eps=values["hit_eps"], i_max=values["i_max"], clearance=0.0,
                                         radius=R, return_iterations=True)
        return v, {"iterations": mi.Float(its)}, Rv


@register
class SDFEdgeMC(SDFTechnique):
    name = "sdf_edge_mc"
    title = "SDF physically based shading with single-ray visibility (chapter 5)"
    summary = ("Eq. 5.1 by Mitsuba's light sampling, each sample's visibility from the single ray's occluder edge "
               "line (5.3.1, no scene intersection), or sphere-traced (5.1), or the separable Eq. 5.2; any light "
               "bounded by a sphere (5.4)")
    params = (Param("estimator", "edge", "choice", choices=sdf_shading.ESTIMATORS, source="[Bán 2019, §5.2–5.3]",
                    doc="edge: 5.3.1 (edge line from the minimum and the SDF gradient); traced: 5.1 with sphere-traced "
                        "samples; separable: Eq. 5.2, the single-ray fraction times the unshadowed light"),
              Param("samples", 8, "int", 1, 64, "per side", source="[Bán 2019, §6.4]",
                    doc="s: s×s stratified light samples per point (Fig. 6.16 uses 50 and 150)"),
              Param("seed", 0, "int", 0, 1_000_000, source="[Bán 2019, §5.3]", doc="seed of the sample jitter"),
              EPSILON, DIRECTION, I_MAX, HIT_EPS, SURFACE_RADIUS)

    def light_visibility(self, frame, sdf, light, o, R0, values):
        v, aovs = sdf_shading.visibility(frame, light, sdf, o, R0, estimator=values["estimator"],
                                         samples=int(values["samples"]), seed=int(values["seed"]),
                                         eps=values["epsilon"], direction=values["direction"],
                                         i_max=values["i_max"], hit_eps=values["hit_eps"])
        _, R = light_sphere(frame.scene, light, fit="bounding")
        return v, aovs, R


for _t in (SDFHard, SDFAAHard, SDFBase, SDFLinear, SDFDiscrete, SDFConvex, SDFQuilez, SDFMC, SDFEdgeMC):
    __doc__ += f"\n\nParameters of ``{_t.name}`` (generated from the declaration):\n\n" + param_table_markdown(_t)
