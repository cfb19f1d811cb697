"""``pcf`` kernels of [Buljan 2020, §3.2]: grid, Gaussian, Poisson disk (16/32/64),
per-point rotated Poisson disk, and hardware-style 2×2 bilinear taps.

Scenes: ``edge`` — a half-plane occluder (x < 0, height 0.5) over a floor under a delta
directional light straight down (orthographic 64² map, map u axis = −x), seen obliquely through
a narrow camera so one shadow-map texel covers ~20 pixels; ``open`` — the same floor without the
occluder; the built-in ``parallel_planes`` with its committed 128² reference (true penumbra 1 m
on the floor ≈ 25 texels of the default 1024² map).
"""

import math

import numpy as np
import pytest

from shadowlab.techniques import get
from shadowlab.techniques import pcf as pcf_mod
from scene_builder import floor, frame_from

EDGE = {
    "name": "edge",
    "camera": {"position": [1.2, 0.9, 0.0], "target": [0.0, 0.0, 0.0], "fov": 8, "resolution": [96, 96]},
    "lights": [{"name": "sun", "kind": "directional", "direction": [0.0, -1.0, 0.0], "up": [0.0, 0.0, 1.0],
                "irradiance": 1.0, "shadow_map": 64}],
    "shapes": [floor(1.0),
               {"name": "occ", "type": "rectangle", "translate": [-0.5, 0.5, 0.0], "rotate": [1, 0, 0, 90],
                "scale": 0.5}],
}
OPEN = {**EDGE, "name": "open", "camera": {**EDGE["camera"], "fov": 60, "resolution": [48, 48]},
        "shapes": EDGE["shapes"][:1]}


def vis(frame, light, tech="pcf", **params):
    return frame.gbuffer.to_image(get(tech).render(frame, params).visibility[light])


@pytest.fixture(scope="module")
def edge(mitsuba_backend):
    from shadowlab.techniques.shadow_map import view_for
    frame = frame_from(EDGE)
    scene = frame.scene
    gb = frame.gbuffer
    floor = (gb.shape_id[..., 0] == scene.shape_names.index("floor")) & gb.mask[..., 0]
    view = view_for(frame, "sun", get("pcf").resolve({}))
    u = gb.to_image(view.lookup(gb.p)["u"])                  # continuous texel coordinate, centres i + 0.5
    return frame, floor, u


@pytest.fixture(scope="module")
def planes(frame_of):
    from shadowlab.reference import store
    frame = frame_of("parallel_planes")
    truth, _ = store.load(frame.scene.spec)
    return frame, truth


# ---------------------------------------------------------------------------------------------
# tap tables and Poisson sets (no rendering)

@pytest.mark.parametrize("pattern", pcf_mod.PATTERNS)
def test_every_pattern_has_nonnegative_weights_summing_to_one(pattern):
    for n in range(1, 10):
        for sigma in (0.0, 0.7, 3.0):
            for rs in (16, 32, 64):
                off, w = pcf_mod.taps(pattern, n, sigma, rs)
                assert off.shape == (len(w), 2) and np.all(w >= 0)
                assert abs(w.sum() - 1.0) < 1e-12
                r = np.linalg.norm(off, axis=1)
                if pattern in ("grid", "gaussian"):
                    assert len(w) == n * n and np.abs(off).max() == (n - 1) / 2
                    assert np.allclose(off.mean(0), 0.0)
                    if pattern == "grid":
                        assert np.all(w == 1.0 / (n * n))
                    else:                                   # Gaussian: largest at the centre, radial
                        assert np.all(np.diff(w[np.argsort(r, kind="stable")]) <= 1e-15)
                else:
                    assert r.max() <= n / 2 * (1 + 1e-12)   # inside the disk inscribed in n×n texels
                    assert np.all(w == w[0])
    if pattern == "grid":
        off, w = pcf_mod.taps("grid", 1)
        assert off.tolist() == [[0.0, 0.0]] and w.tolist() == [1.0]


def test_gaussian_default_sigma_is_n_over_4():
    off, w = pcf_mod.taps("gaussian", 5)
    s = 5 / 4
    ref = np.exp(-(off ** 2).sum(1) / (2 * s * s))
    assert np.allclose(w, ref / ref.sum(), rtol=1e-12)
    assert np.array_equal(w, pcf_mod.taps("gaussian", 5, sigma=1.25)[1])


