"""``ssss`` against its source [Tamás 2015, §6.2–§7]: the exponential layers' decay
exp(−k(z − d)) (a receiver close behind its caster keeps its light, an umbra stays dark; §6.4,
Fig. 11/16), the half-resolution blur against the truth and the full-resolution blur, depth
rejection at a depth discontinuity on both paths, the filter size F = w·sqrt(max(n_z, 0.25))·P/z
(the same world size at any view distance; the 0.25 floor at grazing views) and the banding of
a penumbra map stored below 16 bits (§6.2)."""

import math

import numpy as np
import pytest

from shadowlab.techniques import get

from scene_builder import floor, frame_from, scene  # noqa: E402  (tests/ is on the path)

#: every bias off: the hard test then self-shadows the lit floor (acne) and z − d is the caster gap
NO_BIAS = {"depth_bias": 0, "slope_scaled_depth_bias": 0.0, "grazing_slope_bias": 0.0, "max_slope_bias": 0.0,
           "light_scale": 0.0}
DIR = np.array([1.0, -1.0, 0.3])
SUN = {"name": "sun", "kind": "directional", "direction": DIR.tolist(), "irradiance": 3.0, "angular_diameter": 0.53,
       "shadow_map": 256}
CAM = {"position": [0.0, 3.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 60}
GAPS = ((-1.6, 1.0), (-0.2, 0.5), (1.2, 0.2))


def _plate(h, x):
    return {"name": f"plate{int(round(10 * h))}", "type": "rectangle", "translate": [x, h, 0.0],
            "rotate": [1, 0, 0, 90], "scale": 0.4}


# ----------------------------------------------------------------------------- exponential layers

@pytest.fixture(scope="module")
def gaps(mitsuba_backend):
    """Plates 1.0 m, 0.5 m and 0.2 m above the floor under a sun: their umbrae lie h·|d|/|d_y|
    behind their casters in light space."""
    return frame_from(scene("gaps", camera=CAM, resolution=(64, 64), lights=[SUN],
                            shapes=[floor(3.0)] + [_plate(h, x) for x, h in GAPS]))


def _under(frame, x, h):
    """Visible floor points whose ray toward the light crosses the plate at height h over x at
    least 0.05 m inside its edges (its umbra, away from texel edges)."""
    from shadowlab.render.gbuffer import vec_numpy
    p = vec_numpy(frame.gbuffer.p)
    q = p - DIR * (h / -DIR[1])                                      # where the ray meets height h
    return frame.gbuffer.valid.numpy() & (np.abs(p[:, 1]) < 1e-3) & (np.abs(q[:, 0] - x) < 0.35) & \
        (np.abs(q[:, 2]) < 0.35)


@pytest.mark.parametrize("k", [2.0, 20.0, 80.0])
def test_exponential_layers_store_the_decay_of_the_caster_gap(gaps, k):
    """§6.4, Equation 2: a shadowed point stores exp(−k(z − d)) as floor(255·v)/255, z − d its gap
    behind the caster: the umbra 1 m behind is dark for k ≥ 20, the one 20 cm behind keeps some
    of the light (no self-shadowing of near contact); every point the hard test lights stays 1."""
    gap = np.linalg.norm(DIR) / -DIR[1]                               # light-space gap per metre of height
    r = get("ssss").render(gaps, {**NO_BIAS, "layer_packing": "exponential", "exp_k": k})
    v, hard = r.visibility["sun"].numpy(), np.asarray(r.aovs["sun.hard"]).reshape(-1)
    assert np.all(v[hard > 0.5] == 1.0)
    for x, h in GAPS:
        m = _under(gaps, x, h)
        assert m.sum() > 10 and np.all(hard[m] == 0.0)
        want = math.floor(255.0 * math.exp(-k * h * gap)) / 255.0
        if want == 0.0:
            assert np.all(v[m] <= 1.0 / 255.0), (k, h)
            continue
        # the gap read back from the stored value: within 3 cm (the occluder's depth is its texel
        # centre's, the plate tilted against the light) plus the 8-bit floor's step
        got = -np.log(v[m]) / k
        assert np.all(np.abs(got - h * gap) <= 0.03 + 1.0 / (255.0 * k * want)), (k, h, want, np.unique(v[m]))


def test_exponential_layers_remove_the_self_shadowing_the_binary_ones_keep(gaps):
    """Fig. 11/16: with every bias off the binary layer shows acne on half the lit floor (the
    receiver is its own caster, z − d within a texel's depth slope of 0), the exponential one
    (k = 10/m) stores exp(−k(z − d)) ≈ 1 there (measured: min 0.84, mean 0.955), while the umbra
    1.45 m behind its plate stays at 0."""
    from shadowlab.render.gbuffer import vec_numpy
    p = vec_numpy(gaps.gbuffer.p)
    open_floor = gaps.gbuffer.valid.numpy() & (np.abs(p[:, 1]) < 1e-3) & (p[:, 2] > 0.8)
    b = get("ssss").render(gaps, {**NO_BIAS, "layer_packing": "binary"}).visibility["sun"].numpy()
    e = get("ssss").render(gaps, {**NO_BIAS, "layer_packing": "exponential", "exp_k": 10.0}).visibility["sun"].numpy()
    assert open_floor.sum() > 200
    assert np.mean(b[open_floor] == 0.0) > 0.3                      # acne the binary layer keeps
    assert e[open_floor].min() > 0.8 and e[open_floor].mean() > 0.93  # gone in the exponential one
    assert np.all(e[_under(gaps, -1.6, 1.0)] == 0.0)                # the umbra stays dark


# ----------------------------------------------------------------------------- half resolution

def test_half_resolution_blurs_a_wide_penumbra_like_the_truth_and_the_full_blur(frame_of):
    """parallel_planes (committed 128² truth): penumbrae 20–60 px wide. Blurred on the half grid
    (σ halved there), the penumbra RMSE stays within the full-resolution blur's band (measured:
    full 0.075, half 0.059; σ not halved 0.175, quartered 0.088) and the two agree pixel by pixel
    in the penumbra (measured RMS 0.047; with σ quartered 0.136)."""
    import shadowlab as sl
    frame = frame_of("parallel_planes")
    truth = sl.load_reference("parallel_planes")
    full = get("ssss").render(frame, {})
    half = get("ssss").render(frame, {"half_resolution": True})
    F = np.asarray(half.aovs["panel.filter_px"])
    assert np.median(F[F > 0]) > 20                                  # a wide penumbra, in pixels
    m_full = sl.compare(frame, truth, full, light="panel")["rmse_penumbra"]
    m_half = sl.compare(frame, truth, half, light="panel")["rmse_penumbra"]
    assert m_half < 0.075 and m_half < 1.2 * m_full, (m_half, m_full)
    V = truth.lights["panel"].V.reshape(-1)
    pen = (V > 0.02) & (V < 0.98)
    d = full.visibility["panel"].numpy() - half.visibility["panel"].numpy()
    assert np.sqrt(np.mean(d[pen] ** 2)) < 0.07


# ----------------------------------------------------------------------------- depth rejection

@pytest.fixture(scope="module")
def card(mitsuba_backend):
    """test_ssss's parallel panels with a lit card standing in front of the umbra."""
    from test_ssss import FLOOR, OCCLUDER, PANEL, _frame, _scene
    card = {"name": "card", "type": "rectangle", "translate": [1.2, 0.7, 0.0], "rotate": [0, 1, 0, 90],
            "scale": 0.12}
    return _frame(_scene([PANEL], [FLOOR, OCCLUDER, card]))


def _near_card(f):
    from scipy.ndimage import binary_dilation

    from shadowlab.render.gbuffer import vec_numpy
    gb = f.gbuffer
    sid = gb.shape_id[..., 0]
    is_card = sid == f.scene.shape_names.index("card")
    fl = (sid == f.scene.shape_names.index("floor")) & gb.mask[..., 0]
    x = gb.to_image(vec_numpy(gb.p))[..., 0]
    return binary_dilation(is_card, iterations=4) & fl & (x < -0.7)


@pytest.mark.parametrize("plane", [True, False])
def test_depth_rejection_keeps_a_near_card_out_of_the_half_resolution_umbra(card, plane):
    """The half-resolution path rejects by depth twice (on the half grid and when it reads back):
    the floor's umbra beside a lit card 2–7 m in front mostly stays dark (the source's 4-tap gather
    mixes the card into the half pixels on its silhouette: measured 25–30 % of these points above
    0.02, mean 0.08); without rejection every one brightens (mean 0.20)."""
    near = _near_card(card)
    img = card.gbuffer.to_image
    p = {"kernel": 23, "half_resolution": True, "depth_plane": plane}
    on = img(get("ssss").render(card, p).visibility["panel"].numpy())[near]
    off = img(get("ssss").render(card, {**p, "depth_threshold": 1000.0}).visibility["panel"].numpy())[near]
    assert near.sum() >= 10
    assert np.mean(on > 0.02) < 0.4 and on.mean() < 0.5 * off.mean(), (np.mean(on > 0.02), on.mean(), off.mean())
    assert np.all(off > 0.02)


def test_depth_rejection_threshold_scales_with_the_centre_depth(card):
    """A tap is rejected where |z_tap − z| > threshold · z (the relative reading of the source's
    0.03): the card (z ≈ 1 m) seen beside floor points 3.2–7.8 m away differs by 69–87 % of their
    depth: rejected at threshold 0.03, kept at 1.0 (an absolute 1 m would still reject it)."""
    near = _near_card(card)
    img = card.gbuffer.to_image
    p = {"kernel": 23, "depth_plane": False}
    assert img(get("ssss").render(card, {**p, "depth_threshold": 0.03}).visibility["panel"].numpy())[near].max() < 0.02
    assert img(get("ssss").render(card, {**p, "depth_threshold": 1.0}).visibility["panel"].numpy())[near].max() > 0.2


# ----------------------------------------------------------------------------- filter size (§7)

@pytest.mark.parametrize("height", [1.0, 0.25])
def test_filter_size_is_the_sources_formula_with_the_grazing_floor(mitsuba_backend, height):
    """Code 3: F = w·sqrt(max(n_z, 0.25))·P/z pixels, P = W/(2 tan(fov_x/2)): checked per pixel
    from the stored size, the view-space normal and the depth; seen from a camera 0.25 m over the
    floor (grazing views, n_z < 0.25) the floor 0.25 holds, so F·z/P = w/2 there."""
    from test_ssss import FLOOR, OCCLUDER, PANEL, _frame, _scene
    f = _frame(_scene([PANEL], [FLOOR, OCCLUDER], camera={"position": [2.5, height, 0.3], "target": [-1.0, 0.0, 0.0],
                                                          "fov": 60}))
    r = get("ssss").render(f, {})
    scr = f.screen
    F = np.asarray(r.aovs["panel.filter_px"]).reshape(-1)
    w = np.asarray(r.aovs["panel.penumbra_size"]).reshape(-1)
    n = np.stack([c.numpy() for c in (scr.normal.x, scr.normal.y, scr.normal.z)], 1)
    nz = -(n @ np.asarray(scr.camera.forward, np.float64))
    z = scr.depth.numpy()
    P = scr.width / (2.0 * scr.camera.tan_x)
    ok = scr.valid.numpy() & (w > 0)
    want = w * np.sqrt(np.maximum(nz, 0.25)) * P / np.maximum(z, 1e-12)
    assert ok.sum() > 100
    assert np.allclose(F[ok], want[ok], rtol=1e-4)
    grazing = ok & (nz < 0.25)
    if height > 0.5:
        return
    assert grazing.sum() > 10 and np.allclose(F[grazing] * z[grazing] / P, 0.5 * w[grazing], rtol=1e-4)


def test_filter_size_in_world_units_does_not_depend_on_the_view_distance(mitsuba_backend):
    """§7: "the filter size stays constant wherever the shadow is seen from": the same floor points
    seen from twice as far (the camera pulled back along its axis) get half the filter in pixels,
    the same F·z/P in world units."""
    from test_ssss import FLOOR, OCCLUDER, PANEL, _frame, _scene
    pos, tgt = np.array([2.2, 1.0, 0.0]), np.array([-0.3, 0.0, 0.0])
    out, frames = [], []
    for s in (1.0, 2.0):
        cam = {"position": list(tgt + s * (pos - tgt)), "target": list(tgt), "fov": 60}
        f = _frame(_scene([PANEL], [FLOOR, OCCLUDER], camera=cam))
        frames.append(f)
        r = get("ssss").render(f, {})
        from shadowlab.render.gbuffer import vec_numpy
        p = vec_numpy(f.gbuffer.p)
        F = np.asarray(r.aovs["panel.filter_px"]).reshape(-1)
        z = f.screen.depth.numpy()
        P = f.screen.width / (2.0 * f.screen.camera.tan_x)
        out.append((p, F, F * z / P))
    (p1, F1, W1), (p2, F2, W2) = out
    # the points of the far view that lie on the near view's floor penumbra: nearest neighbours
    from scipy.spatial import cKDTree
    sel = (F2 > 0) & (np.abs(p2[:, 1]) < 1e-3)
    d, j = cKDTree(p1).query(p2[sel])
    close = d < 0.01
    assert close.sum() > 20
    assert np.allclose(W2[sel][close], W1[j[close]], rtol=0.05)
    z1, z2 = (f.screen.depth.numpy() for f in frames)
    assert np.allclose(F2[sel][close] / F1[j[close]], z1[j[close]] / z2[sel][close], rtol=0.05)
    assert np.median(z2[sel][close] / z1[j[close]]) > 1.5                # it is seen from farther away


# ----------------------------------------------------------------------------- banding (§6.2)

def test_a_penumbra_map_below_16_bits_bands(mitsuba_backend):
    """§6.2: store the sizes in at least 16-bit floats, or banding appears: a smooth ramp of sizes
    keeps a relative error ≤ 2⁻¹¹ in half floats and falls onto 256 levels of m/255 in 8 bits."""
    import mitsuba as mi

    from shadowlab.techniques.ssss import store_penumbra
    s = np.linspace(0.0, 0.37, 5001).astype(np.float32)
    h = store_penumbra(mi.Float(s), 16).numpy()
    b = store_penumbra(mi.Float(s), 8).numpy()
    nz = s > 1e-4
    assert np.all(np.abs(h[nz] - s[nz]) <= s[nz] * 2.0 ** -11)
    assert len(np.unique(b)) == 256 and np.abs(b - s).max() <= 0.37 / 510 * 1.0001
    assert np.allclose(np.unique(b) / (0.37 / 255), np.round(np.unique(b) / (0.37 / 255)), atol=1e-3)


def test_the_sources_normalised_depth_threshold_scales_with_the_scenes_depth_span(card):
    """``depth_scale = "normalised"``: a tap is rejected where |z_tap − z| > threshold · (z1 − z0),
    z1 − z0 the view depths the scene spans (the source's 0.03 on a [0, 1] depth): the card, 2.2–6.8 m
    nearer than the floor beside it, is rejected at a tolerance of 1 m and kept at 7.7 m (span
    13.9 m: threshold 0.55, which the relative reading, 0.55·z < the gap everywhere, rejects)."""
    z0, z1 = card.camera.depth_range(card.scene.center, card.scene.radius)
    near = _near_card(card)
    img = card.gbuffer.to_image
    p = {"kernel": 23, "depth_plane": False, "depth_scale": "normalised"}
    v = {tol: img(get("ssss").render(card, {**p, "depth_threshold": tol / (z1 - z0)}).visibility["panel"].numpy())
         for tol in (1.0, 7.7)}
    assert v[1.0][near].max() < 0.02 and v[7.7][near].max() > 0.2
