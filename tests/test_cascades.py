"""Cascaded shadow maps (``csm``, shadowlab/techniques/cascades.py): the split formulas, N = 1 with
the scene fit is ``hard``, selection follows the splits / the maps, stable cascades do not
shimmer under a sub-texel camera move (the box fit does), blending is continuous across a split,
the aliasing AOV is the analytic m̃ on a plane seen head-on, and the bad inputs exit 2."""

import dataclasses

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.techniques import base
from shadowlab.techniques.cascades import (log_splits, practical_splits, select_interval, splits,
                                           uniform_splits)

from conftest import CUDA  # noqa: E402  (tests/ is on the path)
from cross_cpu import grazing_pixels  # noqa: E402
from outdoor_scene import CAMERA, OUTDOOR, SUN  # noqa: E402


@pytest.fixture(scope="module")
def outdoor(mitsuba_backend):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build, parse
    spec = parse(OUTDOOR, "outdoor.toml")
    return spec, make_frame(build(spec), u_strata=1)


def _moved(spec, frame, offset):
    """``frame``'s G-buffer points under a camera translated by ``offset`` (light views follow it)."""
    from shadowlab.render.frame import FrameContext
    from shadowlab.scene import build
    cm = spec.camera
    cam = dataclasses.replace(cm, position=tuple(np.add(cm.position, offset)), target=tuple(np.add(cm.target, offset)))
    sc = build(dataclasses.replace(spec, camera=cam))
    return FrameContext(scene=sc, gbuffer=frame.gbuffer, unshadowed=frame.unshadowed, sdf=frame.sdf)


def _z(frame):
    """View depth of every G-buffer point under ``frame.camera`` (float64)."""
    from shadowlab.render.gbuffer import vec_numpy
    return frame.camera.view_depth(vec_numpy(frame.gbuffer.p))


# ----------------------------------------------------------------------------- splits

@pytest.mark.parametrize("n, f, N", [(0.1, 150.0, 3), (1.0, 1000.0, 8), (0.5, 2.0, 1), (2.0, 64.0, 5)])
def test_split_formulas_match_their_closed_forms(n, f, N):
    i = np.arange(N + 1)
    uni, log = uniform_splits(n, f, N), log_splits(n, f, N)
    assert np.allclose(uni, n + i * (f - n) / N, rtol=1e-12)
    assert np.allclose(log, n * (f / n) ** (i / N), rtol=1e-12)
    assert np.allclose(np.diff(uni), (f - n) / N) and np.allclose(log[1:] / log[:-1], (f / n) ** (1 / N))
    for lam in (0.0, 0.6, 1.0):
        assert np.allclose(practical_splits(n, f, N, lam), lam * log + (1 - lam) * uni, rtol=1e-12)
    for scheme in ("uniform", "log", "practical"):
        c = splits(scheme, n, f, N, 0.6)
        assert len(c) == N + 1 and c[0] == n and c[-1] == f and np.all(np.diff(c) > 0)
    assert np.array_equal(splits("practical", n, f, N, 0.0)[1:-1], uni[1:-1])
    assert np.allclose(splits("practical", n, f, N, 1.0), log, rtol=1e-12)


# ----------------------------------------------------------------------------- N = 1 is hard

def test_one_cascade_with_the_scene_fit_is_hard_bit_for_bit(outdoor):
    _, frame = outdoor
    for bias in ({}, {"depth_bias": 0, "slope_scaled_depth_bias": 0.0, "normal_offset": 1.0}):
        hard = base.get("hard").render(frame, bias).visibility["sun"].numpy()
        csm = base.get("csm").render(frame, {"cascades": 1, "fit": "scene", "filter": "hard", **bias})
        v = csm.visibility["sun"].numpy()
        assert np.array_equal(v, hard)
        assert 0.005 < float(np.mean(v < 0.5)) < 0.95              # the scene has shadows to compare
    pcf = base.get("pcf").render(frame, {"kernel": 5}).visibility["sun"].numpy()
    v = base.get("csm").render(frame, {"cascades": 1, "fit": "scene", "filter": "pcf", "pcf_kernel": 5})
    assert np.array_equal(v.visibility["sun"].numpy(), pcf)


