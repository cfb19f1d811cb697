"""Babylon.js 9 (npm ``@babylonjs/core``, glTF through ``@babylonjs/loaders``) as techniques.

``babylon:basic`` (the unfiltered map), ``babylon:pcf`` (``usePercentageCloserFiltering`` with
``filteringQuality``), ``babylon:poisson`` (``usePoissonSampling``), ``babylon:esm``,
``babylon:esm_blur``, ``babylon:esm_close`` (exponential shadow maps: plain, blurred, "close"),
``babylon:pcss`` (``useContactHardeningShadow``) and ``babylon:csm`` (``CascadedShadowGenerator``
with ``lambda``, ``cascadeBlendPercentage``, ``stabilizeCascades``, ``autoCalcDepthBounds``)
[Babylon 2026]. The engine renders the exported glb headless in Chromium
(:mod:`shadowlab.techniques.engines`); the parameters are the generator's own properties with
Babylon's defaults (``bias`` 0.00005, ``normalBias`` 0, ``filteringQuality`` high,
``contactHardeningLightSizeUVRatio`` 0.1, ``blurScale`` 2, ``blurBoxOffset`` 1, ``blurKernel`` 1,
``depthScale`` 50 (the light's), CSM's 4 cascades, ``lambda`` 0.5, ``cascadeBlendPercentage`` 0.1),
and the light's ``shadowMinZ`` / ``shadowMaxZ`` (0: the depth range of the scene's bounding
sphere from the light; Babylon itself would take the active camera's planes, which here are
fitted to the view, not to what the light sees). The map size is the generator's constructor
argument ``mapSize`` (1024 here, as Babylon's examples).

How the shadow term is read (``engine_pages/babylon_page.js``): the scene loads right-handed (as
glTF, ``scene.useRightHandedSystem``), every surface is drawn with a white ``StandardMaterial``
(no specular, no ambient, both sides lit), one light enabled at a time, into a float
``RenderTargetTexture`` (the camera's ``outputRenderTarget``), with and without
``receiveShadows``; visibility is their ratio, the factor Babylon multiplies the light by.

Lights: the glTF's ``KHR_lights_punctual`` lights as the loader makes them, at the scene's
positions; a rect or disk light (a 90° glTF spot, a 180° Babylon cone) gets the cone that holds
the scene's bounding box as seen from the light (at most 160°); a directional light sits at the
scene's bounding-sphere centre minus (radius + 1) along its direction (Babylon fits its
orthographic frustum to the casters itself, ``autoUpdateExtends``). Babylon knows no light size
outside PCSS's ``contactHardeningLightSizeUVRatio``.

On spot lights (the rect and disk lights) Babylon's comparison-sampler filters (``babylon:pcf``,
``babylon:pcss``) lose shadow rather than blur it, on SwiftShader and on Mesa llvmpipe alike,
whatever the adapter's depth range, cone or comparison-texture format; ``tests/test_engines.py``
pins it and docs/engines.md gives the evidence. The unfiltered map, Poisson and the ESMs are not affected.

Refused with the reason (exit 2): translucent casters (Babylon's ``transparencyShadow`` casts
alpha-blended shadows, not the truth's coloured transmittance), ``babylon:csm`` with a light that
is not directional.
"""

from __future__ import annotations

import numpy as np

from .base import Param, register
from .engines import EngineTechnique, ReceiverPoints

SOURCE = "[Babylon 2026]"
PACKAGE = "@babylonjs/core"

_BIAS = Param("bias", 0.00005, "float", -0.01, 0.05, "shadow-map depth (0..1)", source=SOURCE,
              doc="ShadowGenerator.bias: added to the depth the shadow pass stores (the casters' depth "
                  "metric), against acne")
_NORMAL_BIAS = Param("normalBias", 0.0, "float", 0.0, 0.5, "world units (m)", source=SOURCE,
                     doc="ShadowGenerator.normalBias: the shadow pass moves each caster vertex inward along its "
                         "normal by normalBias × sin θ (θ between the normal and the light)")
_MAP_SIZE = Param("mapSize", 1024, "int", 16, 8192, "texels", source=SOURCE,
                  doc="new ShadowGenerator(mapSize, light): the shadow map's resolution")