@pytest.mark.parametrize("count", [16, 32, 64])
def test_poisson_sets_keep_a_minimum_distance_inside_the_unit_disk(count):
    """Measured minimum distances: 0.88, 0.81, 0.81 × the hexagonal-packing spacing."""
    p, d = pcf_mod.POISSON[count], pcf_mod.POISSON_MIN_DIST[count]
    assert p.shape == (count, 2)
    assert np.linalg.norm(p, axis=1).max() <= 1 + 1e-12
    D = np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1))
    D[np.diag_indices(count)] = np.inf
    assert D.min() >= d * (1 - 1e-12)
    assert d >= 0.75 * math.sqrt(2 * math.pi / (math.sqrt(3) * count))  # a well-filled disk
    assert np.allclose(p.mean(0), 0.0, atol=1e-12)                    # centred: no shift of the edge
    assert np.linalg.norm(p, axis=1).max() > 0.9                      # reaches the rim
    again, d2 = pcf_mod.poisson_disk(count)                            # deterministic
    assert np.array_equal(again, p) and d2 == d
    assert not np.array_equal(pcf_mod.poisson_disk(count, seed=pcf_mod.POISSON_SEED + 1)[0], p)


def test_declarations():
    t = get("pcf")
    names = [p.name for p in t.params]
    for n in ("kernel", "softness", "pattern", "sigma", "rotated_samples", "seed", "bilinear"):
        assert n in names
    assert t.param("pattern").choices == pcf_mod.PATTERNS and t.param("pattern").default == "grid"
    assert t.param("bilinear").default is False and t.param("kernel").hi == 9
    for p in t.params:
        assert p.doc and p.source.startswith(
            "[Buljan 2020, §" if p.name not in ("receiver_plane", "grazing_slope_bias") else "[Isidoro 2006]"
        )
    doc = pcf_mod.__doc__
    assert "[Buljan 2020, §3.2]" in doc                   # the source, by its bibliography key
    for pat in pcf_mod.PATTERNS:
        assert f"``{pat}``" in doc


# ---------------------------------------------------------------------------------------------
# rendering

def test_kernel_1_grid_equals_hard_bit_for_bit(edge, planes):
    for frame, light in ((edge[0], "sun"), (planes[0], "panel")):
        for params in ({}, {"depth_bias": 0, "slope_scaled_depth_bias": 0.0}, {"normal_offset": 1.0, "depth_bits": 16}):
            h = get("hard").render(frame, params).visibility[light].numpy()
            p = get("pcf").render(frame, {**params, "kernel": 1, "softness": 5.0, "pattern": "grid",
                                          "bilinear": False}).visibility[light].numpy()
            assert np.array_equal(h, p)


def test_unoccluded_points_are_exactly_lit_for_every_pattern(mitsuba_backend):
    """Σ w_i·1 / Σ w_i = 1 in the kernel, for the widest footprint (9×9, softness 8)."""
    frame = frame_from(OPEN)
    for pattern in pcf_mod.PATTERNS:
        for bilinear in (False, True):
            v = vis(frame, "sun", kernel=9, softness=8.0, pattern=pattern, bilinear=bilinear)
            assert np.all(v == 1.0), (pattern, bilinear, v.min())


def test_bilinear_2x2_pcf_is_a_linear_one_texel_ramp_across_a_straight_edge(edge):
    """Measured: v = 32.5 − u exactly (slope −1 per texel, residual 3e-14) for u in [31.5, 32.5]:
    the ramp runs between the centres of the last shadowed and first lit texels, and its middle
    is the texel boundary where ``hard`` switches."""
    frame, floor, u = edge
    b = vis(frame, "sun", kernel=1, bilinear=True)
    h = vis(frame, "sun", "hard")
    frac = floor & (b > 0) & (b < 1)
    assert frac.sum() > 200
    uu, bb = u[frac], b[frac]
    assert uu.max() - uu.min() <= 1.0
    A = np.stack([uu, np.ones_like(uu)], 1)
    (slope, icpt), *_ = np.linalg.lstsq(A, bb, rcond=None)
    assert slope == pytest.approx(-1.0, abs=1e-4)
    assert np.abs(A @ (slope, icpt) - bb).max() < 1e-4
    mid = (0.5 - icpt) / slope
    assert mid == pytest.approx(round(mid), abs=1e-3)              # on a texel boundary
    order = np.argsort(u[floor])
    assert np.all(np.diff(b[floor][order]) <= 1e-6)                  # monotone across the edge
    assert np.all(b[floor][u[floor] <= mid - 0.5] == 1.0)
    assert np.all(b[floor][u[floor] >= mid + 0.5] == 0.0)
    lit_h = h[floor] == 1.0
    assert np.all(u[floor][lit_h] < mid) and np.all(u[floor][~lit_h] > mid)


