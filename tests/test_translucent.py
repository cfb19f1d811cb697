"""Translucent casters (issue 12): coloured shadows by straight-line transmission.

The scene ``tests/data/coloured_panes.toml`` is ``parallel_planes`` with translucent panes: a
square light (1 m, height 4) over a half-plane pane x < 0 at height 2 (τ_A) and a second pane
x < −1.5 at height 1 (τ_B), over a floor. Straight-line transmission makes a sample's visibility
1 − b·(1 − τ_c) where b says whether the pane A hides that light sample, so on the floor away from
pane B (x > −1.8) every channel obeys 1 − V_c = (1 − τ_c)(1 − V) with V the opaque half-plane's
visibility from the same samples, and the visible fraction A = 1 − (1 − mean τ)(1 − f) with f the
closed-form visible area of the opaque half-plane; under both panes' umbrae V_c = τ_A·τ_B.
"""

from __future__ import annotations

import copy
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from shadowlab import backend
from shadowlab.cli import main as cli_main
from shadowlab.errors import SceneError
from shadowlab.reference.closed_form import parallel_planes_fraction
from shadowlab.render.frame import make_frame
from shadowlab.render.gbuffer import vec_numpy
from shadowlab.render.shading import compose
from shadowlab.scene import load
from shadowlab.scene.spec import parse
from shadowlab.techniques import get

backend.init()

SCENE = str(Path(__file__).resolve().parent / "data" / "coloured_panes.toml")


@pytest.fixture(scope="module")
def panes():
    sc = load(SCENE)
    return sc, make_frame(sc)


def _taus(sc):
    return (np.array(sc.spec.shapes[1].tau), np.array(sc.spec.shapes[2].tau))


def _floor(frame):
    P = vec_numpy(frame.gbuffer.p)
    floor = frame.gbuffer.valid.numpy() & (np.abs(P[:, 1]) < 1e-4)
    return P[:, 0], floor


# ----------------------------------------------------------------------------------- the scene format
BASE = {
    "name": "t",
    "camera": {"position": [0.0, 3.0, 5.0], "target": [0.0, 0.0, 0.0], "fov": 40, "resolution": [16, 16]},
    "lights": [{"name": "key", "kind": "rect", "position": [0.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0],
                "size": [1.0, 1.0], "power": 100.0}],
    "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0},
               {"name": "pane", "type": "rectangle", "translate": [0, 1, 0], "rotate": [1, 0, 0, 90],
                "transmittance": [1.0, 0.5, 0.25], "opacity": 0.8}],
}


def _with(**pane):
    d = copy.deepcopy(BASE)
    d["shapes"][1].update(pane)
    return d


def test_tau_is_the_opacity_weighted_transmittance():
    spec = parse(_with(), "s.toml")
    assert spec.shapes[1].translucent and not spec.shapes[0].translucent
    assert spec.shapes[1].tau == pytest.approx((1.0, 0.6, 0.4))
    assert parse(_with(transmittance=0.5, opacity=1.0), "s.toml").shapes[1].tau == (0.5, 0.5, 0.5)


@pytest.mark.parametrize("pane, parts", [
    (dict(transmittance=[1.0, 1.2, 0.0]), ["shapes[1].transmittance: expected three numbers in [0, 1]", "1.2"]),
    (dict(transmittance=[0.5, -0.1, 0.0]), ["shapes[1].transmittance: expected three numbers in [0, 1]"]),
    (dict(opacity=1.5), ["shapes[1].opacity: expected a number in [0.0, 1.0]"]),
    (dict(transmittance=None, opacity=0.5), ["shapes[1].opacity: expected no opacity without transmittance"]),
    (dict(alpha_texture="leaf.png"), ["shapes[1].transmittance: expected a translucent shape of a supported type",
                                      "alpha-tested"]),
])
def test_bad_translucency_is_refused_naming_the_key(pane, parts, tmp_path):
    d = _with(**pane)
    if d["shapes"][1].get("transmittance", 0) is None:
        del d["shapes"][1]["transmittance"]
    if "alpha_texture" in pane:
        from PIL import Image
        Image.new("LA", (4, 4), (255, 255)).save(tmp_path / "leaf.png")
    with pytest.raises(SceneError) as e:
        parse(d, str(tmp_path / "s.toml"))
    for p in parts:
        assert p in str(e.value), str(e.value)


