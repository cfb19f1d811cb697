"""Physically based shading with single-ray visibility ([Bán 2019, ch. 5]).

Eq. 5.1 is the direct light of one emitter, ``∫ f_r · V · E cos dl``; shadowlab's visibility of a
light is the ratio of that integral to its unshadowed value U_L (``render/shading.py``), so a
technique that estimates 5.1 returns ``V = Σ f·v / Σ f`` over light samples, with
``f = bsdf·Le·cos/pdf`` from Mitsuba's emitter sampling (the estimator of the ground truth), and
differs from the truth only in how ``v`` is decided. Three estimators (:func:`visibility`):

* ``"separable"`` — Eq. 5.2, ``I ≈ f_r(v, n, l₀) · (∫V dl/∫dl) · ∫E cos dl``: the single-ray
  lit fraction ([Bán 2019, §4], Algorithm 4) times the unshadowed light. For the diffuse surfaces of
  shadowlab's scenes ``f_r(l₀)·∫E cos = ∫f_r E cos = U_L``, so the visibility is the single-ray
  fraction itself (the shaded image is then [Bán 2019, Fig. 6.16]b; with ``sdf_mc``'s fraction, 6.16c;
  with ``sdf_quilez``'s, 6.16a);
* ``"edge"`` — [Bán 2019, §5.3.1]: Monte Carlo over the light's samples in Eq. 5.1, with each sample's
  visibility decided *without intersecting the scene*: the single-ray march (Algorithm 4, toward
  the sphere bounding the light, [Bán 2019, §5.4]) also keeps the axis distance ``t_min`` of the minimum
  and ``f_min``; the occluder is taken for a half-plane in the cross-section there, whose edge
  line lies ``f_min`` from the axis across the SDF gradient ``g⊥`` (projected perpendicular to
  the axis; :func:`shadowlab.sdf.soft.edge_line`). A sample ray from the shading point crossing
  that plane at ``y`` is blocked iff ``⟨y − s(t_min), g⊥⟩ ≤ −f_min``. Where the march found
  nothing (the cone is clear) every sample is lit;
* ``"traced"`` — Eq. 5.1 in full ([Bán 2019, Fig. 6.16]e): each sample's shadow ray is sphere-traced.

Any light with a bounding sphere works ([Bán 2019, §5.4]): sphere, disk and rectangle lights are
sampled by Mitsuba's emitters; the single-ray pass uses :func:`~shadowlab.scene.lights.light_sphere`
with ``fit="bounding"``. Sample i of point k uses stratum (i mod s, i div s) of an s×s grid,
jittered by TEA hashes of (k, i, seed): stateless, so a sample can be drawn inside the flat
trace loop of ``traced`` exactly when the previous ray finished.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..render.shading import seed_hash as fnv_seed
from ..scene.lights import light_sphere
from ..sdf import soft

ESTIMATORS = ("edge", "traced", "separable")


def _u2(idx, i, k, seed_hash):
    """Stratified 2-D sample i of an k×k grid for point idx (TEA hashes; stateless)."""
    a, b = mi.sample_tea_32(idx, i ^ seed_hash)
    ua = mi.Float(a >> 8) * (1.0 / 16777216.0)
    ub = mi.Float(b >> 8) * (1.0 / 16777216.0)
    kf = mi.Float(k)
    return mi.Point2f((mi.Float(i % k) + ua) / kf, (mi.Float(i // k) + ub) / kf)


def _light_sample(emitter, si, o, nrm, valid, idx, i, k, seed_hash):
    """(target point, weight = cos·|Le/pdf| summed over RGB, direction) of emitter sample i."""
    ds, w = emitter.sample_direction(si, _u2(idx, i, k, seed_hash), valid)
    to = ds.p - o
    dist = dr.norm(to)
    omega = to / dr.maximum(dist, 1e-20)
    cos = dr.maximum(dr.dot(nrm, ds.d), 0.0)
    mag = dr.select(valid & (ds.pdf > 0.0), cos * (w.x + w.y + w.z), 0.0)
    return ds.p, dist, omega, mag


@dr.syntax
def _edge_loop(emitter, si, o, nrm, valid, idx, k, seed_hash, x_min, g, f_min, v, found):
    n = dr.width(o)
    fv = dr.zeros(mi.Float, n)
    fs = dr.zeros(mi.Float, n)
    i = mi.UInt32(0)
    while i < k * k:
        _, _, omega, mag = _light_sample(emitter, si, o, nrm, valid, idx, i, k, seed_hash)
        # crossing of the sample ray with the cross-section plane at the minimum
        along = dr.dot(omega, v)
        s = dr.dot(x_min - o, v) / dr.maximum(along, 1e-12)
        y = o + omega * s
        blocked = found & (along > 0.0) & (dr.dot(y - x_min, g) <= -f_min)
        fv += dr.select(blocked, 0.0, mag)
        fs += mag
        i += 1
    return dr.select(fs > 0.0, fv / dr.maximum(fs, 1e-30), 1.0)


@dr.syntax
def _traced_loop(sdf, emitter, si, o, nrm, valid, idx, k, seed_hash, eps, i_max):
    n = dr.width(o)
    kk = k * k
    j = dr.zeros(mi.UInt32, n)
    _, tmax, omega, mag = _light_sample(emitter, si, o, nrm, valid, idx, j, k, seed_hash)
    tmax = tmax * 0.9999
    t = dr.zeros(mi.Float, n)
    st = dr.zeros(mi.UInt32, n)
    its = dr.zeros(mi.UInt32, n)
    fv = dr.zeros(mi.Float, n)
    fs = dr.zeros(mi.Float, n)
    while j < kk:
        f = sdf.distance(mi.Point3f(o + omega * t))
        hit = f < eps
        t = dr.select(hit, t, t + f)
        st += 1
        its += 1
        done = hit | (t >= tmax) | (st >= i_max) | (mag <= 0.0)
        vis = dr.select(hit | (t < tmax), 0.0, 1.0)
        fv += dr.select(done, mag * vis, 0.0)
        fs += dr.select(done, mag, 0.0)
        j = dr.select(done, j + 1, j)
        _, tm2, om2, mg2 = _light_sample(emitter, si, o, nrm, valid, idx, dr.minimum(j, kk - 1), k, seed_hash)
        omega = dr.select(done, om2, omega)
        tmax = dr.select(done, tm2 * 0.9999, tmax)
        mag = dr.select(done, mg2, mag)
        t = dr.select(done, 0.0, t)
        st = dr.select(done, 0, st)
    return dr.select(fs > 0.0, fv / dr.maximum(fs, 1e-30), 1.0), its


def visibility(frame, light, sdf, o, R0, *, estimator: str = "edge", samples: int = 8, seed: int = 0,
               eps: float = 1.0 / 30, direction: str = "A", i_max: int = 256, hit_eps: float = 1e-4):
    """Visibility of ``light`` (a LightSpec) at the frame's points by one chapter-5 estimator
    (module docstring). ``o``: shading points off the surface (mi.Vector3f), ``R0``: their
    surface-sphere radius; ``samples``: s of the s×s light samples. Returns (mi.Float, dict of
    per-point Dr.Jit AOVs)."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, not {estimator!r}")
    gb = frame.gbuffer
    nrm = mi.Vector3f(gb.n)
    valid = gb.valid
    emitter = frame.scene.emitters[light.name]
    n = dr.width(o)
    idx = dr.arange(mi.UInt32, n)
    k = dr.opaque(mi.UInt32, int(samples))
    sh = dr.opaque(mi.UInt32, fnv_seed(0xC5, seed))
    aovs = {}
    if estimator == "traced":
        v, its = _traced_loop(sdf, emitter, gb.si, o, nrm, valid, idx, k, sh, dr.opaque(mi.Float, hit_eps),
                              dr.opaque(mi.UInt32, int(i_max)))
        aovs["iterations"] = mi.Float(its)
        return v, aovs
    center, R = light_sphere(frame.scene, light, fit="bounding")
    cone = soft.make_cone(o, R0, center, dr.opaque(mi.Float, R), direction, bbox=soft.bounds(sdf))
    m = soft.march(sdf, cone, "linear", eps=eps, i_max=i_max)
    aovs.update(r_min=m.r_min, iterations=mi.Float(m.iterations))
    if estimator == "separable":
        return dr.detach(m.visibility), aovs
    x_min, g, f_min = soft.edge_line(sdf, m)
    # the plane's points are measured from the shading point's side: in direction B the march ran
    # from the light, so the cross-section is the same plane (a set of points, not a distance)
    v_axis = dr.normalize(mi.Vector3f(*map(float, center)) - o)
    v = _edge_loop(emitter, gb.si, o, nrm, valid, idx, k, sh, x_min, g, f_min, v_axis, m.found)
    return v, aovs