# ----------------------------------------------------------------------------- selection

def test_interval_selection_follows_the_splits(outdoor):
    _, frame = outdoor
    r = base.get("csm").render(
        frame, {"cascades": 4, "split": "log", "shadow_near": 2.0, "blend": 0.0, "filter": "hard"}
    )
    C = np.asarray(r.stats["splits"])
    z = _z(frame)
    valid = frame.gbuffer.mask.reshape(-1)
    sel = r.aovs["sun.cascade"].reshape(-1)
    expect = np.minimum(np.searchsorted(C[1:], z, side="right"), 3)     # beyond C_N: the last one
    assert np.array_equal(sel[valid], expect[valid])
    assert len(set(sel[valid].tolist())) == 4                         # every cascade is used
    assert np.all(r.aovs["sun.blend_weight"] == 0)
    frac = r.stats["cascade_fraction"]["sun"]
    assert np.allclose(frac, [np.mean(expect[valid] == i) for i in range(4)])
    maps = r.stats["lights"]["sun"]["maps"]
    assert [m["split"] for m in maps] == [[C[i], C[i + 1]] for i in range(4)]
    t = [m["texel_world"] for m in maps]
    assert t == sorted(t) and t[0] < t[-1]                            # near cascades are the finer ones


def test_map_based_selection_picks_the_finest_map_holding_the_point(outdoor):
    import mitsuba as mi
    from shadowlab.render.lightview import FrustumSlice
    _, frame = outdoor
    values = {"cascades": 3, "selection": "map", "filter": "hard", "snap": False}
    r = base.get("csm").render(frame, values)
    C = r.stats["splits"]
    views = [frame.light_view("sun", res=256, bits=32, fit=FrustumSlice(C[i], C[i + 1], 2.0, False, "sphere"))
             for i in range(3)]
    inside = np.stack([np.asarray(v.lookup(frame.gbuffer.p)["inside"].numpy()) for v in views])
    valid = frame.gbuffer.mask.reshape(-1)
    first = np.where(inside.any(0), np.argmax(inside, 0), -1)
    sel = r.aovs["sun.cascade"].reshape(-1)
    assert np.array_equal(sel[valid], first[valid])
    assert isinstance(frame.gbuffer.p, mi.Point3f)
    # a point the first map holds beyond its slice still takes that finer map
    z = _z(frame)
    assert np.any((sel == 0) & (z > C[1]) & valid)
    # selection picks finer maps than the interval rule does, never coarser
    ri = base.get("csm").render(frame, {**values, "selection": "interval", "blend": 0.0})
    si = ri.aovs["sun.cascade"].reshape(-1)
    assert np.all(sel[valid] <= si[valid])


# ----------------------------------------------------------------------------- stable cascades

