"""``hard`` (plain shadow map with the bias variants of [Buljan 2020, §2.3]) and ``pcf`` ([Buljan 2020, §3.2]).

The truth is exact point-light visibility: a Mitsuba shadow ray from every G-buffer point to the
light. The scene: floor, box and sphere under a ``point`` light (a 6-face cube map, 512² per
face), 128² pixels. The floor is tilted by 0.05° so that its light-space depth sweeps many
16-bit depth steps across the face under the light (a level floor there has one depth, and
whether that one value rounds up or down would decide the 16-bit test).
"""

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.metrics import leak_rate, overdark_rate
from shadowlab.techniques import get

SCENE = {
    "name": "point_contact",
    "camera": {"position": [0.0, 3.2, 6.0], "target": [0.0, 0.4, 0.0], "fov": 45, "resolution": [128, 128]},
    "lights": [{"name": "p", "kind": "point", "position": [1.0, 3.5, 1.5], "power": 100.0, "shadow_map": 512}],
    "shapes": [
        {"name": "floor", "type": "rectangle", "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "scale": 4.0},
        {"name": "box", "type": "cube", "translate": [-0.9, 0.5, 0.2], "rotate": [0, 1, 0, 25], "scale": 0.5},
        {"name": "ball", "type": "sphere", "center": [0.8, 0.6, 0.6], "radius": 0.6},
    ],
}
ZERO_BIAS = {"depth_bias": 0, "slope_scaled_depth_bias": 0.0, "constant_bias": 0.0, "slope_bias": 0.0,
             "normal_offset": 0.0}


@pytest.fixture(scope="module")
def setup(mitsuba_backend):
    import drjit as dr
    import mitsuba as mi
    from scene_builder import frame_from

    frame = frame_from(SCENE, "point_contact.toml")
    scene = frame.scene
    gb = frame.gbuffer
    light = mi.Point3f(*SCENE["lights"][0]["position"])
    occluded = scene.mi_scene.ray_test(gb.si.spawn_ray_to(light), gb.valid)
    truth = gb.to_image(dr.select(occluded, 0.0, 1.0))
    # pixels a point light illuminates at all (n·l > 0): elsewhere visibility is multiplied by 0
    facing = gb.to_image(dr.select(gb.valid & (dr.dot(gb.ng, light - gb.p) > 0), 1.0, 0.0)) > 0.5
    return frame, truth, facing


def image(frame, result):
    return frame.gbuffer.to_image(result.visibility["p"])


def render(frame, tech, **params):
    return image(frame, get(tech).render(frame, params))


# ---------------------------------------------------------------------------------------------
# hard shadows against exact point-light visibility

def test_hard_equals_exact_point_light_visibility_up_to_edge_aliasing(setup):
    """Measured: 0.6 % of the valid pixels differ, 0.1 % of those facing the light (shadow-edge
    aliasing at 512² per cube face; the rest are points just past the terminator)."""
    frame, truth, facing = setup
    res = get("hard").render(frame, {})
    vis = image(frame, res)
    valid = frame.gbuffer.mask[..., 0]
    assert set(np.unique(vis[valid])) <= {0.0, 1.0}
    assert np.all(vis[~valid] == 1.0)
    assert np.mean((vis != truth)[valid]) < 0.02
    assert np.mean((vis != truth)[facing]) < 0.005
    assert 0 < np.count_nonzero(truth[facing] == 0)  # the scene does have shadows to get right
    assert res.stats["shadow_map_texels"] == 6 * 512 * 512
    assert res.stats["resolution"] == {"p": 512} and res.stats["depth_bits"] == {"p": 32}
    assert res.aovs["p.texel"].shape == (128, 128)
    assert np.all(res.aovs["p.texel"][valid] > 0)


def test_bias_sweep_acne_then_peter_panning(setup):
    """Measured: zero bias 54 % acne (over-darkened lit pixels); defaults 0.04 % acne and 1.1 %
    leaks; a constant bias of 1 world unit lets 42 % of the umbra leak (Peter Panning)."""
    frame, truth, facing = setup
    zero = render(frame, "hard", **ZERO_BIAS)
    good = render(frame, "hard")
    huge = render(frame, "hard", **{**ZERO_BIAS, "constant_bias": 1.0})
    assert overdark_rate(zero, truth, facing) > 0.10
    assert overdark_rate(good, truth, facing) < 0.005
    assert leak_rate(good, truth, facing) < 0.03
    assert leak_rate(huge, truth, facing) > 0.2
    assert leak_rate(huge, truth, facing) > 5 * leak_rate(good, truth, facing)
    assert overdark_rate(huge, truth, facing) <= overdark_rate(good, truth, facing)


def test_each_bias_variant_removes_most_acne(setup):
    frame, truth, facing = setup
    zero = overdark_rate(render(frame, "hard", **ZERO_BIAS), truth, facing)
    for extra in ({"slope_scaled_depth_bias": 2.0, "depth_bias": 16}, {"normal_offset": 1.0},
                  {"constant_bias": 0.05}, {"slope_bias": 0.01, "constant_bias": 0.002}, {"backface": True}):
        od = overdark_rate(render(frame, "hard", **{**ZERO_BIAS, **extra}), truth, facing)
        assert od < 0.1 * zero, (extra, od, zero)


def test_depth_bias_clamp_limits_the_rasterizer_bias(setup):
    frame, truth, facing = setup
    r = get("hard").render(frame, {"slope_scaled_depth_bias": 64.0, "depth_bias_clamp": 1e-4})
    b = r.aovs["p.depth_bias"]
    assert b.max() <= 1e-4 * (1 + 1e-6)
    neg = get("hard").render(frame, {"depth_bias": -1000, "slope_scaled_depth_bias": -1.0, "depth_bias_clamp": -1e-5})
    assert neg.aovs["p.depth_bias"].min() >= -1e-5 * (1 + 1e-6)


def test_rasterizer_bias_units_follow_direct3d(mitsuba_backend):
    """DepthBias·r: r = 2^(exponent(d) − 23) for fp32 (one ulp of d), 1/(2^bits − 1) for UNORM;
    plus SlopeScaledDepthBias·slope, then DepthBiasClamp."""
    import mitsuba as mi
    from types import SimpleNamespace
    from shadowlab.techniques.shadow_map import BIAS_PARAMS, opaque_bias, rasterizer_bias
    values = {p.name: p.default for p in BIAS_PARAMS}
    D = mi.Float([0.75, 0.3, 1.0, 0.0])
    S = mi.Float([0.0, 0.0, 0.0, 0.5])

    def bias(bits, **kw):
        return rasterizer_bias(SimpleNamespace(bits=bits), D, S, opaque_bias({**values, **kw})).numpy()

    assert np.array_equal(bias(32, depth_bias=1, slope_scaled_depth_bias=0.0), np.float32([2**-24, 2**-25, 2**-23, 0]))
    assert np.allclose(bias(16, depth_bias=3, slope_scaled_depth_bias=0.0), 3 / 65535, rtol=1e-6)
    assert np.allclose(bias(24, depth_bias=0, slope_scaled_depth_bias=2.0), [0, 0, 0, 1.0])
    assert np.allclose(bias(24, depth_bias=0, slope_scaled_depth_bias=2.0, depth_bias_clamp=0.25), [0, 0, 0, 0.25])
    assert np.allclose(bias(24, depth_bias=0, slope_scaled_depth_bias=-2.0, depth_bias_clamp=-0.25), [0, 0, 0, -0.25])
    assert np.allclose(bias(24, depth_bias=0, slope_scaled_depth_bias=-2.0, depth_bias_clamp=0.25), [0, 0, 0, -1.0])


def test_16_bit_depth_has_more_acne_than_32_bit_at_the_same_small_bias(setup):
    """Slope-scaled bias 1 covers the texel discretisation; 2e-5 world units cover float32
    rounding but not half a 16-bit step (≈ 7e-5 world units at the floor under the light).
    Measured: 16-bit 22 % of the lit pixels, 32-bit 0.06 %."""
    frame, truth, facing = setup
    small = {**ZERO_BIAS, "slope_scaled_depth_bias": 1.0, "constant_bias": 2e-5}
    od16 = overdark_rate(render(frame, "hard", depth_bits=16, **small), truth, facing)
    od32 = overdark_rate(render(frame, "hard", depth_bits=32, **small), truth, facing)
    assert od16 > 0.05 and od16 > 10 * od32, (od16, od32)


# ---------------------------------------------------------------------------------------------
# PCF

def test_pcf_kernel_1_is_hard_bit_for_bit(setup):
    frame, _, _ = setup
    for params in ({}, ZERO_BIAS, {"normal_offset": 1.5, "depth_bits": 16, "slope_bias": 0.01}):
        h = get("hard").render(frame, params).visibility["p"].numpy()
        p = get("pcf").render(frame, {**params, "kernel": 1, "softness": 3.0}).visibility["p"].numpy()
        assert np.array_equal(h, p)


SPOT_SCENE = {
    "name": "spot_sphere",
    "camera": {"position": [0.0, 3.2, 5.0], "target": [0.0, 0.3, 0.0], "fov": 40, "resolution": [128, 128]},
    "lights": [{"name": "s", "kind": "spot", "position": [0.0, 3.0, 0.0], "target": [0.0, 0.0, 0.0],
                "angle": 40.0, "power": 100.0, "shadow_map": 512}],
    "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0},
               {"name": "ball", "type": "sphere", "center": [0.3, 1.0, 0.2], "radius": 0.4}],
}


