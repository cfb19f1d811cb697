"""Exponential shadow maps (``esm``), [Buljan 2020, §3.4] [Annen 2008].

Under the assumption z ≤ z̃ (no stored depth is farther than the receiver), the depth test
is the limit of exp(−c(z̃ − z)) for c → ∞, and for a finite c it factorises::

    s(z, z̃) = exp(−c(z̃ − z)) = exp(−c·z̃) · exp(c·z)
    f(t, z̃) = Σ k(t_i − t) s(z(t_i), z̃) = exp(−c·z̃) · Σ k(t_i − t) exp(c·z(t_i))

so the map stores exp(c·zn) (zn ∈ [0, 1], the depth domain of
:mod:`shadowlab.techniques.prefilter`), blurs it with the separable prefilter and reads it
bilinearly: E; visibility = clamp(exp(−c·z̃)·E, 0, 1). The product is evaluated as
exp(ln E − c·z̃): the same number, but exp(−c·z̃) alone would underflow fp32 for c·z̃ > 87.3.

``exponent`` c: 80 recommended for fp32 ([2] in the source); larger c is sharper and leaks
less near contacts (Slika 3.7). The map holds exp(c·zn) up to exp(c) (empty texels, zn = 1),
and the largest fp32 value is ≈ 3.4·10³⁸ = exp(88.72): c > 88.72 overflows to ∞ and is
refused with an InputError. The source's UI range is [1, 88].

Non-planarity (§3.4 "Kršenje pretpostavke", Slika 3.8/3.9): where the filter region holds
depths farther than the receiver, E·exp(−c·z̃) can exceed 1 and a shadowed point shows lit.
``fallback`` selects the source's two classifications of such points, which then get PCF
over the same footprint (:func:`~shadowlab.techniques.prefilter.pcf_footprint`: the biased
depth tests of ``shadow_map.depth_test``, so this technique also declares the Direct3D
rasterizer biases, which only these taps use):

* ``threshold``: exp(−c·z̃)·E > 1 + ε (ε = ``threshold_eps``): fast, catches only the
  failures that overshoot 1 by more than ε;
* ``zmax``: z̃ < z_max, z_max the maximum zn over the footprint (a separable max filter of the
  same n texels, then the maximum of the 4 texels the bilinear lookup reads): catches every
  point whose footprint holds a farther depth, which includes every receiver sloped in light
  space (PCF is then what it gets: correct, just not prefiltered).

The fallback PCF is evaluated for every point and selected where flagged (no branches in the
SIMD kernel), so its cost does not depend on how many points fall back; it is a symbolic loop
over the (n + 1)² taps (one compiled kernel for every ``kernel``). ``stats["fallback"]`` counts
the flagged points per light and the AOV ``<light>.fallback`` marks them (1).

``test_esm_non_planarity_failure_and_both_fallbacks`` (tests/test_moments.py) shows the
failure on ``step`` (a platform under a plate, both ending at x = 0, the floor 0.4 below the
platform, 5×5): points on the platform's top that the hard shadow map shadows are shown lit by
ESM; both classifications flag every one of them and give them PCF's value, and the threshold
flags fewer points than z-max. Every point of a receiver tilted in light space has farther
depths in its footprint, so z-max sends most of an ordinary scene to PCF (``stats["fallback"]``
counts how many). At ``kernel`` = 1 ESM is the hard shadow map except where the 2×2 lookup
straddles an edge (``test_zero_filter_size_reduces_to_the_hard_shadow_map``); on ``bench`` the
non-planarity of the legs' footprints makes it leak more than VSM (``shadowlab compare bench
--techniques vsm,esm`` prints both leak rates).

Only ``exponent`` is differentiable (the fallbacks are classifications: step functions); pass
an ``mi.Float`` with gradients enabled (checked against finite differences in the tests). The
product E·exp(−c·z̃) is evaluated as exp(ln E − c·z̃), so neither the value nor its derivative
overflows for c ≤ 88.72.
"""