_MIN_Z = Param("shadowMinZ", 0.0, "float", 0.0, 1e4, "m", source=SOURCE,
               doc="light.shadowMinZ: the shadow camera's near plane (0: the scene's nearest depth from the light)")
_MAX_Z = Param("shadowMaxZ", 0.0, "float", 0.0, 1e5, "m", source=SOURCE,
               doc="light.shadowMaxZ: the shadow camera's far plane (0: the scene's farthest depth from the light)")
_QUALITY = Param("filteringQuality", "high", "choice", choices=("high", "medium", "low"), source=SOURCE,
                 doc="ShadowGenerator.filteringQuality: QUALITY_HIGH / MEDIUM / LOW (PCF and PCSS tap counts)")
_DEPTH_SCALE = Param("depthScale", 50.0, "float", 1.0, 1000.0, "", source=SOURCE,
                     doc="ShadowGenerator.depthScale: the exponent scale of exponential shadow maps")
_COMMON = (_BIAS, _NORMAL_BIAS, _MAP_SIZE, _MIN_Z, _MAX_Z)


def caster_bias(points: ReceiverPoints) -> dict:
    """Babylon.js's ``bias`` and ``normalBias``, which act on the casters, that do at each point what
    shadowlab's receiver-side biases did: the stored depth metric grows by ``bias``, so the gap a
    receiver shift Δz toward the light opens is Δz·∂metric/∂z; a caster moved inward along its normal
    by normalBias·sin θ moves away along the light's ray by normalBias·sin θ/cos θ, and a receiver
    lifted δ along its normal is δ/cos θ from its plane along that ray, so normalBias = δ/sin θ.

    >>> pts = ReceiverPoints(*(np.array([x]) for x in (0.02, 0.01, 0.0, 0.6, 4.0, 0.01, 0.03)))
    >>> {k: [round(float(x), 6) for x in v] for k, v in caster_bias(pts).items()}
    {'bias': [0.0006], 'normalBias': [0.0125]}
    """
    sin = np.sqrt(np.maximum(1.0 - points.cos ** 2, 0.0))
    return {"bias": points.dz * points.engine_depth_per_unit,
            "normalBias": np.where(points.normal > 0, points.normal / np.maximum(sin, 1e-3), 0.0)}


class _Babylon(EngineTechnique):
    engine = PACKAGE
    page_html = "babylon.html"
    page_per_type = False
    source = SOURCE

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias")

    def unsupported(self, spec) -> str | None:
        why = super().unsupported(spec)
        if why:
            return why
        see_through = [s.name for s in spec.shapes if s.translucent]
        if see_through:
            return (f"{self.name}: Babylon.js cannot express the truth's translucent casters "
                    f"({', '.join(see_through)}): transparencyShadow casts alpha-blended shadows, not "
                    "coloured transmittance; drop transmittance")
        return None


@register
class BabylonBasic(_Babylon):
    """Babylon.js ``ShadowGenerator`` without filtering: one depth test per pixel."""

    name = "babylon:basic"
    title = "Babylon.js ShadowGenerator (no filter)"
    summary = "Babylon.js 9 in Chromium: unfiltered shadow map"
    shadow_type = "basic"
    params = _COMMON
    transfer_from = ("hard",)

    def from_shadowlab(self, points: ReceiverPoints, values: dict) -> dict:
        return caster_bias(points)


@register
class BabylonPcf(_Babylon):
    """Babylon.js ``usePercentageCloserFiltering`` with ``filteringQuality``."""

    name = "babylon:pcf"
    title = "Babylon.js PCF"
    summary = "Babylon.js 9 in Chromium: hardware PCF, filteringQuality"
    shadow_type = "pcf"
    params = _COMMON + (_QUALITY,)


@register
class BabylonPoisson(_Babylon):
    """Babylon.js ``usePoissonSampling``."""

    name = "babylon:poisson"
    title = "Babylon.js Poisson sampling"
    summary = "Babylon.js 9 in Chromium: Poisson-disk sampling"
    shadow_type = "poisson"
    params = _COMMON


@register
class BabylonEsm(_Babylon):
    """Babylon.js ``useExponentialShadowMap``."""

    name = "babylon:esm"
    title = "Babylon.js ESM"
    summary = "Babylon.js 9 in Chromium: exponential shadow map"
    shadow_type = "esm"
    params = _COMMON + (_DEPTH_SCALE,)

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "depthScale")