def test_stable_cascades_do_not_shimmer_under_a_sub_texel_move_the_box_fit_does(outdoor):
    spec, frame = outdoor
    t = base.get("csm")
    stable = {"cascades": 3, "fit": "sphere", "snap": True, "filter": "pcf", "resolution": 128}
    r0 = t.render(frame, stable)
    t0 = r0.stats["lights"]["sun"]["maps"][0]["texel_world"]
    moved = _moved(spec, frame, frame.camera.right * 0.3 * t0)       # a third of the finest texel, sideways
    r1 = t.render(moved, stable)
    assert r0.stats["splits"] == r1.stats["splits"]                  # a sideways move keeps the view depths
    for m0, m1 in zip(r0.stats["lights"]["sun"]["maps"], r1.stats["lights"]["sun"]["maps"]):
        assert m0["texel_world"] == m1["texel_world"]
    from shadowlab.render.lightview import FrustumSlice
    C = r0.stats["splits"]
    for i in range(3):                                                # each cascade's texel grid stays put
        fit = FrustumSlice(C[i], C[i + 1], 2.0, True, "sphere")
        f0 = frame.light_view("sun", res=128, fit=fit).proj.faces[0]
        f1 = moved.light_view("sun", res=128, fit=fit).proj.faces[0]
        assert f0.scale == f1.scale and np.allclose(f0.R, f1.R)
        tex = 2 * f0.scale / 128
        R = np.asarray(f0.R)
        corner0 = R[:2] @ np.asarray(f0.origin) - f0.scale           # the grid's lower-left corner
        corner1 = R[:2] @ np.asarray(f1.origin) - f1.scale
        steps = (corner1 - corner0) / tex
        assert np.allclose(steps, np.round(steps), atol=1e-6)
        assert np.allclose(np.mod(corner0 / tex + 0.5, 1.0), 0.5, atol=1e-6)  # on the world's texel lattice
    v0, v1 = r0.visibility["sun"].numpy(), r1.visibility["sun"].numpy()
    if CUDA:   # OptiX's intersector rounds a grazing texel's hit differently as the grid's origin moves
        assert int((np.abs(v1 - v0) > 1e-6).sum()) <= grazing_pixels(v0.size)
    else:
        assert np.max(np.abs(v1 - v0)) <= 1e-6
    box = {**stable, "fit": "box", "snap": False}
    b0, b1 = (t.render(f, box).visibility["sun"].numpy() for f in (frame, moved))
    assert np.mean(np.abs(b1 - b0)) > 0 and np.max(np.abs(b1 - b0)) > 0.1


# ----------------------------------------------------------------------------- blending

def test_blend_weight_is_continuous_across_a_split():
    """s(z) = cascade + weight of the next: with a band it climbs continuously (slope 1/(2bC)) from
    one cascade to the next; without one it jumps by 1 at the split."""
    import drjit as dr
    import mitsuba as mi
    mitsuba_variant = mi.variant()
    assert mitsuba_variant
    C = [1.0, 4.0, 12.0, 30.0]
    z = np.linspace(0.5, 29.9, 200001)
    dz = z[1] - z[0]
    for b in (0.1, 0.25):
        sel, w = select_interval(mi.Float(z.astype(np.float32)), C, b)
        s = np.asarray(sel.numpy(), np.float64) + np.asarray(w.numpy(), np.float64)
        steps = np.abs(np.diff(s))
        assert steps.max() <= dz / (2 * b * C[1]) * 1.01 + 1e-5
        assert s[0] == 0 and s[-1] == 2 and np.all(np.diff(s) >= -1e-6)
        for c in C[1:3]:                                              # the band [(1−b)C, (1+b)C] is where it climbs
            band = (z > (1 - b) * c * 1.0001) & (z < (1 + b) * c * 0.9999)
            assert np.all(w.numpy()[band] > 0)
        assert np.all(w.numpy()[z > (1 + b) * C[2] * 1.0001] == 0)   # the last cascade never blends
    sel, w = select_interval(mi.Float(z.astype(np.float32)), C, 0.0)
    s = np.asarray(sel.numpy(), np.float64) + np.asarray(w.numpy(), np.float64)
    assert np.abs(np.diff(s)).max() == 1.0
    dr.eval()


