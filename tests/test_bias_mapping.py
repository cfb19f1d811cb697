"""Direct3D depth bias → OpenGL glPolygonOffset / Vulkan depthBias* (shadowlab/exchange/bias.py).

The mapping is derived here from the APIs' definitions, written out in this file independently of
the module: Direct3D's Bias = DepthBias·r + SlopeScaledDepthBias·MaxDepthSlope (UNORM r =
1/(2^n − 1), float r = 2^(exponent(z) − 23)), OpenGL's / Vulkan's o = m·factor + r·units (float
r = 2^(e − 23); fixed point r chosen by the implementation). For UNORM16, UNORM24 and FLOAT32,
several depths, slopes, bias values and clamps and every r an implementation may use, the mapped
parameters give the same bias in depth units; a wrong mapping (the usual units = DepthBias on an
implementation with r = 2 steps, or a factor off by 2) is caught by the same comparison. The
mapping also reproduces shadowlab's own rasterizer bias (what ``hard`` adds to the stored depth).
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.exchange.bias import (R_PRESETS, PolygonOffset, VkDepthBias, bias_mapping, gl_polygon_offset,
                                     vk_depth_bias)

DEPTHS = (1e-3, 0.1, 0.37, 0.5, 0.75, 0.9999)
SLOPES = (0.0, 1e-6, 3e-4, 0.02, 0.5)
PARAMS = ((16, 2.0, 0.0), (1, 0.5, 0.0), (-7, 1.0, 0.0), (1000, 0.0, 1e-4), (250, 3.0, -2e-5), (3, -1.5, 0.0))
# r of an n-bit UNORM buffer, from the specs' wording (not from the module)
R_UNORM = {
    "step": lambda n: 1.0 / (2 ** n - 1),        # one representable step (D3D's "minimum value > 0")
    "pow2": lambda n: 2.0 ** -n,                 # Vulkan depthBiasExact
    "mesa-llvmpipe": lambda n: 2.0 / (2 ** n - 1),
    "spec-max": lambda n: 2.0 * 2.0 ** -n,       # Vulkan's upper bound
    "float": lambda n: 1.0,                      # VK_DEPTH_BIAS_REPRESENTATION_FLOAT_EXT
}


def _clamp(b, c):
    return min(c, b) if c > 0 else max(c, b) if c < 0 else b


def _ieee_exponent(z):
    return math.frexp(z)[1] - 1  # z = 1.f × 2^e


def d3d_bias(depth_bias, ssdb, clamp, bits, z, m):
    """D3D11 "Depth Bias": UNORM r = the minimum representable value > 0; float r = 2^(exponent(z) − 23)."""
    r = 1.0 / (2 ** bits - 1) if bits != 32 else 2.0 ** (_ieee_exponent(z) - 23)
    return _clamp(depth_bias * r + ssdb * m, clamp)


def api_bias(factor, units, clamp, bits, z, m, r_name):
    """OpenGL §14.6.5 / Vulkan "Depth Bias Computation": o = clamp(m·factor + r·units)."""
    r = R_UNORM[r_name](bits) if bits != 32 else 2.0 ** (_ieee_exponent(z) - 23)
    return _clamp(m * factor + r * units, clamp)


def _same(a, b):
    return abs(a - b) <= 1e-12 * max(abs(a), abs(b)) + 1e-300


def _presets(bits):
    return [k for k in R_UNORM if not (bits == 32 and k == "float")]


@pytest.mark.parametrize("bits", [16, 24, 32])
def test_mapping_gives_direct3ds_bias_from_the_definitions(bits):
    n = 0
    for depth_bias, ssdb, clamp in PARAMS:
        for r_name in _presets(bits):
            gl = gl_polygon_offset(depth_bias, ssdb, bits, depth_bias_clamp=clamp, r_gl=r_name)
            vk = vk_depth_bias(depth_bias, ssdb, bits, depth_bias_clamp=clamp, r_vk=r_name)
            assert isinstance(gl, PolygonOffset) and isinstance(vk, VkDepthBias)
            for z in DEPTHS:
                for m in SLOPES:
                    want = d3d_bias(depth_bias, ssdb, clamp, bits, z, m)
                    assert _same(api_bias(*gl, bits, z, m, r_name), want), (bits, r_name, depth_bias, z, m, gl)
                    assert _same(api_bias(vk.depthBiasSlopeFactor, vk.depthBiasConstantFactor, vk.depthBiasClamp,
                                          bits, z, m, r_name), want), (bits, r_name, depth_bias, z, m, vk)
                    n += 1
    assert n == len(PARAMS) * len(_presets(bits)) * len(DEPTHS) * len(SLOPES)


def test_a_wrong_mapping_is_caught():
    """The comparison above fails for the mappings one might write instead."""
    z, m = 0.5, 3e-4
    want = d3d_bias(16, 2.0, 0.0, 24, z, m)
    # units = DepthBias on an implementation whose r is two steps (llvmpipe): the constant term doubles
    assert not _same(api_bias(2.0, 16.0, 0.0, 24, z, m, "mesa-llvmpipe"), want)
    # the slope factor halved along with the units
    assert not _same(api_bias(1.0, 8.0, 0.0, 24, z, 3e-4, "mesa-llvmpipe"), want)
    # 2^-n instead of one step 1/(2^n - 1) is off by 2^-n relative: visible for 16-bit and large DepthBias
    assert not _same(api_bias(2.0, 1000.0, 0.0, 16, z, 0.0, "pow2"), d3d_bias(1000, 2.0, 0.0, 16, z, 0.0))
    assert _same(api_bias(*gl_polygon_offset(1000, 2.0, 16, r_gl="pow2"), 16, z, 0.0, "pow2"),
                 d3d_bias(1000, 2.0, 0.0, 16, z, 0.0))


def test_the_measured_llvmpipe_example():
    """Mesa llvmpipe, 24-bit depth: depth_bias = 16, slope_scaled_depth_bias = 2 matched glPolygonOffset(2, 8)."""
    assert gl_polygon_offset(16, 2, 24, r_gl="mesa-llvmpipe") == PolygonOffset(2.0, 8.0, 0.0)
    assert gl_polygon_offset(16, 2, 24, r_gl=2 / (2 ** 24 - 1)).units == pytest.approx(8.0, rel=1e-12)
    # float depth: r is defined by the specs, whatever the implementation's fixed-point r
    assert gl_polygon_offset(16, 2, 32, r_gl="mesa-llvmpipe") == PolygonOffset(2.0, 16.0, 0.0)
    assert vk_depth_bias(16, 2, 16, r_vk="pow2").depthBiasConstantFactor == pytest.approx(16 * 65536 / 65535, rel=1e-15)
    assert vk_depth_bias(16, 2, 24, r_vk="float").depthBiasConstantFactor == pytest.approx(16 / (2 ** 24 - 1))
    with pytest.raises(InputError, match="float"):
        vk_depth_bias(16, 2, 32, r_vk="float")
    with pytest.raises(InputError, match="depth bits"):
        gl_polygon_offset(16, 2, 8)
    with pytest.raises(InputError, match="expected a number or one of"):
        gl_polygon_offset(16, 2, 24, r_gl="nvidia")
    assert set(R_PRESETS) == set(R_UNORM)


def test_bias_mapping_table_is_the_functions():
    t = bias_mapping(16, 2.0, 0.0, 24)
    assert t["depth_format"] == "unorm24" and t["direct3d"]["DepthBias"] == 16
    gl = {e["r_preset"]: e for e in t["opengl"]}
    assert (gl["mesa-llvmpipe"]["factor"], gl["mesa-llvmpipe"]["units"]) == (2.0, 8.0)
    assert gl["step"]["units"] == 16.0 and gl["mesa-llvmpipe"]["r_value"] == 2 / (2 ** 24 - 1)
    vk = {e["r_preset"]: e for e in t["vulkan"]}
    assert vk["pow2"]["depthBiasConstantFactor"] == vk_depth_bias(16, 2.0, 24, r_vk="pow2").depthBiasConstantFactor
    f = bias_mapping(16, 2.0, 0.0, 32)
    assert f["depth_format"] == "float32" and [e["units"] for e in f["opengl"]] == [16.0]


@pytest.mark.parametrize("bits", [16, 24, 32])
def test_mapping_reproduces_shadowlabs_rasterizer_bias(bits, mitsuba_backend):
    """``hard`` adds shadow_map.rasterizer_bias (Direct3D's bias, in float32) to the stored depth D
    of a texel of slope S; the mapped OpenGL parameters give the same bias at (D, S)."""
    import mitsuba as mi
    from shadowlab.techniques.shadow_map import opaque_bias, rasterizer_bias
    rng = np.random.default_rng(bits)
    D = np.concatenate([np.array(DEPTHS), rng.uniform(0.0, 1.0, 200)]).astype(np.float32)[:205]
    S = np.concatenate([np.array(SLOPES + (0.1,)), rng.uniform(0.0, 0.05, 199)]).astype(np.float32)
    for depth_bias, ssdb, clamp in PARAMS:
        values = {"depth_bias": depth_bias, "slope_scaled_depth_bias": ssdb, "depth_bias_clamp": clamp,
                  "constant_bias": 0.0, "slope_bias": 0.0, "max_slope_bias": 0.0, "normal_offset": 0.0}
        got = np.asarray(rasterizer_bias(SimpleNamespace(bits=bits), mi.Float(D), mi.Float(S), opaque_bias(values)),
                         np.float64)
        for r_name in _presets(bits):
            gl = gl_polygon_offset(depth_bias, ssdb, bits, depth_bias_clamp=clamp, r_gl=r_name)
            want = np.array([api_bias(*gl, bits, float(z), float(m), r_name) for z, m in zip(D, S)])
            np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-12, err_msg=f"{bits} {r_name} {depth_bias}")