@register
class BabylonEsmBlur(_Babylon):
    """Babylon.js ``useBlurExponentialShadowMap``."""

    name = "babylon:esm_blur"
    title = "Babylon.js blurred ESM"
    summary = "Babylon.js 9 in Chromium: blurred exponential shadow map"
    shadow_type = "esm_blur"
    params = _COMMON + (
        _DEPTH_SCALE,
        Param("blurScale", 2, "int", 1, 8, "", source=SOURCE,
              doc="ShadowGenerator.blurScale: the blurred map is mapSize / blurScale"),
        Param("blurBoxOffset", 1, "int", 1, 8, "texels", source=SOURCE,
              doc="ShadowGenerator.blurBoxOffset: half-width of the box blur (when useKernelBlur is false)"),
        Param("useKernelBlur", False, "bool", source=SOURCE,
              doc="ShadowGenerator.useKernelBlur: a Gaussian kernel blur instead of the box blur"),
        Param("blurKernel", 1, "int", 1, 64, "texels", source=SOURCE,
              doc="ShadowGenerator.blurKernel: the kernel blur's size (with useKernelBlur)"),
    )

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "depthScale", "blurBoxOffset")


@register
class BabylonEsmClose(_Babylon):
    """Babylon.js ``useCloseExponentialShadowMap`` (the exponential test inverted, for contact shadows)."""

    name = "babylon:esm_close"
    title = "Babylon.js close ESM"
    summary = "Babylon.js 9 in Chromium: close exponential shadow map"
    shadow_type = "esm_close"
    params = _COMMON + (_DEPTH_SCALE,)

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "depthScale")


@register
class BabylonPcss(_Babylon):
    """Babylon.js ``useContactHardeningShadow``: PCSS with the light's size as a fraction of the map."""

    name = "babylon:pcss"
    title = "Babylon.js contact-hardening shadows (PCSS)"
    summary = "Babylon.js 9 in Chromium: contact hardening (PCSS)"
    shadow_type = "pcss"
    params = _COMMON + (
        _QUALITY,
        Param("contactHardeningLightSizeUVRatio", 0.1, "float", 0.0, 1.0, "× map width", source=SOURCE,
              doc="ShadowGenerator.contactHardeningLightSizeUVRatio: the light's size as a fraction of the shadow "
                  "map's width (the penumbra's scale)"),
    )

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias", "contactHardeningLightSizeUVRatio")


@register
class BabylonCsm(_Babylon):
    """Babylon.js ``CascadedShadowGenerator`` (PCF filtered) for the sun."""

    name = "babylon:csm"
    title = "Babylon.js CascadedShadowGenerator"
    summary = "Babylon.js 9 in Chromium: cascaded shadow maps (PCF)"
    shadow_type = "csm"
    params = _COMMON + (
        _QUALITY,
        Param("numCascades", 4, "int", 2, 4, "cascades", source=SOURCE,
              doc="CascadedShadowGenerator.numCascades"),
        Param("lambda", 0.5, "float", 0.0, 1.0, "", source=SOURCE,
              doc="CascadedShadowGenerator.lambda: 0 uniform, 1 logarithmic cascade splits"),
        Param("cascadeBlendPercentage", 0.1, "float", 0.0, 1.0, "", source=SOURCE,
              doc="CascadedShadowGenerator.cascadeBlendPercentage: the blend band between cascades"),
        Param("stabilizeCascades", False, "bool", source=SOURCE,
              doc="CascadedShadowGenerator.stabilizeCascades: bounding-sphere cascades, stable under camera motion"),
        Param("autoCalcDepthBounds", False, "bool", source=SOURCE,
              doc="CascadedShadowGenerator.autoCalcDepthBounds: fit the cascades to the depth buffer's range"),
    )

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias", "lambda")

    def unsupported(self, spec) -> str | None:
        other = [l.name for l in spec.lights if l.kind != "directional"]
        if other:
            return (f"{self.name}: CascadedShadowGenerator shadows directional lights only (lights "
                    f"{', '.join(other)} are not); use babylon:pcf on them")
        return super().unsupported(spec)