def test_blended_visibility_interpolates_the_two_cascades(outdoor):
    """In a band the visibility is (1 − w)·V_i + w·V_{i+1} of the two cascades' own visibilities
    (the filter family evaluated on each map), outside it the cascade's own: continuous at both
    ends of the band, where w is 0 and 1."""
    from shadowlab.render.lightview import FrustumSlice
    from shadowlab.techniques.base import RenderContext
    _, frame = outdoor
    values = {"cascades": 3, "split": "uniform", "blend": 0.3, "filter": "hard", "resolution": 128}
    r = base.get("csm").render(frame, values)
    C = r.stats["splits"]
    hard = base.get("hard")
    hv = hard.resolve({"resolution": 128})
    ctx = RenderContext(hard, hv)
    hard.prepare(frame, hv, ctx)
    own = []
    for i in range(3):
        view = frame.light_view("sun", res=128, fit=FrustumSlice(C[i], C[i + 1], 2.0, True, "sphere"))
        lr = hard.evaluate(frame, frame.lights[0], view, hv, ctx)
        a = lr.active.numpy()
        own.append((np.where(a, lr.visibility.numpy(), 1.0), a))
    sel = r.aovs["sun.cascade"].reshape(-1).astype(int)
    w = r.aovs["sun.blend_weight"].reshape(-1)
    v = r.visibility["sun"].numpy()
    valid = frame.gbuffer.mask.reshape(-1)
    band = valid & (w > 0)
    assert band.sum() > 20 and r.stats["blended_fraction"]["sun"] == pytest.approx(band.sum() / valid.sum())
    for i in range(2):
        m = band & (sel == i) & own[i][1] & own[i + 1][1]
        assert m.sum() > 5
        expect = (1 - w[m]) * own[i][0][m] + w[m] * own[i + 1][0][m]
        assert np.allclose(v[m], expect, atol=1e-6)
    pure = valid & (w == 0) & (sel >= 0)
    for i in range(3):
        m = pure & (sel == i)
        assert np.array_equal(v[m], own[i][0][m])
    z = _z(frame)
    for i in range(2):                                                # w rises linearly across the band
        m = band & (sel == i)
        assert np.allclose(w[m], (z[m] / C[i + 1] - 0.7) / 0.6, atol=1e-4)


@pytest.mark.parametrize("filt", ["hard", "pcf", "pcss", "evsm"])
def test_every_point_masked_gives_the_compacted_cascades_bits(outdoor, monkeypatch, filt):
    """A GPU runs each cascade's filter over every point with the cascade's points as its mask
    (no count read back); the CPU gathers the cascade's points first. Per point the same values:
    both paths, run here, agree bit for bit, blend band included."""
    from shadowlab.techniques import cascades
    _, frame = outdoor
    values = {"cascades": 3, "split": "uniform", "blend": 0.3, "filter": filt, "resolution": 128}
    out = {}
    for compact in (True, False):
        monkeypatch.setattr(cascades, "compact_cascades", lambda c=compact: c)
        r = base.get("csm").render(frame, values)
        out[compact] = (r.visibility["sun"].numpy(), {k: v.copy() for k, v in r.aovs.items()})
    assert np.array_equal(out[True][0], out[False][0])
    assert out[True][1].keys() == out[False][1].keys()
    for k in out[True][1]:
        assert np.array_equal(out[True][1][k], out[False][1][k]), k
    w = out[True][1]["sun.blend_weight"]
    assert (w > 0).sum() > 20 and len(np.unique(out[True][1]["sun.cascade"])) >= 3


# ----------------------------------------------------------------------------- aliasing AOV

def test_aliasing_is_the_analytic_measure_on_a_plane_seen_head_on(mitsuba_backend):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build, parse
    D, W, fov = 20.0, 32, 50.0
    scene = {"name": "wall", "camera": {"position": [0, 0, 0], "target": [0, 0, -1], "fov": fov,
                                        "resolution": [W, 24], "near": 0.5, "far": 100.0},
             "lights": [{**SUN, "direction": [0.2, -0.3, -1.0]}],
             "shapes": [{"name": "wall", "type": "rectangle", "translate": [0, 0, -D], "scale": 30.0},
                        {"name": "box", "type": "cube", "translate": [1, 1, -D + 2], "scale": 0.5}]}
    frame = make_frame(build(parse(scene, "wall.toml")), u_strata=1)
    r = base.get("csm").render(frame, {"cascades": 3, "shadow_near": 1.0, "shadow_far": 60.0, "blend": 0.0,
                                       "filter": "hard"})
    maps = r.stats["lights"]["sun"]["maps"]
    sel = r.aovs["sun.cascade"].reshape(-1).astype(int)
    shape = frame.gbuffer.shape_id.reshape(-1)
    wall = (shape == frame.scene.shape_names.index("wall")) & (sel >= 0)
    assert wall.sum() > 100
    n_pixels = W / (2 * np.tan(np.radians(fov) / 2))                  # the near plane's distance in pixels
    dz_ds = np.array([m["texel_world"] for m in maps])[sel[wall]]     # world length per texel
    expect = n_pixels * dz_ds / D                                     # m̃ = n·dz/(z·ds)
    got = r.aovs["sun.aliasing"].reshape(-1)[wall]
    assert np.allclose(got, expect, rtol=1e-5)
    assert np.allclose(r.aovs["sun.texel"].reshape(-1)[wall], dz_ds, rtol=1e-6)


