"""three.js r187 (npm ``three``) as techniques: ``three:basic``, ``three:pcf``, ``three:vsm``, ``three:csm``.

The engine renders the exported glb headless in Chromium (:mod:`shadowlab.techniques.engines`);
its shadow term per light is read back as visibility [Cabello 2026]. The parameters are the engine's
own, with its documented defaults: ``LightShadow.bias`` / ``normalBias`` / ``radius`` /
``blurSamples`` / ``mapSize`` and the shadow camera's ``near`` / ``far`` (and, for a directional
light, the half-size ``extent`` of its orthographic frustum, three.js's ±5); the CSM addon's
``cascades``, ``maxFar``, ``mode``, ``shadowMapSize``, ``shadowBias``, ``lightNear``,
``lightFar``, ``lightMargin`` and ``fade``.

How three.js's shadow term is read (``engine_pages/three_page.js``): every surface is drawn with a
white ``MeshLambertMaterial`` (seen from both sides, casting with the side three.js would use for
the glTF material: the back faces of a one-sided material, ``shadowSide`` of the renderer's
table), one light visible at a time, into an RGBA32F target with and without shadows received;
visibility is their ratio, which is exactly the factor three.js multiplies the light by.

How the scene's lights become three.js lights (the glTF's ``KHR_lights_punctual``, as
``GLTFLoader`` makes them): a point or sphere light is a ``PointLight`` (cube shadow map), a spot
a ``SpotLight``; a rect or disk area light is a glTF spot of 90° (its hemisphere), which three.js's
spot shadow camera cannot hold (its field of view is twice the cone: 180°), so the page narrows
the cone to the one that holds the scene's bounding box as seen from the light (at most 80°); a
directional light's shadow camera is put at the scene's bounding-sphere centre minus (radius + 1)
along the light, looking at the centre (three.js places it at the light's position). three.js
knows no light size: an area light's penumbra is the filter's (``radius``) alone.

What three.js cannot express, refused with the reason (exit 2): translucent (coloured) shadow
casters (three.js's shadow maps are opaque), point-light shadows with ``VSMShadowMap`` (r187 has
none), and ``three:csm`` with a light that is not directional.
"""

from __future__ import annotations

import numpy as np

from .base import Param, register
from .engines import EngineTechnique, ReceiverPoints

SOURCE = "[Cabello 2026]"
PACKAGE = "three"

_BIAS = Param("bias", 0.0, "float", -0.01, 0.01, "shadow-map depth (0..1 of near..far)", source=SOURCE,
              doc="LightShadow.bias: added to the fragment's shadow-map depth before the test; three.js suggests "
                  "small negative values (e.g. -0.0001) against acne")
_NORMAL_BIAS = Param("normalBias", 0.0, "float", 0.0, 0.5, "world units (m)", source=SOURCE,
                     doc="LightShadow.normalBias: moves the looked-up position along its normal before the test")
_MAP_SIZE = Param("mapSize", 512, "int", 16, 8192, "texels", source=SOURCE,
                  doc="LightShadow.mapSize.width and .height: the shadow map's resolution")
_NEAR = Param("near", 0.5, "float", 1e-4, 1000.0, "m", source=SOURCE,
              doc="LightShadow.camera.near: the shadow camera's near plane")
_FAR = Param("far", 500.0, "float", 0.01, 1e5, "m", source=SOURCE,
             doc="LightShadow.camera.far: the shadow camera's far plane")
_EXTENT = Param("extent", 5.0, "float", 0.01, 1e4, "m", source=SOURCE,
                doc="DirectionalLightShadow.camera left/right/top/bottom = ∓extent: the half-size of a directional "
                    "light's orthographic shadow frustum (point and spot lights ignore it)")
_RADIUS_PCF = Param("radius", 1.0, "float", 0.0, 32.0, "texels", source=SOURCE,
                    doc="LightShadow.radius: the radius of PCFShadowMap's Vogel disk of 5 hardware-PCF taps")
_RADIUS_VSM = Param("radius", 1.0, "float", 0.0, 32.0, "texels", source=SOURCE,
                    doc="LightShadow.radius: the radius of VSMShadowMap's blur of the moments")
