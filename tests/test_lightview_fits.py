"""Light-view fits (render/lightview.py): SceneSphere reproduces the maps made before fits existed
bit for bit; FrustumSlice covers its camera-frustum slice and snaps to whole texels; a TileRect
is the matching part of a larger map; lookups on the non-default maps agree with Mitsuba's own
shadow rays."""

import copy
import dataclasses
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from lightview_scene import SCENE
from scene_builder import frame_from
from shadowlab.errors import InputError
from shadowlab.render.lightview import FrustumSlice, SceneSphere, TileRect, projection

BASELINE = Path(__file__).parent / "data" / "lightview_baseline.npz"


@pytest.fixture(scope="module")
def frame(mitsuba_backend):
    return frame_from(SCENE, "lightview.toml")


def test_scene_sphere_is_the_old_map(frame):
    """tests/data/lightview_baseline.npz was saved by the light_view before fits existed (res 24,
    every light kind, 32-bit and 16-bit with back faces)."""
    base = np.load(BASELINE)
    for l in frame.scene.spec.lights:
        for bits, back in ((32, False), (16, True)):
            v = frame.light_view(l.name, res=24, bits=bits, backface=back)
            assert v is frame.light_view(l.name, res=24, bits=bits, backface=back, fit=SceneSphere())
            assert isinstance(v.fit, SceneSphere)
            key = f"{l.name}_{bits}_{int(back)}_"
            if not mi.variant().startswith("cuda"):
                # the baseline was cast on one CPU; Dr.Jit compiles its kernels for the host's vector
                # instructions (AVX2, AVX-512), whose hit points differ in the last bits: on another
                # CPU the same texels hit (bit for bit) and the values are within 8 ulp (measured ≤ 5)
                assert np.array_equal(v.hit, base[key + "hit"]), (l.name, bits)
                for k in ("depth", "z", "slope"):
                    np.testing.assert_array_max_ulp(getattr(v, k), base[key + k], maxulp=8)
                continue
            # the baseline was cast by the LLVM backend; OptiX's ray casts differ in the last bits
            both = v.hit & base[key + "hit"]
            assert np.mean(v.hit == base[key + "hit"]) > 0.99, (l.name, bits)
            assert np.allclose(v.z[both], base[key + "z"][both], rtol=1e-4, atol=1e-4), (l.name, bits)


def _slice_points(frame, z0, z1, n=4000, seed=0):
    """Points filling the camera-frustum slice [z0, z1] (uniform in pixel coordinates and depth)."""
    cam = frame.camera
    rng = np.random.default_rng(seed)
    px, py = rng.uniform(0, cam.width, n), rng.uniform(0, cam.height, n)
    z = rng.uniform(z0, z1, n)
    pts = cam.unproject(px, py, z)
    return np.concatenate([pts, cam.frustum_corners(z0, z1)])


def _lookup_np(view, pts):
    import mitsuba as mi
    rec = view.lookup(mi.Point3f(*[np.ascontiguousarray(pts[:, k], np.float32) for k in range(3)]))
    return {k: np.asarray(v.numpy()) for k, v in rec.items()}


