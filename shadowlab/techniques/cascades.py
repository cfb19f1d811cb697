"""Cascaded shadow maps (``csm``) [Buljan 2020, §4.1–4.4, Code A.12–A.14].

The camera's view frustum between the view depths n and f of the shadowed range is cut into N
slices ("cascades") by the splits C_0 = n < C_1 < … < C_N = f (§4.1), and each slice gets its
own orthographic map of the directional light, so near slices get many texels per metre and far
ones few: the perspective aliasing m̃ = n·dz/(z·ds) of §2.5 is spread over the cascades.

**Splits** (§4.1, Slika 4.2), ``split`` = ``uniform``, ``log`` or ``practical``:

* uniform C_i = n + i·(f − n)/N;
* logarithmic C_i = n·(f/n)^(i/N);
* practical C_i = λ·C_i^log + (1 − λ)·C_i^uniform, λ = ``split_lambda`` (0.6 as in 003).

C_0 and C_N are set to n and f exactly (:func:`splits`). ``shadow_near`` / ``shadow_far`` = 0 take
the camera's clip planes, narrowed to the view depths the scene's bounding sphere spans
(:meth:`shadowlab.render.camera.Camera.depth_range`: the default far clip is 100 km).

**Per-cascade light** (§4.2, Code A.13): :class:`~shadowlab.render.lightview.FrustumSlice` of the
slice [C_i, C_{i+1}]: light position p = c − λ·d from the slice's centroid c, λ = ``pull`` × the
slice's bounding-sphere radius (Code A.13's DistanceFactor). ``near_plane`` = ``light`` (the
default, as the source): the map's view volume starts at p (or at the slice's nearest corner where
λ < 1 puts p inside the slice), so a caster farther toward the light than p is clipped: a λ too
low loses casters, one too high spends depth precision (§2.2); ``pancake``: the same near plane,
but such a caster is clamped onto it (depth 0) instead of clipped, so λ sets only the precision;
``caster`` (shadowlab's former default): the depth range starts at the scene's nearest caster
toward the light, so λ changes nothing (fit then leaves ``pull`` out). Measured against the truth
(``docs/families/cascades.md``), the three agree at the default λ = 2 on ``street`` and
``boulevard`` (no caster beyond p, 32-bit maps), so the default is the source's ``light``;
``fit`` = ``sphere`` (the slice's bounding sphere, radius rounded up to 1/8 m as Code A.13 does:
invariant under camera rotation) or ``box`` (the slice corners' light-space bounding square:
tighter, but it changes with every camera move, so shadow edges shimmer); ``snap`` moves the
light across its direction by whole texels (stable cascaded shadow maps, §4.3): a camera
translation then moves each cascade's texel grid only by whole texels. ``fit`` = ``scene`` gives
every cascade the whole-scene map (:class:`~shadowlab.render.lightview.SceneSphere`, ``hard``'s):
with N = 1 ``csm`` is then ``hard`` (same filter) bit for bit.

**Selection** (§4.4, Code A.14): ``interval`` (PSSM): a point at view depth z (under
``frame.camera``, so frame 0's points can be evaluated with frame t's camera) takes the first
cascade i with z < C_{i+1}; points beyond C_N take the last cascade, as Code A.14's blending
branch does (``i == MAX_CASCADES_NUM − 1``), so a shadow its map holds does not stop at C_N, and
a point outside that map is unshadowed (the source's branch without blending leaves such points
at their initial shadow factor; one rule for both keeps ``blend`` from deciding it).
``map``: the first, i.e. finest, cascade whose map holds the point (inside its [−1, 1]² and
depth range); a point in no map is unshadowed.

**Blending** (Code A.14, interval selection only: Code A.14's blending branch selects by depth):
around each split C = C_{i+1} but the last, in the band [(1 − b)·C, (1 + b)·C], b = ``blend``,
the visibility is (1 − w)·V_i + w·V_{i+1}, w = (z/C − (1 − b))/(2b), linear from 0 to 1 across
the band; the first band that holds z wins (bands of close splits may overlap); the last
cascade never blends; b = 0 is no blending. A point of a band outside one of the two maps takes
the other's visibility. With ``map`` selection ``blend`` has no effect.

**Filters** (``filter``): every cascade is sampled by one of the shadow-map families, through
that family's own :meth:`~shadowlab.techniques.shadow_map.ShadowMapTechnique.evaluate` (the
code ``hard``, ``pcf``, ``pcss``, ``vsm``, ``esm``, ``evsm``, ``msm`` render with, not a copy).
Their parameters are the families' declarations under the family's prefix (``pcf_kernel``,
``pcss_light_scale``, ``vsm_min_variance``, …; ``--set csm.pcf_kernel=5``); the map format and
bias parameters (:data:`~shadowlab.techniques.shadow_map.BIAS_PARAMS`: ``resolution`` per
cascade, ``depth_bias``, …) are shared unprefixed. A filter looks the same on both sides of a
split where its footprint is a world size; Code A.14 instead samples every cascade with the same
kernel in texels, so a far cascade (larger texels) filters a wider world footprint.
``filter_scale`` = ``texel`` (the default) does as the source; ``world`` keeps the world size, per
cascade i, with t_i its texel's world size:

* ``pcf_softness`` is in texels of cascade 0: cascade i taps at softness·t_0/t_i of its own
  texels, so the kernel's world footprint is the same in every cascade;
* the prefilter ``kernel`` of ``vsm``/``esm``/``evsm``/``msm`` (whole texels) becomes
  max(1, round(kernel·t_0/t_i)) in cascade i;
* ``pcss`` needs no scaling (its widths come from the light size, in world units), nor do the
  world-unit receiver biases (``constant_bias``, ``slope_bias``, ``max_slope_bias``);
* the acne biases stay per texel, so they follow each cascade's texel size, as acne does:
  ``normal_offset`` (texels), ``slope_scaled_depth_bias`` (× the depth slope per texel) and
  ``depth_bias`` (depth-format steps).

Measured against the truth (``docs/families/cascades.md``), ``texel`` has the lower penumbra error
on ``street`` and ``boulevard`` in 14 of 15 (scene, filter) cases: with ``world`` a far cascade's
taps shrink to a fraction of its coarse texel (softness·t_0/t_i), which leaves its staircase edge
hard, while a kernel of whole texels smooths it; the whole-image RMSE differs by at most 0.0022.

**Cost**: each point is evaluated only in the cascade it selects (two in a blend band), in a loop
over the ≤ 8 cascades (no loop over points). On the CPU a cascade's points are compacted
(``dr.compress``) into a sub-G-buffer, evaluated and scattered back; on a GPU the cascade's filter
runs over every point with the cascade's points as its mask, so the lookup reads no count back
(:func:`compact_cascades`; the same values per point).

AOVs per light: ``cascade`` (index of the selected cascade, −1 unshadowed; ``blend_weight`` of the
next one: the report colours them red, green, blue, … as Slika 4.3/4.5,
:func:`cascade_colours`), ``blend_weight`` (w, 0 outside a band),
``texel`` (world size of the selected cascade's texel, blended by w) and ``aliasing``: the
aliasing measure m̃ from the actual maps, texel world size / the pixel's world footprint at the
point's view depth (:meth:`~shadowlab.render.camera.Camera.pixel_footprint`), i.e. screen pixels
per shadow-map texel: > 1 is undersampling (one texel covers several pixels). On a plane seen
head-on it equals n·dz/(z·ds) with dz/ds the texel's world size and n the near plane measured in
pixels (n = W/(2·tan(fov/2))). The texel is the map's own square; how a receiver tilted against
the light stretches it is not included.

Stats per light: ``maps`` (per cascade: the map's resolution, depth bits, near, far, texels,
``split`` [C_i, C_{i+1}], ``texel_world``, ``fraction`` of the shaded points that select it),
``cascade_fraction`` (the same list), ``blended_fraction`` (points in a band),
``unshadowed_fraction`` (no cascade: map selection and no map holds the point); globally ``splits``, ``cascades``,
``filter``, ``shadow_map_texels``.

Not differentiable: the splits, the blend band and the pull-back move maps and selections by
steps, so fitting searches ``split_lambda``, ``blend`` and ``pull`` without gradients; a filter's
differentiable parameters (``pcss_light_scale``, ``vsm_min_variance``, …) stay differentiable.

>>> splits("uniform", 1.0, 9.0, 4).tolist()
[1.0, 3.0, 5.0, 7.0, 9.0]
>>> splits("log", 1.0, 16.0, 4).tolist()
[1.0, 2.0, 4.0, 8.0, 16.0]
>>> splits("practical", 1.0, 16.0, 2, 0.5).tolist()
[1.0, 6.25, 16.0]
"""

