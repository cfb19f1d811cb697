"""SDF soft-shadow techniques ([Bán 2019]) against the ground truth of the SDF scenes.

The scenes' objects all have Mitsuba twins (except ``mandelbulb``), so the truth is Mitsuba's:
visibility ``V`` = shadowed / unshadowed direct light at the G-buffer's points, ``A`` the
visible solid-angle fraction. The committed 128² references are used; where one is missing the
fixture renders it at 64² into a temporary store (same code path as ``shadowlab reference``).
Penumbra = the truth's 0.02 < V < 0.98 where the light reaches (the metrics' mask).

Measured at defaults on the committed references (visibility RMSE in the penumbra; also in
README "SDF soft shadows"): sdf_simple — base 0.026, linear 0.026, convex 0.026, discrete 0.036,
quilez 0.33, mc (64 rays) 0.019, edge_mc 0.034, hard 0.28, aa_hard 0.20.
"""

import numpy as np
import pytest

EDGE = 1  # pixels


def _case(name, tmp_path_factory):
    from shadowlab.errors import ReferenceError_
    from shadowlab.pipeline import reference
    from shadowlab.reference import store
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    sc = load(name)
    try:
        truth, meta = store.load(sc.spec)
    except ReferenceError_ as e:
        if "no reference" not in str(e):   # a stale reference is an error, not a reason to re-render
            raise
        base = tmp_path_factory.mktemp(f"ref_{name}")
        sc = load(name, resolution=(64, 64))
        reference(name, (64, 64), base=base, progress=False)
        truth, meta = store.load(sc.spec, sc.resolution, base)
    frame = make_frame(sc, ss=int(meta.get("supersampling", 1)), seed=int(meta.get("seed", 0)))
    light = sc.spec.lights[0]
    tv = truth.lights[light.name].V
    mask = truth.mask & frame.lit_mask(light.name)
    return {"scene": sc, "truth": truth, "frame": frame, "light": light, "V": tv, "A": truth.lights[light.name].A,
            "mask": mask, "pen": mask & (tv > 0.02) & (tv < 0.98)}


@pytest.fixture(scope="module")
def simple(mitsuba_backend, tmp_path_factory):
    return _case("sdf_simple", tmp_path_factory)


def vis(case, name, **params):
    from shadowlab.techniques import get
    r = get(name).render(case["frame"], params)
    return case["frame"].image(r.visibility[case["light"].name]), r


def rmse(x):
    return float(np.sqrt(np.mean(np.square(x))))


