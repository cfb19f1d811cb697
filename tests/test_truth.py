"""Ground truth against closed forms, within its own statistical error (DEVELOPERS: tests
assert what is true). Uses the committed 128² references, so nothing long is rendered here."""

import numpy as np

from shadowlab import backend
from shadowlab.reference import store
from shadowlab.reference.closed_form import parallel_planes_fraction, sphere_visible_fraction
from shadowlab.render.gbuffer import gbuffer, vec_numpy
from shadowlab.scene import load
from conftest import CUDA

backend.init()


def _floor_points(name):
    sc = load(name)
    truth, meta = store.load(sc.spec)
    gb = gbuffer(sc)
    W, H = sc.resolution
    P = vec_numpy(gb.p).reshape(H, W, 3).astype(np.float64)
    floor = (gb.shape_id[..., 0] == sc.shape_names.index("floor")) & gb.mask[..., 0]
    return sc, truth, P, floor


def _check_against(lt, closed, floor):
    """Penumbra pixels: z-scores against the closed form look like N(0, 1); unanimous pixels
    (all samples agreed) lie within their rule-of-three bound."""
    pen = floor & (lt.A_se > 0)
    assert pen.sum() > 300, "the scene must have a penumbra to test"
    z = (lt.A[pen] - closed[pen]) / lt.A_se[pen]
    assert abs(z.mean()) < 0.15, f"biased truth: mean z {z.mean():.3f}"
    assert 0.85 < z.std() < 1.2, f"standard errors not honest: z std {z.std():.3f}"
    assert (np.abs(z) > 3).mean() < 0.02
    una = floor & (lt.A_se == 0)
    err = np.abs(lt.A[una] - closed[una])
    assert (err <= lt.bound[una] + 1e-5).mean() > 0.995
    assert err.max() < 2 * lt.bound[una].max()


def test_sphere_light_behind_sphere_matches_cap_intersection():
    sc, truth, P, floor = _floor_points("analytic_sphere")
    light = sc.spec.light("bulb")
    ball = next(s for s in sc.spec.shapes if s.name == "ball")
    closed = sphere_visible_fraction(P.reshape(-1, 3), light.position, light.radius, ball.center,
                                     ball.radius).reshape(P.shape[:2])
    lt = truth.lights["bulb"]
    # the scene has umbra, penumbra and lit floor
    assert (closed[floor] == 0).any() and ((closed[floor] > 0.1) & (closed[floor] < 0.9)).any()
    _check_against(lt, closed, floor)


def test_rect_light_over_half_plane_is_piecewise_linear():
    sc, truth, P, floor = _floor_points("parallel_planes")
    light = sc.spec.light("panel")
    closed = parallel_planes_fraction(P[..., 0], light.position[1], 2.0, light.size[0])
    _check_against(truth.lights["panel"], closed, floor)


