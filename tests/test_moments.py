"""Prefiltered shadow maps of [Buljan 2020, §3.3–§3.5] and MSM ([Peters 2015]):
``vsm``, ``esm``, ``evsm``, ``msm`` and their shared prefilter (shadowlab/techniques/prefilter.py).

Scenes: the built-in ``parallel_planes`` (occluder and floor parallel to the light's image
plane: §3.3's VSM = PCF case), ``stack`` (three parallel slabs at light-space depths a < b < c:
§3.3's leak t²/(2t² + 4t + 4), t = Δx/Δy = (b − a)/(c − b) = 3), ``bench`` (a seat on four legs,
Slika 3.10's comparison at 3×3), ``contact``; and two small scenes defined here: ``step`` (a
platform under a plate, both ending at x = 0, over a floor 0.4 below the platform's top, a
delta directional light straight down: ESM's non-planarity, §3.4 Slika 3.8) and ``spot`` (a
narrow spot light, so that most of the image is outside its light camera).
"""

import dataclasses

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.techniques import get
from scene_builder import floor, frame_from

MOMENT = ("vsm", "esm", "evsm", "msm")

STEP = {
    "name": "step",
    "camera": {"position": [0.5, 0.75, 1.6], "target": [-0.15, 0.45, 0.0], "fov": 30, "resolution": [96, 96]},
    "lights": [{"name": "sun", "kind": "directional", "direction": [0.0, -1.0, 0.0], "up": [0.0, 0.0, 1.0],
                "irradiance": 1.0, "shadow_map": 128}],
    "shapes": [floor(1.0),
               {"name": "platform", "type": "cube", "translate": [-0.5, 0.2, 0.0], "scale": [0.5, 0.2, 0.6]},
               {"name": "plate", "type": "rectangle", "translate": [-0.6, 1.0, 0.0], "rotate": [1, 0, 0, 90],
                "scale": [0.6, 0.8, 1.0]}],
}
SPOT = {
    "name": "spot",
    "camera": {"position": [0.0, 3.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 60, "resolution": [64, 64]},
    "lights": [{"name": "s", "kind": "spot", "position": [0.3, 2.5, 0.2], "target": [0.0, 0.0, 0.0], "angle": 25.0,
                "power": 100.0, "shadow_map": 256}],
    "shapes": [floor(2.0),
               {"name": "box", "type": "cube", "translate": [0.0, 0.3, 0.0], "rotate": [0, 1, 0, 30], "scale": 0.3}],
}
#: a point light inside a ring of occluders (cube map: every face is used)
RING = {
    "name": "ring",
    "camera": {"position": [0.5, 5.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 55, "resolution": [64, 64]},
    "lights": [{"name": "p", "kind": "point", "position": [0.0, 1.2, 0.0], "power": 100.0, "shadow_map": 256}],
    "shapes": [floor(3.0),
               {"name": "east", "type": "cube", "translate": [1.0, 0.35, 0.1], "scale": [0.12, 0.35, 0.3]},
               {"name": "west", "type": "cube", "translate": [-1.0, 0.35, -0.1], "scale": [0.12, 0.35, 0.3]},
               {"name": "north", "type": "sphere", "center": [0.1, 0.35, -1.0], "radius": 0.3},
               {"name": "lid", "type": "sphere", "center": [0.0, 2.1, 0.0], "radius": 0.25}],
}


def leak_formula(t):
    """§3.3: p_max(c) for a receiver at c behind two occluders at a < b, each covering half
    the filter region: t²/(2t² + 4t + 4), t = (b − a)/(c − b)."""
    return t * t / (2 * t * t + 4 * t + 4)


def reduction(v, p):
    return 0.0 if v < p else (v - p) / (1 - p)


def _inline(spec):
    frame = frame_from(spec)
    return frame.scene, frame


def _builtin(frame_of, name, resolution=None):
    """(scene, frame) of a built-in scene, the frame shared through the session (conftest ``frame_of``)."""
    frame = frame_of(name, resolution, u_strata=1)
    return frame.scene, frame


def vis(frame, light, tech, **params):
    return frame.gbuffer.to_image(get(tech).render(frame, params).visibility[light])


def zn_map(view):
    """The normalised linear depth of every texel, as the prefilter computes it (float64)."""
    f0 = view.proj.faces[0]
    return np.clip((view.z.astype(np.float64) - f0.near) / (f0.far - f0.near), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# the prefilter itself

def test_blur_stays_in_its_face_and_clamps_at_the_border(mitsuba_backend):
    """Six faces of 8×8 texels, face f holding f + x-ramp: a 5-tap box blur keeps every face's
    values to itself (no bleeding across faces) and clamps taps past the border to the border
    texel (texel 0 of a row = (3·z0 + z1 + z2)/5)."""
    import mitsuba as mi
    from types import SimpleNamespace
    from shadowlab.techniques import prefilter
    N, F = 8, 6
    z = np.zeros((F, N, N))
    for f in range(F):
        z[f] = 10.0 * f + np.arange(N)[None, :]
    view = SimpleNamespace(res=N, nfaces=F)
    (b,) = prefilter.blur(view, [mi.Float(z.astype(np.float32).ravel())], 5, "box")
    b = b.numpy().reshape(F, N, N)
    for f in range(F):
        row = z[f, 0]
        assert b[f, :, 0] == pytest.approx((3 * row[0] + row[1] + row[2]) / 5, abs=1e-5)
        assert b[f, :, 3] == pytest.approx(row[3], abs=1e-5)              # interior: the ramp's own value
        assert b[f].min() >= 10.0 * f - 1e-5 and b[f].max() <= 10.0 * f + N - 1 + 1e-5
    # even kernels: blurred texel j averages j − n/2 … j + n/2 − 1 (centred on j − ½)
    (b4,) = prefilter.blur(view, [mi.Float(z.astype(np.float32).ravel())], 4, "box")
    assert b4.numpy().reshape(F, N, N)[2, 0, 4] == pytest.approx(20.0 + 3.5, abs=1e-5)
    for n in range(1, 10):
        for kind in ("box", "gaussian"):
            w = prefilter.blur_weights(n, kind)
            assert len(w) == n and abs(sum(w) - 1.0) < 1e-12 and min(w) > 0
            assert np.dot(prefilter.tap_offsets(n), w) == pytest.approx(prefilter.centre_shift(n), abs=1e-12)


# ---------------------------------------------------------------------------------------------
# VSM: §3.3

@pytest.fixture(scope="module")
def planes(frame_of):
    return _builtin(frame_of, "parallel_planes")


def test_vsm_equals_pcf_for_two_parallel_planes(planes):
    """§3.3 (Donnelly & Lauritzen): occluder at d1, receiver at d2, a fraction p of the filter
    region unoccluded: μ = p·d2 + (1 − p)·d1, σ² = (p − p²)(d2 − d1)², p_max(d2) = p: VSM with
    the box prefilter equals PCF over the same footprint (``pcf`` n×n grid of bilinear taps).

    Tolerance: in the umbra (p = 0) σ² = 0 is raised to σ²_min, so VSM gives
    σ²_min/(σ²_min + Δ²) ≤ σ²_min/Δ² (Δ = d2 − d1 in zn: 2.7·10⁻⁵ here) instead of 0; elsewhere
    fp32 rounding of M2 − M1² (measured ≤ 1.5·10⁻⁶). Checked for n = 1…9 (even n too) on a
    128² map, where the penumbra covers hundreds of pixels."""
    scene, frame = planes
    mask = frame.gbuffer.mask[..., 0]
    view = frame.light_view("panel", res=128)
    f0 = view.proj.faces[0]
    delta = 2.0 / (f0.far - f0.near)                   # occluder at height 2, floor at 0, light at 4
    mv = get("vsm").param("min_variance").default
    tol = mv / delta ** 2 + 2e-6
    for n in range(1, 10):
        v = vis(frame, "panel", "vsm", kernel=n, resolution=128)
        p = vis(frame, "panel", "pcf", kernel=n, bilinear=True, resolution=128)
        pen = mask & (p > 0.01) & (p < 0.99)
        assert pen.sum() > 100 * min(n, 3), n
        err = np.abs(v - p)[mask]
        assert err.max() <= tol, (n, err.max(), tol)
    # and without the minimum variance the lit side breaks down (σ² = 0, z̃ a rounding error past μ)
    v0 = vis(frame, "panel", "vsm", kernel=3, resolution=128, min_variance=0.0)
    assert np.abs(v0 - p)[mask].max() > 0.5


def test_chebyshev_floors_the_variance_at_min_variance_it_does_not_add_it(mitsuba_backend):
    """§3.3: σ² = max(M2 − M1², σ²_min), p_max = σ²/(σ² + (z̃ − μ)²) for z̃ > μ, else 1. Hand-made
    moment pairs with μ = 0.5, z̃ = 0.6 ((z̃ − μ)² = 0.01):

    * σ² = 0.01 above σ²_min = 0.004: the floor leaves it, p = 0.01/0.02 = 0.5 (adding would give
      0.014/0.024 = 0.583);
    * σ² = 0.0025 below σ²_min = 0.01: the floor replaces it, p = 0.01/0.02 = 0.5 (adding: 0.0125/0.0225 = 0.556);
    * σ² = 0 (a single depth): p = σ²_min/(σ²_min + 0.01) = 0.004/0.014 = 0.2857;
    * σ²_min = 0 leaves σ²: 0.01/0.02 = 0.5; z̃ ≤ μ is lit: 1."""
    import mitsuba as mi
    from shadowlab.techniques.prefilter import chebyshev
    mu, zr = 0.5, 0.6
    cases = [  # (σ², σ²_min, p_max)
        (0.01, 0.004, 0.5), (0.0025, 0.01, 0.5), (0.0, 0.004, 0.004 / 0.014), (0.01, 0.0, 0.5),
        (0.04, 0.01, 0.04 / 0.05), (0.001, 0.03, 0.03 / 0.04)]
    var = np.array([c[0] for c in cases])
    m1 = mi.Float(np.full(len(cases), mu, np.float32))
    m2 = mi.Float((mu * mu + var).astype(np.float32))
    p = chebyshev(m1, m2, mi.Float(np.full(len(cases), zr, np.float32)),
                  mi.Float(np.array([c[1] for c in cases], np.float32))).numpy()
    assert p == pytest.approx([c[2] for c in cases], abs=2e-5), p
    lit = chebyshev(m1, m2, mi.Float(np.full(len(cases), 0.45, np.float32)), mi.Float(0.004)).numpy()
    assert (lit == 1.0).all()


def test_vsm_min_variance_floors_the_variance_on_parallel_planes(planes):
    """The floor, seen in a render: with σ²_min = 10⁻³ (Δ = d2 − d1 = 2/(far − near) in zn, Δ² = 0.0366)
    VSM still equals PCF (box 3×3, 128² map) wherever the footprint's own variance p(1 − p)Δ² is
    above σ²_min (0.05 < p < 0.95: p(1 − p)Δ² ≥ 0.0017), and in the umbra (p = 0, σ² = 0) it is
    exactly σ²_min/(σ²_min + Δ²) = 0.0266. Adding σ²_min instead would move the penumbra by up to
    0.03 (p = ½: 0.526)."""
    scene, frame = planes
    mask = frame.gbuffer.mask[..., 0]
    f0 = frame.light_view("panel", res=128).proj.faces[0]
    delta = 2.0 / (f0.far - f0.near)                   # occluder at height 2, floor at 0, light at 4
    mv = 1e-3
    v = vis(frame, "panel", "vsm", kernel=3, resolution=128, min_variance=mv)
    p = vis(frame, "panel", "pcf", kernel=3, bilinear=True, resolution=128)
    pen = mask & (p > 0.05) & (p < 0.95)
    umbra = mask & (p == 0.0)
    assert pen.sum() > 200 and umbra.sum() > 1000
    assert np.abs(v - p)[pen].max() < 1e-5, np.abs(v - p)[pen].max()
    assert v[umbra] == pytest.approx(mv / (mv + delta ** 2), rel=1e-4)


def test_evsm_minimum_variance_is_scaled_by_the_square_of_the_warps_derivative(planes):
    """§3.5 (Lauritzen's sample): σ²_min is given in zn² units and mapped to each warp by the
    square of its derivative at the receiver: w = 2·zn − 1, pos = e^{k⁺w}, d pos/d zn = 2k⁺·pos,
    so σ²_min⁺ = σ²_min·(2k⁺·pos(z̃))², σ²_min⁻ = σ²_min·(2k⁻·neg(z̃))². On ``parallel_planes``
    with ``kernel`` 1 and no receiver bias, a floor point (z̃ at depth 4) whose 2×2 lookup sees
    only the occluder (depth 2) has M1 = pos(d1), M2 = M1² (no variance), so

        p⁺ = σ²_min⁺/(σ²_min⁺ + (pos(z̃) − pos(d1))²)   (components 2)
        min(p⁺, p⁻), p⁻ likewise with neg = −e^{−k⁻w}   (components 4)

    computed here in float64 from the depths (zn = (z − near)/(far − near)). Measured: equal to
    10⁻⁶ relative. Without the derivative (σ²_min alone) the umbra would be lit (p⁺ ≈ 1); with
    k instead of 2k it would be 4× darker."""
    import math
    scene, frame = planes
    gb = frame.gbuffer
    from shadowlab.render.gbuffer import vec_numpy
    x = gb.to_image(vec_numpy(gb.p))[..., 0]
    floor = (gb.shape_id[..., 0] == scene.shape_names.index("floor")) & gb.mask[..., 0]
    umbra = floor & (x < -1.0)           # the occluder's shadow, ≥ 3 texels (128² map) from its edge
    assert umbra.sum() > 1000
    f0 = frame.light_view("panel", res=128).proj.faces[0]
    w_rec, w_occ = (2.0 * (z - f0.near) / (f0.far - f0.near) - 1.0 for z in (4.0, 2.0))

    def bound(k, mv, sign):
        r, o = sign * math.exp(sign * k * w_rec), sign * math.exp(sign * k * w_occ)
        s = mv * (2.0 * k * r) ** 2
        return s / (s + (r - o) ** 2)

    nobias = {"constant_bias": 0.0, "slope_bias": 0.0, "max_slope_bias": 0.0, "normal_offset": 0.0}
    for comps, kp, kn, mv in ((2, 40.0, 5.0, 1e-6), (2, 10.0, 5.0, 1e-4), (4, 40.0, 5.0, 1e-3), (4, 10.0, 1.0, 1e-4)):
        r = get("evsm").render(frame, {"kernel": 1, "resolution": 128, "components": comps, "exp_pos": kp,
                                       "exp_neg": kn, "min_variance": mv, **nobias})
        assert np.all(r.aovs["panel.receiver_bias"][umbra] == 0.0)
        v = frame.image(r.visibility["panel"])
        pp, pn = bound(kp, mv, 1.0), bound(kn, mv, -1.0)
        want = pp if comps == 2 else min(pp, pn)
        if comps == 4:
            assert pn < 0.1 * pp                     # the negative warp's bound is the one seen
        assert v[umbra] == pytest.approx(want, rel=1e-4), (comps, kp, kn, mv, v[umbra].min(), v[umbra].max(), want)
    # the numbers (components 2, k⁺ 40, σ²_min 10⁻⁶): 4k²σ²_min/(4k²σ²_min + 1) = 0.0064/1.0064
    assert bound(40.0, 1e-6, 1.0) == pytest.approx(0.0064 / 1.0064, rel=1e-5)


@pytest.fixture(scope="module")
def stack(frame_of):
    from shadowlab.reference import store
    scene, frame = _builtin(frame_of, "stack")
    truth, _ = store.load(scene.spec)
    return scene, frame, truth


def _centre_frame(frame):
    """The stack's frame with every G-buffer point moved onto the receiver C at x = 0 (z from
    −0.8 to 0.8): points the light projects exactly onto the line between the map's two centre
    columns, where A (x < 0) and B (x > 0) meet."""
    import mitsuba as mi
    from shadowlab.render.frame import FrameContext
    gb = frame.gbuffer
    m = gb.size
    z = np.linspace(-0.8, 0.8, m).astype(np.float32)
    zero = np.zeros(m, np.float32)
    gb2 = dataclasses.replace(gb, p=mi.Point3f(zero, zero, z), ng=mi.Normal3f(zero, zero + 1.0, zero),
                              valid=mi.Bool(np.ones(m, bool)))
    return FrameContext(scene=frame.scene, gbuffer=gb2, unshadowed=frame.unshadowed, _views=frame._views)


def test_stack_reproduces_the_leak_formula_at_the_centre_texel(stack):
    """§3.3: receiver C at depth c behind A (depth a) and B (depth b), the filter region half A,
    half B: M1 = (a + b)/2, σ² = (b − a)²/4, p_max(c) = t²/(2t² + 4t + 4), t = Δx/Δy = (b − a)/(c − b)
    (light at height 5 looking down: a = 2.6, b = 4.4, c = 5, t = 1.8/0.6 = 3) → 9/34, where the
    truth is 0.

    At a point the light projects onto the boundary between the map's centre columns any odd or
    even box blur + bilinear lookup weighs A and B exactly ½ each. Expected value from the map's
    own (quantised) depths; nominal t = 3 within 10⁻³."""
    scene, frame, truth = stack
    cf = _centre_frame(frame)
    view = frame.light_view("top")
    N = view.res
    zn = zn_map(view)[0]
    a = np.median(zn[N // 2 - 40:N // 2 + 40, N // 2:N // 2 + 20])    # u > N/2: A (map u axis = −x)
    b = np.median(zn[N // 2 - 40:N // 2 + 40, N // 2 - 20:N // 2])
    f0 = view.proj.faces[0]
    c = (f0.origin[1] - 0.0 - f0.near) / (f0.far - f0.near)              # C's top at height 0
    t = (b - a) / (c - b)
    assert t == pytest.approx(3.0, rel=1e-4)
    expected = leak_formula(t)
    assert expected == pytest.approx(9 / 34, abs=1e-4)
    for n in (1, 2, 3, 5, 8):
        r = get("vsm").render(cf, {"kernel": n})
        v = r.visibility["top"].numpy()
        assert np.abs(v - expected).max() < 2e-5, (n, v.min(), v.max(), expected)
    # the warps and the four moments do not leak there (measured: EVSM 0.0064, ESM 3·10⁻⁵, MSM 4·10⁻⁴)
    for tech in ("evsm", "esm", "msm"):
        assert get(tech).render(cf, {}).visibility["top"].numpy().max() < 0.01, tech
    # light-bleeding reduction: exactly Reduction(v, p) of the same bound
    for p in (0.05, 0.15, 0.25, 0.2647, 0.3, 0.6, 0.95):
        v = get("vsm").render(cf, {"kernel": 3, "bleed": p}).visibility["top"].numpy()
        want = reduction(expected, p)
        assert np.abs(v - want).max() < 2e-5 / (1 - p), (p, v.max(), want)
        if p > expected:
            assert v.max() == 0.0


def test_stack_leaks_where_the_truth_is_umbra_and_bleed_removes_it(stack):
    """On the rendered image: the floor pixels whose light-view footprint straddles the A|B line
    (|x| < 0.1, under both slabs) are umbra in the truth; VSM shows them lit up to the two-depth
    bound max_q q(1−q)Δx²/(q(1−q)Δx² + (Δy + qΔx)²) (q = A's share of the footprint; 0.36 at t = 3),
    and ``bleed`` = 0.4 above that bound maps every one of them to 0 (Reduction)."""
    from shadowlab.render.gbuffer import vec_numpy
    scene, frame, truth = stack
    gb = frame.gbuffer
    P = vec_numpy(gb.p).reshape(gb.height, gb.width, 3)
    floor = (gb.shape_id[..., 0] == scene.shape_names.index("slab_c")) & gb.mask[..., 0]
    strip = floor & (np.abs(P[..., 0]) < 0.1) & (np.abs(P[..., 2]) < 0.8)
    V = truth.lights["top"].V
    assert strip.sum() > 50 and V[strip].max() <= 0.02
    q = np.linspace(0, 1, 100001)
    bound = np.max(q * (1 - q) * 9 / (q * (1 - q) * 9 + (1 + 3 * q) ** 2))
    assert bound == pytest.approx(0.36, abs=0.005)
    for n in (3, 5):
        v = vis(frame, "top", "vsm", kernel=n)
        assert v[strip].max() > 0.2 and v[strip].max() <= bound + 1e-4, (n, v[strip].max())
        assert vis(frame, "top", "vsm", kernel=n, bleed=0.4)[strip].max() == 0.0


# ---------------------------------------------------------------------------------------------
# ESM: §3.4

def test_esm_non_planarity_failure_and_both_fallbacks(mitsuba_backend):
    """§3.4 "Kršenje pretpostavke": on the platform's top, next to its edge at x = 0, the points
    are shadowed by the plate above (hard shadow map: 0), but their 5×5 footprint also holds
    floor texels 0.4 deeper, so E·exp(−c·z̃) ≫ 1 and ESM shows them lit (z_avg > z̃) where PCF
    gives at most 0.6. Both classifications flag every such point and give it PCF over the same
    footprint (the flagged points' visibility equals ``pcf`` grid/bilinear 5×5 to fp32);
    threshold flags fewer points than z-max (measured: 208 failures; threshold 1801 flagged,
    z-max 2289)."""
    scene, frame = _inline(STEP)
    gb = frame.gbuffer
    ng = np.asarray(gb.ng.numpy()).T.reshape(gb.height, gb.width, 3)
    top = (gb.shape_id[..., 0] == scene.shape_names.index("platform")) & gb.mask[..., 0] & (ng[..., 1] > 0.9)
    n = 5
    hard = vis(frame, "sun", "hard")
    pcf = vis(frame, "sun", "pcf", kernel=n, bilinear=True)
    none = get("esm").render(frame, {"kernel": n})
    e0 = frame.image(none.visibility["sun"])
    assert "fallback" not in none.stats
    assert top.sum() > 1000 and (hard[top] < 0.5).mean() > 0.99
    fail = top & (hard < 0.5) & (e0 > 0.99) & (pcf < 0.6)
    assert fail.sum() > 100, fail.sum()
    flagged = {}
    for mode in ("threshold", "zmax"):
        r = get("esm").render(frame, {"kernel": n, "fallback": mode})
        v = frame.image(r.visibility["sun"])
        m = r.aovs["sun.fallback"] > 0.5
        flagged[mode] = int(m.sum())
        assert r.stats["fallback"]["sun"] == flagged[mode]
        assert m[fail].all(), (mode, int((fail & ~m).sum()))
        assert np.abs(v - pcf)[m].max() < 1e-6
        assert np.array_equal(v[~m], e0[~m])                              # the rest is plain ESM
        assert np.abs(v - hard)[fail].mean() < 0.35 < 0.9 < np.abs(e0 - hard)[fail].mean()
    assert flagged["threshold"] < flagged["zmax"]


def test_exponent_above_the_fp32_cap_raises_input_error(frame_of):
    """exp(c·z) for z ≤ 1 must stay below FLT_MAX ≈ 3.4·10³⁸ = exp(88.72) (§3.4); EVSM stores
    exp(2k·w), w ≤ 1, so k ≤ 44.36 (§3.5). Above: InputError naming fp32; at the cap: finite."""
    for tech, name, bad in (("esm", "exponent", 88.73), ("esm", "exponent", "100"),
                            ("evsm", "exp_pos", 44.37), ("evsm", "exp_neg", 60.0)):
        with pytest.raises(InputError, match="fp32"):
            get(tech).resolve({name: bad})
    _, frame = _builtin(frame_of, "contact", resolution=(32, 32))
    for tech, p in (("esm", {"exponent": 88.72}), ("evsm", {"exp_pos": 44.36, "exp_neg": 44.36})):
        v = vis(frame, "key", tech, **p)
        assert np.isfinite(v).all() and v.min() >= 0.0 and v.max() <= 1.0 and v.min() < 0.01


# ---------------------------------------------------------------------------------------------
# EVSM: §3.5

def test_evsm_leaks_less_than_vsm_on_bench(frame_of):
    """Slika 3.10 compares VSM, ESM and EVSM at a 3×3 filter. On ``bench`` the legs under the
    seat are umbra in the truth; in the light's view they lie just inside the seat's outline, so
    their footprints hold the seat (closer) and the floor past its edge (farther), and VSM's
    Chebyshev bound shows them lit. Leak rate (truth ≤ 0.02 shown > 0.5), measured at 3×3:
    VSM 3.6 %, EVSM (4 components) 1.6 %, PCF 0 (MSM 0.7 %, ESM 8.4 %, EVSM with 2 components
    8.4 %; at 5×5 VSM 6.7 %, EVSM 5.1 %). EVSM's visibility is the minimum of its two bounds, so
    the 4-component variant is never above the 2-component one."""
    from shadowlab import pipeline
    from shadowlab.reference import store
    scene, frame = _builtin(frame_of, "bench")
    truth, _ = store.load(scene.spec)
    rate = {}
    for tech, p in (("vsm", {}), ("evsm", {}), ("pcf", {"bilinear": True})):
        r = get(tech).render(frame, {"kernel": 3, **p})
        rate[tech] = pipeline.technique_metrics(frame, truth, r)[0]["leak_rate"]
    assert rate["vsm"] > 0.03, rate
    assert rate["evsm"] < 0.6 * rate["vsm"], rate
    assert rate["pcf"] < rate["evsm"], rate
    v4 = vis(frame, "key", "evsm", kernel=3)
    v2 = vis(frame, "key", "evsm", kernel=3, components=2)
    assert (v4 <= v2).all()


# ---------------------------------------------------------------------------------------------
# properties of all four

def test_zero_filter_size_reduces_to_the_hard_shadow_map(frame_of):
    """``kernel`` = 1: no blur, only the bilinear lookup of the moments. Thresholded at ½ the
    result is the nearest-texel shadow map except where the 2×2 lookup straddles an edge (and
    where the estimate differs there): measured on ``contact`` 0.27–0.31 % of the pixels, on the
    cube-mapped point light of ``ring`` 0.3–0.6 %; bound 1.5 %."""
    for frame, light in ((_builtin(frame_of, "contact")[1], "key"), (_inline(RING)[1], "p")):
        mask = frame.gbuffer.mask[..., 0] & frame.lit_mask(light)
        hard = vis(frame, light, "hard")
        for tech in MOMENT:
            v = vis(frame, light, tech, kernel=1)
            differ = ((v >= 0.5) != (hard >= 0.5)) & mask
            assert differ.sum() / mask.sum() < 0.015, (light, tech, differ.sum() / mask.sum())
            assert np.abs(v - hard)[mask].mean() < 0.015, (light, tech)


CASES = [("vsm", {}), ("vsm", {"kernel": 4, "filter": "gaussian", "bleed": 0.3}),
         ("esm", {}), ("esm", {"kernel": 5, "fallback": "zmax"}), ("esm", {"kernel": 7, "fallback": "threshold"}),
         ("evsm", {}), ("evsm", {"components": 2, "kernel": 6}), ("msm", {}), ("msm", {"kernel": 5, "bleed": 0.2})]


def test_same_bits_unit_interval_and_invalid_or_outside_points_lit(mitsuba_backend):
    """Same inputs, same bits; every value in [0, 1] (no NaN); points without a surface or
    outside the spot light's camera get 1."""
    scene, frame = _inline(SPOT)
    gb = frame.gbuffer
    view = frame.light_view("s")
    inside = gb.to_image(view.lookup(gb.p)["inside"]) > 0.5
    dead = ~gb.mask[..., 0] | ~inside
    assert dead.sum() > 500 and (~dead).sum() > 300
    for tech, p in CASES:
        a = get(tech).render(frame, p).visibility["s"].numpy()
        b = get(tech).render(frame, p).visibility["s"].numpy()
        assert np.array_equal(a, b), (tech, p)
        img = gb.to_image(a)
        assert np.isfinite(img).all() and img.min() >= 0.0 and img.max() <= 1.0, (tech, p)
        assert (img[dead] == 1.0).all(), (tech, p)
        assert img[~dead].min() < 0.1, (tech, p)                           # the box does cast a shadow


def test_a_new_continuous_value_compiles_no_new_kernel(mitsuba_backend):
    """Continuous parameters enter through dr.opaque: after one render per configuration, new
    values of every continuous parameter (and the receiver biases) reuse the kernels."""
    import drjit as dr
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    frame = make_frame(load("contact", resolution=(32, 32)), u_strata=1)  # its own: nothing rendered on it yet
    later = {"vsm": [{"min_variance": 3e-5, "bleed": 0.4, "constant_bias": 0.01, "slope_bias": 0.02}],
             "esm": [{"exponent": 55.5, "max_slope_bias": 0.2, "normal_offset": 1.5}],
             "esm_fb": [{"exponent": 70.0, "threshold_eps": 0.5, "depth_bias": 100, "slope_scaled_depth_bias": 1.0}],
             "evsm": [{"exp_pos": 31.0, "exp_neg": 12.0, "min_variance": 1e-4, "bleed": 0.1}],
             "msm": [{"moment_bias": 1e-3, "msm_depth_bias": 0.01, "bleed": 0.5}]}
    first = {"vsm": {}, "esm": {}, "esm_fb": {"fallback": "threshold"}, "evsm": {}, "msm": {}}
    for key, p0 in first.items():
        tech = get(key.split("_")[0])
        tech.render(frame, p0)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history_clear()
            for p in later[key]:
                tech.render(frame, {**p0, **p})
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        assert jit, key
        assert all(k["cache_hit"] for k in jit), (key, [k.get("cache_hit") for k in jit])


def test_gradients_match_finite_differences(planes, frame_of):
    """Differentiable parameters may be passed as an mi.Float with gradients enabled; the
    gradient of the mean visibility on ``parallel_planes`` (64², 128² map, 5×5) matches central
    differences (measured: esm.exponent AD −1.203·10⁻³, FD −1.192·10⁻³; vsm.bleed −0.10525 both).
    Every declared differentiable parameter gets a finite gradient."""
    import drjit as dr
    import mitsuba as mi
    _, frame = _builtin(frame_of, "parallel_planes", resolution=(64, 64))

    def loss(tech, name, x):
        v = get(tech).render(frame, {"kernel": 5, "resolution": 128, name: x}).visibility["panel"]
        return v

    for tech, name, x0, h in (("esm", "exponent", 20.0, 0.05), ("vsm", "bleed", 0.1, 0.01)):
        x = mi.Float(x0)
        dr.enable_grad(x)
        dr.backward(dr.mean(loss(tech, name, x)))
        g = float(dr.grad(x)[0])
        fd = (loss(tech, name, x0 + h).numpy().astype(np.float64).mean()
              - loss(tech, name, x0 - h).numpy().astype(np.float64).mean()) / (2 * h)
        assert g == pytest.approx(fd, rel=0.05), (tech, name, g, fd)
        assert abs(g) > 1e-4
    for tech in MOMENT:
        t = get(tech)
        for p in t.params:
            if p.differentiable:
                x = mi.Float(float(p.default) if p.default else 0.5 * float(p.hi))
                dr.enable_grad(x)
                dr.backward(dr.mean(get(tech).render(frame, {p.name: x, "resolution": 128}).visibility["panel"]))
                assert np.isfinite(dr.grad(x)[0]), (tech, p.name)
        with pytest.raises(InputError, match="differentiable"):
            t.resolve({"kernel": mi.Float(3.0)})


def test_every_technique_declares_kernel_resolution_and_shared_bias_params(frame_of):
    """The benchmark sweeps ``kernel`` and sets ``resolution`` 512/1024/2048; the receiver biases
    are the very declarations of shadow_map.BIAS_PARAMS (not copies)."""
    from shadowlab.techniques.shadow_map import BIAS_PARAMS
    shared = {p.name: p for p in BIAS_PARAMS}
    _, frame = _builtin(frame_of, "contact", resolution=(16, 16))
    for tech in MOMENT:
        t = get(tech)
        names = [p.name for p in t.params]
        assert "kernel" in names and "resolution" in names
        for p in t.params:
            if p.name in shared:
                assert p is shared[p.name], (tech, p.name)
        for res in (512, 1024, 2048):
            assert t.resolve({"resolution": res, "kernel": 7})["resolution"] == res
        r = t.render(frame, {"resolution": 1024, "kernel": 2})
        assert r.stats["resolution"]["key"] == 1024
        assert r.stats["moment_bytes"]["key"] == 1024 * 1024 * 4 * r.stats["moment_channels"]