@pytest.fixture(scope="module")
def spot(mitsuba_backend):
    """A sphere floating over a level floor, a spot light straight above: the floor is
    perpendicular to the light's axis, so wide PCF kernels see no acne there (on tilted
    receivers they do, [Buljan 2020, §3.2]: PCF does not fix acne) and every fractional value on the
    floor is penumbra."""
    from scene_builder import frame_from
    frame = frame_from(SPOT_SCENE, "spot_sphere.toml")
    scene = frame.scene
    gb = frame.gbuffer
    floor = (gb.shape_id[..., 0] == scene.shape_names.index("floor")) & gb.mask[..., 0]
    return frame, floor


def test_pcf_is_fractional_only_near_shadow_edges_and_softness_widens_it(spot):
    """Measured on the floor, 5×5: 109 fractional pixels at softness 1, 326 at softness 3,
    all within 3 pixels of the hard shadow's edge."""
    from scipy.ndimage import binary_dilation
    frame, floor = spot
    gb = frame.gbuffer
    valid = gb.mask[..., 0]
    hard = gb.to_image(get("hard").render(frame, {}).visibility["s"])
    assert np.count_nonzero(floor & (hard == 0)) > 100
    vs = {s: gb.to_image(get("pcf").render(frame, {"kernel": 5, "softness": s}).visibility["s"])
          for s in (1.0, 3.0)}
    for v in vs.values():
        assert v.min() >= 0.0 and v.max() <= 1.0
        assert np.all(v[~valid] == 1.0)
        assert np.allclose(v * 25, np.round(v * 25), atol=1e-4)  # a 5×5 box: multiples of 1/25
    edge = np.zeros_like(floor)
    edge[:, 1:] |= hard[:, 1:] != hard[:, :-1]
    edge[1:, :] |= hard[1:, :] != hard[:-1, :]
    near = binary_dilation(edge, iterations=3)
    f1, f3 = [(v > 0) & (v < 1) & floor for v in (vs[1.0], vs[3.0])]
    assert f1.sum() > 50
    assert np.all(near[f1]) and np.all(near[f3])
    assert f3.sum() > 2 * f1.sum(), (f1.sum(), f3.sum())


