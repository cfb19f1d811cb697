"""Exponential variance shadow maps (``evsm``), [Buljan 2020, §3.5] [Lauritzen 2008].

VSM (§3.3) applied to exponentially warped depths. Warping with exp(k·z) shrinks the ratio
t = Δx/Δy that drives VSM's light leaking (for a ≤ b ≤ c, t'/t < 1, smaller for larger k);
the negative warp −exp(−k·z) does the opposite and guards against ESM's non-planarity. With
both (4 channels) each gives a Chebyshev upper bound and the visibility is the smaller::

    w  = 2·zn − 1 ∈ [−1, 1]                         (as the source's Code A.8: 2·depth − 1)
    pos = exp(k⁺·w),  neg = −exp(−k⁻·w)
    channels: (pos, pos²)                               components = 2 (positive only)
              (pos, pos², neg, neg²)                    components = 4
    visibility = min(Reduction(p_max⁺(pos(z̃)), p), Reduction(p_max⁻(neg(z̃)), p))

(zn: the normalised linear depth of :mod:`shadowlab.techniques.prefilter`; the same
separable prefilter and bilinear lookup). The second moment exp(2k·w) reaches exp(2k), so
k ≤ 88.72/2 = 44.36 for fp32 (§3.5: "half the value of ESM's"); larger values raise an
InputError. Defaults k⁺ = 40 (the source's Slika 3.10 uses c = 40), k⁻ = 5.

Minimum variance: ``min_variance`` σ²_min is given in zn² units, like VSM's, and mapped to
each warp by the square of the warp's derivative at the receiver (first-order change of
variables, as Lauritzen's sample does): σ²_min⁺ = σ²_min·(2k⁺·pos(z̃))²,
σ²_min⁻ = σ²_min·(2k⁻·neg(z̃))² (capped at 10³⁸). At the ends of the range fp32 runs out: for w
near −1, pos² ≈ exp(−2k⁺) underflows, and so does neg² for w near +1, where that bound then
says little; the other bound still holds. The warped moments reach 10³⁸, so the Chebyshev
bound is evaluated in the log domain (:func:`~shadowlab.techniques.prefilter.chebyshev`): no
overflow in the value or in its reverse-mode derivative.

On ``bench`` at 3×3 (Slika 3.10's filter) EVSM shows fewer umbra pixels lit than VSM, and the
4-component result is never above the 2-component one, being the minimum of the two bounds (the
positive warp alone is ESM-like and fails on non-planar footprints, which the negative warp's
bound catches): ``test_evsm_leaks_less_than_vsm_on_bench`` in tests/test_moments.py asserts
both; ``shadowlab compare bench --techniques vsm,evsm`` prints the leak rates. On ``stack``
(t = 3) the warp removes the two-depth leak: t' = (e^{kb} − e^{ka})/(e^{kc} − e^{kb}) ≪ t. At
``kernel`` = 1 the result is the hard shadow map except where the 2×2 lookup straddles an edge
(``test_zero_filter_size_reduces_to_the_hard_shadow_map``).

``exp_pos``, ``exp_neg``, ``min_variance`` and ``bleed`` are differentiable (pass an
``mi.Float`` with gradients enabled; AD and central differences agree on ``contact``).
"""

from __future__ import annotations

import math

import drjit as dr

from .base import Param, param_table_markdown, register
from .esm import FP32_EXP_LIMIT, fp32_cap_error
from .prefilter import (BLEED, FILTER_PARAMS, MAP_PARAMS, MIN_VARIANCE, RECEIVER_PARAMS, PrefilteredTechnique, bilinear,
                        chebyshev, normalised_depth, reduction, scalar)

#: exp(2k) must be a finite fp32 number
EVSM_EXP_LIMIT = 44.36
assert 2 * EVSM_EXP_LIMIT <= FP32_EXP_LIMIT and math.exp(2 * EVSM_EXP_LIMIT) < 3.4028234663852886e38


@register
class EVSM(PrefilteredTechnique):
    """Exponential variance shadow map, 2 (positive warp) or 4 (both warps) components."""

    name = "evsm"
    title = "Exponential variance shadow map"
    summary = ("VSM on exponentially warped depths exp(k⁺z) and −exp(−k⁻z) (2 or 4 channels), the minimum of "
               "the two Chebyshev bounds, light-bleeding reduction")
    params = FILTER_PARAMS + (
        Param("components", 4, "choice", choices=(2, 4), source="[Buljan 2020, §3.5]",
              doc="2: (exp(kz), exp(2kz)); 4: also (−exp(−kz), −exp(−2kz)), min of the two bounds"),
        Param("exp_pos", 40.0, "float", 1.0, EVSM_EXP_LIMIT, "1/w", True, source="[Buljan 2020, §3.5]",
              doc="k⁺ of the positive warp exp(k⁺w), w = 2zn − 1; ≤ 44.36 so that exp(2k⁺) fits fp32"),
        Param("exp_neg", 5.0, "float", 1.0, EVSM_EXP_LIMIT, "1/w", True, source="[Buljan 2020, §3.5]",
              doc="k⁻ of the negative warp −exp(−k⁻w) (4 components only); ≤ 44.36"),
        MIN_VARIANCE, BLEED,
    ) + MAP_PARAMS + RECEIVER_PARAMS

    def channel_count(self, values) -> int:
        return int(values["components"])

    def resolve(self, overrides=None):
        for k in ("exp_pos", "exp_neg"):
            v = (overrides or {}).get(k)
            if v is not None and not isinstance(v, dr.ArrayBase):
                try:
                    vf = float(v)
                except (TypeError, ValueError):
                    continue
                if math.isfinite(vf) and vf > EVSM_EXP_LIMIT:
                    raise fp32_cap_error(f"evsm.{k}", vf, EVSM_EXP_LIMIT,
                                         "exp(2k·w) (the second moment of the warped depth)")
        return super().resolve(overrides)

    def moments(self, view, values):
        w = 2.0 * normalised_depth(view) - 1.0
        pos = dr.exp(scalar(values, "exp_pos") * w)
        chans = [pos, pos * pos]
        if int(values["components"]) == 4:
            neg = -dr.exp(-scalar(values, "exp_neg") * w)
            chans += [neg, neg * neg]
        return chans

    def estimate(self, view, rec, fp, bias, values, maps):
        comps = int(values["components"])
        kp = scalar(values, "exp_pos")
        mv, bleed = scalar(values, "min_variance"), scalar(values, "bleed")
        wr = 2.0 * rec["zn"] - 1.0
        m = bilinear(view, maps, fp)
        pr = dr.exp(kp * wr)
        vis = reduction(chebyshev(m[0], m[1], pr, (mv * 4.0 * kp * kp * pr) * pr), bleed)
        if comps == 4:
            kn = scalar(values, "exp_neg")
            nr = -dr.exp(-kn * wr)
            vn = reduction(chebyshev(m[2], m[3], nr, (mv * 4.0 * kn * kn * nr) * nr), bleed)
            vis = dr.minimum(vis, vn)
        return vis, {}, {}


__doc__ += "\n\nParameters of ``evsm`` (generated from the declaration):\n\n" + param_table_markdown(EVSM)
