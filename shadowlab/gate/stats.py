"""The statistical test of a gate: Mitsuba's per-pixel Z-test with Šidák correction, plus a bias test.

Per value (pixel × channel) of the tested pixels, as in Mitsuba 3's render tests
(``src/python/python/testing``, ``z_test``):

    d = c − r,  σ² = var_r + var_c,  z = d / σ,  p = 2 (1 − Φ(|z|)) = erfc(|z| / √2)

with var_r the reference's per-pixel variance of its mean and var_c the candidate's (0 when not
given). A variance estimated from few independent passes (Mitsuba's ``direct`` image: 4 passes,
3 degrees of freedom) is itself noisy, and z then has Student-t tails: at the Šidák level of 16 k
pixels a normal p-value fails ~0.2 % of the pixels of two independent renders. Given the degrees
of freedom ν_r, ν_c of the variances (None = exact), p comes from Student's t with the
Welch–Satterthwaite ν = (var_r + var_c)² / (var_r²/ν_r + var_c²/ν_c). Because N values are tested at once, each is
tested at the Šidák-corrected level
α_value = 1 − (1 − α)^(1/N), so that all N pass together with probability 1 − α when the candidate
equals the reference up to noise. A value also passes when it is within the tolerance
|d| ≤ atol + rtol·|r| + ptol·peak. σ = 0 with d ≠ 0 outside the tolerance is z = ±∞ (fails);
σ = 0 with d = 0 passes. A pixel passes when all its channels pass; the check ``stat.pixels``
passes when at least ``min_pass_fraction`` of the tested pixels pass (Mitsuba: 0.9975).

The per-pixel test cannot see a small systematic error: a 1 % brightening of the penumbra moves
each z by well under the Šidák threshold (≈ 5 σ at 16 k pixels). The bias tests look at the mean:
per pixel z̄ = mean of z over its channels with σ > 0 (pixels whose σ is 0 everywhere carry no
information and are left out, as are infinite z, which the per-pixel test already fails), then a
one-sample Student t-test of mean(z̄) = 0 over the region, t = mean · √n / sd with n − 1 degrees of
freedom. The t-test estimates the spread of z̄ from the data, so it does not depend on the
variances being exact, only on the noise being zero-mean, which holds for two independent
estimates of one image. Regions: all tested pixels (``stat.bias``) and the penumbra
(``stat.bias_penumbra``), each at level 1 − (1 − α)^(1/2). A region with fewer than
:data:`MIN_BIAS_PIXELS` informative pixels is not tested (the check passes and says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special, stats

__all__ = ["sidak", "z_test", "bias_test", "ZTest", "BiasTest", "MIN_BIAS_PIXELS"]

MIN_BIAS_PIXELS = 16


def sidak(alpha: float, n: int) -> float:
    """Per-test level so that ``n`` independent tests all pass with probability 1 − alpha.

    >>> round(sidak(0.01, 1), 12), f"{sidak(0.01, 16384):.3e}"
    (0.01, '6.134e-07')
    """
    return float(-math.expm1(math.log1p(-alpha) / max(int(n), 1)))


@dataclass
class ZTest:
    z: np.ndarray           # H×W×C z-scores (0 where σ = 0 and d = 0, ±inf where σ = 0 and d ≠ 0)
    p: np.ndarray           # H×W smallest p-value over channels (1 inside the tolerance), NaN off-mask
    passed: np.ndarray      # H×W bool, tested pixels that pass (False off-mask)
    tested: np.ndarray      # H×W bool
    alpha_value: float      # Šidák level of one value
    n_values: int
    informative: np.ndarray  # H×W×C bool: σ > 0

    @property
    def n_tested(self) -> int:
        return int(self.tested.sum())

    @property
    def n_failed(self) -> int:
        return int((self.tested & ~self.passed).sum())

    @property
    def fraction(self) -> float:
        n = self.n_tested
        return float(self.passed.sum()) / n if n else 1.0


def _hwc(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a[..., None] if a.ndim == 2 else a


def z_test(cand, ref, var_ref=None, var_cand=None, mask=None, *, alpha: float = 1e-3,
           atol: float = 0.0, rtol: float = 0.0, ptol: float = 0.0, dof_ref=None, dof_cand=None) -> ZTest:
    """Per-pixel Z-test of ``cand`` against ``ref`` (H×W or H×W×C, same shape); see the module
    docstring. ``var_*`` are per-value variances (None = 0); ``mask`` H×W bool (None = all);
    ``dof_*`` the degrees of freedom of those variances (None = exact: normal p-values).

    >>> import numpy as np
    >>> r = np.zeros((4, 4)); c = r + 0.01; v = np.full((4, 4), 1e-4)
    >>> t = z_test(c, r, v, v)
    >>> round(float(t.z.max()), 4), t.fraction
    (0.7071, 1.0)
    """
    c, r = _hwc(cand), _hwc(ref)
    vr = np.zeros_like(r) if var_ref is None else np.maximum(_hwc(var_ref), 0.0)
    vc = np.zeros_like(c) if var_cand is None else np.maximum(_hwc(var_cand), 0.0)
    m = np.ones(r.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    d = c - r
    sigma = np.sqrt(vr + vc)
    informative = sigma > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(informative, d / np.where(informative, sigma, 1.0), np.where(d == 0, 0.0, np.sign(d) * np.inf))
    if dof_ref is None and dof_cand is None:
        p = special.erfc(np.abs(z) / math.sqrt(2.0))
    else:
        inv = lambda v, nu: 0.0 if nu is None else v * v / float(nu)  # noqa: E731
        with np.errstate(divide="ignore", invalid="ignore"):
            nu = np.where(informative, (vr + vc) ** 2 / (inv(vr, dof_ref) + inv(vc, dof_cand)), np.inf)
        p = 2.0 * stats.t.sf(np.abs(z), np.where(np.isnan(nu), np.inf, nu))
    peak = float(np.max(np.abs(r[m]))) if m.any() else 0.0
    within = np.abs(d) <= atol + rtol * np.abs(r) + ptol * peak
    p = np.where(within, 1.0, p)
    n_values = int(m.sum()) * r.shape[2]
    a_v = sidak(alpha, n_values)
    ok = (p > a_v).all(axis=2) & m
    pmin = np.where(m, p.min(axis=2), np.nan)
    return ZTest(z=z, p=pmin, passed=ok, tested=m, alpha_value=a_v, n_values=n_values,
                 informative=informative & m[..., None])


@dataclass
class BiasTest:
    region: str
    n: int
    mean_z: float
    t: float
    p: float
    alpha: float
    tested: bool            # False: too few informative pixels, the check is not run

    @property
    def passed(self) -> bool:
        return (not self.tested) or self.p > self.alpha


def bias_test(zt: ZTest, region: np.ndarray, *, alpha: float, name: str = "all", n_regions: int = 2) -> BiasTest:
    """One-sample t-test of the mean per-pixel z over ``region`` (H×W bool); see module docstring.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> r = rng.normal(size=(32, 32)); v = np.ones((32, 32))
    >>> bias_test(z_test(r + 1.0, r * 0, v, None), np.ones((32, 32), bool), alpha=1e-3).passed
    False
    """
    fin = zt.informative & np.isfinite(zt.z)
    cnt = fin.sum(axis=2)
    use = region & zt.tested & (cnt > 0)
    zbar = (np.where(fin, zt.z, 0.0).sum(axis=2)[use] / cnt[use]).astype(np.float64)
    a = sidak(alpha, n_regions)
    n = int(zbar.size)
    if n < MIN_BIAS_PIXELS:
        return BiasTest(region=name, n=n, mean_z=float(zbar.mean()) if n else 0.0, t=0.0, p=1.0, alpha=a, tested=False)
    mean = float(zbar.mean())
    sd = float(zbar.std(ddof=1))
    if sd == 0.0:
        t = 0.0 if mean == 0.0 else math.copysign(math.inf, mean)
    else:
        t = mean * math.sqrt(n) / sd
    p = float(2.0 * stats.t.sf(abs(t), n - 1)) if math.isfinite(t) else 0.0
    return BiasTest(region=name, n=n, mean_z=mean, t=t, p=p, alpha=a, tested=True)
