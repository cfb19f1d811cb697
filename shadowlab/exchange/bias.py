"""Direct3D depth bias → OpenGL ``glPolygonOffset`` and Vulkan ``depthBias*``, per depth format.

shadowlab's shadow-map techniques add Direct3D's rasterizer depth bias to the stored caster depth
(:mod:`shadowlab.techniques.shadow_map`). The three APIs define the bias with the same formula
and differ only in the unit ``r`` of the constant term. Definitions (D3D11 "Depth Bias" page;
OpenGL 4.6 core §14.6.5 "Depth Offset"; Vulkan "Depth Bias Computation"; all in window depth
z ∈ [0, 1], slopes per pixel):

* Direct3D: Bias = DepthBias·r + SlopeScaledDepthBias·MaxDepthSlope, MaxDepthSlope = max(|∂z/∂x|,
  |∂z/∂y|); UNORM: r = the smallest representable value > 0 = 1/(2^n − 1); 32-bit float:
  r = 2^(exponent(max z of the primitive) − 23). DepthBiasClamp > 0: min(clamp, Bias); < 0:
  max(clamp, Bias); 0: none.
* OpenGL: o = m·factor + r·units; ``glPolygonOffsetClamp`` clamps like DepthBiasClamp. m is the
  exact gradient length √((∂z/∂x)² + (∂z/∂y)²) or its approximation max(|∂z/∂x|, |∂z/∂y|) (the
  implementation chooses). Fixed point: r is an implementation constant ("the smallest difference
  guaranteed to remain distinct"); floating point: r = 2^(e − 23), e the largest exponent of the
  primitive's z, exactly Direct3D's.
* Vulkan: o = dbclamp(m·depthBiasSlopeFactor + r·depthBiasConstantFactor), the same m and clamp.
  Fixed point: r is implementation-dependent but at most 2·2^−n; with ``VK_EXT_depth_bias_control``
  and ``depthBiasExact`` it is 2^−n, with ``VK_DEPTH_BIAS_REPRESENTATION_FLOAT_EXT`` it is 1.
  Floating point: r = 2^(e − 23), Direct3D's.

Mapping (the same bias in depth units for every depth and slope, see
``tests/test_bias_mapping.py``)::

    factor = depthBiasSlopeFactor   = SlopeScaledDepthBias
    units  = depthBiasConstantFactor = DepthBias · r_D3D / r_API
    clamp  = depthBiasClamp         = DepthBiasClamp

The slope term is exact where the implementation uses the max approximation of m (Mesa llvmpipe
does); with the exact gradient length it is up to √2 larger for a slope along a diagonal. r_API
of a fixed-point buffer depends on the implementation (:data:`R_PRESETS`):

==============  ================  ==============================  ==========================
format          r_D3D             r_API                           units / constantFactor
==============  ================  ==============================  ==========================
UNORM n bits    1/(2^n − 1)       ``"step"`` 1/(2^n − 1)          DepthBias
                                  ``"pow2"`` 2^−n (Vulkan exact)  DepthBias · 2^n/(2^n − 1)
                                  ``"mesa-llvmpipe"`` 2/(2^n − 1) DepthBias / 2
                                  ``"float"`` 1 (Vulkan FLOAT)    DepthBias / (2^n − 1)
FLOAT32         2^(e − 23)        2^(e − 23) (every API)          DepthBias
==============  ================  ==============================  ==========================

Mesa's llvmpipe (the OpenGL rasteriser measured here: 24-bit depth, ``depth_bias = 16,
slope_scaled_depth_bias = 2`` matched ``glPolygonOffset(2, 8)``) scales ``units`` by twice the
format's step 1/(2^n − 1) for UNORM buffers (its setup code: units · mrd · 2), uses
max(|∂z/∂x|, |∂z/∂y|) for m and D3D's exponent rule for float buffers; older llvmpipe releases
scaled by one step (``"step"``). Other drivers choose their own r (Vulkan bounds it by 2·2^−n, and
no buffer resolves less than one step), so between about DepthBias/2 and DepthBias units reproduce
one Direct3D DepthBias: measure a driver once (render a plane facing the light with ``units`` only
and read the depth back) and pass its r.

>>> gl_polygon_offset(16, 2.0, 24, r_gl="mesa-llvmpipe")
PolygonOffset(factor=2.0, units=8.0, clamp=0.0)
>>> gl_polygon_offset(16, 2.0, 24)                      # r = one UNORM step
PolygonOffset(factor=2.0, units=16.0, clamp=0.0)
>>> gl_polygon_offset(16, 2.0, 32, r_gl="mesa-llvmpipe")  # float depth: r is defined, not chosen
PolygonOffset(factor=2.0, units=16.0, clamp=0.0)
>>> vk_depth_bias(16, 2.0, 16, depth_bias_clamp=1e-3, r_vk="pow2")
VkDepthBias(depthBiasConstantFactor=16.000244..., depthBiasSlopeFactor=2.0, depthBiasClamp=0.001)
>>> o = polygon_offset(*gl_polygon_offset(16, 2.0, 24, r_gl="pow2"), m=1e-4, r=api_r(24, "pow2"))
>>> abs(o - d3d_depth_bias(16, 2.0, 1e-4, 24)) < 1e-18
True
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import NamedTuple

from ..errors import InputError

__all__ = ["PolygonOffset", "VkDepthBias", "R_PRESETS", "DEPTH_BITS", "d3d_r", "api_r", "d3d_depth_bias",
           "polygon_offset", "gl_polygon_offset", "vk_depth_bias", "bias_mapping"]

DEPTH_BITS = (16, 24, 32)  # 16/24-bit UNORM, 32-bit float

#: r of an OpenGL / Vulkan implementation for an n-bit UNORM depth buffer (exact fractions)
R_PRESETS = {
    "step": lambda n: Fraction(1, 2 ** n - 1),           # one UNORM step (= Direct3D's r)
    "pow2": lambda n: Fraction(1, 2 ** n),               # 2^-n: Vulkan with depthBiasExact
    "mesa-llvmpipe": lambda n: Fraction(2, 2 ** n - 1),  # Mesa llvmpipe: units * mrd * 2
    "spec-max": lambda n: Fraction(2, 2 ** n),           # the largest r Vulkan allows (2 * 2^-n)
    "float": lambda n: Fraction(1),                      # VK_DEPTH_BIAS_REPRESENTATION_FLOAT_EXT: r = 1
}
R_PRESET_NOTES = {
    "step": "r = 1/(2^n - 1), one UNORM step (Direct3D's r; older Mesa llvmpipe)",
    "pow2": "r = 2^-n (Vulkan with VK_EXT_depth_bias_control depthBiasExact)",
    "mesa-llvmpipe": "r = 2/(2^n - 1) (Mesa llvmpipe: one unit = 2 DepthBias steps)",
    "spec-max": "r = 2 * 2^-n, the largest r Vulkan allows",
    "float": "r = 1 (Vulkan VK_DEPTH_BIAS_REPRESENTATION_FLOAT_EXT: the constant is in depth units)",
}


class PolygonOffset(NamedTuple):
    """``glPolygonOffsetClamp(factor, units, clamp)`` (``glPolygonOffset(factor, units)`` when clamp is 0)."""

    factor: float
    units: float
    clamp: float


class VkDepthBias(NamedTuple):
    """The ``VkPipelineRasterizationStateCreateInfo`` / ``vkCmdSetDepthBias`` members."""

    depthBiasConstantFactor: float
    depthBiasSlopeFactor: float
    depthBiasClamp: float


def _check_bits(bits) -> int:
    if bits not in DEPTH_BITS:
        raise InputError(f"depth bits {bits!r}: expected 16 or 24 (UNORM) or 32 (float)")
    return int(bits)


def _exponent(z: float) -> int:
    """IEEE exponent of a float32 value (z > 0): z = 1.f × 2^e."""
    return math.frexp(z)[1] - 1


def d3d_r(bits: int, depth: float | None = None) -> float:
    """Direct3D's r: 1/(2^n − 1) for n-bit UNORM, 2^(exponent(depth) − 23) for 32-bit float
    (``depth``: the largest depth of the primitive; 0 gives r = 0).

    >>> d3d_r(16) == 1 / 65535, d3d_r(32, 0.75) == 2.0 ** -24
    (True, True)
    """
    bits = _check_bits(bits)
    if bits != 32:
        return 1.0 / (2 ** bits - 1)
    if depth is None:
        raise InputError("32-bit float depth: r = 2^(exponent(z) - 23) needs the depth z")
    return 0.0 if depth <= 0 else 2.0 ** (_exponent(depth) - 23)


def api_r(bits: int, r="step", depth: float | None = None) -> float:
    """r of an OpenGL / Vulkan implementation: for UNORM a :data:`R_PRESETS` name or a number; for
    32-bit float the spec's 2^(e − 23) whatever ``r`` says (except ``"float"``: 1)."""
    bits = _check_bits(bits)
    if isinstance(r, str):
        if r not in R_PRESETS:
            raise InputError(f"r {r!r}: expected a number or one of {', '.join(R_PRESETS)}")
        if bits == 32 and r != "float":
            return d3d_r(32, depth)
        return float(R_PRESETS[r](bits))
    if bits == 32:
        return d3d_r(32, depth)
    if not (isinstance(r, (int, float)) and r > 0 and math.isfinite(r)):
        raise InputError(f"r {r!r}: expected a positive number (the implementation's minimum resolvable difference)")
    return float(r)


