"""Sphere tracing, cone tracing and the cone-traced G-buffer ([Bán 2019, §2.7–2.9], §3.1)
against Mitsuba ray intersections of the SDF twins, closed forms, and dense marching."""

import numpy as np
import pytest

from shadowlab import backend
from shadowlab.errors import InputError
from shadowlab.render.gbuffer import gbuffer, vec_numpy
from shadowlab.scene import load
from shadowlab.render.sdf_gbuffer import SDFGBuffer, cone_gbuffer, pixel_tan_alpha
from shadowlab.render.sdf_gbuffer import unshadowed as sdf_unshadowed
from shadowlab.scene.twins import sdf_of
from shadowlab.sdf import Mandelbulb, Sphere, cone_trace, hard_visibility, sphere_trace

backend.init()
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from conftest import CUDA  # noqa: E402


def _vec(a, cls=None):
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    return (cls or mi.Vector3f)(*(mi.Float(np.ascontiguousarray(a[:, i], dtype=np.float32)) for i in range(3)))


# scenes whose occluders are solids (no free-standing rectangles or discs, whose 2 cm slab twins
# differ from Mitsuba's zero-thickness surfaces when seen edge-on or from behind)
SOLID_TWINS = ["sdf_simple", "sdf_pointed", "sdf_thin", "contact"]


@pytest.mark.parametrize("name", SOLID_TWINS)
def test_sphere_trace_hits_match_mitsuba_intersections_of_the_twin(name):
    """Camera rays and rays leaving the visible surfaces towards the light: the sphere-traced hit
    point equals Mitsuba's intersection with the twin's Mitsuba primitives within 1e-3, and both
    agree on which rays hit (but for rays grazing a surface within eps)."""
    sc = load(name)
    sdf, gb = sdf_of(sc), gbuffer(sc)
    rays = [(mi.Vector3f(gb.rays.o), mi.Vector3f(gb.rays.d), None)]
    # rays from every surface point towards points around the light (outside its sphere), where
    # they leave the surface (a ray into the solid is a hit at t = 0 for the SDF, at its far side
    # for Mitsuba)
    rng = np.random.default_rng(0)
    P = vec_numpy(gb.p)
    light = sc.spec.lights[0]
    u = rng.normal(size=P.shape)
    tgt = np.asarray(light.position) + u / np.linalg.norm(u, axis=1, keepdims=True) * 2 * max(light.radius, 0.3)
    d = tgt - P
    L = np.linalg.norm(d, axis=1)
    d /= L[:, None]
    o = _vec(P + d * 1e-3)
    # (not from points where the surface touches another solid: there the origin is inside it)
    leaving = gb.valid.numpy() & ((vec_numpy(gb.ng) * d).sum(1) > 0.05) & (sdf.distance(o).numpy() > 1e-5)
    rays.append((o, _vec(d), mi.Float((L - 2e-3).astype(np.float32))))
    checked = 0
    for o, dd, maxt in rays:
        tmax = maxt if maxt is not None else mi.Float(1e3)
        hit, t, _ = sphere_trace(sdf, o, dd, tmax, eps=1e-5, i_max=2000)
        ray = mi.Ray3f(mi.Point3f(o), dd)
        ray.maxt = tmax
        si = sc.mi_scene.ray_intersect(ray)
        mh = si.is_valid() & ~si.shape.is_emitter()
        dr.eval(hit, t, mh, si.p)
        sel = leaving if maxt is not None else np.ones_like(leaving)
        h, m = hit.numpy() & sel, mh.numpy() & sel
        # a ray that passes within eps of a surface is a hit for the SDF, not for Mitsuba
        # (measured: 1 of ~10⁴ rays on contact, grazing its pole after 357 steps)
        assert (h != m).sum() <= 5e-4 * sel.sum(), f"{(h != m).sum()} rays hit in one and not the other"
        assert not (m & ~h).any(), "sphere tracing missed a surface Mitsuba hits"
        h &= m
        err = np.linalg.norm(vec_numpy(o + dd * t) - vec_numpy(si.p), axis=1)[h]
        assert err.max() <= 1e-3, f"hit points differ by up to {err.max():.2e}"
        checked += h.sum()
    assert checked > 10000


