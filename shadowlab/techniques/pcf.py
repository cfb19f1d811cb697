"""Percentage-closer filtering (``pcf``), n×n grid, 003_b5589b67cce60746.txt §3.2.

Filter the results of the depth comparison, not the depths (§3.1 shows why the latter stays
binary)::

    f_pcf(t, z̃) = Σ_{t_i ∈ K} k(t_i − t) · H(z(t_i) − z̃)

with K the regular n×n grid t_i = t + softness · (a, b), a, b ∈ {−(n−1)/2, …, (n−1)/2} texels
(the source's Code A.4 scales the texel spacing by ``softness``), and the constant kernel
k = 1/n², so the result takes one of n² + 1 values. Each tap is a nearest-texel depth test with
all the bias variants of §2.3 (``BIAS_PARAMS`` of :mod:`shadowlab.techniques.shadow_map`, the
same declaration and defaults as ``hard``); ``kernel`` = 1 is exactly ``hard``, bit for bit.
Taps of a cube-map face are clamped to that face (no seam crossing).

PCF does not remove acne (§3.2): a tap ``a`` texels away compares the receiver's depth with a
caster ``a`` texels away, so on tilted receivers wide kernels need more slope-scaled bias (or
``normal_offset``) than ``hard``: about 2·((n − 1)/2 · softness + 1/2) for a planar caster.
With the shared defaults (slope-scaled bias 2) the mean over-darkening against exact point-light
visibility is 0.5 % (3×3) and 11 % (5×5) on ``contact``. The box-filtered nearest-texel taps
make the visibility piecewise constant in ``softness`` and the biases: no parameter is
``differentiable``.
``softness`` and the biases enter the kernel through ``dr.opaque``; the n² taps unroll in Python
(``kernel`` is structural: each n compiles once).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .base import Param, param_table_markdown, register
from .shadow_map import BIAS_PARAMS, ShadowMapTechnique, depth_test, texel_index

PCF_PARAMS = (
    Param("kernel", 3, "int", 1, 9, "taps per side", False, source="003 §3.2",
          doc="n of the n×n tap grid (1 = plain shadow map; 3, 5, 7 in the source)"),
    Param("softness", 1.0, "float", 0.25, 8.0, "texels", False, source="003 §3.2",
          doc="spacing of the taps in shadow-map texels (the source's `softness`)"),
)


@register
class PCF(ShadowMapTechnique):
    """n×n percentage-closer filtering with a box kernel over nearest-texel biased depth tests."""

    name = "pcf"
    title = "PCF n×n grid"
    summary = "percentage-closer filtering on an n×n grid of nearest-texel biased depth tests"
    params = PCF_PARAMS + BIAS_PARAMS

    def filter(self, view, rec, bias, values):
        n = int(values["kernel"])
        s = dr.opaque(mi.Float, float(values["softness"]))
        offs = [k - (n - 1) / 2.0 for k in range(n)]
        acc = None
        for b in offs:
            iy = texel_index(rec["v"] + b * s)
            for a in offs:
                t = depth_test(view, rec, texel_index(rec["u"] + a * s), iy, bias)
                acc = t if acc is None else acc + t
        return acc * (1.0 / (n * n))


__doc__ += "\n\nParameters of ``pcf`` (generated from the declaration):\n\n" + param_table_markdown(PCF)