from __future__ import annotations

import math
from dataclasses import replace

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import InputError
from ..io.png import NO_DATA
from ..render.lightview import NEAR_PLANES, FrustumSlice, SceneSphere
from . import esm, evsm, msm, pcf, pcss, shadow_map, vsm  # noqa: F401  (register the filter families)
from .base import (
    LightResult,
    Panel,
    Param,
    RenderContext,
    Technique,
    get,
    needs_mitsuba_geometry,
    param_table_markdown,
    register,
)
from .shadow_map import (BIAS_PARAMS, Points, SubFrame, check_map_params, map_entry, map_layers, map_settings,
                         map_stats)

SOURCE = "[Buljan 2020, §4]"
CASCADES_MAX = 8
SCHEMES = ("uniform", "log", "practical")
FILTERS = ("hard", "pcf", "pcss", "vsm", "esm", "evsm", "msm")
#: families whose prefilter ``kernel`` (whole texels) is scaled per cascade
PREFILTERED = ("vsm", "esm", "evsm", "msm")
#: ``filter_scale``: a filter's footprint is the same in world units or in texels in every cascade
FILTER_SCALES = ("world", "texel")


# ----------------------------------------------------------------------------------------------
# splits (§4.1)


def uniform_splits(n: float, f: float, N: int) -> np.ndarray:
    """C_i = n + i·(f − n)/N, i = 0 … N."""
    i = np.arange(N + 1, dtype=np.float64)
    return n + i * (f - n) / N


