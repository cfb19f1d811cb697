"""A frame without host round trips: ``make_frame`` builds the G-buffer and the unshadowed light on
the device and evaluates them once; what used to go through numpy inside a frame (film
coordinates) gives the same bits on the device."""

from __future__ import annotations

import numpy as np
import pytest


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
    make_frame(sc)
    fr, jit = _jit_kernels(lambda: make_frame(sc))
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
