"""The shadow pass in Dr.Jit (render/lightview.py): a light view is one kernel, evaluated once
(layers and near-plane clipping included), and a moved light camera (another cascade, another
tile) launches that same kernel; techniques read the maps as Dr.Jit arrays without an upload,
and the numpy copies hold the same values."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from lightview_scene import SCENE
from scene_builder import frame_from
from shadowlab.render.lightview import FrustumSlice, TileRect, light_view


@pytest.fixture(scope="module")
def frame(mitsuba_backend):
    return frame_from(SCENE, "lightview.toml")


def _kernels(make):
    """(make(), the JIT kernels it launched)."""
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.sync_thread()
        dr.kernel_history()  # forget what ran before
        out = make()
        dr.sync_thread()
        return out, [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]


def _view(frame, light, **kw):
    return light_view(frame.scene, frame.scene.spec.light(light), res=32, **kw)


@pytest.mark.parametrize("light, kw", [
    ("sun", {"fit": FrustumSlice(0.5, 6.0, near_plane="light"), "layers": 3}),
    ("bulb", {"layers": 2, "backface": True}),
])
def test_a_light_view_is_one_kernel(frame, light, kw):
    """Rays, casts (clipped at the near plane, layers behind the first) and depth formats of every
    face are one wavefront: no evaluation per face, layer or clipped texel."""
    view, ks = _kernels(lambda: _view(frame, light, **kw))
    assert len(ks) == 1, [k["hash"] for k in ks]
    assert ks[0]["size"] == view.nfaces * 32 * 32
    assert view.layers == kw["layers"] and view.hit.any()


def test_a_moved_light_camera_reuses_the_kernel(frame):
    """The light camera's values (origin, axes, scale, near, far, NDC shift) enter the kernel as
    data: maps of other slices of the view (cascades) or other tiles launch the same kernel."""
    slices = [FrustumSlice(0.5, 2.0, near_plane="light"), FrustumSlice(2.0, 6.0, 0.5, near_plane="light")]
    for light, fits in (("sun", slices),
                        ("spot", [TileRect(-1.0, -1.0, 0.0, 0.0), TileRect(0.0, 0.0, 0.5, 0.5)])):
        views, hashes = [], []
        for fit in fits:
            view, ks = _kernels(lambda: _view(frame, light, fit=fit))
            assert len(ks) == 1
            views.append(view)
            hashes.append(ks[0]["hash"])
        f, g = views[0].proj.faces[0], views[1].proj.faces[0]
        moved = f.shift != g.shift if light == "spot" else (f.origin != g.origin and f.near != g.near)
        assert f.scale != g.scale and moved
        assert hashes[0] == hashes[1], light


def test_maps_are_drjit_arrays_and_the_numpy_copies_agree(frame):
    view = frame.light_view("bulb", res=32, layers=2)
    N, F = view.res, view.nfaces
    for name, kind in (("depth", mi.Float), ("z", mi.Float), ("slope", mi.Float), ("hit", mi.Bool)):
        a = view.dr(name)
        assert type(a) is kind and dr.width(a) == F * N * N and view.dr(name) is a
        assert np.array_equal(getattr(view, name), a.numpy().reshape(F, N, N))
    assert np.array_equal(view.layer_depth, view.dr("layer_depth").numpy().reshape(1, F, N, N))
    _, ks = _kernels(lambda: (view.depth, view.dr("z")))
    assert not ks                                  # evaluated when made: reading launches nothing
    empty = ~view.hit
    assert (view.depth[empty] == 1.0).all() and (view.slope[empty] == 0.0).all()
    assert view.trans_rgb is None and view.translucent is None


def test_a_lookup_in_a_moved_light_camera_reuses_the_kernel(frame):
    """Projecting points into a map (and the NDC depth of the receiver) reads the camera's values
    as data too: the lookups of two cascades, or two tiles, are one compiled kernel."""
    p = frame.gbuffer.p
    for light, fits in (("sun", [FrustumSlice(0.5, 2.0), FrustumSlice(2.0, 6.0, 0.5)]),
                        ("spot", [TileRect(-1.0, -1.0, 0.0, 0.0), TileRect(0.0, 0.0, 0.5, 0.5)])):
        hashes, values = [], []
        for fit in fits:
            view = _view(frame, light, fit=fit)
            rec, ks = _kernels(lambda: _looked_up(view, p))
            hashes.append(sorted(k["hash"] for k in ks))
            values.append(rec["u"].numpy())
        assert hashes[0] == hashes[1] and hashes[0], light
        assert not np.array_equal(values[0], values[1])


def _looked_up(view, p):
    rec = view.lookup(p)
    rec["z_decoded"] = view.proj.linear_depth(rec["d"])
    dr.eval(rec)
    return rec


def test_a_warm_lookup_writes_no_camera_values_again(frame):
    """The light camera's opaque scalars are made once per value: looking a view up again writes
    nothing to the device (a ``dr.opaque`` per value and render was ~50 writes per light)."""
    p = frame.gbuffer.p
    view = _view(frame, "spot")
    _looked_up(view, p)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.sync_thread()
        dr.kernel_history()
        _looked_up(view, p)
        dr.sync_thread()
        writes = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.Memset]
    assert not writes, len(writes)