def test_bilinear_grid_of_n_taps_gives_a_linear_ramp_n_texels_wide(edge):
    """n bilinear taps at unit spacing sample n adjacent one-texel ramps: their mean is one
    linear ramp n texels wide (slope −1/n), over (n+1) texels' tests."""
    frame, floor, u = edge
    b = vis(frame, "sun", kernel=3, softness=1.0, bilinear=True)
    frac = floor & (b > 0) & (b < 1)
    uu, bb = u[frac], b[frac]
    assert 2.5 < uu.max() - uu.min() <= 3.0
    A = np.stack([uu, np.ones_like(uu)], 1)
    (slope, icpt), *_ = np.linalg.lstsq(A, bb, rcond=None)
    assert slope == pytest.approx(-1 / 3, abs=1e-4)
    assert np.abs(A @ (slope, icpt) - bb).max() < 1e-4


def test_rotated_poisson_same_seed_same_bits_other_seed_changes_only_the_penumbra(planes):
    """Measured (9×9, softness 3): 1375 pixels differ between seeds 1 and 2, every one of them
    fractional in one of the two images and within 2 pixels of the truth's penumbra."""
    from scipy.ndimage import binary_dilation
    frame, truth = planes
    P = {"pattern": "rotated_poisson", "kernel": 9, "softness": 3.0}
    a1, a1b, a2 = (vis(frame, "panel", **P, seed=s) for s in (1, 1, 2))
    assert np.array_equal(a1, a1b)
    diff = a1 != a2
    assert diff.sum() > 100
    frac = lambda v: (v > 0) & (v < 1)  # noqa: E731
    assert np.all(frac(a1)[diff] | frac(a2)[diff])
    tv = truth.lights["panel"].V
    pen = (tv > 0.02) & (tv < 0.98)
    assert not np.any(diff & ~binary_dilation(pen, iterations=2))


def test_every_pattern_beats_hard_in_the_penumbra_of_parallel_planes(planes):
    """Kernel 9, softness 3 (27 texels for a true penumbra of 1 m ≈ 25 texels). Measured penumbra
    RMSE: hard 0.287; nearest / bilinear taps: grid 0.041 / 0.036, gaussian 0.073 / 0.066,
    poisson16 0.040 / 0.033, poisson32 0.029 / 0.024, poisson64 0.013 / 0.013,
    rotated_poisson 0.039 / 0.034."""
    import mitsuba as mi
    from shadowlab.pipeline import technique_metrics
    from shadowlab.techniques.shadow_map import view_for
    frame, truth = planes
    view = view_for(frame, "panel", get("pcf").resolve({}))
    texel = view.lookup(mi.Point3f(0.0, 0.0, 0.0))["texel"].numpy()[0]
    assert 9 * 3.0 == pytest.approx(1.0 / texel, rel=0.2)          # the footprint matches the penumbra

    def rmse(tech, **p):
        r = get(tech).render(frame, p)
        v = frame.image(r.visibility["panel"])
        valid = frame.gbuffer.mask[..., 0]
        assert v.min() >= 0.0 and v.max() <= 1.0 and np.all(v[~valid] == 1.0)
        return technique_metrics(frame, truth, r)[1]["panel"]["rmse_penumbra"]

    hard = rmse("hard")
    assert hard > 0.2
    for pattern in pcf_mod.PATTERNS:
        for bilinear in (False, True):
            e = rmse("pcf", kernel=9, softness=3.0, pattern=pattern, bilinear=bilinear)
            assert e < 0.4 * hard, (pattern, bilinear, e, hard)


def test_new_softness_seed_kernel_or_sigma_reuses_the_compiled_kernel(planes):
    import drjit as dr
    frame, _ = planes
    pcf = get("pcf")
    first = {"rotated": {"pattern": "rotated_poisson", "seed": 1, "softness": 1.0, "kernel": 3},
             "table": {"pattern": "gaussian", "kernel": 3, "bilinear": True}}
    later = {
        "rotated": [{"pattern": "rotated_poisson", "seed": 99, "softness": 2.75, "kernel": 7, "rotated_samples": 64}],
        "table": [
            {"pattern": "gaussian", "kernel": 9, "sigma": 1.7, "softness": 3.5, "bilinear": True},
            {"pattern": "poisson64", "kernel": 1, "bilinear": True},
            {"pattern": "grid", "kernel": 5, "softness": 0.5, "bilinear": True},
        ],
    }
    for key, p0 in first.items():
        pcf.render(frame, p0)                                       # compile (or load) once
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            dr.kernel_history_clear()
            for p in later[key]:
                pcf.render(frame, p)
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        assert jit, "the render launched no kernel"
        assert all(k["cache_hit"] for k in jit), (key, [k.get("cache_hit") for k in jit])


def test_stats_count_taps(planes):
    frame, _ = planes
    r = get("pcf").render(frame, {"pattern": "poisson32", "bilinear": True})
    assert r.stats["taps_per_point"] == 32 and r.stats["depth_tests_per_point"] == 128
    r = get("pcf").render(frame, {"kernel": 5})
    assert r.stats["taps_per_point"] == 25 and r.stats["depth_tests_per_point"] == 25
