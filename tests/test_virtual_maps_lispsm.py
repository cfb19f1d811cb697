"""LiSPSM focusing of the virtual maps (``warp`` = ``lispsm``; shadowlab/render/tiles.py ``Warp``,
techniques/virtual_maps.py ``lispsm_warp``) from the properties of [Wimmer 2004, §4–5]: the warp and
its inverse agree; the texel density along the view axis falls as 1/b², (1 + d/n)² from the near
end to the far end; n_opt = (z_n + √(z_n·z_f))/sin γ, so at γ = 90° n = z_n + √(z_n·z_f) and as
γ → 0 the warp tends to the orthographic fit; a point on a texel centre looks up that texel and its
ray's depth is the surface's; the slope bias is the depth's slope per warped texel; and the warped
map of a view over a floor leaves fewer wrong pixels than the orthographic one of as many texels."""

import math

import numpy as np
import pytest

from shadowlab.techniques import base

from scene_builder import floor, frame_from, scene  # noqa: E402  (tests/ is on the path)

#: a sun straight down and a camera looking horizontally: γ = 90°
SUN_DOWN = {"name": "sun", "kind": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 3.0,
            "angular_diameter": 0.0, "shadow_map": 256}
CAM_LEVEL = {"position": [0.0, 1.7, 0.0], "target": [0.0, 1.7, -20.0], "fov": 60, "near": 0.1, "far": 80.0}
POSTS = [{"name": f"post{i}", "type": "cube", "translate": [0.6 * (-1) ** i, 0.6, -3.0 - 4.0 * i],
          "scale": [0.08, 0.6, 0.08]} for i in range(6)]


def _warp(**kw):
    from shadowlab.render.tiles import Warp
    return Warp(**{"ex": 0.6, "ey": 0.8, "a0": 0.1, "b_min": -0.9, "n": 0.3, "d": 1.7, "p0": -2.0, "p1": 2.5, **kw})


# ----------------------------------------------------------------------------- the warp's closed forms

def test_the_warp_and_its_inverse_agree_and_the_jacobian_is_the_inverse_s_derivative():
    w = _warp()
    rng = np.random.default_rng(0)
    X, Y = rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200)
    x, y = w.invert(X, Y)
    X2, Y2 = w.apply(x, y)
    assert np.max(np.abs(X2 - X)) < 1e-12 and np.max(np.abs(Y2 - Y)) < 1e-12
    h = 1e-6
    fd = [(np.subtract(*[w.invert(X + s * h, Y)[k] for s in (1, -1)]) / (2 * h)) for k in (0, 1)]
    fd += [(np.subtract(*[w.invert(X, Y + s * h)[k] for s in (1, -1)]) / (2 * h)) for k in (0, 1)]
    for got, want in zip(w.jacobian(X, Y), fd):
        assert np.allclose(got, want, rtol=1e-6, atol=1e-9)


def test_the_warp_in_dr_jit_equals_the_numpy_warp(mitsuba_backend):
    import drjit as dr
    import mitsuba as mi
    w = _warp()
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-1, 1, 100), rng.uniform(-1, 1, 100)
    X, Y = w.apply(mi.Float(x), mi.Float(y))
    dr.eval(X, Y)
    Xn, Yn = w.apply(x, y)
    assert np.allclose(X.numpy(), Xn, atol=2e-5) and np.allclose(Y.numpy(), Yn, atol=2e-5)
    xi, yi = w.invert(mi.Float64(Xn), mi.Float64(Yn))
    assert np.allclose(xi.numpy(), x, atol=1e-12) and np.allclose(yi.numpy(), y, atol=1e-12)