_BLUR = Param("blurSamples", 8, "int", 1, 64, "samples", source=SOURCE,
              doc="LightShadow.blurSamples: taps of VSMShadowMap's separable blur")


#: variance per axis of one hardware 2×2 comparison tap (a tent one texel wide), in texels²
BILINEAR_TAP_VARIANCE = 1.0 / 6.0
#: variance per axis of PCFShadowMap's 5 Vogel-disk taps at radius 1 (offsets √((i + ½)/5): mean square ½)
VOGEL5_VARIANCE = 0.25
#: VSMShadowMap's reads besides its blur, texels² per axis: the blur passes' taps (one axis reads the
#: nearest-filtered depth, 1/12, the other the linear-filtered moments, 1/6: 1/8 on average) and the
#: receiver's bilinear lookup of the blurred moments (1/6)
VSM_READ_VARIANCE = 1.0 / 8.0 + 1.0 / 6.0


def vsm_blur_variance(samples: int) -> float:
    """Per-axis variance of VSMShadowMap's blur at radius 1: ``samples`` box taps evenly spaced over
    [−1, 1] (three.js's vsm.glsl), mean square (S + 1)/(3(S − 1)); one sample does not blur.

    >>> [round(vsm_blur_variance(s), 6) for s in (1, 2, 3, 8)]
    [0.0, 1.0, 0.666667, 0.428571]
    """
    return 0.0 if samples <= 1 else (samples + 1) / (3.0 * (samples - 1))


def depth_bias(points: ReceiverPoints) -> dict:
    """three.js's ``bias`` (added to the receiver's window depth: negative moves it toward the light)
    and ``normalBias`` (world units along the receiver's normal) that do at each point what shadowlab did.

    >>> pts = ReceiverPoints(*(np.array([x]) for x in (0.02, 0.01, 0.0, 1.0, 4.0, 0.01, 0.03)))
    >>> {k: [round(float(x), 6) for x in v] for k, v in depth_bias(pts).items()}
    {'bias': [-0.0006], 'normalBias': [0.01]}
    """
    return {"bias": -points.dz * points.engine_depth_per_unit, "normalBias": points.normal}


class _Three(EngineTechnique):
    engine = PACKAGE
    page_html = "three.html"
    source = SOURCE

    def unsupported(self, spec) -> str | None:
        why = super().unsupported(spec)
        if why:
            return why
        see_through = [s.name for s in spec.shapes if s.translucent]
        if see_through:
            return (f"{self.name}: three.js cannot express translucent shadow casters ({', '.join(see_through)}): its "
                    "shadow maps are opaque; compare shadowlab's techniques on this scene, or drop transmittance")
        return None


@register
class ThreeBasic(_Three):
    """three.js ``BasicShadowMap``: one unfiltered depth test per pixel."""

    name = "three:basic"
    title = "three.js BasicShadowMap"
    summary = "three.js r187 in Chromium: unfiltered shadow-map test"
    shadow_type = "basic"
    params = (_BIAS, _NORMAL_BIAS, _MAP_SIZE, _NEAR, _FAR, _EXTENT)
    transfer_from = ("hard",)

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias")

    def from_shadowlab(self, points: ReceiverPoints, values: dict) -> dict:
        return depth_bias(points)


@register
class ThreePcf(_Three):
    """three.js ``PCFShadowMap``: 5 hardware-PCF taps on a Vogel disk rotated per pixel."""

    name = "three:pcf"
    title = "three.js PCFShadowMap"
    summary = "three.js r187 in Chromium: 5 hardware-PCF taps on a Vogel disk"
    shadow_type = "pcf"
    params = (_BIAS, _NORMAL_BIAS, _RADIUS_PCF, _MAP_SIZE, _NEAR, _FAR, _EXTENT)
    transfer_from = ("pcf", "hard")

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias", "radius")

    def from_shadowlab(self, points: ReceiverPoints, values: dict) -> dict:
        """:func:`depth_bias`, and the ``radius`` whose footprint (5 Vogel taps of radius r texels,
        each a 2×2 comparison) has shadowlab's filter variance: r²·¼ + ⅙ = σ²/texel² (r = 0 when
        shadowlab's filter is narrower than one hardware tap)."""
        var = points.filter_var / points.engine_texel ** 2
        radius = np.sqrt(np.maximum(var - BILINEAR_TAP_VARIANCE, 0.0) / VOGEL5_VARIANCE)
        return {**depth_bias(points), "radius": radius}