# ----------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("item, allowed", [("csm.cascades=9", r"\[1, 8\]"), ("csm.cascades=0", r"\[1, 8\]"),
                                           ("csm.split_lambda=1.5", r"\[0(\.0)?, 1(\.0)?\]"),
                                           ("csm.split_lambda=-0.1", r"\[0(\.0)?, 1(\.0)?\]"),
                                           ("csm.blend=0.6", r"\[0(\.0)?, 0\.5\]"),
                                           ("csm.blend=-0.01", r"\[0(\.0)?, 0\.5\]"),
                                           ("csm.filter=blur", "hard, pcf, pcss, vsm, esm, evsm, msm")])
def test_bad_csm_values_exit_2_naming_the_valid_values(item, allowed):
    with pytest.raises(InputError, match=allowed) as e:
        base.parse_sets([item], ["csm"])
    assert e.value.exit_code == 2


def test_csm_refuses_a_light_it_does_not_support(mitsuba_backend):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build, parse
    spot = {"name": "lamp", "kind": "spot", "position": [0, 5, 0], "target": [0, 0, -5], "angle": 40.0,
            "power": 100.0}
    scene = {**OUTDOOR, "camera": {**CAMERA, "resolution": [8, 6]}, "lights": [spot]}
    spec = parse(scene, "spot.toml")
    why = base.get("csm").unsupported(spec)
    assert "'lamp'" in why and "spot" in why and "directional" in why
    frame = make_frame(build(spec), u_strata=1)
    with pytest.raises(InputError, match=r"light 'lamp' is a spot light.*orthographic.*directional") as e:
        base.get("csm").render(frame, {})
    assert e.value.exit_code == 2
    assert base.get("pcf").unsupported(spec) is None


def test_filter_parameters_are_the_families_declarations_under_their_prefix():
    csm = base.get("csm")
    for fam in ("pcf", "pcss", "vsm", "esm", "evsm", "msm"):
        for p in base.get(fam).params:
            q = csm.param(p.name if p.name in {b.name for b in base.get("hard").params} else f"{fam}_{p.name}")
            assert (q.default, q.kind, q.lo, q.hi, q.choices, q.differentiable) == \
                (p.default, p.kind, p.lo, p.hi, p.choices, p.differentiable)
    assert base.parse_sets(["csm.pcf_kernel=5", "csm.vsm_min_variance=1e-4"], ["csm"]) == \
        {"csm": {"pcf_kernel": 5, "vsm_min_variance": 1e-4}}
    with pytest.raises(InputError, match="out of range"):
        base.parse_sets(["csm.pcf_kernel=11"], ["csm"])


