"""``pcss`` ([Buljan 2020, §3.6]): blocker search, penumbra estimate, variable-width PCF.

Main scene: the built-in ``parallel_planes`` with its committed 128² reference — a square light of
side 1 at height 4, a half-plane occluder x < 0 at height 2 and the floor at 0, all parallel (PCSS's
own assumption): the true penumbra on the floor is x ∈ [−0.5, 0.5], a linear ramp whose visible
area fraction has a closed form (``parallel_planes_fraction``); PCSS predicts
w_penumbra = (4 − 2)/2 · 1 = 1, i.e. a 10–90 % width of 0.8. Measured (1024² map, defaults):
penumbra RMSE of the shaded image 0.0092 (hard 0.397, pcf 0.341), 10–90 % width 0.801.
"""

import math

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.reference.closed_form import parallel_planes_fraction
from shadowlab.techniques import get
from shadowlab.techniques import blocker_search as search_mod

LIGHT = "panel"
H_LIGHT, H_OCC = 4.0, 2.0


def _build(spec, u_strata=1):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build, parse
    return make_frame(build(parse(spec, f"{spec['name']}.toml")), u_strata=u_strata)


@pytest.fixture(scope="module")
def planes(mitsuba_backend):
    from shadowlab.reference import store
    from shadowlab.render.frame import make_frame
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.scene import load
    scene = load("parallel_planes")
    truth, _ = store.load(scene.spec)
    frame = make_frame(scene)
    gb = frame.gbuffer
    x = gb.to_image(vec_numpy(gb.p))[..., 0]
    floor = (gb.shape_id[..., 0] == scene.shape_names.index("floor")) & gb.mask[..., 0]
    return frame, truth, x, floor


def _vis(frame, light=LIGHT, **params):
    return frame.gbuffer.to_image(get("pcss").render(frame, params).visibility[light])


def _width(x, v, sel):
    """10–90 % width of a linear ramp v(x): 0.8 / slope of a line fitted where 0.2 < v < 0.8."""
    s = sel & (v > 0.2) & (v < 0.8)
    assert s.sum() > 20, "too few penumbra pixels to fit the ramp"
    slope, _ = np.polyfit(x[s], v[s], 1)
    return 0.8 / slope


# ---------------------------------------------------------------------------------------------
# against the ground truth and the closed form

def test_matches_the_truth_in_the_penumbra_and_beats_hard_and_pcf(planes):
    from shadowlab.pipeline import technique_metrics
    frame, truth, _, _ = planes
    m = {n: technique_metrics(frame, truth, get(n).render(frame, {}))[0] for n in ("pcss", "hard", "pcf")}
    # measured: shaded 0.0092, visibility 0.0067; hard 0.397, pcf (3×3) 0.341
    assert m["pcss"]["rmse_penumbra"] < 0.015, m["pcss"]["rmse_penumbra"]
    assert m["pcss"]["vis_rmse_penumbra"] < 0.012, m["pcss"]["vis_rmse_penumbra"]
    assert m["pcss"]["rmse_penumbra"] < 0.1 * m["hard"]["rmse_penumbra"]
    assert m["pcss"]["rmse_penumbra"] < 0.1 * m["pcf"]["rmse_penumbra"]
    assert m["pcss"]["leak_rate"] == 0.0 and m["pcss"]["overdark_rate"] == 0.0


def test_penumbra_width_agrees_with_the_w_penumbra_prediction(planes):
    frame, truth, x, floor = planes
    r = get("pcss").render(frame, {})
    v = frame.image(r.visibility[LIGHT])
    closed = parallel_planes_fraction(x, H_LIGHT, H_OCC, 1.0)
    pen = floor & (closed > 0.02) & (closed < 0.98)
    # the AOVs: z_avg = the occluder's depth 2, w_penumbra = (4 − 2)/2 · 1 = 1 everywhere in the penumbra
    assert np.allclose(r.aovs[f"{LIGHT}.blocker_depth"][pen], H_OCC, rtol=1e-3)
    predicted = r.aovs[f"{LIGHT}.penumbra_width"][pen]
    assert np.allclose(predicted, (H_LIGHT - H_OCC) / H_OCC * 1.0, rtol=1e-3)
    # a box filter of full width w over a straight edge: linear ramp, 10–90 % width 0.8·w (measured 0.801)
    w = _width(x, v, floor)
    assert w == pytest.approx(0.8 * float(np.median(predicted)), rel=0.02)
    assert w == pytest.approx(_width(x, truth.lights[LIGHT].V, floor), rel=0.06)  # truth fit: 0.777
    # the ramp is centred under the edge: v = ½ at x = 0 within a pixel's footprint
    s = floor & (np.abs(x) < 0.03)
    assert np.all(np.abs(v[s] - (0.5 + x[s])) < 0.02)


