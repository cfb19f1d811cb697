"""PCF acne on flat-shaded curved meshes, and ``pcf.receiver_plane`` [Isidoro 2006].

A UV sphere (PLY, flat shaded) over a floor under a spot light. Speckles are over-darkened lit
pixels (exact visibility of the light's centre 1, PCF < 0.99) at least 4 pixels away from any
shadowed pixel, where a filter has nothing to blur. A 3×3 PCF tap one texel away reads a texel of
a neighbouring facet, whose depth the receiver's own slope bias does not cover: at the default
biases the lit side of the sphere speckles. Comparing each tap against the receiver's tangent plane
at the tap (``receiver_plane``, on by default) removes most of them without more leaks; receivers
lit at grazing angles (|cos| < ``RECEIVER_PLANE_MIN_COS``) keep the plain test, so some remain near
the terminator, where the shading is dark anyway.
"""

import numpy as np
import pytest

from shadowlab.techniques.base import get

from mesh_scene import ball_frame


@pytest.fixture(scope="module")
def ball(tmp_path_factory, mitsuba_backend):
    return ball_frame(tmp_path_factory.mktemp("acne"), 32)


def _rates(frame, **params):
    from scipy.ndimage import binary_dilation
    from shadowlab.reference.truth import centre_visibility
    gb = frame.gbuffer
    ex = centre_visibility(frame, "L").numpy()
    reach = frame.lit_mask("L").ravel() & gb.valid.numpy()
    shadow = (ex < 0.5).reshape(gb.height, gb.width)
    far = reach & (ex > 0.5) & ~binary_dilation(shadow, iterations=4).ravel()
    umbra = reach & (ex < 0.5)
    v = get("pcf").render(frame, params).visibility["L"].numpy()
    return float(((v < 0.99) & far).mean() / far.mean()), float(((v > 0.5) & umbra).sum() / umbra.sum())


def test_receiver_plane_removes_speckles_on_a_flat_shaded_sphere(ball):
    plain, plain_leak = _rates(ball, receiver_plane=False)
    plane, plane_leak = _rates(ball)
    everywhere, _ = _rates(ball, receiver_plane=True, depth_bias=16)
    print(f"speckles: plain {plain:.4f}, receiver plane {plane:.4f}; leaks {plain_leak:.4f} -> {plane_leak:.4f}")
    assert plain > 0.005, "3×3 PCF without the receiver plane must speckle here, or the test shows nothing"
    assert plane < 0.35 * plain
    assert plane_leak <= plain_leak + 0.002
    assert everywhere == plane                       # depth_bias 16 is the default: the same render


def test_grazing_receivers_keep_the_plain_test(ball):
    """Below the cutoff the gradient is zero: with a cutoff of 1 (every receiver grazing) the
    receiver plane changes nothing."""
    import shadowlab.techniques.pcf as pcf_module
    plain = get("pcf").render(ball, {"receiver_plane": False}).visibility["L"].numpy()
    old = pcf_module.RECEIVER_PLANE_MIN_COS
    try:
        pcf_module.RECEIVER_PLANE_MIN_COS = 1.01
        cut = get("pcf").render(ball, {}).visibility["L"].numpy()
    finally:
        pcf_module.RECEIVER_PLANE_MIN_COS = old
    assert np.array_equal(plain, cut)