@register
class ThreeVsm(_Three):
    """three.js ``VSMShadowMap``: blurred depth moments and Chebyshev's bound."""

    name = "three:vsm"
    title = "three.js VSMShadowMap"
    summary = "three.js r187 in Chromium: variance shadow map"
    shadow_type = "vsm"
    params = (_BIAS, _NORMAL_BIAS, _RADIUS_VSM, _BLUR, _MAP_SIZE, _NEAR, _FAR, _EXTENT)
    transfer_from = ("vsm",)

    def fit_params(self, values: dict) -> tuple:
        return ("bias", "normalBias", "radius")

    def from_shadowlab(self, points: ReceiverPoints, values: dict) -> dict:
        """:func:`depth_bias`, and the blur ``radius`` whose footprint at ``blurSamples`` has
        shadowlab's filter variance: r²·:func:`vsm_blur_variance` + :data:`VSM_READ_VARIANCE` = σ²/texel²."""
        var = points.filter_var / points.engine_texel ** 2
        k = vsm_blur_variance(int(values["blurSamples"]))
        radius = np.sqrt(np.maximum(var - VSM_READ_VARIANCE, 0.0) / k) if k else np.zeros_like(var)
        return {**depth_bias(points), "radius": radius}

    def unsupported(self, spec) -> str | None:
        point = [l.name for l in spec.lights if l.kind in ("point", "sphere")]
        if point:
            return (f"{self.name}: three.js r187's VSMShadowMap has no point-light shadows (lights "
                    f"{', '.join(point)}); use three:pcf or three:basic on this scene")
        return super().unsupported(spec)


@register
class ThreeCsm(_Three):
    """three.js's CSM addon (``three/addons/csm/CSM.js``): cascades of directional lights with PCF."""

    name = "three:csm"
    title = "three.js CSM addon"
    summary = "three.js r187 in Chromium: cascaded shadow maps (addon), PCF"
    shadow_type = "csm"
    params = (
        Param("cascades", 3, "int", 1, 4, "cascades", source=SOURCE, doc="CSM cascades: the number of cascades"),
        Param("maxFar", 100000.0, "float", 0.1, 1e6, "m", source=SOURCE,
              doc="CSM maxFar: the farthest view depth the cascades cover (with the camera's far)"),
        Param("mode", "practical", "choice", choices=("practical", "uniform", "logarithmic"), source=SOURCE,
              doc="CSM mode: how the view depth is split into cascades"),
        Param("shadowMapSize", 2048, "int", 16, 8192, "texels", source=SOURCE,
              doc="CSM shadowMapSize: each cascade's map resolution"),
        Param("shadowBias", 1e-6, "float", -0.01, 0.01, "shadow-map depth", source=SOURCE,
              doc="CSM shadowBias: LightShadow.bias of every cascade's light"),
        Param("normalBias", 0.0, "float", 0.0, 0.5, "world units (m)", source=SOURCE,
              doc="LightShadow.normalBias of every cascade's light (CSM leaves it at 0)"),
        Param("lightNear", 1.0, "float", 1e-3, 1e4, "m", source=SOURCE,
              doc="CSM lightNear: near plane of each cascade's shadow camera"),
        Param("lightFar", 2000.0, "float", 0.1, 1e6, "m", source=SOURCE,
              doc="CSM lightFar: far plane of each cascade's shadow camera"),
        Param("lightMargin", 200.0, "float", 0.0, 1e5, "m", source=SOURCE,
              doc="CSM lightMargin: how far behind a cascade's box its light is put"),
        Param("fade", False, "bool", source=SOURCE, doc="CSM fade: blend neighbouring cascades at their border"),
    )

    def fit_params(self, values: dict) -> tuple:
        return ("shadowBias", "normalBias")

    def unsupported(self, spec) -> str | None:
        other = [l.name for l in spec.lights if l.kind != "directional"]
        if other:
            return (f"{self.name}: the CSM addon shadows directional lights only (lights {', '.join(other)} are "
                    "not); use three:pcf on them")
        return super().unsupported(spec)