def single_ray(case, eps, variant="linear", i_max=4096, residual=True):
    """Visibility, relative distance and plane residual of the single ray at the frame's points."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.scene.lights import light_sphere
    from shadowlab.sdf import soft
    from shadowlab.techniques.sdf_shadows import SURFACE_RADIUS, surface_points
    fr = case["frame"]
    o, R0 = surface_points(fr, SURFACE_RADIUS.default)
    c, R = light_sphere(case["scene"], case["light"])
    cone = soft.make_cone(o, R0, c, dr.opaque(mi.Float, R), "A", bbox=soft.bounds(fr.sdf))
    m = soft.march(fr.sdf, cone, variant, eps=eps, i_max=i_max)
    res = fr.image(soft.plane_residual(fr.sdf, m)) if residual else None
    return fr.image(m.visibility), res


# ---------------------------------------------------------------------------------------------
# sdf_simple: every variant against the truth

#: visibility RMSE in the penumbra at defaults on the committed 128² reference: (lower, upper).
#: Measured (also in the module docstring): base 0.0264, linear 0.0264, convex 0.0257, discrete
#: 0.0362, mc 0.0190, edge_mc 0.0335, quilez 0.327, hard 0.281, aa_hard 0.204. Every input is fixed
#: (committed reference, fixed seeds: reruns give the same digits), so each band is the measured
#: value −20 % / +20…35 %, rounded outward: wide enough for another backend's rounding and for the
#: Monte-Carlo variants' seed spread (seeds 0–7: mc 0.0185–0.0206, edge_mc 0.0310–0.0352, ±7 %),
#: narrow enough that both ends can fail. A value outside its band is a change of behaviour (or a
#: broken comparison): re-measure, and update the numbers quoted here, in the docstring and README.
BOUNDS = {
    "sdf_base": (0.021, 0.035), "sdf_linear": (0.021, 0.035), "sdf_convex": (0.020, 0.035),
    "sdf_discrete": (0.029, 0.045), "sdf_mc": (0.015, 0.03), "sdf_edge_mc": (0.026, 0.045),
    "sdf_quilez": (0.25, 0.40), "sdf_hard": (0.22, 0.34), "sdf_aa_hard": (0.15, 0.25),
}


def test_penumbra_error_of_every_variant_on_sdf_simple(simple):
    pen = simple["pen"]
    assert pen.sum() > 150
    errs = {}
    for name, (lo, hi) in BOUNDS.items():
        v, _ = vis(simple, name)
        errs[name] = rmse((v - simple["V"])[pen])
    print("penumbra visibility RMSE on sdf_simple:", {k: round(v, 4) for k, v in errs.items()})
    for name, (lo, hi) in BOUNDS.items():
        assert 0.0 < lo < hi < 1.0, name          # an RMSE of values in [0, 1] lies in [0, 1]: both ends must bite
        assert lo <= errs[name] <= hi, (name, errs[name])
    # the soft variants are 8–10× closer than the hard shadow, and much closer than the Quílez baseline
    assert errs["sdf_linear"] < 0.15 * errs["sdf_hard"] and errs["sdf_linear"] < 0.15 * errs["sdf_quilez"]


def test_base_and_linear_within_eps_where_one_planar_occluder_casts_the_penumbra(simple):
    """Where the occluder at the minimum is planar across the cone (plane residual < 0.2 of the cone
    radius; [Bán 2019, §4.1]'s assumption), the single ray is within ε of the truth (visible fraction A;
    V differs from A by the cosine weighting, 0.007 RMSE here), down to a floor of ~0.02 at
    small ε: the spheres' curvature across the cone and the surface sphere's offset."""
    pen, A = simple["pen"], simple["A"]
    for eps in (1 / 10, 1 / 32, 1 / 256):
        out = {}
        for variant in ("base", "linear"):
            v, res = single_ray(simple, eps, variant)
            planar = pen & (res < 0.2)
            assert planar.sum() > 0.6 * pen.sum()
            out[variant] = v
            err = rmse((v - A)[planar])
            assert err <= max(eps, 0.025), (variant, eps, err)
            assert np.quantile(np.abs(v - A)[planar], 0.99) <= max(3 * eps, 0.08)
        assert np.abs(out["base"] - out["linear"])[simple["mask"]].max() <= 1.5 * eps


def test_hard_equals_point_light_visibility_except_within_one_pixel_of_edges(simple):
    """sdf_hard and sdf_aa_hard (light radius 0) against Mitsuba's point-light visibility: a
    ray_test from each G-buffer point to the light's centre (stopping at the light sphere).
    Outside one pixel of an edge of that visibility or of the geometry (where the surface sphere
    of sdf_aa_hard touches the neighbouring surface) they agree: hard exactly, aa_hard within ε."""
    import drjit as dr
    import mitsuba as mi
    from scipy.ndimage import maximum_filter, minimum_filter
    from shadowlab.scene.lights import light_sphere
    fr, sc = simple["frame"], simple["scene"]
    gb = fr.gbuffer
    c, R = light_sphere(sc, simple["light"])
    o = mi.Vector3f(gb.p) + mi.Vector3f(gb.ng) * 1e-3
    to = mi.Vector3f(*map(float, c)) - o
    d = dr.norm(to)
    ray = mi.Ray3f(mi.Point3f(o), to / d)
    ray.maxt = d - R * 1.002
    point = fr.image(dr.select(sc.mi_scene.ray_test(ray, gb.valid), 0.0, 1.0))
    k = 2 * EDGE + 1
    sid = gb.shape_id[..., 0].astype(np.float32)
    near_edge = (maximum_filter(point, k) != minimum_filter(point, k)) | (
        maximum_filter(sid, k) != minimum_filter(sid, k)
    )
    far = simple["mask"] & ~near_edge
    assert far.sum() > 0.8 * simple["mask"].sum() and (point[far] == 0).sum() > 300
    hard, _ = vis(simple, "sdf_hard")
    assert np.array_equal(hard[far], point[far])
    aa, r = vis(simple, "sdf_aa_hard")
    eps = 0.03125  # sdf_aa_hard.epsilon: the march stops once the lit fraction is ≤ ε
    assert np.abs(aa - point)[far].max() <= eps + 1e-4
    # on the edges, aa_hard ramps where hard jumps
    band = simple["mask"] & near_edge
    assert ((aa[band] > 0.05) & (aa[band] < 0.95)).sum() > 3 * ((hard[band] > 0.05) & (hard[band] < 0.95)).sum()


def test_quilez_penumbra_is_narrower_and_darker_than_the_truth(simple):
    """[Bán 2019, §6.4]: the Quílez/Aaltonen estimate cannot see behind the occluder's silhouette, so the
    inner half of the penumbra comes out as umbra."""
    pen, m, V = simple["pen"], simple["mask"], simple["V"]
    lin, _ = vis(simple, "sdf_linear")
    n_true = pen.sum()
    for variant in ("quilez2010", "aaltonen2018"):
        q, _ = vis(simple, "sdf_quilez", variant=variant)
        n_q = ((q > 0.02) & (q < 0.98) & m).sum()
        assert n_q < 0.85 * n_true, (variant, n_q, n_true)            # measured 0.72 / 0.82 of the truth's
        assert (q - V)[pen].mean() < -0.2                               # measured −0.30 / −0.33
        inner = pen & (V < 0.5)
        assert np.mean(q[inner] < 0.02) > 0.5                           # the inner half is umbra
    assert abs((lin - V)[pen].mean()) < 0.02


def test_the_light_below_the_receivers_horizon_darkens_the_single_ray(simple):
    """Where the light sphere straddles the receiver's tangent plane (terminators, grazing faces)
    the single ray counts the part below the horizon as shadowed; the truth's V (a ratio to the
    unshadowed light, which gets nothing from there) and A both stay 1. A model difference of
    the thesis' visibility term, measured: mean 0.87 on such pixels of sdf_simple."""
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.scene.lights import light_sphere
    fr = simple["frame"]
    gb = fr.gbuffer
    c, R = light_sphere(simple["scene"], simple["light"])
    P, N = vec_numpy(gb.p), vec_numpy(gb.ng)
    D = np.asarray(c)[None] - P
    dist = np.linalg.norm(D, axis=1)
    cosn = (D * N).sum(1) / dist
    straddle = fr.image((np.abs(cosn) < R / dist).astype(np.float32)) > 0.5
    sel = simple["mask"] & straddle & (simple["V"] > 0.98)
    assert sel.sum() > 50
    v, _ = vis(simple, "sdf_linear")
    assert v[sel].mean() < 0.95 and simple["A"][sel].mean() > 0.98


