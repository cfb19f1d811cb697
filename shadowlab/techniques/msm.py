"""Moment shadow maps (``msm``), Hamburger 4MSM [Peters 2015] (Peters & Klein, "Moment Shadow
Mapping", I3D 2015). [Buljan 2020, §5.1] lists MSM among the implemented techniques (the
thesis used the authors' HLSL, with "one parameter for light-leak reduction different from
VSM's"); it does not derive it, so the algorithm follows the paper:

1. moments b = (zn, zn², zn³, zn⁴) of the normalised linear depth (the depth domain of
   :mod:`shadowlab.techniques.prefilter`), 32-bit float, blurred by the separable prefilter
   and read bilinearly (no 16-bit optimised quantisation: the maps are fp32);
2. moment bias: b' = (1 − α)·b + α·(½, ½, ½, ½), α = ``moment_bias`` (default 3·10⁻⁵, see
   below), which keeps the Hankel matrix B = [[1, b'₁, b'₂], [b'₁, b'₂, b'₃], [b'₂, b'₃, b'₄]]
   positive definite;
3. z_f = z̃ − ``msm_depth_bias``; solve B·c = (1, z_f, z_f²)ᵀ by a Cholesky (LDLᵀ)
   factorisation (forward substitution, scaling, backward substitution);
4. the roots z₂ ≤ z₃ of c₃z² + c₂z + c₁ = 0 and z_f are the three candidate depths of the
   reconstructed distribution; the shadow intensity (the sharpest lower bound, Hamburger):

       z_f ≤ z₂:        G = 0
       z₂ < z_f ≤ z₃:   G = (z_f·z₃ − b'₁(z_f + z₃) + b'₂) / ((z₃ − z₂)(z_f − z₂))
       z₃ < z_f:        G = 1 − (z₂·z₃ − b'₁(z₂ + z₃) + b'₂) / ((z_f − z₂)(z_f − z₃))

   visibility = Reduction(1 − clamp(G, 0, 1), p), p = ``bleed`` (the §3.3 light-bleeding
   reduction applied to MSM's visibility, as Pettineo's sample does).

Checked line by line against the public HLSL of M. Pettineo's "Shadows" sample (MSM.hlsl,
``ComputeMSMHamburger``, which several engines copy): the same moment bias towards ½, the same
LDLᵀ solve with D33·D22 = (b₄ − b₂²)·D22 − (b₃ − b₁b₂)², the same three-candidate switch, and
visibility = 1 − saturate(G) before the light-bleeding reduction. Differences: the divisions
are guarded (denominators bounded away from 0, the discriminant clamped at 0) so that
degenerate moments give finite values and finite gradients instead of NaN, and the depth is
the linear zn, not the NDC depth.

``moment_bias`` α: 3·10⁻⁵, a value in common use with 32-bit moments (measured below). The solve runs in fp32 on raw
moments; where a footprint holds a single depth the Hankel matrix is singular but for α, and
round-off can then darken a lit point: measured on ``parallel_planes`` (128² map, 5×5) one lit
pixel at 0.51 with α = 3·10⁻⁵, none from 6·10⁻⁵ on. Larger α leaks more: ``bench`` leak rate at
3×3 1.4 % (α = 10⁻⁵), 2.3 % (3·10⁻⁵), 4.1 % (6·10⁻⁵), 5.6 % (3·10⁻⁴); visibility RMSE on
``contact`` at 3×3 0.057, 0.051, 0.048, 0.046. ``kernel`` = 1 differs from ``hard`` at 0.3 %
of ``contact``'s pixels; at the centre of ``stack`` (VSM's leak 9/34) MSM gives 4·10⁻⁴.

``moment_bias``, ``msm_depth_bias`` and ``bleed`` move the visibility continuously and are
differentiable (pass an ``mi.Float`` with gradients enabled; AD and central differences agree
on ``contact``).
"""

from __future__ import annotations

import drjit as dr