def test_no_translucent_shape_in_an_sdf_scene():
    d = _with()
    d["sdf"] = [{"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5}]
    with pytest.raises(SceneError, match="translucent shapes"):
        parse(d, "s.toml")


def test_transmittance_out_of_range_exits_2_and_writes_nothing(tmp_path, monkeypatch, capsys):
    store = tmp_path / "store"
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store))
    text = Path(SCENE).read_text().replace("transmittance = [1.0, 0.6, 0.2]", "transmittance = [1.0, 1.6, 0.2]")
    f = tmp_path / "bad.toml"
    f.write_text(text)
    rc = cli_main(["reference", str(f), "--resolution", "8x8"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "transmittance: expected three numbers in [0, 1]" in err and "Traceback" not in err
    assert not store.exists() or not any(store.rglob("*"))


def test_scenes_without_translucency_hash_as_before():
    # the hashed dict leaves the keys out unless used: the committed references' hashes hold
    # (tests/test_validation.py checks every built-in scene); a translucent pane changes the hash
    plain = copy.deepcopy(BASE)
    for k in ("transmittance", "opacity"):
        del plain["shapes"][1][k]
    assert parse(plain, "s.toml").digest() != parse(_with(), "s.toml").digest()
    assert parse(_with(), "s.toml").digest() != parse(_with(opacity=0.5), "s.toml").digest()


def test_mitsuba_notes_say_direct_ignores_translucency(panes):
    sc, _ = panes
    assert "mitsuba_direct_ignores_translucency" in sc.mitsuba_notes()
    assert "mitsuba_direct_ignores_translucency" not in load("parallel_planes").mitsuba_notes()


# ----------------------------------------------------------------------------------- light views
def test_light_view_stores_opaque_depth_and_the_casters_colour(panes):
    sc, frame = panes
    tA, tB = _taus(sc)
    plain = frame.light_view("panel", res=64)
    lv = frame.light_view("panel", res=64, translucent=True)
    assert lv is not plain and plain.trans_rgb is None
    rgb = lv.trans_rgb.reshape(-1, 3)
    # every texel ray crosses none, pane A, or both panes: exactly these colours
    found = {tuple(np.round(c, 5)) for c in np.unique(rgb, axis=0)}
    assert found == {(1.0, 1.0, 1.0), tuple(np.round(tA.astype(np.float32), 5)),
                     tuple(np.round((tA * tB).astype(np.float32), 5))}, found
    # the opaque depth is the floor's wherever the plain map saw a pane
    pane = (rgb != 1.0).any(1)
    assert pane.any()
    assert (lv.depth.ravel()[pane] > plain.depth.ravel()[pane]).all()
    assert np.array_equal(lv.depth.ravel()[~pane], plain.depth.ravel()[~pane])
    # the nearest translucent surfaces' map is the plain map over the panes, empty elsewhere
    near = lv.translucent
    assert np.array_equal(near.depth.ravel()[pane], plain.depth.ravel()[pane])
    assert np.array_equal(near.slope.ravel()[pane], plain.slope.ravel()[pane])
    assert (near.depth.ravel()[~pane] == 1.0).all() and not near.hit.ravel()[~pane].any()


def test_tint_colours_receivers_behind_the_nearest_translucent_caster_only(panes):
    from shadowlab.techniques.shadow_map import depth_test, opaque_bias
    _, frame = panes
    lv = frame.light_view("panel", res=64, translucent=True)
    j, i = np.nonzero(lv.translucent.depth[0] < 1.0)
    td = lv.translucent.depth[0, j, i]
    rgb = lv.trans_rgb[0, j, i]
    for dt, behind in ((td + 1e-4, True), (td - 1e-4, False)):
        rec = {"u": mi.Float((i + 0.5).astype(np.float32)), "v": mi.Float((j + 0.5).astype(np.float32)),
               "face": mi.UInt32(np.zeros(len(i), np.uint32)), "dt": mi.Float(dt.astype(np.float32))}
        np.testing.assert_array_equal(vec_numpy(lv.tint(rec["face"], mi.Int32(i), mi.Int32(j))), rgb)
        no_bias = opaque_bias({k: 0.0 for k in ("depth_bias", "slope_scaled_depth_bias", "depth_bias_clamp",
                                                 "constant_bias", "slope_bias", "max_slope_bias", "normal_offset")})
        lit = depth_test(lv.translucent, rec, mi.Int32(i), mi.Int32(j), no_bias)
        assert (lit.numpy() == (0.0 if behind else 1.0)).all()


def test_a_scene_without_translucency_gets_the_plain_view(frame_of):
    frame = frame_of("parallel_planes")
    assert frame.light_view("panel", res=64, translucent=True) is frame.light_view("panel", res=64)


# ----------------------------------------------------------------------------------- the truth
def test_transmission_of_a_segment(panes):
    """Straight-line transmission of single segments: nothing on it 1, both panes τ_A·τ_B, one
    pane τ_A, an opaque surface (the floor, from below) 0 whatever panes follow."""
    from shadowlab.render.shading import transmitted
    sc, _ = panes
    tA, tB = _taus(sc)
    a = np.array([[3.0, 0.5, 0.0], [-3.0, 0.5, 0.0], [-1.0, 0.5, 0.0], [-3.0, -1.0, 0.0]], np.float32)
    b = np.array([[3.0, 3.0, 0.0], [-3.0, 3.0, 0.0], [-1.0, 3.0, 0.0], [-3.0, 3.0, 0.0]], np.float32)
    o = mi.Point3f(*a.T)
    ray = mi.Ray3f(o, mi.Vector3f(*(b - a).T))
    ray.maxt = mi.Float(np.ones(4, np.float32))
    tau = vec_numpy(transmitted(sc.mi_scene, ray, mi.Bool(True), sc.translucency()))
    np.testing.assert_allclose(tau, [[1, 1, 1], tA * tB, tA, [0, 0, 0]], atol=1e-6)


@pytest.fixture(scope="module")
def truth(panes):
    from shadowlab.reference.truth import visibility
    sc, frame = panes
    return visibility(frame, "panel", seed=1)


def test_truth_colour_under_both_panes_is_the_product_of_transmittances(panes, truth):
    sc, frame = panes
    tA, tB = _taus(sc)
    x, floor = _floor(frame)
    C = truth.V_rgb.reshape(-1, 3)
    both = floor & (x < -2.3)          # umbra of both panes
    only_a = floor & (x > -1.7) & (x < -0.6)  # umbra of pane A only
    assert both.sum() > 50 and only_a.sum() > 50
    np.testing.assert_allclose(C[both], np.broadcast_to(tA * tB, C[both].shape), atol=1e-5)
    np.testing.assert_allclose(C[only_a], np.broadcast_to(tA, C[only_a].shape), atol=1e-5)
    lit = floor & (x > 0.6)
    assert (C[lit] == 1.0).all()
    # samples that crossed different panes are not unanimous: the lower pane's penumbra (only
    # translucent casters there) is sampled on, with an estimated error
    pen_b = floor & (x > -2.1) & (x < -1.9)
    assert pen_b.sum() > 20 and (truth.samples.reshape(-1)[pen_b] >= 8 * 64).all()
    # a pane is not coloured by itself (the camera sees pane A from below)
    y = vec_numpy(frame.gbuffer.p)[:, 1]
    on_a = frame.gbuffer.valid.numpy() & (np.abs(y - 2.0) < 1e-4)
    assert on_a.sum() > 20
    assert (C[on_a] == 1.0).all()
    # the scalar V is the channel mean
    np.testing.assert_allclose(truth.V.reshape(-1)[floor], C[floor].mean(1), atol=1e-6)


def test_truth_penumbra_is_straight_line_transmission(panes, truth):
    """1 − V_c = (1 − τ_c)(1 − V) per pixel from the same samples: (1 − V_G)/(1 − τ_G) and
    (1 − V_B)/(1 − τ_B) agree; and the visible fraction matches the closed form of the opaque
    half-plane through A = 1 − (1 − mean τ)(1 − f), within the truth's standard error."""
    sc, frame = panes
    tA, _ = _taus(sc)
    x, floor = _floor(frame)
    C = truth.V_rgb.reshape(-1, 3).astype(np.float64)
    pen = floor & (x > -0.45) & (x < 0.45)
    assert pen.sum() > 100
    occ_g = (1.0 - C[pen, 1]) / (1.0 - tA[1])
    occ_b = (1.0 - C[pen, 2]) / (1.0 - tA[2])
    np.testing.assert_allclose(occ_g, occ_b, atol=2e-5)
    assert (C[pen, 0] == 1.0).all()  # pane A lets all red through
    f = parallel_planes_fraction(x, 4.0, 2.0, 1.0)
    expect = 1.0 - (1.0 - tA.mean()) * (1.0 - f)
    A, se = truth.A.reshape(-1), truth.A_se.reshape(-1)
    m = pen & (se > 0)
    z = (A[m] - expect[m]) / se[m]
    assert m.sum() > 100
    assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.25, (z.mean(), z.std())


def test_shaded_truth_uses_the_colour(panes, truth):
    sc, frame = panes
    U = vec_numpy(frame.unshadowed["panel"])
    C = truth.V_rgb.reshape(-1, 3)
    img = compose(frame, {"panel": truth.V.reshape(-1)}, {"panel": C})
    np.testing.assert_allclose(img.reshape(-1, 3), (U * C).astype(np.float32), rtol=1e-6)


# ----------------------------------------------------------------------------------- ssss
def test_ssss_colour_is_the_product_of_transmittances(panes):
    """With the penumbra size 0 (no blur) a lit pixel's colour is its tint from the layered
    translucency map: the product of the transmittances it lies behind, as RGBA8
    (floor(255·τ)/255); shadowed pixels stay 0 and the scalar visibility is the channel mean."""
    sc, frame = panes
    tA, tB = _taus(sc)
    r = get("ssss").render(frame, {"light_scale": 0.0})
    C = vec_numpy(r.colour["panel"])
    x, floor = _floor(frame)
    q = lambda t: np.floor(255.0 * t.astype(np.float32)) / 255.0  # noqa: E731
    both = floor & (x < -2.3)
    only_a = floor & (x > -1.2) & (x < -0.2)
    np.testing.assert_allclose(C[both], np.broadcast_to(q(tA * tB), C[both].shape), atol=1e-6)
    np.testing.assert_allclose(C[only_a], np.broadcast_to(q(tA), C[only_a].shape), atol=1e-6)
    assert (C[floor & (x > 0.2)] == 1.0).all()
    np.testing.assert_allclose(r.visibility["panel"].numpy(), C.mean(1), atol=1e-6)
    assert r.stats["translucency_words_per_pixel"] == 1


def test_ssss_blurred_colour_follows_the_truth(panes, truth):
    """Blurred (the defaults): far inside both umbrae the colour is the product; over the floor
    the coloured shadow is close to the truth's channel by channel (one penumbra size per pixel
    spreads the lower pane's red edge wider than the truth's, the largest of the three errors),
    and far closer than a technique that sees the panes as opaque."""
    sc, frame = panes
    tA, tB = _taus(sc)
    r = get("ssss").render(frame)
    C = vec_numpy(r.colour["panel"])
    T = truth.V_rgb.reshape(-1, 3)
    x, floor = _floor(frame)
    deep = floor & (x < -3.6)
    assert deep.sum() > 50
    np.testing.assert_allclose(C[deep].mean(0), tA * tB, atol=0.015)
    err = np.sqrt(((C[floor] - T[floor]) ** 2).mean(0))
    assert (err < 0.08).all(), err
    V = truth.V.reshape(-1)[floor]
    rmse = lambda v: float(np.sqrt(((v[floor] - V) ** 2).mean()))  # noqa: E731
    assert rmse(r.visibility["panel"].numpy()) < 0.25 * rmse(get("pcss").render(frame).visibility["panel"].numpy())


def test_other_techniques_see_translucent_casters_as_opaque(panes):
    sc, frame = panes
    r = get("hard").render(frame)
    assert r.colour == {}
    x, floor = _floor(frame)
    assert (r.visibility["panel"].numpy()[floor & (x < -1.0)] == 0.0).all()


def test_only_lights_whose_shadows_have_colour_store_rgb():
    """The committed many_lights reference: the lights that shine through a pane have C.* channels,
    the others (their samples never crossed a coloured surface) only V."""
    from shadowlab.reference import store
    truth, _ = store.load(load("many_lights").spec)
    coloured = {n for n, lt in truth.lights.items() if lt.V_rgb is not None}
    assert {"c1_spot", "c2_a", "sun"} <= coloured
    assert {"lone_bl", "lone_br", "right_spot"}.isdisjoint(coloured)
    for n in coloured:
        lt = truth.lights[n]
        np.testing.assert_allclose(lt.V, lt.V_rgb.mean(-1), atol=1e-6)
        assert not np.array_equal(lt.V_rgb[..., 0], lt.V_rgb[..., 2])
