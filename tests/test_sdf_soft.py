"""Single-ray soft shadows ([Bán 2019, ch. 3–4]) against closed forms.

Geometry of the planar-edge checks: the shading point at the origin, a spherical light of
radius R centred at (0, 0, d) above it, so the cone to the light has tanα = k (R = d·sin α).
The occluder is the half-space x ≥ b·z cut to a slab z ∈ [z0, z1] (a block with one face
through the cone's apex): its central projection onto every cross-section of the cone is the
same half-disk, at relative distance r = b/k from the centre, so the visible part of the light's
disk is exactly τ(r) ([Bán 2019, §4.1]), and its visible solid angle is a 1-D integral
(:func:`solid_angle_fraction`). One SDF serves every lane; the lanes differ in R (hence r).
"""

import math

import numpy as np
import pytest

from shadowlab.errors import InputError

D_LIGHT = 10.0
Z0, Z1 = 4.0, 5.0


@pytest.fixture(scope="module")
def mods(mitsuba_backend):
    import drjit as dr
    import mitsuba as mi
    from shadowlab.sdf import field, soft
    return dr, mi, field, soft


def solid_angle_fraction(b, k, n=20001):
    """Fraction of the solid angle of the cone of half-angle atan(k) around +z whose directions
    have ω_x/ω_z < b: in gnomonic coordinates (X, Y) the solid-angle density is
    (1 + X² + Y²)^(-3/2); integrating over Y in closed form leaves a 1-D integral over X."""
    X = np.linspace(-k, k, n)
    Yc = np.sqrt(np.maximum(k * k - X * X, 0))
    g = 2 * Yc / ((1 + X * X) * np.sqrt(1 + X * X + Yc * Yc))
    w = np.where(X < b, g, 0.0)
    return np.trapezoid(w, X) / np.trapezoid(g, X)


def wedge(field, b):
    """Half-space x ≥ b·z within the slab z ∈ [Z0, Z1]."""
    return field.Intersection(field.Plane((-1.0, 0.0, b), 0.0),
                              field.Box((50.0, 50.0, (Z1 - Z0) / 2), (0.0, 0.0, (Z0 + Z1) / 2)))


def lanes(mods, ks):
    dr, mi, field, soft = mods
    ks = np.asarray(ks, dtype=np.float64)
    R = D_LIGHT * ks / np.sqrt(1 + ks * ks)              # sin α = R/d, tan α = k
    n = len(ks)
    p = mi.Vector3f(dr.zeros(mi.Float, n), 0.0, 0.0)
    return p, mi.Float(R.astype(np.float32))


def march(mods, sdf, ks, variant, direction, eps, i_max=8192, R0=1e-7):
    dr, mi, field, soft = mods
    p, R = lanes(mods, ks)
    cone = soft.make_cone(p, dr.full(mi.Float, R0, len(ks)), (0.0, 0.0, D_LIGHT), R, direction)
    return soft.march(sdf, cone, variant, eps=eps, i_max=i_max)


# ---------------------------------------------------------------------------------------------
# τ and τ⁻¹ ([Bán 2019, §4.1], §4.3.1)

def test_tau_end_points_symmetry_monotonicity_and_slope(mods):
    dr, mi, _, soft = mods
    r = np.linspace(-1, 1, 200001)
    t = soft.tau(r)
    assert soft.tau(np.array(-1.0)) == 0.0 and soft.tau(np.array(1.0)) == 1.0
    assert abs(float(soft.tau(np.array(0.0))) - 0.5) < 1e-15
    assert np.all(np.diff(t) > 0), "τ must be strictly increasing on [−1, 1]"
    assert np.allclose(t + t[::-1], 1.0, atol=1e-12)       # τ(−r) = 1 − τ(r)
    slope = np.diff(t) / np.diff(r)
    assert abs(slope.max() - 2 / math.pi) < 1e-6           # τ'(0) = 2/π is the largest slope
    assert float(soft.tau(np.array(-3.0))) == 0.0 and float(soft.tau(np.array(7.0))) == 1.0   # τ̂ clamps
    # the area of the unit disk beyond a chord: τ(r) = (π − θ + sin θ)/(2π)... in its segment form
    th = 2 * np.arccos(np.clip(r, -1, 1))                  # central angle of the shadowed segment
    assert np.allclose(t, 1 - (th - np.sin(th)) / (2 * math.pi), atol=1e-12)
    # Dr.Jit float32 agrees with numpy
    tj = soft.tau(mi.Float(r[::1000].astype(np.float32))).numpy()
    assert np.abs(tj - t[::1000]).max() < 2e-6