from __future__ import annotations

import math

import drjit as dr

from ..errors import InputError
from .base import Param, device_count, param_table_markdown, register
from .prefilter import (FILTER_PARAMS, MAP_PARAMS, RASTER_PARAMS, RECEIVER_PARAMS, PrefilteredTechnique, bilinear,
                        corner_max, max_filter, normalised_depth, pcf_footprint, scalar)

#: ln(FLT_MAX): the largest c for which exp(c·z), z ≤ 1, is a finite fp32 number
FP32_EXP_LIMIT = 88.72
assert math.exp(FP32_EXP_LIMIT) < 3.4028234663852886e38


def fp32_cap_error(where: str, value: float, cap: float, stored: str) -> InputError:
    return InputError(
        f"{where}={value:g} is above the fp32 limit {cap:g}: the map stores {stored} for normalised depths "
        f"up to 1, and the largest 32-bit float is ≈ 3.4e38 = exp(88.72), so a larger exponent overflows to "
        f"infinity ([Buljan 2020, §3.4/§3.5]); use a value ≤ {cap:g}")


@register
class ESM(PrefilteredTechnique):
    """Exponential shadow map with the threshold and z-max fallbacks to PCF."""

    name = "esm"
    title = "Exponential shadow map"
    summary = ("prefiltered exp(c·z) of the normalised linear depth, visibility exp(−c·z̃)·E; optional "
               "threshold or z-max classification of non-planar points, which fall back to PCF")
    channels = 1
    params = FILTER_PARAMS + (
        Param("exponent", 80.0, "float", 1.0, FP32_EXP_LIMIT, "1/zn", True, source="[Buljan 2020, §3.4]",
              doc="c of exp(−c(z̃ − z)); 80 recommended for fp32; above 88.72 exp(c) overflows fp32"),
        Param("fallback", "none", "choice", choices=("none", "threshold", "zmax"), source="[Buljan 2020, §3.4]",
              doc="classify non-planar points and use PCF there: threshold (result > 1 + ε) or zmax "
                  "(z̃ < max depth in the footprint)"),
        Param("threshold_eps", 0.05, "float", 0.0, 10.0, "", False, source="[Buljan 2020, §3.4]",
              doc="ε of the threshold classification"),
    ) + MAP_PARAMS + RECEIVER_PARAMS + RASTER_PARAMS

    def resolve(self, overrides=None):
        c = (overrides or {}).get("exponent")
        if c is not None and not isinstance(c, dr.ArrayBase):
            try:
                cf = float(c)
            except (TypeError, ValueError):
                cf = None
            if cf is not None and math.isfinite(cf) and cf > FP32_EXP_LIMIT:
                raise fp32_cap_error("esm.exponent", cf, FP32_EXP_LIMIT, "exp(c·z)")
        return super().resolve(overrides)

    def moments(self, view, values):
        return [dr.exp(scalar(values, "exponent") * normalised_depth(view))]

    def estimate(self, view, rec, fp, bias, values, maps):
        n, kind = int(values["kernel"]), values["filter"]
        c = scalar(values, "exponent")
        (E,) = bilinear(view, maps, fp)
        raw = dr.exp(dr.log(E) - c * rec["zn"])
        vis = dr.clip(raw, 0.0, 1.0)
        mode = values["fallback"]
        if mode == "none":
            return vis, {}, {}
        if mode == "threshold":
            flag = raw > 1.0 + scalar(values, "threshold_eps")
        else:
            flag = rec["zn"] < corner_max(view, max_filter(view, normalised_depth(view), n), fp)
        flag &= rec["active"]
        vis = dr.select(flag, pcf_footprint(view, rec, fp, bias, n, kind), vis)
        return vis, {"fallback": dr.select(flag, 1.0, 0.0)}, {"fallback": device_count(flag)}


__doc__ += "\n\nParameters of ``esm`` (generated from the declaration):\n\n" + param_table_markdown(ESM)
