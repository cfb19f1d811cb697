"""``bias_mode = "rasterizer"``: the depth bias added to every surface along a texel's ray, the
smallest biased depth kept, as Direct3D and OpenGL bias every fragment before the depth test
([Buljan 2020, §2.3]); ``first_hit`` (the default) biases the first surface only.

Scene: a sun straight down over a horizontal floor, and a steep ramp just above it. Under a
vertical sun every texel whose ray meets only the floor stores the same depth D_C (slope 0), so
at a texel whose ray meets the ramp first and the floor behind, the rasterizer's stored depth must
be min(saturate(D_A + Bias_A), D_C + Bias_C): the first-hit value, or the floor's, taken from a
texel that sees nothing but the floor.
"""

import numpy as np
import pytest

from shadowlab.techniques.base import get
from scene_builder import floor, frame_from, scene


@pytest.fixture(scope="module")
def ramp(tmp_path_factory, mitsuba_backend):
    sun = {"name": "L", "kind": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 3.0, "shadow_map": 256}
    shapes = [floor(3.0),
              {"name": "ramp", "type": "rectangle", "rotate": [[0, 0, 1, 60], [1, 0, 0, -90]],
               "translate": [0.0, 0.05, 0.0], "scale": [0.08, 1.0, 1.0]}]
    d = scene("ramp", camera={"position": [0, 4, 3], "target": [0, 0, 0], "fov": 50}, resolution=(64, 64),
              lights=[sun], shapes=shapes)
    return frame_from(d, tmp_path_factory.mktemp("ramp") / "ramp.toml")


def _stored(view, values):
    import mitsuba as mi
    from shadowlab.techniques.shadow_map import opaque_bias, stored_depth
    N = view.res
    iy, ix = np.divmod(np.arange(N * N), N)
    Db, empty, _ = stored_depth(view, mi.UInt32(0), mi.Int32(ix), mi.Int32(iy), opaque_bias(values))
    return Db.numpy().reshape(N, N), empty.numpy().reshape(N, N)


@pytest.mark.parametrize("slope_bias, depth_bias", [(2.0, 16), (6.0, 0), (0.5, 1000)])
def test_rasterizer_keeps_the_smallest_biased_depth_along_the_ray(ramp, slope_bias, depth_bias):
    from shadowlab.techniques.shadow_map import RASTER_LAYERS
    hard = get("hard")
    vals = hard.resolve({"slope_scaled_depth_bias": slope_bias, "depth_bias": depth_bias})
    first = ramp.light_view("L")
    layered = ramp.light_view("L", layers=RASTER_LAYERS)
    D1, _ = _stored(first, vals)
    Dr_, _ = _stored(layered, vals)
    two = layered.hit[0] & (layered.layer_depth[0, 0] < 1.0)         # the ramp, then the floor
    floor_only = first.hit[0] & ~two & (first.slope[0] < 1e-9)
    assert two.sum() > 50 and floor_only.sum() > 1000
    D_floor = np.unique(D1[floor_only])
    assert D_floor.max() - D_floor.min() < 1e-6          # one depth (to float rounding): a horizontal floor
    lo, hi = np.minimum(D1[two], D_floor.min()), np.minimum(D1[two], D_floor.max())
    assert ((Dr_[two] >= lo) & (Dr_[two] <= hi)).all()
    assert (Dr_[two] < D1[two]).sum() > 20, "the steep ramp's bias must pass the floor behind it"
    assert np.array_equal(Dr_[~two], D1[~two])                         # one surface: the same bits


def test_without_bias_both_modes_store_the_first_surface(ramp):
    from shadowlab.techniques.shadow_map import RASTER_LAYERS
    vals = get("hard").resolve({"slope_scaled_depth_bias": 0.0, "depth_bias": 0})
    D1, _ = _stored(ramp.light_view("L"), vals)
    Dr_, _ = _stored(ramp.light_view("L", layers=RASTER_LAYERS), vals)
    assert np.array_equal(D1, Dr_)


def test_the_mode_is_a_parameter_of_every_shadow_map_technique(ramp):
    for name in ("hard", "pcf", "pcss", "csm", "sm_dpsv"):
        assert get(name).param("bias_mode").default == "first_hit"
    a = get("hard").render(ramp, {"bias_mode": "rasterizer", "slope_scaled_depth_bias": 6.0})
    b = get("hard").render(ramp, {"slope_scaled_depth_bias": 6.0})
    va, vb = a.visibility["L"].numpy(), b.visibility["L"].numpy()
    assert ((va == 0) | (va == 1)).all()
    assert (va <= vb).all()                 # a smaller stored depth never lights a point the first hit shadowed