def test_tau_inverse_by_bisection_to_1e6(mods):
    dr, mi, _, soft = mods
    r = np.linspace(-1, 1, 100001)
    # numpy (float64) and Dr.Jit Float64: invert to 1e-6 in r over all of [−1, 1]
    assert np.abs(soft.tau_inv(soft.tau(r)) - r).max() <= 1e-6
    r64 = mi.Float64(r)
    back = soft.tau_inv(soft.tau(r64)).numpy()
    assert np.abs(back - r).max() <= 1e-6
    # float32 (what the marches use): exact in value, and in r where τ is not flat to float32
    m = np.linspace(0, 1, 100001).astype(np.float32)
    mf = mi.Float(m)
    inv = soft.tau_inv(mf)
    assert np.abs(soft.tau(inv).numpy() - m).max() <= 2e-6
    rr = mi.Float(r.astype(np.float32))
    err = np.abs(soft.tau_inv(soft.tau(rr)).numpy() - r.astype(np.float32))
    assert err[np.abs(r) <= 0.9].max() <= 1e-6
    # beyond, float32 rounding of τ itself (~1e-7) is divided by the slope τ' = (2/π)√(1 − r²)
    slope = 2 / math.pi * np.sqrt(np.maximum(1 - r * r, 1e-12))
    inner = np.abs(r) <= 0.9999
    assert np.all(err[inner] <= 1e-6 + 3e-7 / slope[inner])
    assert soft.tau_inv(np.array(-0.5)) == -1.0 and soft.tau_inv(np.array(1.5)) == 1.0


# ---------------------------------------------------------------------------------------------
# a single planar occluder edge: the single ray equals τ(r) and the light's visible fraction

KS = np.array([0.0102, 0.0125, 0.016, 0.02, 0.025, 0.033, 0.05, 0.07, 0.1, 0.14, 0.2])


@pytest.mark.parametrize("variant", ["base", "linear", "convex", "discrete"])
@pytest.mark.parametrize("direction", ["A", "B"])
def test_planar_edge_equals_the_visible_fraction_within_eps(mods, variant, direction):
    dr, mi, field, soft = mods
    for b in (0.01, -0.01):                       # the axis outside (penumbra's lit half) / inside
        sdf = wedge(field, b)
        r = b / KS
        exact_disk = soft.tau(r)
        exact_sa = np.array([solid_angle_fraction(b, k) for k in KS])
        assert np.abs(exact_sa - exact_disk).max() < 0.004   # the two measures differ by O(tan²α)
        for eps in (1 / 10, 1 / 30, 1 / 256):
            ks = KS if eps > 0.01 else KS[KS >= 0.05]        # tiny ε and a tiny cone: ~ln(z1/z0)/(εk) steps
            m = march(mods, sdf, ks, variant, direction, eps)
            v = m.visibility.numpy()
            assert (m.iterations.numpy() < 8192).all()
            sel = KS >= ks.min()
            tol = eps if variant != "discrete" else 1.25 * eps   # discrete: levels of ε, plus rounding
            err = np.abs(v - exact_disk[sel])
            assert err.max() <= tol + 1e-4, (variant, direction, b, eps, err.max())
            assert np.abs(v - exact_sa[sel]).max() <= tol + 0.004
            if variant != "discrete":                 # the minimum itself is found: r_min ≈ b/k
                assert np.all(m.found.numpy())


