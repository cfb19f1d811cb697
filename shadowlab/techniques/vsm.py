"""Variance shadow maps (``vsm``), [Buljan 2020, §3.3] [Donnelly 2006].

Store the first two moments (zn, zn²) of the normalised linear depth (the depth domain of
:mod:`shadowlab.techniques.prefilter`), blur them with the separable prefilter, read them
bilinearly at the receiver and bound the fraction of the filter region that is not closer to
the light than the receiver by Chebyshev's one-tailed inequality::

    μ = M1,  σ² = max(M2 − M1², σ²_min)
    p_max(z̃) = σ² / (σ² + (z̃ − μ)²)   if z̃ > μ,   else 1
    visibility = Reduction(p_max, p) = 0 if p_max < p else (p_max − p)/(1 − p)   (p = ``bleed``)

Properties (tests/test_moments.py):

* two parallel planes (one casts, one receives, depths d1 < d2): μ = p·d2 + (1 − p)·d1,
  σ² = (p − p²)(d2 − d1)², p_max(d2) = p: VSM with the ``box`` prefilter equals PCF over the same
  footprint (``pcf``, n×n ``grid`` of ``bilinear`` taps, softness 1), up to σ²_min/Δ² in the
  umbra, where σ² = 0 is raised to σ²_min and p_max = σ²_min/(σ²_min + Δ²) instead of 0, and up
  to fp32 rounding elsewhere (``test_vsm_equals_pcf_for_two_parallel_planes`` asserts that bound
  on ``parallel_planes`` for n = 1…9). With ``min_variance`` = 0 the lit side fails (σ² = 0 and
  z̃ a rounding error beyond μ: p_max = 0), the numerical problem §3.3 names;
* light leaking: a receiver at depth c behind two occluders at a < b, each covering half the
  filter region, gets p_max = t²/(2t² + 4t + 4), t = (b − a)/(c − b), instead of 0 (scene
  ``stack``: t = 3, 9/34 ≈ 0.2647 for any kernel at the centre of the map,
  ``test_stack_reproduces_the_leak_formula_at_the_centre_texel``; with other
  shares q of A the two-depth bound q(1−q)Δx²/(q(1−q)Δx² + (Δy + qΔx)²) peaks at 0.36);
  ``bleed`` = p gives exactly Reduction(p_max, p), 0 for p ≥ the leak, at the cost of darker
  penumbrae (§3.3, Slika 3.5);
* ``bench`` (3×3, Slika 3.10's filter): the legs under the seat, whose footprints hold the
  closer seat and the farther floor, are umbra shown lit, more often than with EVSM
  (``test_evsm_leaks_less_than_vsm_on_bench``; ``shadowlab compare bench --techniques vsm,evsm``
  prints both leak rates);
* ``kernel`` = 1 (no blur, bilinear lookup) is the hard shadow map except where the 2×2 lookup
  straddles an edge (``test_zero_filter_size_reduces_to_the_hard_shadow_map`` bounds the share).

The source's Code A.6 also clamps p_max ≥ 0.01 (so no point is ever fully dark); shadowlab
does not: σ²_min is the only floor. ``min_variance`` and ``bleed`` move the visibility smoothly
(``bleed`` up to the kink at p_max = p) and are differentiable (pass an ``mi.Float`` with
gradients enabled; tests/test_moments.py compares with finite differences).
"""

from __future__ import annotations

from .base import param_table_markdown, register
from .prefilter import (BLEED, FILTER_PARAMS, MAP_PARAMS, MIN_VARIANCE, RECEIVER_PARAMS, PrefilteredTechnique, bilinear,
                        chebyshev, normalised_depth, reduction, scalar)


@register
class VSM(PrefilteredTechnique):
    """Variance shadow map: blurred (z, z²), Chebyshev upper bound, light-bleeding reduction."""

    name = "vsm"
    title = "Variance shadow map"
    summary = ("moments (z, z²) of the normalised linear depth, separable prefilter blur, bilinear lookup, "
               "Chebyshev bound with minimum variance and light-bleeding reduction")
    channels = 2
    params = FILTER_PARAMS + (MIN_VARIANCE, BLEED) + MAP_PARAMS + RECEIVER_PARAMS

    def moments(self, view, values):
        z = normalised_depth(view)
        return [z, z * z]

    def estimate(self, view, rec, fp, bias, values, maps):
        m1, m2 = bilinear(view, maps, fp)
        p = chebyshev(m1, m2, rec["zn"], scalar(values, "min_variance"))
        return reduction(p, scalar(values, "bleed")), {}, {}


__doc__ += "\n\nParameters of ``vsm`` (generated from the declaration):\n\n" + param_table_markdown(VSM)