def _clamp(b: float, clamp: float) -> float:
    return min(clamp, b) if clamp > 0 else max(clamp, b) if clamp < 0 else b


def d3d_depth_bias(depth_bias: float, slope_scaled_depth_bias: float, max_depth_slope: float, bits: int,
                   depth: float | None = None, depth_bias_clamp: float = 0.0) -> float:
    """Direct3D's Bias (depth units) of a primitive with ``max_depth_slope`` and largest depth ``depth``."""
    b = depth_bias * d3d_r(bits, depth) + slope_scaled_depth_bias * max_depth_slope
    return _clamp(b, depth_bias_clamp)


def polygon_offset(factor: float, units: float, clamp: float = 0.0, *, m: float, r: float) -> float:
    """The OpenGL / Vulkan offset o = clamp(m·factor + r·units) (depth units)."""
    return _clamp(m * factor + r * units, clamp)


def _units(depth_bias: float, bits: int, r) -> float:
    """DepthBias · r_D3D / r_API, exact for the presets."""
    bits = _check_bits(bits)
    if bits == 32:
        if r == "float":
            raise InputError("32-bit float depth with r = 1 (VK_DEPTH_BIAS_REPRESENTATION_FLOAT_EXT): Direct3D's "
                             "float bias 2^(exponent(z) - 23) depends on the depth and has no constant equivalent; "
                             "use the format's representation")
        return float(depth_bias)  # both define r = 2^(e - 23)
    if isinstance(r, str):
        api_r(bits, r)  # validates the name
        return float(Fraction(depth_bias) * Fraction(1, 2 ** bits - 1) / R_PRESETS[r](bits))
    return float(depth_bias) * d3d_r(bits) / api_r(bits, r)