def test_fit_searches_the_cascade_parameters_and_the_filters(outdoor):
    from shadowlab.fit.run import default_params, parse_ranges, plan
    _, frame = outdoor
    csm = base.get("csm")
    assert default_params(csm, csm.resolve({})) == ("split_lambda", "blend", "pull", "pcf_kernel", "pcf_softness")
    assert default_params(csm, csm.resolve({"filter": "pcss"})) == ("split_lambda", "blend", "pull",
                                                                    "pcss_light_scale")
    assert default_params(csm, csm.resolve({"filter": "hard"}))[3:] == ("slope_scaled_depth_bias", "depth_bias")
    ranges = parse_ranges(["csm.split_lambda=0.2:0.8"], ["csm"])["csm"]
    p = plan("csm", frame, sets={"filter": "vsm"}, ranges=ranges)
    assert p.names == ["split_lambda", "blend", "pull", "vsm_min_variance", "vsm_bleed"]
    dims = {d.name: d for d in p.dims}
    assert (dims["split_lambda"].lo, dims["split_lambda"].hi) == (0.2, 0.8)
    assert dims["split_lambda"].method != "adam" and dims["blend"].method != "adam"


def test_the_report_colours_the_cascades(outdoor, tmp_path):
    """compare's images carry the cascade AOV coloured red, green, blue (Slika 4.3/4.5), and the
    report shows it beside the technique's visibility."""
    from types import SimpleNamespace

    from test_report import make_run, parse_png

    from shadowlab.pipeline import technique_metrics
    from shadowlab.report import build
    _, frame = outdoor
    r = base.get("csm").render(frame, {"cascades": 3, "blend": 0.0, "filter": "hard"})
    H, W = frame.gbuffer.mask.shape[:2]
    mask = frame.gbuffer.mask[..., 0]
    truth = SimpleNamespace(mask=mask, shaded=np.zeros((H, W, 3)), lights={"sun": SimpleNamespace(V=np.ones((H, W)))})
    _, _, imgs = technique_metrics(frame, truth, r)
    col = imgs["cascade"]["sun"]
    sel = r.aovs["sun.cascade"]
    vis = frame.image(r.visibility["sun"])
    for i, rgb in enumerate(([1, 0, 0], [0, 1, 0], [0, 0, 1])):
        m = (sel == i) & mask & (vis == 1.0)
        assert m.sum() > 0 and np.allclose(col[m], np.array(rgb) * 1.0, atol=1 / 255)
    run = make_run(names=("pcf",))
    N = run["resolution"][0]
    cas = np.zeros((N, N, 3))
    cas[:, : N // 2, 0] = 1.0
    cas[:, N // 2:, 2] = 1.0
    run["images"]["techniques"]["pcf"].update(cascade={"key": cas}, panels=base.get("csm").panels)
    index = build(tmp_path / "rep", run)
    html = index.read_text()
    pngs = [p for p in (tmp_path / "rep" / "img").iterdir() if "cascade" in p.name]
    assert len(pngs) == 1 and pngs[0].name in html and "cascades" in html
    px = parse_png(pngs[0].read_bytes())
    assert px[0, 0].tolist() == [255, 0, 0] and px[0, -1].tolist() == [0, 0, 255]


def test_filter_footprints_keep_their_world_size_in_every_cascade():
    """A cascade with texels 1/k as fine as cascade 0's (k = t_0/t_i) taps pcf at softness·k of its
    own texels and blurs prefiltered maps over max(1, round(kernel·k)) texels: the same world size."""
    from shadowlab.techniques.cascades import CSM
    t0, ti = 0.05, 0.2
    k = t0 / ti
    pcf = CSM.cascade_values("pcf", {"softness": 2.0, "kernel": 5}, k)
    assert pcf["softness"] * ti == pytest.approx(2.0 * t0) and pcf["kernel"] == 5
    assert CSM.cascade_values("vsm", {"kernel": 9}, k)["kernel"] == 2
    assert CSM.cascade_values("msm", {"kernel": 3}, k)["kernel"] == 1
    assert CSM.cascade_values("esm", {"kernel": 7}, 1.0)["kernel"] == 7
    same = {"light_scale": 1.0, "min_filter": 1.0, "normal_offset": 1.0, "slope_scaled_depth_bias": 2.0}
    assert CSM.cascade_values("pcss", same, k) == same                 # light-size widths are world sizes already
    assert CSM.cascade_values("hard", same, k) == same                 # acne biases stay per texel