def test_pcf_grid_reaches_further_with_a_larger_kernel(spot):
    frame, floor = spot
    gb = frame.gbuffer
    counts = [np.count_nonzero(floor & (v > 0) & (v < 1)) for v in
              (gb.to_image(get("pcf").render(frame, {"kernel": n}).visibility["s"]) for n in (3, 5, 7))]
    assert counts[0] < counts[1] < counts[2], counts


# ---------------------------------------------------------------------------------------------
# parameters

def test_declarations_are_shared_and_complete():
    from shadowlab.techniques import param_table_markdown
    from shadowlab.techniques.shadow_map import BIAS_PARAMS
    hard, pcf = get("hard"), get("pcf")
    assert hard.params == BIAS_PARAMS
    assert all(any(p is q for q in pcf.params) for p in BIAS_PARAMS)
    assert {"kernel", "softness"} <= {p.name for p in pcf.params}
    for p in pcf.params:
        assert (
            p.doc
            and p.source.startswith(
                "[Buljan 2020, §" if p.name not in ("receiver_plane", "grazing_slope_bias") else "[Isidoro 2006]"
            )
            and p.kind in ("float", "int", "bool", "choice")
        )
    table = param_table_markdown(pcf)
    assert "`slope_scaled_depth_bias`" in table and "`softness`" in table
    import shadowlab.techniques.pcf as pcf_module
    import shadowlab.techniques.shadow_map as sm_module
    for module in (pcf_module, sm_module):
        # the source is cited by its bibliography key (docs/references.md), no longer by file name
        assert "[Buljan 2020, §" in module.__doc__ and "`normal_offset`" in module.__doc__


