"""A frame without host round trips: ``make_frame`` builds the G-buffer and the unshadowed light on
the device and evaluates them once; a render evaluates every light together and reads its stats
back once; what used to go through numpy inside a frame (film coordinates, the penumbra map's
storage) gives the same bits on the device."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from shadowlab.bench.frames import first_sync
from shadowlab.techniques.base import LightResult, Pooled, Technique, device_count, device_total, to_host


@pytest.fixture(scope="module")
def two(mitsuba_backend):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    return make_frame(load("two_lights", resolution=(48, 32)))


def _jit_kernels(fn):
    import drjit as dr
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        out = fn()
        dr.sync_thread()
        return out, [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


@pytest.mark.parametrize("size", [(48, 32, 1), (33, 17, 3), (640, 360, 1), (97, 61, 2)])
def test_film_coordinates_made_on_the_device_are_pixel_uv_in_float32(mitsuba_backend, size):
    """The device's (2·(x·s + i) + 1) / (2·W·s) is the float32 rounding of ``pixel_uv``, bit for bit
    (a division by a literal, which Dr.Jit turns into a product with the reciprocal, is not)."""
    from shadowlab.render.camera import pixel_uv
    from shadowlab.render.gbuffer import film_uv
    W, H, s = size
    want = pixel_uv(W, H, s).astype(np.float32)
    got = film_uv(W, H, s)
    assert np.array_equal(got.x.numpy(), want[:, 0]) and np.array_equal(got.y.numpy(), want[:, 1])


def test_make_frame_is_one_kernel_and_reads_nothing_back(mitsuba_backend):
    """G-buffer and every light's U_L in one evaluation; the numpy images are what the device holds,
    read when first asked for."""
    import mitsuba as mi

    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    sc = load("two_lights", resolution=(40, 24))
    with pytest.MonkeyPatch.context() as m:
        m.setenv("SHADOWLAB_REPLAY", "0")              # traced: one kernel
        make_frame(sc)
        _, jit = _jit_kernels(lambda: make_frame(sc))
        assert len(jit) == 1
    make_frame(sc)
    make_frame(sc)                                     # traced, then recorded (render/replay.py)
    fr, jit = _jit_kernels(lambda: make_frame(sc))     # replayed: the recorded kernel
    assert len(jit) == 1
    gb = fr.gbuffer
    assert "mask" not in vars(gb) and "albedo" not in vars(gb)       # nothing read back yet
    valid = gb.valid.numpy()
    assert gb.mask.shape == (24, 40, 1) and np.array_equal(gb.mask.ravel(), valid)
    d = np.linalg.norm(np.asarray(gb.p.numpy()).T - np.asarray(fr.camera.position, np.float32), axis=1)
    assert np.allclose(gb.view_depth.ravel()[valid], d[valid], rtol=1e-5) and np.all(gb.view_depth.ravel()[~valid] == 0)
    alb = gb.albedo.reshape(-1, 3)
    assert np.all(alb[~valid] == 0) and np.all(alb[valid] > 0)
    names = fr.scene.shape_names
    assert np.all(gb.shape_id.ravel()[valid] >= 0) and gb.shape_id.max() < len(names)
    assert all(isinstance(U, mi.Color3f) for U in fr.unshadowed.values())


class Two(Technique):
    """Visibility = clip(x + shift), no evaluation of its own; stats left on the device."""

    name = "two_stage_toy"

    def render_light(self, frame, light, values, ctx):
        import drjit as dr
        gb = frame.gbuffer
        x = mi_x(gb) + (0.25 if light.name == frame.lights[0].name else -0.25)
        act = gb.valid & (x > 0.0)
        v = dr.clip(x + 0.5, 0.0, 1.0)
        lit = Pooled(device_total(dr.select(act, dr.floor(v * 4.0), 0.0)), device_count(act))
        return LightResult(v, {"x": x}, active=act, stats={"points": device_count(gb.valid), "lit": lit},
                           counts={"active": device_count(act)})

    def light_stats(self, frame, light, values, ctx, result):
        return {"active": result.counts["active"] + 0.5}


def mi_x(gb):
    import mitsuba as mi
    return mi.Vector3f(gb.p).x


def _first_wait(fn):
    """The name of the function where ``fn`` first waits for the device (the bench's
    :func:`~shadowlab.bench.frames.first_sync`), None if it never does."""
    where = first_sync(fn)
    return None if where is None else where.rsplit("(", 1)[1].rstrip(")")


def test_a_render_waits_for_the_device_once_after_every_light(two):
    """Each light is one kernel (visibility, AOVs and device stats together), and nothing is read
    back between lights: the one wait is the stats' read-back after the last light (none without
    device stats); device stats come back as Python numbers (pooled over lights like host ones);
    AOV images are read when first asked for and pickle as a plain dict."""
    from shadowlab.techniques import get
    t = Two()
    t.render(two)
    r, jit = _jit_kernels(lambda: t.render(two))
    gb = two.gbuffer
    assert len([k for k in jit if k["size"] == gb.size]) == len(two.lights) == 2
    assert _first_wait(lambda: t.render(two)) == "to_host"
    assert _first_wait(lambda: get("hard").render(two)) is None
    valid = gb.valid.numpy()
    tot = cnt = 0
    for n in r.visibility:
        st = r.stats["lights"][n]
        assert type(st["points"]) is int and st["points"] == int(valid.sum())
        v = r.visibility[n].numpy()
        act = valid & (np.asarray(gb.p.numpy())[0] + (0.25 if n == two.lights[0].name else -0.25) > 0)
        q = np.floor(v[act] * np.float32(4.0))
        tot, cnt = tot + float(q.sum()), cnt + int(act.sum())
        assert type(st["lit"]) is float and st["lit"] == q.sum() / act.sum()
        assert st["active"] == act.sum() + 0.5                      # counts reach light_stats as numbers
    assert r.stats["lit"]["all"] == tot / cnt
    keys = list(r.aovs)
    img = r.aovs[keys[0]]
    assert img.shape == (32, 48) and r.aovs[keys[0]] is img
    copy = pickle.loads(pickle.dumps(r.aovs))
    assert type(copy) is dict and list(copy) == keys and all(np.array_equal(copy[k], r.aovs[k]) for k in keys)


def test_to_host_reads_every_device_value_once(mitsuba_backend):
    import drjit as dr
    import mitsuba as mi
    x = dr.arange(mi.Float, 10)
    tree = {"a": dr.count(x > 3.5), "b": [dr.max(x), 2], "p": Pooled(dr.sum(mi.Float64(x)), dr.count(x >= 0)), "c": "s"}
    out = to_host(tree)
    assert out["a"] == 6 and type(out["a"]) is int
    assert out["b"] == [9.0, 2] and type(out["b"][0]) is float
    assert out["p"].total == 45.0 and out["p"].count == 10 and out["p"].mean() == 4.5 and out["c"] == "s"


def _store_penumbra_numpy(s: np.ndarray, bits: int) -> np.ndarray:
    """The host version the device one replaced (half float by numpy's cast; 8-bit UNORM codes)."""
    s = np.asarray(s, np.float32)
    if bits == 16:
        return s.astype(np.float16).astype(np.float32)
    m = float(s.max())
    if m <= 0.0:
        return np.zeros_like(s)
    code = np.round(np.clip(s / m, 0.0, 1.0) * 255.0)
    return (code * (m / 255.0)).astype(np.float32)


@pytest.mark.parametrize("bits", [16, 8])
def test_the_penumbra_map_is_stored_on_the_device_with_the_hosts_bits(mitsuba_backend, bits):
    import mitsuba as mi

    from shadowlab.techniques.ssss import store_penumbra
    rng = np.random.default_rng(3)
    s = np.concatenate([rng.random(20000) * 0.37, rng.random(20000) * 1e-3, [0.0, 0.37, 65519.0, 70000.0],
                        np.linspace(0, 0.37, 511)]).astype(np.float32)
    # sizes whose codes are exactly k + ½ (over a maximum of 255): numpy rounds them half to even
    ties = np.append(np.arange(255, dtype=np.float32) + np.float32(0.5), np.float32(255.0))
    for x in (s, ties):
        with np.errstate(over="ignore"):
            want = _store_penumbra_numpy(x, bits)
        assert np.array_equal(store_penumbra(mi.Float(x), bits).numpy(), want)
    assert np.array_equal(store_penumbra(mi.Float(np.zeros(7, np.float32)), bits).numpy(), np.zeros(7, np.float32))


@pytest.mark.parametrize("scene", ["contact", "two_lights"])
def test_the_moment_blur_is_one_kernel_per_pass(mitsuba_backend, scene):
    """msm's four moment channels of a light's map: made in one kernel, each blur pass of all four
    in one more, a light at a time (``two_lights``: two maps of one size)."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    from shadowlab.techniques import get
    fr = make_frame(load(scene, resolution=(32, 24)))
    msm = get("msm")
    msm.render(fr, {"resolution": 256, "kernel": 3})
    assert {v.res * v.res * v.nfaces for v in fr.light_views.values()} == {256 * 256}
    _, jit = _jit_kernels(lambda: msm.render(fr, {"resolution": 256, "kernel": 3}))
    assert len([k for k in jit if k["size"] == 256 * 256]) == 3 * len(fr.lights)