@pytest.mark.parametrize("n, d", [(0.3, 1.7), (2.0, 0.5), (50.0, 1.0)])
def test_texel_density_along_the_axis_falls_as_one_over_b_squared(n, d):
    """dY/db = 2n(n + d)/(d·b²) [Wimmer 2004, §4]: the near end (b = n) gets (1 + d/n)² times the
    texels per unit length of the far end (b = n + d); across the axis (at fixed b) the density
    is constant."""
    w = _warp(n=n, d=d)
    e = np.array([w.ex, w.ey])
    start = e * w.b_min + np.array([-w.ey, w.ex]) * w.a0      # the body's near end, on the centre's line
    dens = []
    for b in (n, n + d, n + 0.5 * d):
        p, h = start + e * (b - n), 1e-6 * d
        (_, Y1), (_, Y0) = w.apply(*(p + e * h)), w.apply(*(p - e * h))
        dens.append((Y1 - Y0) / (2 * h))
        assert dens[-1] == pytest.approx(2 * n * (n + d) / (d * b * b), rel=1e-6)
    assert dens[0] / dens[1] == pytest.approx((1 + d / n) ** 2, rel=1e-6)
    # the body's ends are the square's: Y = −1 at the near end, +1 at the far end
    assert w.apply(*start)[1] == pytest.approx(-1.0, abs=1e-12)
    assert w.apply(*(start + e * d))[1] == pytest.approx(1.0, abs=1e-12)