def test_truth_is_aligned_with_pixel_centres():
    """The penumbra of parallel_planes is a linear ramp in x: a half-pixel shift of the truth
    image would move every penumbra pixel by the ramp's slope times half a pixel's footprint.
    Evaluate the closed form at floor points computed independently (pinhole camera, pixel
    centres) and check the residual is noise, not a shift."""
    sc, truth, P, floor = _floor_points("parallel_planes")
    cam = sc.spec.camera
    W, H = cam.resolution
    o = np.array(cam.position)
    f = np.array(cam.target) - o
    f /= np.linalg.norm(f)
    right = np.cross(f, cam.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    t = np.tan(np.radians(cam.fov) / 2)
    j, i = np.mgrid[0:H, 0:W]
    x = (2 * (i + 0.5) / W - 1) * t
    y = (1 - 2 * (j + 0.5) / H) * t * H / W
    d = f + x[..., None] * right + y[..., None] * up
    s = -o[1] / d[..., 1]
    Pa = o + s[..., None] * d
    assert np.abs(Pa - P)[floor].max() < 1e-3 * sc.radius, "pixel (i, j) is not the pinhole ray through its centre"
    lt = truth.lights["panel"]
    pen = floor & (lt.A_se > 0)
    for shift in (0.0, 0.5):
        # the camera looks down -x: floor x changes along image rows
        x_shift = Pa[..., 0] + shift * (Pa[..., 0] - np.roll(Pa[..., 0], 1, axis=0))
        closed = parallel_planes_fraction(x_shift, 4.0, 2.0, 1.0)
        z = (lt.A[pen] - closed[pen]) / lt.A_se[pen]
        if shift == 0.0:
            assert abs(z.mean()) < 0.15
        else:
            assert abs(z.mean()) > 1.0, "a half-pixel shift must be detectable by this test"


def test_gbuffer_view_depth_equals_ray_plane_distance():
    sc, truth, P, floor = _floor_points("parallel_planes")
    gb = gbuffer(sc)
    o = np.array(sc.spec.camera.position)
    dist = np.linalg.norm(P - o, axis=-1)
    assert np.allclose(gb.view_depth[..., 0][floor], dist[floor], rtol=1e-5)
    # and the stored reference carries the same depth; the references are rendered with llvm_ad_rgb
    # (Embree): OptiX's ray-rectangle intersection on cuda_ad_rgb gives t a few float32 ulps apart
    # (measured up to 5e-7 relative on an H200), so there 1e-5 (about 80 ulps)
    assert np.allclose(truth.view_depth[floor], gb.view_depth[..., 0][floor], rtol=1e-5 if CUDA else 1e-6)


def test_gbuffer_depth_matches_mitsuba_depth_aov():
    """Mitsuba's own depth AOV, rendered with many samples over each pixel's box footprint,
    agrees with the G-buffer's pixel-centre depth to second order on the flat floor."""
    import mitsuba as mi
    sc, truth, P, floor = _floor_points("parallel_planes")
    gb = gbuffer(sc)
    img = np.asarray(mi.render(sc.mi_scene, spp=64, integrator=mi.load_dict({"type": "aov", "aovs": "dd:depth"})))
    depth = img[..., 0]
    inner = floor & np.roll(floor, 1, 0) & np.roll(floor, -1, 0) & np.roll(floor, 1, 1) & np.roll(floor, -1, 1)
    rel = np.abs(depth[inner] - gb.view_depth[..., 0][inner]) / gb.view_depth[..., 0][inner]
    assert np.median(rel) < 2e-3


def test_same_seed_same_bits_and_seed_changes_noise(frame_of):
    from shadowlab.reference.truth import visibility
    fr = frame_of("contact", (48, 48))
    a = visibility(fr, "key", seed=3, max_rounds=16)
    b = visibility(fr, "key", seed=3, max_rounds=16)
    c = visibility(fr, "key", seed=4, max_rounds=16)
    assert np.array_equal(a.V, b.V) and np.array_equal(a.V_se, b.V_se)
    assert not np.array_equal(a.V, c.V)
    pen = (a.V_se > 0) & (c.V_se > 0)
    z = (a.V - c.V)[pen] / np.hypot(a.V_se, c.V_se)[pen]
    assert 0.6 < z.std() < 1.4


def test_adaptive_sampling_spends_rays_in_the_penumbra():
    sc = load("contact")
    truth, meta = store.load(sc.spec)
    lt = truth.lights["key"]
    m = truth.mask
    pen = m & (lt.V_se > 0)
    settled = m & (lt.V_se == 0)
    assert lt.samples[pen].mean() > 4 * lt.samples[settled].mean()
    assert lt.V_se[m].max() <= meta["samples"]["target_se"] * 1.5 or lt.samples[m].max() >= 64 * 64


def test_shaded_truth_agrees_with_mitsuba_direct_integrator():
    """Σ U·V at pixel centres vs mi.render (box filter over the pixel): equal in the mean and
    within noise where the image is smooth (away from silhouettes)."""
    sc = load("contact")
    truth, _ = store.load(sc.spec)
    m = truth.mask
    rel = abs(truth.shaded[m].mean() - truth.mitsuba[m].mean()) / truth.mitsuba[m].mean()
    assert rel < 0.01
    z = (truth.shaded - truth.mitsuba) / np.sqrt(truth.shaded_var + truth.mitsuba_var + 1e-12)
    assert np.median(np.abs(z[m])) < 1.0  # |z| of N(0,1) has median 0.67


def test_the_truths_cost_is_recorded_per_light(frame_of):
    """stats["per_light"]: each light's seconds and shadow rays; the rays add up to the total and
    equal the sum of that light's per-pixel ray counts (the stored N channel)."""
    from shadowlab.reference.truth import render_truth
    fr = frame_of("two_lights", (32, 32))
    sc = fr.scene
    t = render_truth(fr, spp=0, max_rounds=8)
    per = t.stats["per_light"]
    assert set(per) == {l.name for l in sc.lights}
    assert sum(c["shadow_rays"] for c in per.values()) == t.stats["shadow_rays"]
    for n, c in per.items():
        assert c["time_s"] > 0
        assert c["shadow_rays"] == int(t.lights[n].samples.sum()) > 0   # the per-pixel counts (channel N)