def log_splits(n: float, f: float, N: int) -> np.ndarray:
    """C_i = n·(f/n)^(i/N), i = 0 … N."""
    i = np.arange(N + 1, dtype=np.float64)
    return n * (f / n) ** (i / N)


def practical_splits(n: float, f: float, N: int, lam: float) -> np.ndarray:
    """C_i = λ·C_i^log + (1 − λ)·C_i^uniform."""
    return lam * log_splits(n, f, N) + (1.0 - lam) * uniform_splits(n, f, N)


def splits(scheme: str, n: float, f: float, N: int, lam: float = 0.6) -> np.ndarray:
    """The N + 1 split depths of ``scheme`` between n and f, C_0 = n and C_N = f exactly."""
    if not (0 < n < f and math.isfinite(f)):
        raise InputError(f"csm: the shadowed range needs 0 < near < far, got near {n:g}, far {f:g}; set "
                         "csm.shadow_near / csm.shadow_far (0 = the camera's clip planes)")
    if scheme == "uniform":
        c = uniform_splits(n, f, N)
    elif scheme == "log":
        c = log_splits(n, f, N)
    elif scheme == "practical":
        c = practical_splits(n, f, N, lam)
    else:
        raise InputError(f"csm.split={scheme!r}: expected one of {', '.join(SCHEMES)}")
    c[0], c[-1] = n, f
    return c


def shadow_range(camera, scene, values: dict) -> tuple:
    """(n, f) of the shadowed range: ``shadow_near`` / ``shadow_far``, 0 = the camera's clip
    plane narrowed to the view depths the scene's bounding sphere spans."""
    z0, z1 = camera.depth_range(scene.center, scene.radius)
    n = float(values["shadow_near"]) or max(camera.near, z0)
    f = float(values["shadow_far"]) or min(camera.far, z1)
    if not n < f:
        raise InputError(f"csm: shadowed range near {n:g} m ≥ far {f:g} m; set csm.shadow_near below "
                         "csm.shadow_far (0 = the camera's clip planes within the scene)")
    return n, f


def select_interval(z, C, blend: float, b=None):
    """Interval selection with Code A.14's blend bands (Dr.Jit): (cascade index Int32, the last
    one, N − 1, beyond C_N as in Code A.14; weight of cascade index + 1). ``C``: the split depths
    as floats or opaque Dr.Jit scalars, ``blend``: b (a float; 0 = none), ``b``: the same as the
    opaque scalar the kernel reads (default ``blend``)."""
    blend_on = blend > 0
    blend = blend if b is None else b
    N = len(C) - 1
    sel = dr.full(mi.Int32, N - 1, dr.width(z))          # beyond C_N too: the last cascade
    w = dr.zeros(mi.Float, dr.width(z))
    for i in range(N - 2, -1, -1):        # downwards: the first i whose band holds z wins
        c = C[i + 1]
        if blend_on:
            lo, hi = c * (1.0 - blend), c * (1.0 + blend)
            ramp = (z / c - (1.0 - blend)) * (1.0 / (2.0 * blend))
            w = dr.select(z < lo, 0.0, dr.select(z < hi, ramp, w))
            sel = dr.select(z < hi, mi.Int32(i), sel)
        else:
            w = dr.select(z < c, 0.0, w)
            sel = dr.select(z < c, mi.Int32(i), sel)
    return sel, w


