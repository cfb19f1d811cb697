"""render/screen.py: the G-buffer as screen-space Dr.Jit arrays (gathers, depth-aware blurs,
screen <-> world)."""

import numpy as np
import pytest

from lightview_scene import SCENE
from shadowlab.render.camera import Camera


@pytest.fixture(scope="module")
def scene(mitsuba_backend):
    from shadowlab.scene import build, parse
    return build(parse(SCENE, "screen.toml"))


@pytest.fixture(scope="module")
def frame(scene):
    from shadowlab.render.frame import make_frame
    return make_frame(scene, u_strata=1)


def _step_screen():
    """A 32×24 synthetic screen: depth 2 on the left half, 6 on the right half."""
    from shadowlab.render.screen import Screen
    cam = Camera((0, 0, 5), (0, 0, 0), fov=60, width=32, height=24)
    z = np.full((24, 32), 2.0)
    z[:, 16:] = 6.0
    return Screen.from_depth(cam, z), z


def test_blur_of_a_constant_is_the_constant(mitsuba_backend):
    import mitsuba as mi
    scr, _ = _step_screen()
    c = mi.Float(np.full(32 * 24, 0.37, np.float32))
    for axis in ("x", "y"):
        for kw in ({}, {"depth_sigma": 0.05}, {"sigma": 5.0, "normal_power": 8.0}):
            out = scr.blur(c, 6, axis, **kw)
            assert np.allclose(out.numpy(), 0.37, atol=1e-6), (axis, kw)
    v = mi.Color3f(*[mi.Float(np.full(32 * 24, x, np.float32)) for x in (0.2, 0.5, 0.9)])
    assert np.allclose(np.asarray(scr.blur(v, 3, "y", depth_sigma=0.1).numpy()).T, [0.2, 0.5, 0.9], atol=1e-6)


def test_depth_rejection_keeps_a_depth_step_sharp(mitsuba_backend):
    import mitsuba as mi
    scr, z = _step_screen()
    val = mi.Float(np.where(z > 4, 1.0, 0.0).ravel().astype(np.float32))
    sharp = scr.to_image(scr.blur(val, 4, "x", depth_sigma=0.05))
    far = z > 4
    assert np.all(sharp[~far] == 0.0)                               # no bleeding across the step
    assert np.allclose(sharp[far], 1.0, atol=1e-6)                  # (weights renormalised: last bits)
    soft = scr.to_image(scr.blur(val, 4, "x"))                      # without rejection it bleeds
    assert 0 < soft[:, 15].min() and soft[:, 16].max() < 1
    # along y nothing changes: the step runs down the columns
    assert np.allclose(scr.to_image(scr.blur(val, 4, "y")), np.where(far, 1.0, 0.0), atol=1e-6)
    # a separable x then y pass of a single bright pixel stays on its side of the step
    dot = np.zeros((24, 32))
    dot[12, 14] = 1.0
    b = scr.blur(scr.blur(mi.Float(dot.ravel().astype(np.float32)), 3, "x", depth_sigma=0.05), 3, "y", depth_sigma=0.05)
    img = scr.to_image(b)
    assert img[:, 16:].max() == 0 and img[:, :16].max() > 0
    assert img[12, 14] < 1 and img[12, 13] > 0


def test_gather_is_a_clamped_neighbour_fetch(frame):
    scr = frame.screen
    assert scr is frame.screen and (scr.width, scr.height) == (64, 48)
    gb = frame.gbuffer
    for f in ("depth", "normal", "position", "valid"):
        a, b = scr.gather(f, 0, 0).numpy(), scr.field(f).numpy()
        assert np.array_equal(a, b), f
    depth = scr.to_image(scr.depth)
    assert np.allclose(depth, np.where(gb.mask[..., 0], gb.z_depth[..., 0], 0), atol=1e-4)
    right = scr.to_image(scr.gather("depth", 1, 0))
    assert np.array_equal(right[:, :-1], depth[:, 1:]) and np.array_equal(right[:, -1], depth[:, -1])
    up = scr.to_image(scr.gather("depth", 0, -2))
    assert np.array_equal(up[2:], depth[:-2]) and np.array_equal(up[0], depth[0]) and np.array_equal(up[1], depth[0])