# ---------------------------------------------------------------------------------------------
# the failure modes of [Bán 2019, §6.5–6.6] on their scenes

def test_light_leaks_through_the_thin_plate_not_the_thick_slab(mitsuba_backend, tmp_path_factory):
    from shadowlab.render.gbuffer import vec_numpy
    case = _case("sdf_thin", tmp_path_factory)
    fr = case["frame"]
    x = fr.image(vec_numpy(fr.gbuffer.p))[..., 0]
    umbra = case["mask"] & (case["V"] <= 0.02)
    thin, thick = umbra & (x < 0), umbra & (x > 0)
    assert thin.sum() > 100 and thick.sum() > 100
    v, _ = vis(case, "sdf_linear")
    mc, _ = vis(case, "sdf_mc")
    print(
        f"sdf_thin umbra: thin plate {v[thin].mean():.3f}, thick slab {v[thick].mean():.3f}, mc {mc[thin].mean():.3f}"
    )
    assert v[thin].mean() > 0.3          # measured 0.47: the cone passes through the 2 cm plate
    assert v[thick].mean() < 0.06        # measured 0.03 (≤ ε: the march stops at τ ≤ ε)
    assert mc[thin].mean() < 0.01        # sphere-traced rays do not leak


def test_pointed_occluders_are_too_dark_outside_and_eroded_inside(mitsuba_backend, simple, tmp_path_factory):
    """[Bán 2019, §6.5] (pointed objects): at the hexagon's corners of the cube pointing at the light the
    occluder is a wedge, not a half-plane, so the outer penumbra is too dark; [Bán 2019, §6.6] (offset):
    the cone's negative offset erodes edges, so the inner penumbra is too bright."""
    case = _case("sdf_pointed", tmp_path_factory)
    V, pen = case["V"], case["pen"]
    v, res = single_ray(case, 1 / 32)
    outer_np = pen & (V > 0.5) & (res >= 0.5)
    inner = pen & (V < 0.5)
    assert outer_np.sum() > 100
    bias_outer = (v - V)[outer_np].mean()
    print(f"sdf_pointed: outer non-planar bias {bias_outer:+.3f}, inner bias {(v - V)[inner].mean():+.3f}")
    assert bias_outer < -0.05                            # measured −0.073
    assert (v - V)[inner].mean() > 0.02                  # measured +0.047
    vs, _ = single_ray(simple, 1 / 32, residual=False)   # the round occluders of sdf_simple: much less
    assert abs((vs - simple["V"])[simple["pen"] & (simple["V"] > 0.5)].mean()) < 0.5 * abs(bias_outer)


# ---------------------------------------------------------------------------------------------
# chapter 5