def select_map(insides):
    """Map-based selection: the first (finest) cascade whose map holds the point, −1 none."""
    sel = mi.Int32(-1)
    for i in range(len(insides) - 1, -1, -1):
        sel = dr.select(insides[i], mi.Int32(i), sel)
    return sel


def compact_cascades() -> bool:
    """Whether a cascade's filter runs on its own points only (gathered by ``dr.compress``, which
    reads their count back): on the CPU, where a masked lane still costs its vector lane, so three
    cascades over every point would be three lookups' work. On a GPU a masked thread costs almost
    nothing, so each cascade's filter runs over every point with its points as the mask, and the
    lookup waits for no count (the same values per point)."""
    return dr.backend_v(mi.Float) != dr.JitBackend.CUDA


# ----------------------------------------------------------------------------------------------
# the report's cascade image

#: colours of cascades 0 … 7 (linear [0, 1]): red, green, blue as Slika 4.3/4.5, then more
CASCADE_COLOURS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 0.5, 0],
                            [0.5, 0, 1]], np.float64)


def cascade_colours(index, weight=None, visibility=None) -> np.ndarray:
    """H×W×3 uint8 image of a cascade index AOV (−1 = none, grey); ``weight``: the blend weight
    toward cascade index + 1; ``visibility``: multiplies the colour (Code A.14's visualisation).

    >>> cascade_colours(np.array([[0, 1, 2, -1]]))[0].tolist()
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128]]
    >>> cascade_colours(np.array([[0.0]]), np.array([[0.5]]))[0].tolist()
    [[128, 128, 0]]
    """
    idx = np.rint(np.asarray(index, np.float64)).astype(np.int64)
    if idx.ndim == 3 and idx.shape[2] == 1:
        idx = idx[:, :, 0]
    k = len(CASCADE_COLOURS)
    a = CASCADE_COLOURS[np.clip(idx, 0, k - 1)]
    if weight is not None:
        w = np.clip(np.asarray(weight, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
        a = (1.0 - w) * a + w * CASCADE_COLOURS[np.clip(idx + 1, 0, k - 1)]
    if visibility is not None:
        a = a * np.clip(np.asarray(visibility, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
    a = np.where((idx < 0)[..., None], NO_DATA / 255.0, a)
    return np.round(a * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# parameters

def family(name: str):
    """The registered technique of filter family ``name`` (``hard``, ``pcf``, …)."""
    return get(name)


def _family_params(family: str) -> tuple:
    """The family's own declarations (not the shared BIAS_PARAMS) under the ``family_`` prefix."""
    shared = {p.name for p in BIAS_PARAMS}
    out = []
    for p in get(family).params:
        if p.name in shared:
            continue
        out.append(replace(p, name=f"{family}_{p.name}",
                           doc=f"`{family}` filter: {p.doc}" if not p.doc.startswith(f"`{family}`") else p.doc))
    return tuple(out)


def prefixed(family: str, name: str) -> str:
    """The csm name of a family's parameter (shared bias/map parameters keep their name)."""
    return name if name in {p.name for p in BIAS_PARAMS} else f"{family}_{name}"


CSM_PARAMS = (
    Param("cascades", 3, "int", 1, CASCADES_MAX, "cascades", False, source="[Buljan 2020, §4.1]",
          doc="N: number of cascades (frustum slices, one map each; 3 in the source)"),
    Param("split", "practical", "choice", choices=SCHEMES, source="[Buljan 2020, §4.1]",
          doc="split scheme: uniform n + i(f−n)/N, logarithmic n(f/n)^(i/N), or practical λ·log + (1−λ)·uniform"),
    Param("split_lambda", 0.6, "float", 0.0, 1.0, "", False, source="[Buljan 2020, §4.1, Code A.12]",
          doc="λ of the practical split (1 = logarithmic, 0 = uniform)"),
    Param("shadow_near", 0.0, "float", 0.0, 1e5, "m (view depth)", False, source="[Buljan 2020, §4.1]",
          doc="n = C_0, near end of the shadowed range; 0 = the camera's near clip (within the scene's depth range)"),
    Param("shadow_far", 0.0, "float", 0.0, 1e5, "m (view depth)", False, source="[Buljan 2020, §4.1]",
          doc="f = C_N, far end of the split range (beyond it: the last cascade's map); 0 = the camera's far clip "
              "(within the scene's depth range)"),
    Param("pull", 2.0, "float", 0.25, 16.0, "slice radii", False, source="[Buljan 2020, §4.2, Code A.13]",
          doc="pull-back λ of the light position p = c − λ·r·d from the slice centroid (Code A.13's DistanceFactor)"),
    Param("near_plane", "light", "choice", choices=NEAR_PLANES, source="[Buljan 2020, §2.2, Code A.13]",
          doc="where each cascade's depth range starts: `light` at p = c − λ·r·d, casters nearer the light "
              "clipped (Code A.13); `pancake` the same plane, such casters clamped onto it; `caster` the "
              "scene's nearest caster (then `pull` changes nothing)"),
    Param("fit", "sphere", "choice", choices=("sphere", "box", "scene"), source="[Buljan 2020, §4.2, Code A.13]",
          doc="projection fit per cascade: the slice's bounding sphere (radius rounded to 1/8 m), its light-space "
              "bounding box (shimmers), or the whole scene (`hard`'s map; N = 1 equals `hard`)"),
    Param("snap", True, "bool", source="[Buljan 2020, §4.3]",
          doc="stable CSM: move each cascade's light across its direction by whole texels"),
    Param("selection", "interval", "choice", choices=("interval", "map"), source="[Buljan 2020, §4.4, Code A.14]",
          doc="interval (PSSM: first C_i above the view depth) or map-based (finest map that holds the point)"),
    Param("blend", 0.1, "float", 0.0, 0.5, "× split depth", False, source="[Buljan 2020, §4.4, Code A.14]",
          doc="blend band ±b around each split (interval selection): linear blend over [(1−b)C, (1+b)C]; "
              "0 = none; the last cascade never blends"),
    Param("filter", "pcf", "choice", choices=FILTERS, source="[Buljan 2020, §4.4]",
          doc="the shadow-map family that samples every cascade (its parameters: csm.FAMILY_PARAM)"),
    Param("filter_scale", "texel", "choice", choices=FILTER_SCALES, source="[Buljan 2020, Code A.14]",
          doc="a filter's footprint per cascade: `world` the same world size in every cascade (pcf softness and "
              "prefilter kernels scaled by t_0/t_i), `texel` the same kernel in texels in every cascade (Code A.14)"),
)


def _opaque3(v):
    return [dr.opaque(mi.Float, float(x)) for x in v]


@register
class CSM(Technique):
    """Cascaded shadow maps: practical / log / uniform splits, per-slice sphere or box fits,
    stable snapping, interval or map-based selection with blend bands, any shadow-map filter."""

    name = "csm"
    title = "Cascaded shadow maps"
    source = SOURCE
    summary = ("the camera frustum split into 1–8 slices (uniform, logarithmic, practical), one orthographic "
               "map of the directional light per slice (sphere or box fit, whole-texel snapping), interval or "
               "map-based selection with blend bands, any shadow-map filter per cascade")
    params = CSM_PARAMS + BIAS_PARAMS + tuple(q for f in FILTERS[1:] for q in _family_params(f))
    panels = (
        Panel("colour", "cascades", (("cascade", ""),), "cascades",
              note="red, green, blue, … = cascade 0, 1, 2, … (blended in the bands, × visibility)"),
        Panel("log2_ratio", "aliasing m̃", (("aliasing", ""),), "aliasing",
              note="shadow-map texel / pixel footprint, log₂: red = a texel covers several pixels (undersampled), "
                   "blue = several texels per pixel, grey = no cascade"),
    )
    band_aovs = ("cascade",)

    def report_images(self, frame, result, mask, vis):
        """The cascade index coloured as [Buljan 2020, Slika 4.3/4.5] (:func:`cascade_colours`,
        blended by ``blend_weight``, × visibility) and the aliasing measure m̃ ([Buljan 2020, §2.5],
        a texel / pixel ratio, shown as a heat map of its log₂)."""
        out = {}
        for l in frame.lights:
            a = result.aovs
            if f"{l.name}.cascade" in a:
                out.setdefault("cascade", {})[l.name] = cascade_colours(
                    a[f"{l.name}.cascade"], a.get(f"{l.name}.blend_weight"), vis[l.name]) / 255.0
            if f"{l.name}.aliasing" in a:
                out.setdefault("aliasing", {})[l.name] = a[f"{l.name}.aliasing"]
        return out

    # -- the scenes it renders -------------------------------------------------------------------
    def unsupported(self, spec) -> str | None:
        if why := needs_mitsuba_geometry(self.name, spec):
            return why
        for l in spec.lights:
            if l.kind != "directional":
                return (f"csm: light {l.name!r} is a {l.kind} light; cascaded shadow maps split the camera frustum "
                        "into slices, each covered by an orthographic map, which is the light camera of a "
                        "directional light (parallel rays); spot, point and area lights need other schemes (a "
                        "perspective map or cube faces per slice): use hard, pcf, pcss, … for this scene")
        return None

    # -- per render ----------------------------------------------------------------------------
    def family_values(self, values: dict) -> dict:
        """The chosen filter's values under the family's own names (validated by the family)."""
        fam = family(values["filter"])
        raw = {p.name: values[prefixed(fam.name, p.name)] for p in fam.params}
        return fam.resolve(raw)

    def fit_params(self, values: dict) -> tuple:
        """The parameters ``shadowlab fit`` searches by default: the cascades' continuous ones
        (``split_lambda``, ``blend``, and ``pull`` unless ``near_plane`` = ``caster`` makes it
        inert; searched without gradients) and the chosen filter's
        own default fit parameters, under their csm names."""
        fam = family(values["filter"])
        pull = ("pull",) if values["near_plane"] != "caster" else ()
        return ("split_lambda", "blend") + pull + tuple(prefixed(fam.name, n)
                                                         for n in fam.fit_params(self.family_values(values)))

    def prepare(self, frame, values, ctx):
        check_map_params(values, self.name)
        fam = family(values["filter"])
        fv = self.family_values(values)
        fctx = RenderContext(fam, fv)
        fam.prepare(frame, fv, fctx)
        ctx.family, ctx.fvalues, ctx.fctx = fam, fv, fctx
        cam = frame.camera
        n, f = shadow_range(cam, frame.scene, values)
        N = int(values["cascades"])
        ctx.splits = splits(values["split"], n, f, N, float(values["split_lambda"]))
        C = ctx.splits
        if values["fit"] == "scene":
            ctx.fits = [SceneSphere()] * N
        else:
            ctx.fits = [FrustumSlice(C[i], C[i + 1], float(values["pull"]), bool(values["snap"]), values["fit"],
                                     values["near_plane"]) for i in range(N)]

    @staticmethod
    def cascade_values(fam: str, fv: dict, k: float) -> dict:
        """The family ``fam``'s values in a cascade whose texels are 1/k of cascade 0's (world
        units): ``pcf`` softness × k, the prefilter kernel max(1, round(kernel × k))."""
        out = dict(fv)
        if "softness" in fv and fam == "pcf":
            out["softness"] = float(fv["softness"]) * k
        if "kernel" in fv and fam in PREFILTERED:
            out["kernel"] = max(1, int(round(int(fv["kernel"]) * k)))
        return out

    def render_light(self, frame, light, values, ctx):
        res, bits = map_settings(frame, light.name, values)
        views = frame.light_views_of(light.name, ctx.fits, res=res, bits=bits, backface=bool(values["backface"]),
                                     layers=map_layers(values))
        N = len(views)
        texel = [2.0 * v.proj.faces[0].scale / v.res for v in views]
        gb = frame.gbuffer
        npts = dr.width(gb.valid)
        cam = frame.camera
        o, fwd = _opaque3(cam.position), _opaque3(cam.forward)
        z = dr.dot(gb.p - mi.Point3f(*o), mi.Vector3f(*fwd))
        b = float(values["blend"])
        if values["selection"] == "interval":
            C = [dr.opaque(mi.Float, float(c)) for c in ctx.splits]
            sel, w = select_interval(z, C, b, dr.opaque(mi.Float, b))
        else:
            sel = select_map([v.lookup(gb.p)["inside"] for v in views])
            w = dr.zeros(mi.Float, npts)
        sel = dr.select(gb.valid, sel, -1)
        blended = (w > 0.0) & (sel >= 0) & (sel < N - 1)
        dr.eval(sel, w, blended)
        A, B = dr.full(mi.Float, 1.0, npts), dr.full(mi.Float, 1.0, npts)
        a_in, b_in = dr.full(mi.Bool, False, npts), dr.full(mi.Bool, False, npts)
        maps = []
        compact = compact_cascades()
        for i in range(N):
            mask = (sel == i) | (blended & (sel + 1 == i))
            k = texel[0] / texel[i] if values["filter_scale"] == "world" else 1.0
            entry = {**map_entry(views[i]), "cascade": i, "split": [float(ctx.splits[i]), float(ctx.splits[i + 1])],
                     "texel_world": texel[i]}
            maps.append(entry)
            if compact:
                idx = dr.compress(mask)
                if dr.width(idx) == 0:
                    continue
                pts = Points(dr.gather(mi.Point3f, gb.p, idx), dr.gather(mi.Normal3f, gb.ng, idx),
                             dr.gather(mi.Bool, gb.valid, idx))
            else:
                pts = Points(gb.p, gb.ng, gb.valid & mask)
            cv = self.cascade_values(ctx.family.name, ctx.fvalues, k)
            r = ctx.family.evaluate(SubFrame(frame.scene, pts), light, views[i], cv, ctx.fctx)
            v = r.visibility
            act = r.active if r.active is not None else dr.full(mi.Bool, True, dr.width(pts.valid))
            v = dr.select(act, v, 1.0)
            if compact:
                full_v = dr.full(mi.Float, 1.0, npts)
                full_a = dr.full(mi.Bool, False, npts)
                dr.scatter(full_v, v, idx)
                dr.scatter(full_a, act, idx)
            else:
                full_v, full_a = dr.select(mask, v, 1.0), mask & act
            A = dr.select(sel == i, full_v, A)
            a_in = dr.select(sel == i, full_a, a_in)
            B = dr.select(sel + 1 == i, full_v, B)
            b_in = dr.select(sel + 1 == i, full_a, b_in)
        # a band point outside one of its two maps takes the other's visibility
        w_eff = dr.select(blended, dr.select(~b_in, 0.0, dr.select(~a_in, 1.0, w)), 0.0)
        vis = dr.select(w_eff > 0.0, dr.lerp(A, B, w_eff), A)
        shadowed = sel >= 0
        vis = dr.select(shadowed, vis, 1.0)
        tex_tab = mi.Float([float(t) for t in texel + [texel[-1]]])
        t_a = dr.gather(mi.Float, tex_tab, mi.UInt32(dr.maximum(sel, 0)))
        t_b = dr.gather(mi.Float, tex_tab, mi.UInt32(dr.minimum(dr.maximum(sel + 1, 0), N)))
        t_sel = dr.select(shadowed, dr.lerp(t_a, t_b, w_eff), 0.0)
        pix = dr.maximum(z, 1e-12) * (2.0 * cam.tan_x / cam.width)
        aovs = {"cascade": mi.Float(sel), "blend_weight": w_eff, "texel": t_sel,
                "aliasing": dr.select(shadowed, t_sel / pix, 0.0)}
        return LightResult(vis, aovs, stats=map_stats(views[0]), maps=maps)

    def light_stats(self, frame, light, values, ctx, result):
        # counted on the device and read back once (the AOVs themselves stay there)
        sel, valid = result.aovs["cascade"], frame.gbuffer.valid
        N = int(values["cascades"])
        counts = [dr.count(valid & (sel == float(i))) for i in range(N)]
        counts += [dr.count(valid & (result.aovs["blend_weight"] > 0.0)), dr.count(valid & (sel < 0.0)),
                   dr.count(valid)]
        dr.eval(counts)
        c = [int(x[0]) for x in counts]
        n = max(c[-1], 1)
        frac = [float(k) / n for k in c[:N]]
        for m, f in zip(result.maps, frac):
            m["fraction"] = f
        return {"cascade_fraction": frac, "blended_fraction": float(c[N]) / n,
                "unshadowed_fraction": float(c[N + 1]) / n}

    def summarise(self, frame, values, ctx, lights):
        return {"shadow_map_texels": sum(m["texels"] for st in lights.values() for m in st.get("maps", ())),
                "cascades": int(values["cascades"]), "splits": [float(c) for c in ctx.splits],
                "filter": values["filter"], "selection": values["selection"]}


__doc__ += "\n\nParameters of ``csm`` (generated from the declaration):\n\n" + param_table_markdown(CSM)