@pytest.mark.parametrize("bound", ["sphere", "box"])
@pytest.mark.parametrize("snap", [False, True])
def test_frustum_slice_covers_the_slice(frame, bound, snap):
    fit = FrustumSlice(2.0, 5.0, pull=2.0, snap=snap, bound=bound)
    view = frame.light_view("sun", res=64, fit=fit)
    assert view.fit == fit and view.proj.faces[0].ortho
    pts = _slice_points(frame, fit.z0, fit.z1)
    rec = _lookup_np(view, pts)
    N = view.res
    assert rec["inside"].all()
    assert (rec["u"] >= 0).all() and (rec["u"] <= N).all() and (rec["v"] >= 0).all() and (rec["v"] <= N).all()
    assert ((rec["d"] >= 0) & (rec["d"] <= 1)).all()
    # the face's own matrices say the same as the lookup
    f = view.proj.faces[0]
    c = f.world_to_clip @ np.c_[pts, np.ones(len(pts))].T
    ndc = c[:3] / c[3]
    assert np.allclose((ndc[0] + 1) * 0.5 * N, rec["u"], atol=1e-3)
    assert np.allclose((1 - ndc[1]) * 0.5 * N, rec["v"], atol=1e-3)
    assert np.allclose(ndc[2], rec["d"], atol=1e-5)
    # an orthographic map's NDC depth is linear in light-space z: (z - near) / (far - near)
    assert np.allclose((rec["z"].astype(np.float64) - f.near) / (f.far - f.near), rec["d"], atol=1e-5)
    # casters outside the slice toward the light are in the depth range: the whole scene is
    scene_c = np.array([[x, y, z] for lo, hi in frame.scene.shape_boxes for x in (lo[0], hi[0])
                        for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    assert ((scene_c - np.array(f.origin)) @ np.array(f.R[2]) > f.near).all()
    # a tighter map than the whole scene's
    assert f.scale < frame.light_view("sun", res=64).proj.faces[0].scale


def _translated(scene, delta):
    """The same scene seen by a camera moved by ``delta`` (position and target)."""
    cam = scene.spec.camera
    moved = dataclasses.replace(
        cam, position=tuple(np.add(cam.position, delta)), target=tuple(np.add(cam.target, delta))
    )
    sc = copy.copy(scene)
    sc.spec = dataclasses.replace(scene.spec, camera=moved)
    return sc


def test_snapping_moves_the_light_by_whole_texels(frame):
    sun = frame.scene.spec.light("sun")
    fit = FrustumSlice(2.0, 5.0, snap=True)
    N = 64
    f = projection(sun, frame.scene, N, fit).faces[0]
    t = 2 * f.scale / N
    R = np.array(f.R)
    ox, oy = R[:2] @ np.array(f.origin)
    assert abs(ox / t - round(ox / t)) < 1e-6 and abs(oy / t - round(oy / t)) < 1e-6
    free = projection(sun, frame.scene, N, dataclasses.replace(fit, snap=False)).faces[0]
    assert f.scale == pytest.approx(free.scale * N / (N - 1)) and np.linalg.norm(np.subtract(free.origin, f.origin)) < t
    for delta in ((0.3 * t, 0.0, 0.0), (0.0, 0.0, 0.45 * t), (0.7 * t, -0.2 * t, 0.4 * t), (3.3 * t, 0.0, 1.7 * t)):
        g = projection(sun, _translated(frame.scene, delta), N, fit).faces[0]
        assert g.scale == f.scale and g.R == f.R
        shift = (R[:2] @ (np.array(g.origin) - np.array(f.origin))) / t
        assert np.allclose(shift, np.round(shift), atol=1e-6), shift  # the texel grid stays where it was
        # without snapping the grid swims by sub-texel amounts
        h = projection(sun, _translated(frame.scene, delta), N, dataclasses.replace(fit, snap=False)).faces[0]
        s2 = (R[:2] @ (np.array(h.origin) - np.array(free.origin))) / t
        assert not np.allclose(s2, np.round(s2), atol=1e-3)


def test_frustum_slice_refuses_other_lights_and_bad_slices(frame):
    with pytest.raises(InputError, match="directional"):
        frame.light_view("spot", fit=FrustumSlice(1.0, 3.0))
    with pytest.raises(InputError, match="z0 < z1"):
        FrustumSlice(3.0, 1.0)
    with pytest.raises(InputError, match="bound"):
        FrustumSlice(1.0, 3.0, bound="cone")
    with pytest.raises(InputError, match="square"):
        TileRect(0, 0, 0.5, 0.25)
    with pytest.raises(InputError, match="fit"):
        frame.light_view("sun", fit="whole")


@pytest.mark.parametrize("light", ["spot", "sun", "bulb", "panel"])
def test_tile_is_the_matching_part_of_a_larger_map(frame, light):
    """A 16² tile over NDC [0, 0.5] × [−0.5, 0] has the texel grid of a 64² map there: its depth
    texels equal that map's columns 32..47, rows 32..47 (ray casting at texel centres)."""
    big = frame.light_view(light, res=64)
    tile = frame.light_view(light, res=16, fit=TileRect(0.0, -0.5, 0.5, 0.0))
    assert tile.nfaces == big.nfaces
    part = (slice(None), slice(32, 48), slice(32, 48))
    same = tile.hit == big.hit[part]
    assert same.mean() > 0.99 and tile.hit.any()
    both = tile.hit & big.hit[part]
    assert np.allclose(tile.z[both], big.z[part][both], rtol=2e-6, atol=1e-6)
    assert np.allclose(tile.depth[both], big.depth[part][both], atol=2e-6)
    # lookups: a point's tile texel is its big-map texel less the tile's offset
    pts = np.asarray(frame.gbuffer.p.numpy()).T[np.asarray(frame.gbuffer.valid.numpy())]
    rb, rt = _lookup_np(big, pts), _lookup_np(tile, pts)
    inside = rt["inside"] & rb["inside"] & (rt["face"] == rb["face"])
    assert inside.sum() > 20
    assert np.allclose(rt["u"][inside], rb["u"][inside] - 32, atol=1e-3)
    assert np.allclose(rt["v"][inside], rb["v"][inside] - 32, atol=1e-3)
    assert np.allclose(rt["d"][inside], rb["d"][inside], atol=1e-6)
    tex_t, tex_b = (np.broadcast_to(r["texel"], inside.shape) for r in (rt, rb))  # one value for ortho maps
    assert np.allclose(tex_t[inside], tex_b[inside], rtol=1e-5)
    # a tile of a tile is a tile
    sub = frame.light_view(light, res=8, fit=TileRect(0.0, 0.0, 1.0, 1.0, base=TileRect(0.0, -0.5, 0.5, 0.0)))
    sub_both = sub.hit & big.hit[:, 32:40, 40:48]
    assert np.allclose(sub.z[sub_both], big.z[:, 32:40, 40:48][sub_both], rtol=2e-6, atol=1e-6)


def _depth_test_vs_rays(frame, view, exact, bias):
    """Fraction of lit, in-map, off-edge G-buffer points whose depth test (nearest texel, a
    constant bias of ``bias`` texels' world size) agrees with ``exact`` (1 = visible); 'off edge'
    = the tests against the 3×3 texels around agree."""
    import drjit as dr
    import mitsuba as mi
    gb = frame.gbuffer
    rec = view.lookup(gb.p)
    b = bias * rec["texel"]
    iu, iv = mi.Int32(dr.floor(rec["u"])), mi.Int32(dr.floor(rec["v"]))
    tests = []
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            zt = view.fetch("z", rec["face"], iu + dx, iv + dy)
            tests.append(gb.to_image(dr.select(rec["z"] - b > zt, 0.0, 1.0)))
    tests = np.stack(tests)
    keep = (tests.min(0) == tests.max(0)) & (gb.to_image(dr.select(rec["inside"], 1.0, 0.0)) > 0.5)
    keep &= frame.lit_mask(view.light.name) & frame.gbuffer.mask[..., 0]
    return float((tests[4][keep] == exact[keep]).mean()), int(keep.sum()), float((exact[keep] == 0).mean())


def test_lookup_on_a_slice_map_matches_shadow_rays(frame):
    import drjit as dr
    import mitsuba as mi
    gb = frame.gbuffer
    d = np.asarray(SCENE["lights"][1]["direction"], float)
    d /= np.linalg.norm(d)
    occ = frame.scene.mi_scene.ray_test(gb.si.spawn_ray(mi.Vector3f(*[float(x) for x in -d])), gb.valid)
    exact = gb.to_image(dr.select(occ, 0.0, 1.0))
    lo, hi = frame.camera.depth_range(frame.scene.center, frame.scene.radius)
    view = frame.light_view("sun", res=512, fit=FrustumSlice(lo, hi, snap=True))
    agree, n, shadowed = _depth_test_vs_rays(frame, view, exact, bias=3.0)
    assert n > 1000 and shadowed > 0.05
    assert agree > 0.995


def test_lookup_on_a_tile_map_matches_shadow_rays(frame):
    import drjit as dr
    import mitsuba as mi
    gb = frame.gbuffer
    pos = mi.Point3f(*[float(x) for x in SCENE["lights"][0]["position"]])
    occ = frame.scene.mi_scene.ray_test(gb.si.spawn_ray_to(pos), gb.valid)
    exact = gb.to_image(dr.select(occ, 0.0, 1.0))
    view = frame.light_view("spot", res=256, fit=TileRect(-0.5, -0.5, 0.5, 0.5))
    agree, n, shadowed = _depth_test_vs_rays(frame, view, exact, bias=3.0)
    assert n > 500 and shadowed > 0.02
    assert agree > 0.995


def test_projection_helpers_per_face(frame):
    """Cube maps share their planes (uniform); ndc_depth / linear_depth by face index agree."""
    view = frame.light_view("bulb", res=16)
    proj = view.proj
    assert proj.cube and proj.uniform
    z = np.linspace(proj.faces[0].near, proj.faces[0].far, 7)
    for i in range(6):
        assert np.array_equal(proj.ndc_depth(z, face=i), proj.ndc_depth(z))
        V, P = proj.matrices(i)
        assert np.allclose(V[:3, :3] @ V[:3, :3].T, np.eye(3))
    faces = np.arange(6).repeat(7)
    assert np.allclose(proj.ndc_depth(np.tile(z, 6), face=faces), np.tile(proj.ndc_depth(z), 6))
    assert np.allclose(proj.linear_depth(proj.ndc_depth(z)), z)


def test_a_scene_fitted_camera_is_made_once_per_light(frame):
    """The SceneSphere camera is kept with the scene's geometry: the same light gets the same object,
    a moved light (same name) its own camera, the one computed afresh."""
    from shadowlab.render import lightview
    sc = frame.scene
    bulb = sc.spec.light("bulb")
    moved = dataclasses.replace(bulb, position=(bulb.position[0] + 0.5, *bulb.position[1:]))
    first = projection(bulb, sc, 16)
    assert projection(bulb, sc, 16) is first
    assert projection(moved, sc, 16) == lightview._scene_sphere(moved, sc, 16) != first
    assert projection(bulb, sc, 24) == lightview._scene_sphere(bulb, sc, 24) != first