@pytest.mark.parametrize("tech, params, names", [
    ("hard", {"bogus": 1}, ["depth_bias", "normal_offset", "backface"]),
    ("pcf", {"radius": 2}, ["kernel", "softness", "slope_scaled_depth_bias"]),
    ("pcf", {"kernel": 10}, ["1", "9"]),
    ("pcf", {"softness": 100.0}, ["0.25", "8"]),
    ("hard", {"depth_bits": 8}, ["16", "24", "32"]),
    ("hard", {"resolution": 32}, ["64", "8192"]),
    ("hard", {"resolution": 10000}, ["8192"]),
    ("hard", {"normal_offset": -1}, ["0", "8"]),
])
def test_bad_parameters_raise_input_error_naming_the_valid_ones(tech, params, names):
    with pytest.raises(InputError) as e:
        get(tech).resolve(params)
    for n in names:
        assert n in str(e.value)


def test_render_validates_parameters(setup):
    frame, _, _ = setup
    with pytest.raises(InputError, match="softness"):
        get("pcf").render(frame, {"sofness": 2.0})


def test_new_softness_or_bias_value_reuses_the_compiled_kernel(setup):
    import drjit as dr
    frame, _, _ = setup
    pcf = get("pcf")
    pcf.render(frame, {"kernel": 3, "softness": 1.0})          # compile (or load) once
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        pcf.render(frame, {"kernel": 3, "softness": 2.5, "depth_bias": 7, "constant_bias": 0.01,
                           "slope_scaled_depth_bias": 1.25, "normal_offset": 0.3, "depth_bias_clamp": 0.5})
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert jit, "the render launched no kernel"
    assert all(k["cache_hit"] for k in jit), [k.get("cache_hit") for k in jit]


def test_render_is_deterministic(setup):
    frame, _, _ = setup
    a = get("pcf").render(frame, {"kernel": 3}).visibility["p"].numpy()
    b = get("pcf").render(frame, {"kernel": 3}).visibility["p"].numpy()
    assert np.array_equal(a, b)