def _face(light_dir, scale=10.0):
    from shadowlab.render.lightview import Face
    f = np.asarray(light_dir, np.float64)
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.cross(f, [1.0, 0.0, 0.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return Face((0.0, 20.0, -10.0), (tuple(r), tuple(u), tuple(f)), True, scale, 0.01, 40.0)


def _camera(forward):
    from shadowlab.render.camera import Camera
    return Camera((0.0, 1.7, 0.0), np.array([0.0, 1.7, 0.0]) + np.asarray(forward, np.float64), fov=60)


def _body():
    """400 base NDC points (x, y)."""
    rng = np.random.default_rng(3)
    return tuple(rng.uniform(-0.9, 0.9, (2, 400)))


def test_n_opt_at_ninety_degrees_is_z_n_plus_the_root_of_z_n_z_f():
    """[Wimmer 2004, §5]: with the light perpendicular to the view, n_opt = z_n + √(z_n·z_f), in
    metres: the warp's n (base NDC units) times the map's half extent."""
    from shadowlab.techniques.virtual_maps import lispsm_warp
    face = _face([0.0, -1.0, 0.0], scale=10.0)
    for zn, zf in ((0.5, 40.0), (2.0, 30.0)):
        w = lispsm_warp(face, _camera([0.0, 0.0, -1.0]), _body(), zn, zf)
        assert w.n * face.scale == pytest.approx(zn + math.sqrt(zn * zf), rel=1e-12)
    w2 = lispsm_warp(face, _camera([0.0, 0.0, -1.0]), _body(), 0.5, 40.0, n_scale=0.25)
    assert w2.n * face.scale == pytest.approx(0.25 * (0.5 + math.sqrt(20.0)), rel=1e-12)


def test_the_perspective_centre_lies_on_the_eye_s_line_along_the_axis():
    """[Wimmer 2004, §5]: the centre of projection is placed in line with the eye, so the line
    through the eye along the view axis (in the light's plane) is one column of the warped map."""
    from shadowlab.techniques.virtual_maps import base_ndc, lispsm_warp
    face = _face([0.3, -1.0, 0.2], scale=10.0)
    cam = _camera([0.4, -0.2, -1.0])
    w = lispsm_warp(face, cam, _body(), 0.5, 40.0)
    eye = base_ndc(face, cam.position)[0]
    e = np.array([w.ex, w.ey])
    pts = eye + np.outer(np.linspace(0.0, 1.5, 7), e)
    X, Y = w.apply(pts[:, 0], pts[:, 1])
    assert np.ptp(X) < 1e-12 and np.ptp(Y) > 0.5


@pytest.mark.parametrize("gamma_deg", [60.0, 30.0, 10.0])
def test_n_grows_as_one_over_sin_gamma(gamma_deg):
    from shadowlab.techniques.virtual_maps import lispsm_warp
    g = math.radians(gamma_deg)
    face = _face([0.0, -math.sin(g), -math.cos(g)])    # γ between the light and a view along −z
    w = lispsm_warp(face, _camera([0.0, 0.0, -1.0]), _body(), 1.0, 50.0)
    assert w.n * face.scale * math.sin(g) == pytest.approx(1.0 + math.sqrt(50.0), rel=1e-9)


def test_as_the_light_turns_toward_the_view_the_warp_tends_to_the_orthographic_fit():
    """γ → 0: n_opt → ∞ and the warp becomes affine, the body's bounding box in the rotated
    frame mapped onto the square; at γ = 0 there is nothing to warp (None)."""
    from shadowlab.techniques.virtual_maps import lispsm_warp
    body = np.stack(_body(), -1)
    errs = []
    for g in (1e-1, 1e-2, 1e-3):
        face = _face([0.0, -math.cos(g), -math.sin(g)])
        w = lispsm_warp(face, _camera([0.0, -1.0, 0.0]), tuple(body.T), 1.0, 50.0)
        e = np.array([w.ex, w.ey])
        al, la = body @ e, body @ np.array([-e[1], e[0]])
        aff = np.stack([2 * (la - la.min()) / np.ptp(la) - 1, 2 * (al - al.min()) / np.ptp(al) - 1], -1)
        got = np.stack(w.apply(body[:, 0], body[:, 1]), -1)
        errs.append(np.max(np.abs(got - aff)))
    assert errs[0] > errs[1] > errs[2] and errs[2] < 2e-3
    assert lispsm_warp(_face([0.0, -1.0, 0.0]), _camera([0.0, -1.0, 0.0]), tuple(body.T), 1.0, 50.0) is None


# ----------------------------------------------------------------------------- through the technique

@pytest.fixture(scope="module")
def level(mitsuba_backend):
    """A sun straight down over a floor with posts, seen by a level camera (γ = 90°)."""
    return frame_from(scene("level", camera=CAM_LEVEL, resolution=(96, 64), lights=[SUN_DOWN],
                            shapes=[floor(40.0)] + POSTS))


def _tiled(frame, values, tiles=None):
    from shadowlab.render.tiles import Tiles, render_tiles
    t = base.get("fvsm")
    v = t.resolve(values)
    light = frame.lights[0]
    b = t.base(frame, light, v)
    w = t.warp(frame, v, b)
    tiles = tiles or Tiles([-1.0], [-1.0], [1.0], [1.0], [64], [64])
    return b, w, render_tiles(frame.scene, light, b, tiles, 32, False, w)


def test_the_visible_focus_takes_n_from_the_visible_depths(level):
    from shadowlab.render.gbuffer import vec_numpy
    b, w, _ = _tiled(level, {"warp": "lispsm", "focus": "visible"})
    gb = level.own_gbuffer
    z = level.camera.view_depth(vec_numpy(gb.p)[np.asarray(gb.valid.numpy(), bool).reshape(-1)])
    zn, zf = max(z.min(), level.camera.near), z.max()
    assert w.n * b.faces[0].scale == pytest.approx(zn + math.sqrt(zn * zf), rel=1e-6)   # float32 depths


def test_a_point_on_a_texel_centre_looks_up_that_texel_and_its_depth_is_the_surface_s(level):
    """A texel's ray starts at the inverse warp of its centre: on the floor (y = 0) under a sun
    straight down its depth is the light plane's height over the floor; a point placed on that
    centre's ray reads texel (i + ½, j + ½)."""
    import drjit as dr
    import mitsuba as mi
    b, w, tv = _tiled(level, {"warp": "lispsm"})
    f0 = b.faces[0]
    i, j = np.meshgrid(np.arange(0, 64, 3), np.arange(0, 64, 3))
    X, Y = -1.0 + (i + 0.5) * 2 / 64, 1.0 - (j + 0.5) * 2 / 64
    x, y = w.invert(X.ravel(), Y.ravel())
    R, o = np.asarray(f0.R), np.asarray(f0.origin)
    q = np.stack([(x + f0.shift[0]) * f0.scale, (y + f0.shift[1]) * f0.scale], -1)
    z_floor = (o[1] + q @ R[:2, 1]) / -R[2, 1]                # light-space depth where the ray meets y = 0
    P = o + q @ R[:2] + z_floor[:, None] * R[2]
    tvb = tv.bind(mi.Int32(np.zeros(len(P), np.int32)))
    rec = tvb.lookup(mi.Point3f(*[mi.Float(P[:, c].astype(np.float32)) for c in range(3)]))
    dr.eval(rec["u"], rec["v"])
    assert np.allclose(rec["u"].numpy(), (i + 0.5).ravel(), atol=2e-3)
    assert np.allclose(rec["v"].numpy(), (j + 0.5).ravel(), atol=2e-3)
    # the texel's world size at the point: the larger of its sides, between neighbouring centres
    side = [np.linalg.norm(np.stack(w.invert(X.ravel() + dX, Y.ravel() + dY), -1)
                           - np.stack(w.invert(X.ravel() - dX, Y.ravel() - dY), -1), axis=1)
            for dX, dY in ((1 / 64, 0.0), (0.0, 1 / 64))]
    assert np.allclose(rec["texel"].numpy(), np.maximum(*side) * f0.scale, rtol=5e-3)
    depth = tv.depth.numpy().reshape(64, 64)[j.ravel(), i.ravel()]
    on_floor = np.abs(np.abs(P[:, 0]) - 0.6) > 0.2              # away from the posts' column
    want = f0.ndc_depth(z_floor)
    assert np.mean(on_floor) > 0.5
    assert np.max(np.abs(depth - want)[on_floor]) < 1e-5


def test_the_slope_bias_is_the_depth_slope_per_warped_texel(mitsuba_backend):
    """The stored slope is max(|∂d/∂X|·ΔX, |∂d/∂Y|·ΔY) in the warped square: on a tilted plane it
    equals the difference of neighbouring texels' depths (which the orthographic texel widths
    would get wrong by the warp's stretch, growing toward the near end)."""
    ramp = {"name": "ramp", "type": "rectangle", "rotate": [1, 0, 0, -70], "scale": 40.0}
    cam = {"position": [0.0, 3.0, 6.0], "target": [0.0, 0.0, -10.0], "fov": 60, "near": 0.1, "far": 80.0}
    sun = {**SUN_DOWN, "direction": [0.2, -1.0, 0.1]}
    fr = frame_from(scene("ramp", camera=cam, resolution=(64, 48), lights=[sun], shapes=[ramp]))
    _, w, tv = _tiled(fr, {"warp": "lispsm"})
    assert w is not None
    d = tv.depth.numpy().reshape(64, 64).astype(np.float64)
    s = tv.slope.numpy().reshape(64, 64)
    dx = np.abs(d[1:-1, 2:] - d[1:-1, :-2]) / 2
    dy = np.abs(d[2:, 1:-1] - d[:-2, 1:-1]) / 2
    fd = np.maximum(dx, dy)
    inner = s[1:-1, 1:-1]
    hit = (d[1:-1, 1:-1] < 1.0) & (d[2:, 1:-1] < 1) & (d[:-2, 1:-1] < 1) & (d[1:-1, 2:] < 1) & (d[1:-1, :-2] < 1)
    assert hit.mean() > 0.5
    rel = np.abs(inner - fd)[hit] / fd[hit]
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05


def test_lispsm_leaves_fewer_wrong_pixels_than_the_orthographic_map_of_as_many_texels(mitsuba_backend):
    """[Wimmer 2004, §1]: the warp spends the texels where the view needs them. One ordinary
    focused map each (vtsm's one tile of t_max²) over a floor seen at grazing angles: the
    warped map gets more of the posts' shadows right, and its near texels are (1 + d/n)² denser."""
    from shadowlab.reference.truth import centre_visibility
    sun = {**SUN_DOWN, "direction": [0.6, -1.0, 0.2]}        # the posts' shadows fall beside them
    level = frame_from(scene("level", camera=CAM_LEVEL, resolution=(96, 64), lights=[sun],
                             shapes=[floor(40.0)] + POSTS))
    centre = centre_visibility(level, "sun").numpy() >= 0.5
    valid = np.asarray(level.gbuffer.valid.numpy(), bool)
    err, texels = {}, {}
    for warp in ("ortho", "lispsm"):
        r = base.get("vtsm").render(level, {"warp": warp, "grid": 1, "t_max": 256})
        v = r.visibility["sun"].numpy() >= 0.5
        err[warp] = float(np.mean(v[valid] != centre[valid]))
        texels[warp] = r.stats["lights"]["sun"]["texels"]
        if warp == "lispsm":
            lp = r.stats["lights"]["sun"]["lispsm"]
            assert lp["density_ratio"] == pytest.approx((1 + lp["depth"] / lp["n"]) ** 2)
    assert texels["ortho"] == texels["lispsm"] == 256 * 256
    assert np.mean(~centre[valid]) > 0.01                   # shadows are there to get right
    assert err["lispsm"] < 0.6 * err["ortho"]


def test_under_the_warp_every_pixel_gets_at_least_one_texel_of_its_tile(level):
    """[Giegl 2007, §4.3] in the warped square: with ξ = 0, nothing discarded and every pixel in
    the SMTMM, a pixel whose demand the grid can meet reads a tile with at least one texel
    across its footprint per axis: the half extent Δ of its footprint, measured here through the
    warp from the pixel's right and lower neighbours on the floor, times the tile's texels per
    NDC unit 2^provided/2, is at least ½. A demand taken in the unwarped map fails this where the
    warp compresses the map (the far end). No overlap: a later tile's overlap ring may give a
    neighbouring cell's pixels fewer texels, with or without the warp."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.render.tiles import face_ndc
    from shadowlab.techniques.virtual_maps import demand_level
    values = {"warp": "lispsm", "grid": 8, "t_max": 256, "xi": 0, "smtmm_scale": 1, "discard": 0.0, "overlap": 0}
    r = base.get("fvsm").render(level, values)
    t = base.get("fvsm")
    v = t.resolve(values)
    b = t.base(level, level.lights[0], v)
    w = t.warp(level, v, b)
    scr = level.screen
    P = scr.position
    ndc = [face_ndc(b.faces[0], q, w) for q in (P, scr.gather("position", 1, 0), scr.gather("position", 0, 1))]
    dr.eval(ndc)
    X, Y = [np.stack([a[k].numpy() for a in ndc]) for k in (0, 1)]
    ok = (scr.valid & scr.gather("valid", 1, 0) & scr.gather("valid", 0, 1) & (scr.x < scr.width - 1)
          & (scr.y < scr.height - 1)).numpy().astype(bool)
    ok &= np.abs(mi.Float(P.y).numpy()) < 1e-3                   # on the floor
    H, W = scr.height, scr.width
    cap = int(math.log2(8 * 256))
    for axis, A in (("x", X), ("y", Y)):
        delta = 0.5 * (np.abs(A[1] - A[0]) + np.abs(A[2] - A[0]))
        need = demand_level(delta)
        prov = r.aovs[f"sun.provided_{axis}"].reshape(-1)
        m = ok & (need <= cap) & (r.aovs["sun.tile"].reshape(-1) >= 0)
        assert m.sum() > 0.3 * H * W
        texels = delta * 2.0 ** prov / 2.0
        # a few pixels beside the posts take the other neighbour (the smaller |Δz|) in the demand
        assert np.mean(texels[m] >= 0.5 * (1 - 1e-3)) > 0.99, axis


def test_each_pixel_reads_a_tile_that_holds_its_warped_position(level):
    """[Giegl 2007, §3.2]: a tile writes the pixels whose points fall in its texture, here the
    warped square's rectangle of the tile."""
    import drjit as dr
    from shadowlab.render.tiles import face_ndc
    values = {"warp": "lispsm", "grid": 8, "t_max": 64, "uncovered": "lit"}
    t = base.get("fvsm")
    v = t.resolve(values)
    b = t.base(level, level.lights[0], v)
    w = t.warp(level, v, b)
    tiles = t.plan(level, level.lights[0], v, b, w)[0]
    r = t.render(level, values)
    assert r.stats["lights"]["sun"]["tiles"] == len(tiles) > 4
    X, Y, _ = face_ndc(b.faces[0], level.gbuffer.p, w)
    dr.eval(X, Y)
    X, Y = X.numpy(), Y.numpy()
    k = r.aovs["sun.tile"].reshape(-1).astype(np.int64)
    has = k >= 0
    assert has.mean() > 0.35                                   # the floor: the lower half of the view
    kk = k[has]
    eps = 1e-6
    assert np.all((X[has] >= tiles.x0[kk] - eps) & (X[has] <= tiles.x1[kk] + eps))
    assert np.all((Y[has] >= tiles.y0[kk] - eps) & (Y[has] <= tiles.y1[kk] + eps))