def test_base_keeps_its_trace_cone_at_least_as_far_below_as_the_linearized_one(mods):
    """Algorithm 4 moves the trace cone e = επ/2 below T in r, Algorithm 3 τ⁻¹(τ(R^T) − ε) below
    it, which is never closer (τ' ≤ 2/π) and farther where τ is flat: base needs fewer (costlier)
    steps for the same ε."""
    dr, mi, field, soft = mods
    r = np.linspace(-1, 1, 4001)
    for eps in (1 / 10, 1 / 30, 1 / 256):
        live = soft.tau(r) > eps                         # where the march goes on
        gap = r[live] - soft.tau_inv(soft.tau(r[live]) - eps)
        assert np.all(gap >= eps * math.pi / 2 - 1e-6)
        assert gap[-1] > 1.5 * eps * math.pi / 2        # at R^T = 1, where τ is flat
    sdf = wedge(field, 0.01)
    ks = KS[KS >= 0.02]
    it = {v: march(mods, sdf, ks, v, "A", 1 / 30).iterations.numpy() for v in ("base", "linear")}
    assert it["base"].sum() < it["linear"].sum()


def test_convex_steps_are_longer_past_convex_occluders(mods):
    dr, mi, field, soft = mods
    sdf = wedge(field, 0.01)                       # a convex block beside the cone
    ks = KS[KS >= 0.02]
    lin = march(mods, sdf, ks, "linear", "A", 1 / 30)
    cvx = march(mods, sdf, ks, "convex", "A", 1 / 30)
    assert np.abs(lin.visibility.numpy() - cvx.visibility.numpy()).max() <= 1 / 30
    assert cvx.iterations.numpy().sum() < 0.5 * lin.iterations.numpy().sum()


def test_directions_a_and_b_agree(mods):
    dr, mi, field, soft = mods
    sdf = field.Union(wedge(field, 0.01), field.Sphere((0.3, 0.0, 7.0), 0.2))
    ks = KS
    va = march(mods, sdf, ks, "linear", "A", 1 / 100).visibility.numpy()
    vb = march(mods, sdf, ks, "linear", "B", 1 / 100).visibility.numpy()
    assert np.abs(va - vb).max() <= 2 / 100


def test_light_radius_gradient_matches_finite_differences(mods):
    """The result is recomputed from the minimum found, so d/dR comes by the envelope theorem."""
    dr, mi, field, soft = mods
    sdf = wedge(field, 0.01)
    ks = np.array([0.02, 0.03, 0.05])
    p, R = lanes(mods, ks)
    R = mi.Float(R)
    dr.enable_grad(R)
    cone = soft.make_cone(p, dr.full(mi.Float, 1e-7, 3), (0.0, 0.0, D_LIGHT), R, "A")
    v = soft.march(sdf, cone, "linear", eps=1 / 256, i_max=8192).visibility
    dr.backward(dr.sum(v))
    g = dr.grad(R).numpy()
    Rn = R.numpy().astype(np.float64)
    h = 1e-3
    k = lambda Rv: (Rv / D_LIGHT) / np.sqrt(1 - (Rv / D_LIGHT) ** 2)   # noqa: E731
    fd = (soft.tau(0.01 / k(Rn + h)) - soft.tau(0.01 / k(Rn - h))) / (2 * h)
    assert np.all(g < 0)                                   # a bigger light: less of it is visible
    assert np.allclose(g, fd, rtol=0.02), (g, fd)


# ---------------------------------------------------------------------------------------------
# the model's known failures, measured ([Bán 2019, §6.5–6.6])