def test_blocker_search_width_is_the_closed_form_from_the_scene_numbers(planes):
    """Step 1, w_search = (z̃ − z_near)/z̃ · w_light in near-plane units, N/(2·z_near·tan) texels
    per near-plane unit. ``parallel_planes`` by hand: light at height 4 looking down, its side 1;
    its camera's near plane is half the 2 m gap to the nearest geometry (the occluder's top):
    z_near = 1; tan(half fov) = 1.02 × 10/2 = 5.1 (the occluder's far corner, x = −10 at depth 2,
    plus the fit's 2 % margin); N = 1024. The floor (z̃ = 4): 3/4 · 1024/10.2 = 75.294 texels;
    the occluder's top (z̃ = 2): 1/2 · 1024/10.2 = 50.196; both scale with ``light_scale``."""
    frame, _, _, floor = planes
    scene = frame.scene
    gb = frame.gbuffer
    occ = (gb.shape_id[..., 0] == scene.shape_names.index("occluder")) & gb.mask[..., 0]
    f0 = frame.light_view(LIGHT).proj.faces[0]
    near, tan, N = 1.0, 5.1, 1024
    assert (f0.near, f0.scale, frame.light_view(LIGHT).res) == (pytest.approx(near, rel=1e-6),
                                                              pytest.approx(tan, rel=1e-6), N)
    assert floor.sum() > 1000 and occ.sum() > 1000
    # (z̃ − z_near)/z̃ · w_light · N/(2·z_near·tan) at w_light = 1: floor 3/4 · 1024/10.2, occluder 1/2 · 1024/10.2
    at_one = {H_LIGHT: 75.29411764705883, H_LIGHT - H_OCC: 50.19607843137255}
    for z, w in at_one.items():
        assert (z - near) / z * N / (2.0 * near * tan) == pytest.approx(w, rel=1e-12)
    for scale in (1.0, 0.6):
        r = get("pcss").render(frame, {"light_scale": scale, "blocker_samples": 16, "pcf_samples": 1})
        st = r.aovs[f"{LIGHT}.search_texels"]
        for sel, z in ((floor, H_LIGHT), (occ, H_LIGHT - H_OCC)):
            want = scale * at_one[z]
            assert np.allclose(st[sel], want, rtol=2e-5), (scale, z, st[sel].min(), st[sel].max(), want)


def test_orthographic_blocker_search_width_is_the_closed_form(sun_edge):
    """Directional light: w_search = (z̃ − z_near)·tan(w_light) world units, 2·half_extent/N per
    texel. ``sun_edge`` by hand: the non-emitting geometry's box is [−4, 2] × [0, 1] × [−2, 2],
    centre (−1, ½, 0), radius R = √(3² + ½² + 2²) = √13.25; the light camera sits 2R above the
    centre looking down, z_near = R, half extent R; the floor's depth z̃ = ½ + 2R, so
    w_search = (½ + R)·tan(√π/2·4°)·1024/(2R) = 36.075 texels (the camera sees only the floor)."""
    frame = sun_edge
    R = math.sqrt(13.25)
    f0 = frame.light_view("sun").proj.faces[0]
    assert f0.ortho and f0.near == pytest.approx(R, rel=1e-6) and f0.scale == pytest.approx(R, rel=1e-6)
    assert f0.origin[1] == pytest.approx(0.5 + 2 * R, rel=1e-6)
    w_light = math.sqrt(math.pi) / 2 * math.radians(SUN_THETA)
    want = (0.5 + R) * math.tan(w_light) * 1024 / (2 * R)
    assert want == pytest.approx(36.0749, abs=1e-4)
    m = frame.gbuffer.mask[..., 0]
    assert m.sum() > 1000
    r = get("pcss").render(frame, {"blocker_samples": 16, "pcf_samples": 1})
    st = r.aovs["sun.search_texels"]
    assert np.allclose(st[m], want, rtol=2e-5), (st[m].min(), st[m].max(), want)