from .base import Param, param_table_markdown, register
from .prefilter import (BLEED, FILTER_PARAMS, MAP_PARAMS, RECEIVER_PARAMS, PrefilteredTechnique, bilinear,
                        normalised_depth, reduction, scalar)

_EPS = 1e-20


def _safe(x):
    """x bounded away from 0 (sign kept): a guard for divisions."""
    return dr.select(dr.abs(x) > _EPS, x, dr.select(x < 0, -_EPS, _EPS))


def hamburger4(b, zf):
    """Shadow intensity G ∈ [0, 1] of the Hamburger 4MSM for (biased) moments ``b`` = (b1..b4)
    and fragment depth ``zf`` (Peters & Klein 2015, Algorithm 2)."""
    b1, b2, b3, b4 = b
    # Cholesky (LDL^T) of the Hankel matrix, non-trivial entries only
    l32d22 = dr.fma(-b1, b2, b3)
    d22 = _safe(dr.fma(-b1, b1, b2))
    sq_var = dr.fma(-b2, b2, b4)
    d33d22 = _safe(sq_var * d22 - l32d22 * l32d22)
    inv_d22 = dr.rcp(d22)
    l32 = l32d22 * inv_d22
    # solve B c = (1, zf, zf^2)
    c1 = zf - b1
    c2 = zf * zf - b2 - l32 * c1
    c1 = c1 * inv_d22
    c2 = c2 * (d22 / d33d22)
    c1 = c1 - l32 * c2
    c0 = 1.0 - (c1 * b1 + c2 * b2)
    # roots of c0 + c1 z + c2 z^2
    c2s = _safe(c2)
    p = c1 / c2s
    q = c0 / c2s
    r = dr.sqrt(dr.maximum(p * p * 0.25 - q, _EPS))
    z2 = -0.5 * p - r
    z3 = -0.5 * p + r
    beyond = z3 < zf            # z_f past both roots
    between = (~beyond) & (z2 < zf)
    s0 = dr.select(beyond, z2, zf)
    s1 = dr.select(beyond, zf, z2)
    quot = (s0 * z3 - b1 * (s0 + z3) + b2) / _safe((z3 - s1) * (zf - z2))
    G = dr.select(beyond, 1.0 + quot, dr.select(between, quot, 0.0))
    return dr.clip(G, 0.0, 1.0)


@register
class MSM(PrefilteredTechnique):
    """Moment shadow map, Hamburger 4MSM with moment bias and depth bias."""

    name = "msm"
    title = "Moment shadow map (Hamburger 4MSM)"
    summary = ("four moments (z, z², z³, z⁴) of the normalised linear depth, separable prefilter blur, "
               "moment bias, Cholesky solve and three-candidate Hamburger reconstruction (Peters & Klein 2015)")
    channels = 4
    params = (
        FILTER_PARAMS
        + (
            Param(
                "moment_bias",
                3e-5,
                "float",
                0.0,
                0.1,
                "",
                True,
                source="Peters & Klein 2015",
                doc="α of b' = (1 − α)·b + α·(½, ½, ½, ½) (fp32 moments; larger α: fewer round-off artifacts, more "
                    "leaking)",
            ),
            Param("msm_depth_bias", 0.0, "float", -0.1, 0.1, "zn", True, source="Peters & Klein 2015",
                  doc="subtracted from the receiver's normalised depth before the reconstruction"),
            BLEED,
        )
        + MAP_PARAMS
        + RECEIVER_PARAMS
    )

    def moments(self, view, values):
        z = normalised_depth(view)
        z2 = z * z
        return [z, z2, z2 * z, z2 * z2]

    def estimate(self, view, rec, fp, bias, values, maps):
        m = bilinear(view, maps, fp)
        a = scalar(values, "moment_bias")
        b = [dr.fma(mi_, 1.0 - a, 0.5 * a) for mi_ in m]
        G = hamburger4(b, rec["zn"] - scalar(values, "msm_depth_bias"))
        return reduction(1.0 - G, scalar(values, "bleed")), {}, {}


__doc__ += "\n\nParameters of ``msm`` (generated from the declaration):\n\n" + param_table_markdown(MSM)