def test_two_occluders_from_opposite_sides_leak_light(mods):
    """[Bán 2019, §6.5] "több árnyékoló": only the largest occluder counts. Two blocks from opposite
    sides each hide 1 − τ(r) of the light; together 2(1 − τ(r)); the single ray sees one."""
    dr, mi, field, soft = mods
    b = 0.01
    left = field.Intersection(field.Plane((-1.0, 0.0, b), 0.0), field.Box((50, 50, 0.5), (0, 0, 3.5)))
    right = field.Intersection(field.Plane((1.0, 0.0, b), 0.0), field.Box((50, 50, 0.5), (0, 0, 5.5)))
    sdf = field.Union(left, right)
    ks = np.array([0.02, 0.025, 0.033, 0.05])
    r = b / ks
    truth = 2 * soft.tau(r) - 1
    single = march(mods, sdf, ks, "linear", "A", 1 / 256).visibility.numpy()
    assert np.abs(single - soft.tau(r)).max() <= 1 / 256 + 1e-4   # exactly the larger one's shadow
    p, R = lanes(mods, ks)
    mc = soft.mc_cone_visibility(sdf, p, mi.Vector3f(0, 0, 1), ((0, 0, D_LIGHT), 0.0), 2048, radius=R,
                                 clearance=0.0, i_max=20000, measure="disk").numpy()
    assert np.abs(mc - truth).max() < 0.02
    leak = single - mc                                            # over-bright by 1 − τ(r): 0.2 … 0.38
    assert np.all(leak > 0.15) and np.abs(leak - (1 - soft.tau(r))).max() < 0.02, leak


def test_thin_occluder_lets_light_through(mods):
    """[Bán 2019, §6.6] "vékony objektumok": an opaque plate across the whole cone blocks everything (the
    Monte-Carlo reference measures 0), yet when it is thinner than the cone's diameter there the
    axis' distance never drops below −w/2, so the single ray reports τ(−w/(2ρ)): 40–48 % of the
    light leaks. A plate thicker than the cone's diameter gives 0, as it should."""
    dr, mi, field, soft = mods
    ks = np.array([0.05, 0.1, 0.15])
    rho = 4.5 * ks                                                  # the cone's radius at the plate
    p, R = lanes(mods, ks)
    for w in (0.02, 2.0):                                           # 2ρ ≤ 1.35 < 2
        sdf = field.Box((50.0, 50.0, w / 2), (0.0, 0.0, 4.5))
        v = march(mods, sdf, ks, "linear", "A", 1 / 256).visibility.numpy()
        mc = soft.mc_cone_visibility(sdf, p, mi.Vector3f(0, 0, 1), ((0, 0, D_LIGHT), 0.0), 256, radius=R,
                                     clearance=0.0, i_max=20000, measure="disk").numpy()
        assert np.all(mc == 0.0), (w, mc)
        leak = v - mc
        if w < 2 * rho.min():
            assert np.all(leak > 0.4), (w, leak)
            assert np.abs(v - soft.tau(-w / 2 / rho)).max() < 0.01, (w, v)
        else:
            assert np.all(leak <= 1 / 256 + 1e-4), (w, leak)


def test_negative_offset_spreads_an_edges_penumbra_into_the_umbra(mods):
    """[Bán 2019, §6.6] "ofszet": a square prism seen across one of its edges (faces at ±45° to the axis)
    projects to a half-plane, so the truth is τ(b/k) on both sides (Monte Carlo measures it).
    Outside the prism the single ray finds the edge at ϱ = b/k: exact. Inside, the axis is at
    most |b|·z/√2 deep (the eroded edge lies √2·|d| back, Fig. 6.20), so it reports τ(b/(√2·k)):
    the inner penumbra comes out too bright."""
    dr, mi, field, soft = mods
    z_e, a = 4.5, 0.5                                    # the edge's depth; vertex to centre of the prism
    ks = np.array([0.02, 0.025, 0.033, 0.05])
    p, R = lanes(mods, ks)
    for b in (0.01, -0.01):
        x_e = b * z_e                                    # the edge is the line x = x_e, z = z_e along y
        prism = field.transform(field.Box((a / math.sqrt(2), 50.0, a / math.sqrt(2))), translate=(x_e + a, 0, z_e),
                                rotate=[(0, 1, 0, 45)])
        v = march(mods, prism, ks, "linear", "A", 1 / 256).visibility.numpy()
        mc = soft.mc_cone_visibility(prism, p, mi.Vector3f(0, 0, 1), ((0, 0, D_LIGHT), 0.0), 2048, radius=R,
                                     clearance=0.0, i_max=20000, measure="disk").numpy()
        assert np.abs(mc - soft.tau(b / ks)).max() < 0.02, (b, mc)
        if b > 0:
            assert np.abs(v - soft.tau(b / ks)).max() <= 1 / 256 + 1e-3, (b, v)
        else:
            assert np.abs(v - soft.tau(b / (math.sqrt(2) * ks))).max() <= 1 / 256 + 1e-3, (b, v)
            excess = v - mc                              # measured 0.035 … 0.085 too bright
            assert np.all(excess > 0.03), (v, mc)
            assert np.abs(excess - (soft.tau(b / (math.sqrt(2) * ks)) - soft.tau(b / ks))).max() < 0.02