def _interior(ids, mask, normals=None, cos_crease=np.cos(np.radians(10))):
    """Pixels whose 3×3 neighbourhood is one shape (and, with normals, has no crease > 10°)."""
    H, W = ids.shape
    pad = np.pad(np.where(mask, ids, -1), 1, mode="edge")
    ok = mask.copy()
    npad = None if normals is None else np.pad(normals, ((1, 1), (1, 1), (0, 0)), mode="edge")
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            ok &= pad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] == np.where(mask, ids, -1)
            if npad is not None:
                ok &= (npad[1 + dy:1 + dy + H, 1 + dx:1 + dx + W] * normals).sum(-1) > cos_crease
    return ok


@pytest.mark.parametrize("name,max_excluded", [("sdf_simple", 0.2), ("sdf_pointed", 0.1), ("sdf_composite", 0.4)])
def test_cone_traced_gbuffer_agrees_with_mitsuba_gbuffer(name, max_excluded):
    """Where both hit, away from silhouettes and creases (pixels whose 3×3 neighbourhood holds
    another shape, a miss, or a normal turning by > 10° in either G-buffer: measured 14 % of the
    hit pixels on sdf_simple, 6 % on sdf_pointed, 33 % on sdf_composite's 26 small objects):

    * the centre ray's hit (``p_surface``) is Mitsuba's: within a quarter of the pixel's footprint
      (measured ≤ 4e-4 m), depth within 1e-3 relative, normal within 1°;
    * the surface point ``p`` ([Bán 2019, §2.9]) lies on the camera ray in front of Mitsuba's hit by at
      least its ball's radius (the ball is empty) and by at most (1 + κ) cone radii / |cos θ|
      (measured 1.00–1.255), with its normal within 6° (curvature over that gap) and U within
      6 % of the largest U (the point is that much closer to the light);
    * the pixel-covering cone never misses what the centre ray hits."""
    from shadowlab.render.shading import unshadowed
    from shadowlab.sdf.trace import CONE_KAPPA
    sc = load(name)
    sdf = sdf_of(sc)
    g, c = gbuffer(sc), cone_gbuffer(sc, sdf)
    W, H = sc.resolution
    mm, mc = g.mask[..., 0], c.mask[..., 0]
    assert not (mm & ~mc).any(), "the pixel cone missed a surface the pixel centre's ray hits"
    assert (mc & ~mm).mean() < 0.015   # cones also catch silhouettes that centre rays pass
    names = [n.split("__")[0] for n in sc.shape_names]
    prim_names = [p.name for p in sdf.primitives]
    im = np.array([prim_names.index(names[i]) if i >= 0 else -1 for i in g.shape_id.ravel()]).reshape(H, W)
    ic = c.shape_id[..., 0]
    nm = vec_numpy(g.n).reshape(H, W, 3)
    ns = vec_numpy(c.n_surface).reshape(H, W, 3)
    keep = _interior(im, mm, nm) & _interior(ic, mc, ns) & (im == ic)
    both = mm & mc
    excluded = 1 - keep.sum() / both.sum()
    assert excluded <= max_excluded, f"{excluded:.1%} of the pixels excluded"
    k = keep.ravel()
    cam = np.asarray(sc.spec.camera.position)
    depth_m = g.view_depth.reshape(-1)[k]
    ps = vec_numpy(c.p_surface)[k]
    footprint = depth_m * 2 * pixel_tan_alpha(sc.spec.camera)   # pixel diagonal at that depth
    pos = np.linalg.norm(vec_numpy(g.p)[k] - ps, axis=1)
    assert np.all(pos <= 0.25 * footprint), f"position off by {np.max(pos / footprint):.2f} pixel"
    assert np.all(np.abs(np.linalg.norm(ps - cam, axis=1) - depth_m) <= 1e-3 * depth_m)
    cos = (nm.reshape(-1, 3)[k] * ns.reshape(-1, 3)[k]).sum(1)
    assert np.all(cos >= np.cos(np.radians(1.0))), f"normals differ by up to {np.degrees(np.arccos(cos.min())):.2f}°"
    assert np.allclose(g.albedo[keep], c.albedo[keep], atol=1e-6)
    # the surface point and its ball
    gap = depth_m - c.view_depth.reshape(-1)[k]
    radius = c.radius.numpy()[k]
    cone_r = c.t.numpy()[k] * c.tan_alpha
    cos_i = np.abs((nm.reshape(-1, 3)[k] * vec_numpy(g.rays.d)[k]).sum(1))
    assert np.all(gap >= radius - 1e-5), "the surface point's ball reaches past the surface"
    assert np.all(radius >= cone_r - 1e-4), "the ball does not cover the pixel cone"
    assert np.all(gap * cos_i <= (1 + CONE_KAPPA) * cone_r * 1.01 + 1e-4)
    cos = (nm.reshape(-1, 3)[k] * vec_numpy(c.n)[k]).sum(1)
    assert np.all(cos >= np.cos(np.radians(6.0)))
    light = sc.spec.lights[0].name
    Um = vec_numpy(unshadowed(sc, g, light)).sum(1)[k]
    Uc = vec_numpy(sdf_unshadowed(sc, c, light)).sum(1)[k]
    assert np.all(np.abs(Uc - Um) <= 0.06 * Um.max())


