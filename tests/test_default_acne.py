"""Defaults that leave no acne: ``hard`` and ``pcf`` at their default parameters on a flat-shaded
mesh and on a built-in scene, and what ``grazing_slope_bias`` contributes.

Acne is measured where it cannot be mistaken for aliasing: lit pixels (exact visibility of the
light's centre, :func:`~shadowlab.reference.truth.centre_visibility`) at least 2 pixels from any
shadowed one, darkened at all (visibility < 0.99; a 3×3 PCF speckle is 1/9 dark). Leaks are
:func:`shadowlab.metrics.masks.leak_rate` against the stored truth (``contact``) or the umbra of
the centre visibility (the mesh scene, which has no stored truth). The acne of both scenes sits on
receivers lit at grazing angles (curved and faceted terminators), where the caster in a texel's
neighbourhood is steeper than the receiver's own slope covers; ``grazing_slope_bias`` = 0 brings it
back.
"""

import numpy as np
import pytest

from shadowlab.techniques.base import get

from mesh_scene import ball_frame


@pytest.fixture(scope="module")
def ball(tmp_path_factory, mitsuba_backend):
    return ball_frame(tmp_path_factory.mktemp("default_acne"), 16)   # a coarse sphere: few large facets


@pytest.fixture(scope="module")
def contact(frame_of):
    import shadowlab
    return frame_of("contact"), shadowlab.load_reference("contact")


def _regions(frame, light):
    """(lit pixels ≥ 2 px from the centre shadow, umbra pixels ≥ 2 px from the lit ones), (H, W)."""
    from scipy.ndimage import binary_dilation
    from shadowlab.reference.truth import centre_visibility
    gb = frame.gbuffer
    ex = frame.image(centre_visibility(frame, light))
    reach = frame.lit_mask(light) & gb.valid.numpy().reshape(gb.height, gb.width)
    shadow = ex < 0.5
    lit = reach & ~shadow & ~binary_dilation(shadow, iterations=2)
    umbra = reach & shadow & ~binary_dilation(~shadow & reach, iterations=2)
    return lit, umbra


def _acne(frame, light, technique, **params):
    """(fraction of the far-lit pixels darkened below 0.99, visibility image)."""
    lit, _ = _regions(frame, light)
    t = get(technique)
    v = frame.image(t.render(frame, t.resolve(params)).visibility[light])
    return float(((v < 0.99) & lit).sum() / lit.sum()), v


@pytest.mark.parametrize("technique", ["hard", "pcf"])
def test_defaults_leave_no_acne_on_a_flat_shaded_mesh(ball, technique):
    from shadowlab.metrics.masks import leak_rate
    acne, v = _acne(ball, "L", technique)
    off, v_off = _acne(ball, "L", technique, grazing_slope_bias=0.0)
    _, umbra = _regions(ball, "L")
    truth = np.where(umbra, 0.0, 1.0)
    print(f"{technique}: acne {acne:.5f} (grazing_slope_bias 0: {off:.5f}); leaks "
          f"{leak_rate(v, truth, umbra):.5f} ({leak_rate(v_off, truth, umbra):.5f})")
    assert acne <= 0.0025                         # pcf 0.9 % without the term; tan capped at 3 leaves some
    if technique == "pcf":
        assert off > 0.006, "without the grazing term 3×3 PCF must speckle here, or the test shows nothing"
    assert leak_rate(v, truth, umbra) <= leak_rate(v_off, truth, umbra) + 0.001


def test_defaults_leave_no_acne_on_contact(contact):
    from shadowlab.metrics.masks import leak_rate, overdark_rate
    frame, truth = contact
    acne, v = _acne(frame, "key", "pcf")
    off, v_off = _acne(frame, "key", "pcf", grazing_slope_bias=0.0)
    valid = truth.mask & frame.lit_mask("key")
    tv = truth.lights["key"].V
    print(f"contact pcf: acne {acne:.5f} (grazing_slope_bias 0: {off:.5f}); over-darkening "
          f"{overdark_rate(v, tv, valid):.5f}, leaks {leak_rate(v, tv, valid):.5f} ({leak_rate(v_off, tv, valid):.5f})")
    assert acne <= 0.001
    assert off > 0.005, "without the grazing term the sphere's and cylinder's terminators must speckle"
    assert overdark_rate(v, tv, valid) <= 0.003                 # the standard metric: lit (truth ≥ 0.98), vis < 0.5
    assert leak_rate(v, tv, valid) <= leak_rate(v_off, tv, valid) + 0.001


def test_the_grazing_term_leaves_non_grazing_receivers_alone(contact):
    """Receivers with cos(n, l) ≥ GRAZING_MAX_COS see exactly the former test: every difference the
    term makes is on a grazing receiver (and it only ever lightens)."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.techniques.shadow_map import GRAZING_MAX_COS, to_light, view_for
    frame, _ = contact
    t = get("hard")
    v = frame.image(t.render(frame, t.resolve({})).visibility["key"])
    v0 = frame.image(t.render(frame, t.resolve({"grazing_slope_bias": 0.0})).visibility["key"])
    view = view_for(frame, "key", t.resolve({}))
    cos = frame.image(dr.dot(mi.Vector3f(frame.gbuffer.ng), to_light(view, frame.gbuffer.p)))
    changed = v != v0
    assert np.all((cos[changed] >= 0) & (cos[changed] < GRAZING_MAX_COS))
    assert np.all(v[changed] > v0[changed])