def test_pointed_corner_is_too_dark(mods):
    """[Bán 2019, §6.5] "hegyes objektumok": a right-angled edge (the quarter-space x ≥ 0, y ≥ 0 along the
    axis) hides a quarter of the light; the single ray takes its nearest point for a half-plane
    and hides half."""
    dr, mi, field, soft = mods
    sdf = field.Intersection(field.Plane((-1.0, 0.0, 0.0), 0.0), field.Plane((0.0, -1.0, 0.0), 0.0),
                             field.Box((50, 50, 0.5), (0, 0, 4.5)))
    ks = np.array([0.03, 0.05, 0.1])
    v = march(mods, sdf, ks, "linear", "A", 1 / 256).visibility.numpy()
    assert np.abs(v - 0.5).max() < 0.01
    p, R = lanes(mods, ks)
    mc = soft.mc_cone_visibility(sdf, p, mi.Vector3f(0, 0, 1), ((0, 0, D_LIGHT), 0.0), 2048, radius=R,
                                 clearance=0.0, i_max=20000, measure="disk").numpy()
    assert np.abs(mc - 0.75).max() < 0.02


# ---------------------------------------------------------------------------------------------
# the baseline, the Monte-Carlo reference, hard shadows

def test_quilez_treats_the_inner_half_of_the_penumbra_as_umbra(mods):
    dr, mi, field, soft = mods
    ks = KS
    p, R = lanes(mods, ks)
    for b in (0.01, -0.01):
        sdf = wedge(field, b)
        for variant in soft.QUILEZ_VARIANTS:
            v, _ = soft.quilez(sdf, p, (0.0, 0.0, D_LIGHT), R, variant=variant, i_max=8192)
            v = v.numpy()
            r = b / ks
            if b < 0:   # the axis crosses the occluder: a hit, 0, where the truth is τ(r) ∈ (0, ½)
                assert np.all(v == 0.0) and np.all(soft.tau(r) > 0.001)
            elif variant == "quilez2010":   # k·h/t = ϱ (k = 1/tanα): a ramp over ϱ ∈ [0, 1], not τ over [−1, 1]
                assert np.allclose(v, np.clip(r, 0, 1), atol=0.02), (variant, v, r)
            else:       # Aaltonen's closest-approach estimate assumes a round occluder: darker still on a plane
                assert np.all(v <= np.clip(r, 0, 1) + 0.02) and np.all(v > 0.8 * np.clip(r, 0, 1)), (v, r)
            if b > 0:
                assert np.all(v < soft.tau(r))


@pytest.mark.parametrize("scheme", ["sqrt", "r_weighted"])
def test_monte_carlo_in_the_cone_converges_to_the_visible_fraction(mods, scheme):
    dr, mi, field, soft = mods
    b = 0.01
    sdf = wedge(field, b)
    ks = np.array([0.0125, 0.02, 0.033, 0.05, 0.1])
    p, R = lanes(mods, ks)
    n = 4096
    for measure, exact in (("disk", soft.tau(b / ks)), ("solid_angle", [solid_angle_fraction(b, k) for k in ks])):
        vs = [soft.mc_cone_visibility(sdf, p, mi.Vector3f(0, 0, 1), ((0, 0, D_LIGHT), 0.0), n, radius=R,
                                      clearance=0.0, i_max=20000, scheme=scheme, measure=measure, seed=s).numpy()
              for s in range(4)]
        est = np.mean(vs, 0)
        spread = np.std(vs, 0, ddof=1) / 2
        # Halton points: far below the binomial error sqrt(v(1 − v)/n) ≈ 0.008 per seed
        assert np.abs(est - np.asarray(exact)).max() < max(4 * spread.max(), 0.004), (measure, est, exact)