def test_chapter5_estimators_on_a_sphere_light(simple):
    pen, V = simple["pen"], simple["V"]
    traced, _ = vis(simple, "sdf_edge_mc", estimator="traced", samples=12)
    edge, _ = vis(simple, "sdf_edge_mc", estimator="edge", samples=12)
    sep, _ = vis(simple, "sdf_edge_mc", estimator="separable")
    lin, _ = vis(simple, "sdf_linear")
    # 5.1 with sphere-traced samples is an unbiased estimate of the truth (144 stratified samples)
    assert rmse((traced - V)[pen]) < 0.03 and abs((traced - V)[pen].mean()) < 0.01
    # Eq. 5.2 with the single ray = sdf_linear for a sphere light (bounding sphere = the light)
    assert np.abs(sep - lin)[simple["mask"]].max() < 1e-5
    # 5.3.1 shares the single ray's model: close to it, and to the truth within its error
    assert rmse((edge - lin)[pen]) < 0.04
    assert rmse((edge - V)[pen]) < 1.3 * rmse((lin - V)[pen]) + 0.01


def test_chapter5_on_a_rectangle_light(mitsuba_backend, tmp_path_factory):
    """[Bán 2019, §5.4]: any light bounded by a sphere: ``contact``'s 1 m square light."""
    case = _case("contact", tmp_path_factory)
    pen, V = case["pen"], case["V"]
    hard, _ = vis(case, "sdf_hard")
    traced, _ = vis(case, "sdf_edge_mc", estimator="traced", samples=12)
    edge, _ = vis(case, "sdf_edge_mc", samples=12)
    e = {n: rmse((x - V)[pen]) for n, x in (("hard", hard), ("traced", traced), ("edge", edge))}
    print("contact penumbra RMSE:", e)
    assert e["traced"] < 0.035 and e["edge"] < 0.08 and e["edge"] < 0.3 * e["hard"]


# ---------------------------------------------------------------------------------------------
# mandelbulb (no Mitsuba twin: the truth is the Monte-Carlo cone reference)

def test_mandelbulb_mc_reproduces_its_reference_and_the_single_ray_leaks(mitsuba_backend, tmp_path_factory):
    case = _case("mandelbulb", tmp_path_factory)
    meta_truth = case["truth"].stats.get("truth")
    assert meta_truth == "sdf_mc_cone"
    A, m = case["A"], case["mask"]
    mc, _ = vis(case, "sdf_mc", samples=256, measure="solid_angle", seed=7)
    se = np.sqrt(A * (1 - A) / 256)
    z = (mc - A)[m] / np.sqrt(se[m] ** 2 + 1e-6)
    assert np.mean(np.abs(z) < 4) > 0.99                     # an independent estimate of the same integral
    # the Mandelbulb's distance estimator is not a signed distance inside the set (|f| ≪ depth):
    # the cone passes through it as through a thin object ([Bán 2019, §6.6]) and the umbra leaks
    umbra = m & (A <= 0.02) & (case["frame"].gbuffer.shape_id[..., 0] == 0)
    v, _ = vis(case, "sdf_linear")
    print(f"mandelbulb: umbra on the floor {umbra.sum()} px, single ray {v[umbra].mean():.3f}")
    assert umbra.sum() > 200 and v[umbra].mean() > 0.1       # measured 0.19


# ---------------------------------------------------------------------------------------------
# differentiability on a scene

def test_light_scale_gradient_on_a_scene(frame_of):
    """Forward-mode d(visibility)/d(light_scale) per pixel against central differences, in the
    soft part of the shadow (the marches run detached; the result is recomputed from the minimum)."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.techniques import get
    fr = frame_of("sdf_simple", (48, 48), u_strata=1)
    for name in ("sdf_linear", "sdf_quilez"):
        t = get(name)
        s = mi.Float(1.0)
        dr.enable_grad(s)
        v = t.render(fr, {"light_scale": s}).visibility["sun"]
        dr.forward(s)
        g = dr.grad(v).numpy()
        h = 0.01
        vp, vm = (t.render(fr, {"light_scale": 1.0 + d}).visibility["sun"].numpy() for d in (h, -h))
        fd = (vp - vm) / (2 * h)
        v0 = dr.detach(v).numpy()
        soft_px = (v0 > 0.05) & (v0 < 0.95)
        assert soft_px.sum() > 30
        rel = np.abs(g - fd)[soft_px] / np.maximum(np.abs(fd[soft_px]), 1e-3)
        assert np.median(rel) < 0.05 and np.mean(rel < 0.1) > 0.8, (name, np.median(rel), np.mean(rel < 0.1))
        assert np.all(g[v0 == 1.0] == 0)                # fully lit: no gradient