def test_cone_trace_stops_where_the_cone_first_touches_a_sphere():
    """Cone of half-angle α along +z past a ball (centre (b, 0, z0), radius R): the trace must stop
    between the first t where f = (1 + κ)·t·tanα + eps and the first t where f = t·tanα ([Bán 2019, §2.8]:
    each step keeps the cone's slice inside the empty ball); without such a t it misses."""
    from shadowlab.sdf.trace import CONE_KAPPA
    R, z0, ta, eps = 0.5, 4.0, 0.05, 1e-4
    b = np.linspace(0.0, 1.2, 241)
    ball = Sphere((0, 0, z0), R)
    o = _vec(np.stack([-b, np.zeros_like(b), np.zeros_like(b)], 1))   # move the ray, not the ball
    hit, t, _ = cone_trace(ball, o, mi.Vector3f(0, 0, 1), 10.0, ta, eps=eps)
    hit, t = hit.numpy(), t.numpy()
    ts = np.linspace(0, 10, 200001)
    f = np.sqrt(b[:, None] ** 2 + (ts[None] - z0) ** 2) - R
    first = lambda cond: np.where(cond.any(1), ts[np.argmax(cond, 1)], np.inf)  # noqa: E731
    t_touch = first(f <= ts * ta)
    t_stop_earliest = first(f < (1 + CONE_KAPPA) * ts * ta + eps)
    assert np.array_equal(hit, np.isfinite(t_stop_earliest))
    h = hit
    assert np.all(t[h] >= t_stop_earliest[h] - 1e-4) and np.all(t[h] <= t_touch[h] + 1e-4)
    # a ray through the ball is a hit, a ray far off is not; tanα = 0 is sphere tracing
    assert hit[0] and not hit[-1]
    h0, t0, _ = cone_trace(ball, o, mi.Vector3f(0, 0, 1), 10.0, 0.0, eps=eps, kappa=0.0)
    h1, t1, _ = sphere_trace(ball, o, mi.Vector3f(0, 0, 1), 10.0, eps=eps)
    assert np.array_equal(h0.numpy(), h1.numpy()) and np.allclose(t0.numpy(), t1.numpy(), atol=1e-4)


@dr.syntax
def _dense_march(sdf, o, d, t_max, h):
    """First sample (step h) where the field is negative: inside the solid."""
    t = dr.zeros(mi.Float, dr.width(o))
    found = mi.Bool(False)
    while ~found & (t < t_max):
        found = sdf.distance(o + d * t) < 0.0
        t = dr.select(found, t, t + h)
    return found, t