def test_monte_carlo_cosine_weight_is_the_ratio_of_eq_5_1(mods):
    """With cosine=True the estimate is ∫v·cos/∫cos over the light (the diffuse truth's V): for a
    receiver normal tilted toward the occluder the blocked half weighs more."""
    dr, mi, field, soft = mods
    sdf = field.Intersection(field.Plane((-1.0, 0.0, 0.0), 0.0), field.Box((50, 50, 0.5), (0, 0, 4.5)))
    k = 0.3
    R = D_LIGHT * k / math.sqrt(1 + k * k)
    p = mi.Vector3f(0.0, 0.0, 0.0)
    nrm = mi.Vector3f(math.sin(0.6), 0.0, math.cos(0.6))              # tilted toward +x (the occluder)
    v_plain = soft.mc_cone_visibility(sdf, p, nrm, ((0, 0, D_LIGHT), R), 4096, clearance=0.0, i_max=20000)
    v_cos = soft.mc_cone_visibility(sdf, p, nrm, ((0, 0, D_LIGHT), R), 4096, clearance=0.0, i_max=20000,
                                    cosine=True)
    # exact: directions with X < 0 lit, weight (n·ω) over the gnomonic disk, with the solid-angle density
    X, Y = np.meshgrid(np.linspace(-k, k, 1601), np.linspace(-k, k, 1601))
    inside = X * X + Y * Y <= k * k
    dens = (1 + X * X + Y * Y) ** -1.5
    cosw = (math.sin(0.6) * X + math.cos(0.6)) / np.sqrt(1 + X * X + Y * Y)
    exact = (dens * cosw * inside * (X < 0)).sum() / (dens * cosw * inside).sum()
    assert abs(float(v_plain.numpy()[0]) - 0.5) < 0.01
    assert abs(float(v_cos.numpy()[0]) - exact) < 0.01 and exact < 0.47
    # both measures from one set of rays (the SDF reference's A and V) are the two separate estimates
    both = soft.mc_cone_visibility(sdf, p, nrm, ((0, 0, D_LIGHT), R), 4096, clearance=0.0, i_max=20000,
                                   cosine="both")
    assert both[0].numpy()[0] == v_plain.numpy()[0] and both[1].numpy()[0] == v_cos.numpy()[0]


def test_anti_aliased_hard_shadow_is_a_ramp_of_the_surface_sphere(mods):
    """[Bán 2019, §4.3.3]: light radius 0, surface sphere R0: the shadow edge of a plate is a ramp whose
    width on the receiver is 2·R0 (the cone's diameter at the point), hard outside it."""
    dr, mi, field, soft = mods
    sdf = field.Box((50.0, 50.0, 0.25), (50.0, 0.0, 4.5))            # occluder x ≥ 0
    xs = np.linspace(-0.05, 0.05, 201)
    n = len(xs)
    R0 = 0.01
    p = mi.Vector3f(mi.Float(xs.astype(np.float32)), 0.0, 0.0)
    # a point light at (0, 0, d): the axis crosses the plate at x·(1 − z/d), where the cone's radius
    # is R0·(1 − z/d), so ϱ = −x/R0 and the ramp τ(−x/R0) spans x ∈ [−R0, R0]
    cone = soft.make_cone(p, dr.full(mi.Float, R0, n), (0.0, 0.0, D_LIGHT), dr.zeros(mi.Float, 1), "A")
    v = soft.march(sdf, cone, "linear", eps=1 / 256, i_max=4096).visibility.numpy()
    assert np.abs(v - soft.tau(-xs / R0)).max() <= 1 / 256 + 2e-3
    ramp = (v > 0.01) & (v < 0.99)
    assert np.all(v[xs < -R0 * 1.2] > 0.99) and np.all(v[xs > R0 * 1.2] < 0.01)
    width = xs[ramp].max() - xs[ramp].min()
    assert 0.8 * 2 * R0 < width < 1.2 * 2 * R0, width