def gl_polygon_offset(depth_bias: float, slope_scaled_depth_bias: float, bits: int, *,
                      depth_bias_clamp: float = 0.0, r_gl="step") -> PolygonOffset:
    """``glPolygonOffsetClamp`` arguments that reproduce Direct3D's (DepthBias,
    SlopeScaledDepthBias, DepthBiasClamp) on an OpenGL implementation whose minimum resolvable
    difference is ``r_gl`` (a :data:`R_PRESETS` name or a number; ignored for float depth, where
    OpenGL defines r as Direct3D does)."""
    return PolygonOffset(float(slope_scaled_depth_bias), _units(depth_bias, bits, r_gl), float(depth_bias_clamp))


def vk_depth_bias(depth_bias: float, slope_scaled_depth_bias: float, bits: int, *,
                  depth_bias_clamp: float = 0.0, r_vk="step") -> VkDepthBias:
    """``depthBiasConstantFactor``, ``depthBiasSlopeFactor``, ``depthBiasClamp`` that reproduce
    Direct3D's bias with the implementation's r = ``r_vk`` (``"pow2"`` with depthBiasExact,
    ``"float"`` with the FLOAT representation, or the driver's own)."""
    return VkDepthBias(_units(depth_bias, bits, r_vk), float(slope_scaled_depth_bias), float(depth_bias_clamp))


def bias_mapping(depth_bias: float, slope_scaled_depth_bias: float, depth_bias_clamp: float, bits: int) -> dict:
    """The per-format mapping lights.json carries: the Direct3D values and their OpenGL / Vulkan
    equivalents for each r of :data:`R_PRESETS` that applies to the format."""
    bits = _check_bits(bits)
    fmt = "float32" if bits == 32 else f"unorm{bits}"
    out = {
        "depth_format": fmt,
        "direct3d": {"DepthBias": depth_bias, "SlopeScaledDepthBias": float(slope_scaled_depth_bias),
                     "DepthBiasClamp": float(depth_bias_clamp),
                     "r": "2^(exponent(max z of the primitive) - 23)" if bits == 32 else f"1/(2^{bits} - 1)",
                     "r_value": None if bits == 32 else d3d_r(bits)},
        "bias_depth_units": "DepthBias * r + SlopeScaledDepthBias * max(|dz/dx|, |dz/dy|), clamped by "
                            "DepthBiasClamp (z: window depth 0..1, per texel)",
    }
    if bits == 32:
        gl, vk = gl_polygon_offset(depth_bias, slope_scaled_depth_bias, 32, depth_bias_clamp=depth_bias_clamp), \
            vk_depth_bias(depth_bias, slope_scaled_depth_bias, 32, depth_bias_clamp=depth_bias_clamp)
        out["opengl"] = [{"r": "2^(e - 23) (defined by the spec)", **gl._asdict()}]
        out["vulkan"] = [{"r": "2^(e - 23) (defined by the spec; format representation)", **vk._asdict()}]
        return out
    out["opengl"] = [{"r_preset": k, "r": R_PRESET_NOTES[k], "r_value": float(R_PRESETS[k](bits)),
                      **gl_polygon_offset(depth_bias, slope_scaled_depth_bias, bits, depth_bias_clamp=depth_bias_clamp,
                                          r_gl=k)._asdict()}
                     for k in ("step", "mesa-llvmpipe", "pow2")]
    out["vulkan"] = [{"r_preset": k, "r": R_PRESET_NOTES[k], "r_value": float(R_PRESETS[k](bits)),
                      **vk_depth_bias(depth_bias, slope_scaled_depth_bias, bits, depth_bias_clamp=depth_bias_clamp,
                                      r_vk=k)._asdict()}
                     for k in ("step", "pow2", "float")]
    return out