def test_project_unproject_round_trip(frame):
    import drjit as dr
    import mitsuba as mi
    scr = frame.screen
    px, py, z = scr.project(scr.position)
    ok = scr.valid.numpy()
    # G-buffer points lie on the rays through the pixel centres
    assert np.allclose(px.numpy()[ok], scr.x.numpy()[ok] + 0.5, atol=2e-3)
    assert np.allclose(py.numpy()[ok], scr.y.numpy()[ok] + 0.5, atol=2e-3)
    assert np.allclose(z.numpy()[ok], scr.depth.numpy()[ok], rtol=1e-5)
    p = scr.unproject(px, py, z)
    assert np.abs(np.asarray((p - scr.position).numpy()).T[ok]).max() < 1e-4
    # and the other way round: pixel + depth -> world -> pixel
    rng = np.random.default_rng(0)
    qx, qy, qz = (mi.Float(rng.uniform(a, b, 500).astype(np.float32)) for a, b in ((0, 64), (0, 48), (0.5, 9)))
    rx, ry, rz = scr.project(scr.unproject(qx, qy, qz))
    for a, b in ((rx, qx), (ry, qy), (rz, qz)):
        assert np.allclose(a.numpy(), b.numpy(), atol=1e-3)
    # the numpy camera agrees
    cx, cy, cz = frame.camera.project(np.asarray(scr.position.numpy()).T[ok])
    assert np.allclose(cx, px.numpy()[ok], atol=1e-3) and np.allclose(cz, z.numpy()[ok], rtol=1e-5)
    assert dr.width(scr.film_uv(qx, qy)) == 500


def test_texture_lookup_at_pixel_centres(frame):
    import mitsuba as mi
    scr = frame.screen
    tex = scr.texture("depth")
    assert tex is scr.texture("depth")
    uv = scr.film_uv(mi.Float(scr.x) + 0.5, mi.Float(scr.y) + 0.5)
    assert np.allclose(tex.eval(uv)[0].numpy(), scr.depth.numpy(), atol=1e-5)
    n = scr.texture("normal").eval(uv)
    assert np.allclose(np.stack([c.numpy() for c in n], 1), np.asarray(scr.normal.numpy()).T, atol=1e-5)


def test_supersampled_grid(scene):
    """ss = 2: the screen is the 128×96 sub-pixel grid; indices and projection agree with it."""
    from shadowlab.render.frame import make_frame
    fr = make_frame(scene, ss=2, u_strata=1)
    scr = fr.screen
    assert (scr.width, scr.height) == (128, 96)
    import drjit as dr
    import mitsuba as mi
    k = dr.arange(mi.UInt32, 128 * 96)
    assert np.array_equal(scr.index(scr.x, scr.y).numpy(), k.numpy())
    px, py, _ = scr.project(scr.position)
    ok = scr.valid.numpy()
    assert np.allclose(px.numpy()[ok], scr.x.numpy()[ok] + 0.5, atol=2e-3)
    assert np.allclose(py.numpy()[ok], scr.y.numpy()[ok] + 0.5, atol=2e-3)
    img = scr.to_image(scr.depth)
    assert img.shape == (96, 128)
    # averaging 2×2 blocks of the grid gives the G-buffer's pixel values
    zd = np.where(fr.gbuffer.mask, fr.gbuffer.z_depth, 0).mean(2)
    assert np.allclose(img.reshape(48, 2, 64, 2).mean((1, 3)), zd, atol=1e-4)


def test_new_blur_settings_reuse_the_compiled_kernel(mitsuba_backend):
    """sigma, depth_sigma and normal_power enter the pass opaquely: new values launch the kernels
    the first values compiled (a screen-space technique's fit varies them)."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.fit.objective import KernelCounter
    scr, z = _step_screen()
    val = mi.Float(np.where(z > 4, 1.0, 0.0).ravel().astype(np.float32))
    run = lambda s, d, p: dr.eval(scr.blur(val, 3, "x", sigma=s, depth_sigma=d, normal_power=p))  # noqa: E731
    with KernelCounter() as kc:
        run(1.0, 0.05, 2.0)
        kc.take()
        run(1.7, 0.2, 5.0)
        second = kc.take()
    assert second["launched"] >= 1 and second["new"] == 0, second