@pytest.mark.parametrize("size", [0.5, 1.0, 1.5])
def test_widths_grow_linearly_with_light_size_like_the_closed_form(planes, size):
    frame, _, x, floor = planes
    v = _vis(frame, light_scale=size)
    closed = parallel_planes_fraction(x, H_LIGHT, H_OCC, size)
    pen = floor & (closed > 0.02) & (closed < 0.98)
    # measured widths 0.400 / 0.801 / 1.200, RMSE against the closed form 8e-5 / 4e-4 / 6e-4
    assert _width(x, v, floor) == pytest.approx(0.8 * size, rel=0.02)
    assert np.sqrt(np.mean((v - closed)[pen] ** 2)) < 0.005
    assert np.all(v[floor & (closed == 0.0)] < 0.01) and np.all(v[floor & (closed == 1.0)] > 0.99)


def test_zero_light_size_reduces_to_the_hard_shadow_map(planes, mitsuba_backend):
    """light_scale → 0 (w_light → 0; the lights' sides are 1) leaves a hard shadow filtered by
    ``min_filter`` (one texel); with one PCF tap and no minimum it is one 2×2 bilinear tap.
    Measured: parallel_planes 0.78 % of the pixels differ (none by > 0.5), 0 with one tap;
    contact 1.2 % / 0.94 % differ, 0.07 % / 0.05 % by more than 0.5."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    contact = make_frame(load("contact"), u_strata=1)
    for frame, light in ((planes[0], LIGHT), (contact, "key")):
        hard = frame.image(get("hard").render(frame, {}).visibility[light])
        for p in ({"light_scale": 1e-6}, {"light_scale": 1e-6, "pcf_samples": 1, "min_filter": 0.0}):
            d = np.abs(_vis(frame, light, **p) - hard)
            assert np.mean(d > 1e-6) < 0.02, (light, p, np.mean(d > 1e-6))
            assert np.mean(d > 0.5) < 0.002, (light, p, np.mean(d > 0.5))
    frame = planes[0]
    d = np.abs(_vis(frame, light_scale=1e-6, pcf_samples=1, min_filter=0.0)
               - frame.image(get("hard").render(frame, {}).visibility[LIGHT]))
    assert d.max() < 1e-6


#: sun of angular diameter SUN_THETA° straight overhead, half-plane occluder (x ∈ [−4, 0],
#: z ∈ [−2, 2]) at height SUN_H over a 4 × 4 floor, camera at height 0.5 looking straight down
SUN_THETA, SUN_H = 4.0, 1.0
SUN_EDGE = {
    "name": "sun_edge",
    "camera": {"position": [0.0, 0.5, 0.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, 1], "fov": 30,
               "resolution": [64, 64]},
    "lights": [{"name": "sun", "kind": "directional", "direction": [0, -1, 0], "angular_diameter": SUN_THETA,
                "irradiance": 3.0, "shadow_map": 1024}],
    "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 2.0},
               {"name": "occluder", "type": "rectangle", "translate": [-2.0, SUN_H, 0.0], "rotate": [1, 0, 0, 90],
                "scale": 2.0}]}


@pytest.fixture(scope="module")
def sun_edge(mitsuba_backend):
    return _build(SUN_EDGE)


def test_directional_light_penumbra_is_depth_difference_times_tan_light_size(sun_edge):
    """Sun of angular diameter 4° straight overhead, half-plane occluder at height 1, camera
    looking straight down: w_penumbra = 1·tan(√π/2·θ) = 0.0620, 10–90 % width 0.0496 (measured
    0.04957; the disk's true 10–90 % width is 0.0480), RMSE against the disk closed form 0.020."""
    theta, h = SUN_THETA, SUN_H
    frame = sun_edge
    from shadowlab.render.gbuffer import vec_numpy
    gb = frame.gbuffer
    x = gb.to_image(vec_numpy(gb.p))[..., 0]
    r = get("pcss").render(frame, {})
    v = gb.to_image(r.visibility["sun"])
    size = math.sqrt(math.pi) / 2 * math.radians(theta)
    assert r.stats["light_size"]["sun"] == pytest.approx(size, rel=1e-6)
    pw = r.aovs["sun.penumbra_width"]
    assert np.allclose(pw[pw > 0], h * math.tan(size), rtol=0.01)
    assert _width(x, v, gb.mask[..., 0]) == pytest.approx(0.8 * h * math.tan(size), rel=0.03)
    s = np.clip(x / (h * math.tan(math.radians(theta / 2))), -1, 1)
    disk = 0.5 + (s * np.sqrt(1 - s * s) + np.arcsin(s)) / math.pi
    assert np.sqrt(np.mean((v - disk) ** 2)) < 0.03


def test_receiver_plane_removes_self_blocking_of_a_tilted_receiver(mitsuba_backend):
    """A floor alone, tilted in the light's view: the source's test finds the floor itself as a
    blocker (measured: 37 % of the pixels below 0.99, min 0.79); the receiver-plane test none."""
    frame = _build({
        "name": "tilt",
        "camera": {"position": [0.0, 3.0, 4.0], "target": [0.0, 0.0, 0.0], "fov": 50, "resolution": [64, 64]},
        "lights": [{"name": "key", "kind": "rect", "position": [1.5, 3.0, 1.0], "target": [0, 0, 0],
                    "size": [1.0, 1.0], "power": 100, "shadow_map": 512}],
        "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0}]})
    m = frame.gbuffer.mask[..., 0]
    assert np.mean(_vis(frame, "key", receiver_plane=False)[m] < 0.99) > 0.1
    assert np.all(_vis(frame, "key", receiver_plane=True)[m] > 0.999)
    assert np.all(_vis(frame, "key")[m] > 0.999), "the default is the receiver-plane test"


def test_receiver_plane_leaves_parallel_planes_unchanged(planes):
    frame = planes[0]
    assert np.abs(_vis(frame, receiver_plane=True) - _vis(frame, receiver_plane=False)).max() < 1e-5


# ---------------------------------------------------------------------------------------------
# light size: mapping and gradient

def test_light_size_mapping_from_the_scene(planes):
    """w_light at ``light_scale`` 1 = the side of the light's equal-area square (the module
    docstring's table): rect w × h → √(w·h); disk, spot, sphere, point of radius r → √(π r²) =
    √π·r; directional of angular diameter θ → √(π (θ/2)²) = √π/2·θ (radians). The expected values
    are worked out by hand from the scene keys (√π = 1.7724538509055159), not from the module."""
    from shadowlab.scene.spec import LightSpec
    cases = [(LightSpec("a", "rect", size=(2.0, 0.5)), 1.0),                      # √(2·0.5) = √1
             (LightSpec("a2", "rect", size=(3.0, 1.2)), 1.8973665961010275),      # √3.6
             (LightSpec("b", "disk", radius=0.5), 0.8862269254527579),            # √π·0.5
             (LightSpec("c", "sphere", radius=0.2), 0.3544907701811032),          # √π·0.2
             (LightSpec("d", "spot", radius=0.1), 0.1772453850905516),            # √π·0.1
             (LightSpec("e", "point", radius=0.3), 0.5317361552716547),           # √π·0.3
             (LightSpec("e0", "point", radius=0.0), 0.0),                         # delta light
             (LightSpec("f", "directional", angular_diameter=0.53), 0.008197816217557791),  # √π/2·0.53°·π/180
             (LightSpec("f2", "directional", angular_diameter=2.0), 0.03093515553795393)]   # √π/2·2°·π/180
    for light, expected in cases:
        assert search_mod.scene_light_size(light) == pytest.approx(expected, rel=1e-12), light.name
    # the equal-area property itself: w_light² = the light's area (solid angle for the sun, small angle)
    assert search_mod.scene_light_size(LightSpec("g", "disk", radius=0.7)) ** 2 == pytest.approx(math.pi * 0.7 ** 2)
    r = get("pcss").render(planes[0], {})
    assert r.stats["light_size"][LIGHT] == 1.0
    assert get("pcss").render(planes[0], {"light_scale": 0.7}).stats["light_size"][LIGHT] == pytest.approx(0.7)


def test_light_scale_gradient_matches_central_differences(planes):
    import drjit as dr
    import mitsuba as mi
    frame, truth, _, _ = planes
    target = mi.Float(truth.lights[LIGHT].V.reshape(-1).astype(np.float32))
    p = {"blocker_samples": 16, "pcf_samples": 16}

    def loss(size):
        v = get("pcss").render(frame, {**p, "light_scale": size}).visibility[LIGHT]
        return dr.mean(dr.square(v - target))

    assert get("pcss").param("light_scale").differentiable
    for s0, sign in ((0.7, -1.0), (1.3, 1.0)):
        ls = mi.Float(s0)
        dr.enable_grad(ls)
        dr.backward(loss(ls))
        g = float(dr.grad(ls)[0])
        h = 0.01
        fd = (float(loss(s0 + h)[0]) - float(loss(s0 - h)[0])) / (2 * h)
        # measured: 0.7: AD −0.00840, FD −0.00830; 1.3: AD 0.00403, FD 0.00440
        assert g * sign > 0 and fd * sign > 0
        assert g == pytest.approx(fd, rel=0.15), (s0, g, fd)


# ---------------------------------------------------------------------------------------------
# compilation, determinism, range, AOVs, validation

def test_new_light_scale_or_continuous_value_compiles_no_new_kernel(planes):
    import drjit as dr
    frame = planes[0]
    t = get("pcss")
    t.render(frame, {})                                               # compile (or load) once
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        for p in ({"light_scale": 0.7}, {"light_scale": 1.3, "min_filter": 2.5},
                  {"light_scale": 0.4, "depth_bias": 3, "slope_scaled_depth_bias": 1.0, "constant_bias": 0.01}):
            t.render(frame, p)
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert jit, "the render launched no kernel"
    assert all(k["cache_hit"] for k in jit), [k.get("cache_hit") for k in jit]


def test_same_inputs_same_bits_and_results_in_unit_interval(planes):
    frame = planes[0]
    for p in ({}, {"light_scale": 1.7, "blocker_samples": 16, "pcf_samples": 32},
              {"receiver_plane": True, "blocker_samples": 25, "pcf_samples": 1, "min_filter": 4.0}):
        a = get("pcss").render(frame, p)
        b = get("pcss").render(frame, p)
        va, vb = a.visibility[LIGHT].numpy(), b.visibility[LIGHT].numpy()
        assert np.array_equal(va, vb)
        for k in a.aovs:
            assert np.array_equal(a.aovs[k], b.aovs[k]), k
        assert np.all(np.isfinite(va)) and va.min() >= 0.0 and va.max() <= 1.0


def test_aovs_and_stats(planes):
    frame = planes[0]
    r = get("pcss").render(frame, {"blocker_samples": 25, "pcf_samples": 32})
    for k in ("penumbra_width", "penumbra_texels", "filter_texels", "blocker_depth", "blocker_count",
              "search_texels"):
        a = r.aovs[f"{LIGHT}.{k}"]
        assert a.shape == (128, 128) and np.all(np.isfinite(a)) and a.min() >= 0.0
    cnt = r.aovs[f"{LIGHT}.blocker_count"]
    assert cnt.max() <= 25 + 1e-4
    assert np.all(r.aovs[f"{LIGHT}.filter_texels"][cnt > 0] >= 1.0)              # min_filter
    spp = r.stats["samples_per_pixel"]
    assert 25 <= spp[LIGHT] <= 25 + 32 and spp["all"] == spp[LIGHT]
    assert r.stats["blocker_samples"] == 25 and r.stats["pcf_samples"] == 32


def test_sampling_patterns():
    for n, pts in search_mod.SEARCH_SETS.items():
        assert pts.shape == (n, 2) and np.all(np.abs(pts) <= 0.5 + 1e-12)
        assert np.allclose(pts.mean(0), 0.0, atol=1e-12)
        d = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)) + np.eye(n)
        assert d.min() > 0.35 / math.sqrt(n)                              # well spread
    for n in search_mod.PCF_COUNTS:
        p = search_mod.pcf_pattern(n)
        assert p.shape == (n, 2) and np.allclose(p.mean(0), 0.0) and np.all(np.abs(p) < 0.5)
        if n > 1:                                                      # one tap per row and column
            assert len(np.unique(np.round(p[:, 0] * n, 6))) == n and len(np.unique(np.round(p[:, 1] * n, 6))) == n
    assert np.array_equal(search_mod.best_candidate(16), search_mod.SEARCH_SETS[16])  # deterministic


def test_invalid_parameters_are_refused(mitsuba_backend):
    import mitsuba as mi
    t = get("pcss")
    with pytest.raises(InputError):
        t.resolve({"blocker_samples": 20})
    with pytest.raises(InputError):
        t.resolve({"pcf_samples": 8})
    with pytest.raises(InputError):
        t.resolve({"light_scale": -1.0})
    with pytest.raises(InputError):
        t.resolve({"min_filter": mi.Float(2.0)})                       # not differentiable
    with pytest.raises(InputError):
        t.resolve({"light_scale": mi.Float([1.0, 2.0])})
    ls = mi.Float(0.5)
    assert t.resolve({"light_scale": ls})["light_scale"] is ls