def test_hard_shadow_is_binary_and_matches_the_plate(mods):
    from shadowlab.sdf.trace import hard_visibility
    dr, mi, field, soft = mods
    sdf = field.Box((50.0, 50.0, 0.25), (50.0, 0.0, 4.5))            # occluder x ≥ 0
    xs = np.linspace(-1, 1, 101)
    p = mi.Vector3f(mi.Float(xs.astype(np.float32)), 0.0, 0.0)
    v, its = hard_visibility(sdf, p, None, (0.0, 0.0, D_LIGHT), return_iterations=True)
    # the ray from (x, 0, 0) to (0, 0, 10) crosses the plate at x·(1 − z/10): blocked iff x ≥ 0
    assert np.array_equal(v.numpy(), np.where(xs >= 0, 0.0, 1.0))
    assert its.numpy().max() < 256


# ---------------------------------------------------------------------------------------------
# techniques: registration, bad input, kernels

SDF_TECHNIQUES = ("sdf_hard", "sdf_aa_hard", "sdf_base", "sdf_linear", "sdf_discrete", "sdf_convex", "sdf_quilez",
                  "sdf_mc", "sdf_edge_mc")


def test_every_variant_is_a_registered_technique_with_declared_params():
    from shadowlab.techniques import get, names
    for n in SDF_TECHNIQUES:
        assert n in names()
        t = get(n)
        assert t.source.startswith("[Bán 2019") and t.params
    assert get("sdf_linear").param("light_scale").differentiable
    assert not get("sdf_discrete").param("light_scale").differentiable
    with pytest.raises(InputError, match="epsilon"):
        get("sdf_linear").resolve({"epsilon": 0.9})
    with pytest.raises(InputError, match="direction"):
        get("sdf_base").resolve({"direction": "C"})


def test_a_scene_without_sdf_is_an_input_error(frame_of):
    from shadowlab.techniques import get
    frame = frame_of("foliage", (16, 16), u_strata=1)
    assert frame.sdf is None
    for n in SDF_TECHNIQUES:
        with pytest.raises(InputError, match="signed distance field"):
            get(n).render(frame, {})


@pytest.fixture(scope="module")
def small_frame(frame_of):
    return frame_of("sdf_simple", (32, 32), u_strata=1)


def test_render_is_pure_and_parameters_reuse_kernels(small_frame):
    import drjit as dr
    from shadowlab.techniques import get
    t = get("sdf_linear")
    a = t.render(small_frame, {"epsilon": 0.05, "light_scale": 1.2}).visibility["sun"].numpy()
    b = t.render(small_frame, {"epsilon": 0.05, "light_scale": 1.2}).visibility["sun"].numpy()
    assert np.array_equal(a, b)
    dr.sync_thread()
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        c = t.render(small_frame, {"epsilon": 0.02, "light_scale": 0.7, "surface_radius": 0.3}).visibility["sun"]
        dr.eval(c)
        dr.sync_thread()
        h = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert h and not [k for k in h if not k.get("cache_hit")], "new values of ε / light_scale compiled kernels"
    assert not np.array_equal(a, c.numpy())


def test_light_scale_zero_is_a_point_light_and_bigger_lights_soften(small_frame):
    from shadowlab.techniques import get
    t = get("sdf_linear")
    pen = {}
    for s in (0.0, 1.0, 3.0):
        v = t.render(small_frame, {"light_scale": s}).visibility["sun"].numpy()
        pen[s] = int(((v > 0.02) & (v < 0.98)).sum())
    assert pen[0.0] < pen[1.0] < pen[3.0]