def test_mandelbulb_sphere_tracing_does_not_tunnel():
    """The distance estimator as a step size: sphere tracing never passes the first point that a
    dense march (steps of 2.5e-4) finds inside the fractal by more than 1 cm (about half a pixel
    of the mandelbulb scene; the estimator is not a strict bound in the fractal's fuzz), and it
    finds every ray the march finds."""
    m = Mandelbulb()
    rng = np.random.default_rng(1)
    n = 512
    o = rng.normal(size=(n, 3))
    o *= 2.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.7, 0.7, size=(n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    O, D = _vec(o), _vec(d)
    hit, t, its = sphere_trace(m, O, D, 4.0, eps=1e-4, i_max=2000)
    found, tm = _dense_march(m, O, D, mi.Float(4.0), mi.Float(2.5e-4))
    hit, t, found, tm = hit.numpy(), t.numpy(), found.numpy(), tm.numpy()
    assert found.sum() > 0.8 * n
    assert np.all(hit[found]), "sphere tracing missed a ray that passes through the fractal"
    # cuda_ad_rgb evaluates the estimator's sin/cos/log2/exp2 with the GPU's approximate
    # instructions (a few ulps; the power-8 fold amplifies them near the fuzz), so there the
    # tolerance is one pixel, 2 cm (measured on an H200: 1.8 cm)
    tol = 0.02 if CUDA else 0.01
    assert np.all(t[found] <= tm[found] + tol), f"tunnelled by {np.max(t[found] - tm[found]):.3f}"
    # and its hits are on the surface: the estimate there is below eps
    P = _vec(o[hit] + d[hit] * t[hit, None])
    assert np.all(m.distance(P).numpy() < 1e-4)


def test_hard_visibility_matches_mitsuba_shadow_rays():
    """Hard shadows of the light's centre ([Bán 2019, §3.1]) at the Mitsuba G-buffer's points: the SDF
    sphere trace and Mitsuba's ray_test agree except for rays that graze an occluder."""
    sc = load("sdf_simple")
    sdf, gb = sdf_of(sc), gbuffer(sc)
    c = mi.Vector3f(*sc.spec.lights[0].position)
    v = hard_visibility(sdf, gb.p, gb.ng, c)
    o = mi.Point3f(mi.Vector3f(gb.p) + mi.Vector3f(gb.ng) * 4e-4)
    occ = sc.mi_scene.ray_test(_segment(o, c, sc.spec.lights[0].radius * 1.01), gb.valid)  # up to the light
    dr.eval(v, occ)
    valid = gb.valid.numpy()
    vm = np.where(occ.numpy(), 0.0, 1.0)
    dis = (v.numpy() != vm) & valid
    assert 0.05 < (vm[valid] == 0).mean() < 0.95, "the scene must have shadow and light"
    assert dis.sum() <= 0.002 * valid.sum(), f"{dis.sum()} of {valid.sum()} points disagree"


def _segment(o, target, short):
    d = mi.Vector3f(target) - mi.Vector3f(o)
    L = dr.norm(d)
    ray = mi.Ray3f(o, d / L)
    ray.maxt = L - short
    return ray


def test_mandelbulb_frame_uses_the_cone_traced_gbuffer_and_refuses_shadow_maps(frame_of):
    frame = frame_of("mandelbulb")
    sc = frame.scene
    assert sc.spec.sdf and sc.radius > 1.0
    gb = frame.gbuffer
    assert isinstance(gb, SDFGBuffer) and frame.sdf is not None
    names = [p.name for p in frame.sdf.primitives]
    assert names == ["floor", "bulb"]
    bulb = gb.shape_id == names.index("bulb")
    assert 0.05 < bulb.mean() < 0.6 and (gb.shape_id == 0).mean() > 0.2
    # surface points ([Bán 2019, §2.9]): their ball covers the pixel cone and reaches at most (1 + κ) of it
    from shadowlab.sdf.trace import CONE_KAPPA
    m = gb.mask.ravel()
    f, cone_r = frame.sdf.distance(gb.p).numpy()[m], gb.t.numpy()[m] * gb.tan_alpha
    assert np.allclose(f, gb.radius.numpy()[m])
    assert np.all((f >= cone_r - 1e-4) & (f <= (1 + CONE_KAPPA) * cone_r + 1e-4))
    # the centre rays' own hits are on the fractal or the floor, where a ray finds one near p
    fs = np.abs(frame.sdf.distance(gb.p_surface).numpy())
    assert (fs[bulb.ravel()] < 1e-4).mean() > 0.5 and (fs[m & (gb.shape_id.ravel() == 0)] < 1e-4).all()
    # the bulb has an albedo of its own, and lit pixels get light
    assert np.allclose(gb.albedo[bulb], [0.75, 0.6, 0.4])
    U = frame.image(frame.unshadowed["sun"]).sum(-1)
    assert (U[gb.mask[..., 0]] > 0).mean() > 0.7
    with pytest.raises(InputError, match="SDF-only"):
        frame.light_view("sun")


def test_mandelbulb_reference_is_not_a_mitsuba_truth(tmp_path):
    """`shadowlab reference mandelbulb`: the Monte-Carlo cone reference (its meta.json says the
    truth is not Mitsuba's); A and V come from the same rays (one set per light)."""
    from shadowlab import pipeline
    from shadowlab.reference import sdf_truth as sref
    path, meta = pipeline.reference("mandelbulb", (32, 32), base=tmp_path, progress=False)
    assert meta["truth"] == sref.TRUTH_KIND and "not a Mitsuba truth" in meta["not_mitsuba_truth"]
    from shadowlab.reference import store
    from shadowlab.scene.spec import load_spec, resolve
    truth, _ = store.load(load_spec(resolve("mandelbulb")).with_resolution(32, 32), base=tmp_path)
    assert truth.mitsuba is None
    assert meta["samples"]["shadow_rays"] == truth.mask.sum() * meta["samples"]["mc_cone_samples"]
    V = truth.lights["sun"].V[truth.mask]
    assert (V < 0.5).any() and (V > 0.5).any() and np.all((V >= 0) & (V <= 1))


def test_scene_of_sdf_objects_only(tmp_path):
    """A scene without [[shapes]]: CSG and a plane in [[sdf]] tables; its bounds come from the
    bounded objects, its G-buffer is cone traced (the plane floor is hit, the hole of the nut
    shows the floor through it), and a scene of planes only is refused."""
    from shadowlab.errors import SceneError
    from shadowlab.render.frame import make_frame
    from scene_builder import write_scene
    head = {"name": "only_sdf", "camera": {"position": [0, 4, 0.01], "target": [0, 0, 0], "fov": 40},
            "resolution": (64, 64), "lights": [{"name": "L", "kind": "sphere", "position": [0, 5, 0], "radius": 0.3,
                                                "power": 100}]}
    ground = {"name": "ground", "type": "plane"}
    nut = {"name": "nut", "type": "difference", "translate": [0, 0.5, 0],
           "children": [{"type": "box", "half": [1, 0.2, 1]},
                        {"type": "cylinder", "p0": [0, -1, 0], "p1": [0, 1, 0], "radius": 0.3}]}
    p = write_scene(tmp_path / "s.toml", **head, sdf=[ground, nut])
    sc = load(str(p))
    assert np.allclose(sc.bbox_min, [-1, 0.3, -1]) and np.allclose(sc.bbox_max, [1, 0.7, 1])
    frame = make_frame(sc)
    ids = frame.gbuffer.shape_id[..., 0]
    assert frame.gbuffer.mask.all()                      # the plane fills the view
    assert ids[32, 32] == 0 and ids[32, 20] == 1         # the floor through the hole; the nut
    assert (ids == 0).any() and (ids == 1).mean() > 0.3
    write_scene(p, **head, sdf=[ground])
    with pytest.raises(SceneError, match="no bounded object"):
        load(str(p))
