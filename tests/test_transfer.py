"""Transfer of a shadowlab technique's values onto an engine's parameters (no browser here: the
engine's own render is tested in ``test_engines.py``).

What must hold:

* a filter's per-axis variance is the closed form of its tap table (an n×n grid of spacing s:
  s²(n² − 1)/12, plus one tap's own 1/12 nearest or 1/6 bilinear);
* three.js's ``radius`` gives back shadowlab's variance through PCFShadowMap's footprint
  (5 Vogel taps, mean square radius ½, each a 2×2 comparison), and its ``bias`` is the
  receiver's depth shift in the engine's window depth, negative toward the light;
* an engine camera placed exactly where shadowlab's light view is maps every point onto itself:
  the same texel size, the same depth per world unit as shadowlab's NDC depth, and a depth shift
  that is exactly the bias shadowlab applies (so the conventions of both sides agree).
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest


def test_filter_variance_is_the_tap_tables_closed_form():
    from shadowlab.techniques.base import get
    pcf, hard = get("pcf"), get("hard")
    assert hard.filter_variance(hard.resolve()) == pytest.approx(1 / 12)
    for n, s in ((1, 1.0), (3, 1.0), (5, 2.0), (7, 0.5)):
        for bilinear, tap in ((False, 1 / 12), (True, 1 / 6)):
            v = pcf.filter_variance(pcf.resolve({"kernel": n, "softness": s, "bilinear": bilinear}))
            assert v == pytest.approx(s * s * (n * n - 1) / 12 + tap, rel=1e-12), (n, s, bilinear)


def test_prefiltered_filter_variance_is_the_blurs_second_moment_plus_the_lookup():
    from shadowlab.techniques.base import get
    vsm = get("vsm")
    for n in (1, 2, 3, 4, 7):
        assert vsm.filter_variance(vsm.resolve({"kernel": n})) == pytest.approx((n * n - 1) / 12 + 1 / 6), n
    g = vsm.filter_variance(vsm.resolve({"kernel": 9, "filter": "gaussian"}))
    assert 1 / 6 < g < (81 - 1) / 12 + 1 / 6 and g == pytest.approx(1.5 ** 2 + 1 / 6, rel=0.05)  # σ = n/6, truncated


def test_three_vsm_radius_inverts_its_blur_of_evenly_spaced_taps():
    from shadowlab.techniques.base import get
    from shadowlab.techniques.engines import ReceiverPoints
    three = get("three:vsm")
    for samples in (2, 8, 17):
        taps = np.linspace(-1.0, 1.0, samples)               # three.js's vsm.glsl offsets at radius 1
        r, t = np.array([0.5, 2.0, 6.0]), 0.02
        var = (r * r * np.mean(taps ** 2) + 1 / 8 + 1 / 6) * t * t
        pts = ReceiverPoints(dz=np.zeros(3), normal=np.zeros(3), filter_var=var, cos=np.ones(3), engine_z=np.ones(3),
                             engine_texel=np.full(3, t), engine_depth_per_unit=np.ones(3))
        out = three.from_shadowlab(pts, three.resolve({"blurSamples": samples}))
        np.testing.assert_allclose(out["radius"], r, rtol=1e-9)


def test_three_pcf_radius_and_bias_invert_the_engines_footprint_and_depth():
    from shadowlab.techniques.base import get
    from shadowlab.techniques.engines import ReceiverPoints
    three = get("three:pcf")
    r, texel = np.array([0.0, 0.5, 1.0, 3.0]), np.array([0.01, 0.02, 0.01, 0.05])
    var = (r * r / 4 + 1 / 6) * texel ** 2            # PCFShadowMap's footprint at radius r
    dz, per_unit = np.array([0.01, 0.0, 0.02, 0.001]), np.array([0.03, 0.05, 0.001, 0.2])
    pts = ReceiverPoints(dz=dz, normal=np.full(4, 0.007), filter_var=var, cos=np.ones(4), engine_z=np.ones(4),
                         engine_texel=texel,
                         engine_depth_per_unit=per_unit)
    out = three.from_shadowlab(pts, three.resolve())
    np.testing.assert_allclose(out["radius"], r, atol=1e-9)
    np.testing.assert_allclose(out["bias"], -dz * per_unit)
    np.testing.assert_allclose(out["normalBias"], 0.007)
    narrow = ReceiverPoints(*(np.array([x]) for x in (0.0, 0.0, (1 / 12) * 0.01 ** 2, 1.0, 1.0, 0.01, 1.0)))
    assert three.from_shadowlab(narrow, three.resolve())["radius"][0] == 0.0     # narrower than one hardware tap


def test_perspective_camera_depth_per_unit_is_the_window_depths_derivative():
    from shadowlab.techniques.transfer import camera_at
    n, f, N, fov = 0.5, 40.0, 256, 60.0
    cam = {"projection": "perspective", "position": [1.0, 2.0, 3.0], "direction": [0.0, -1.0, 0.0],
           "right": [1.0, 0.0, 0.0], "up": [0.0, 0.0, -1.0], "near": n, "far": f, "resolution": N, "fovY": fov}
    z = np.array([1.0, 4.0, 9.0])
    p = np.array([1.0, 2.0, 3.0]) + z[:, None] * np.array([0.0, -1.0, 0.0]) + np.array([0.1, 0.0, 0.0])
    r = camera_at(cam, p)
    window = lambda z: f / (f - n) * (1 - n / z)   # noqa: E731  (OpenGL's and Direct3D's [0, 1] depth)
    h = 1e-6
    np.testing.assert_allclose(r["depth_per_unit"], (window(z + h) - window(z - h)) / (2 * h), rtol=1e-5)
    np.testing.assert_allclose(r["texel"], 2 * z * math.tan(math.radians(fov / 2)) / N)
    assert r["inside"].all()
    assert not camera_at(cam, np.array([[1.0, 2.0 - 0.2, 3.0]]))["inside"][0]      # nearer than the near plane


@pytest.mark.parametrize("ortho", [False, True])
def test_a_matrix_camera_gives_the_texel_and_depth_metric_of_its_projection(ortho):
    """Babylon.js's form: clip = [p, 1]·M (row vectors), the map storing (z_clip + n)/(n + f)."""
    from shadowlab.techniques.transfer import camera_at
    n, f, N, s = 0.5, 30.0, 512, 0.4                       # s: tan(half fov), or the half-size (m) when ortho
    o = np.array([1.0, 5.0, -2.0])
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])      # rows: right, up, forward (−y)
    view = np.eye(4)
    view[:3, :3], view[3, :3] = R.T, -(R @ o)              # row vectors: [p, 1]·view = [R(p − o), 1]
    if ortho:
        proj = np.array([[1 / s, 0, 0, 0], [0, 1 / s, 0, 0], [0, 0, 2 / (f - n), 0], [0, 0, -(f + n) / (f - n), 1]])
    else:
        proj = np.array([[1 / s, 0, 0, 0], [0, 1 / s, 0, 0], [0, 0, (f + n) / (f - n), 1],
                         [0, 0, -2 * f * n / (f - n), 0]])
    # Babylon's depth values: a spot's planes; a directional light's (1, 1), so its metric is the window depth
    lo, hi = (1.0, 1.0) if ortho else (n, f)
    cam = {"projection": "matrix", "matrix": (view @ proj).ravel().tolist(), "minZ": lo, "maxZ": hi, "resolution": N}
    z = np.array([1.0, 3.0, 12.0])
    p = o + z[:, None] * R[2] + 0.02 * z[:, None] * R[0]
    r = camera_at(cam, p)
    texel = 2 * s / N if ortho else 2 * z * s / N
    np.testing.assert_allclose(r["texel"], texel, rtol=1e-3)
    per_unit = 1 / (f - n)                                  # either way: linear in the depth along the axis
    np.testing.assert_allclose(r["depth_per_unit"], per_unit, rtol=1e-4)
    assert r["inside"].all()
    assert not camera_at(cam, (o + 40.0 * R[2])[None])["inside"][0]          # beyond the far plane


def test_babylons_caster_biases_open_the_gap_shadowlabs_receiver_biases_open():
    from shadowlab.techniques.base import get
    from shadowlab.techniques.engines import ReceiverPoints
    babylon = get("babylon:basic")
    cos = np.array([1.0, 0.8, 0.5, 0.1])
    pts = ReceiverPoints(dz=np.full(4, 0.01), normal=np.full(4, 0.02), filter_var=np.zeros(4), cos=cos,
                         engine_z=np.ones(4), engine_texel=np.ones(4), engine_depth_per_unit=np.full(4, 0.05))
    out = babylon.from_shadowlab(pts, babylon.resolve())
    np.testing.assert_allclose(out["bias"], 0.01 * 0.05)
    sin = np.sqrt(1 - cos ** 2)
    gap_caster = out["normalBias"] * sin / cos              # the caster's plane moved away along the light's ray
    np.testing.assert_allclose(gap_caster[1:], 0.02 / cos[1:])                # the lifted receiver's gap


@pytest.mark.parametrize("scene", ["contact", "street"])
def test_an_engine_camera_on_shadowlabs_own_light_view_maps_each_point_onto_itself(mitsuba_backend, scene):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    from shadowlab.techniques import transfer as T
    from shadowlab.techniques.base import get
    from shadowlab.techniques.shadow_map import opaque_bias, receiver, stored_depth, texel_index, view_for
    frame = make_frame(load(scene, resolution=(64, 48)), u_strata=1)
    hard = get("hard")
    values = hard.resolve({"normal_offset": 0.5, "constant_bias": 0.003, "slope_scaled_depth_bias": 3.0})
    light = frame.lights[0].name
    view = view_for(frame, light, values)
    f0 = view.proj.faces[0]
    cam = {"position": list(f0.origin), "direction": list(f0.R[2]), "right": list(f0.R[0]), "up": list(f0.R[1]),
           "near": f0.near, "far": f0.far, "resolution": view.res}
    cam.update({"projection": "orthographic", "halfWidth": f0.scale, "halfHeight": f0.scale} if f0.ortho else
               {"projection": "perspective", "fovY": math.degrees(2 * math.atan(f0.scale))})
    pts = T.receiver_points(frame, hard, values, light, cam)
    assert pts.size > 100
    # shadowlab's own numbers at the same points
    bias = opaque_bias(values)
    rec = receiver(frame, view, bias)
    _, _, b = stored_depth(view, rec["face"], texel_index(rec["u"]), texel_index(rec["v"]), bias)
    first = view.lookup(frame.gbuffer.p)
    keep = (rec["active"].numpy() & first["inside"].numpy() & frame.lit_mask(light).reshape(-1))
    texel = np.broadcast_to(first["texel"].numpy(), keep.shape)[keep]
    z = first["z"].numpy()[keep]
    per_unit = (1 / (f0.far - f0.near)) if f0.ortho else f0.far * f0.near / ((f0.far - f0.near) * z.astype(float) ** 2)
    assert pts.size == int(keep.sum())                 # the camera is shadowlab's: it keeps every point
    np.testing.assert_allclose(pts.engine_texel, texel, rtol=2e-5)
    np.testing.assert_allclose(pts.engine_depth_per_unit, per_unit, rtol=2e-5)
    ndc_shift = pts.dz * pts.engine_depth_per_unit                   # what shadowlab shifts, in its own NDC depth
    expected = rec["zbias"].numpy()[keep] * per_unit + b.numpy()[keep]
    np.testing.assert_allclose(ndc_shift, expected, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(pts.normal, 0.5 * texel, rtol=2e-5)


def test_transfer_refuses_pairs_without_a_mapping_with_exit_2():
    for args, words in ((["-t", "vsm", "--to", "three:pcf"], "no transfer from vsm to three:pcf"),
                        (["-t", "pcf", "--to", "pcss"], "not an engine technique"),
                        (["-t", "pcf", "--to", "babylon:pcss"], "no transfer from pcf to babylon:pcss"),
                        (["-t", "pcf", "--to", "babylon:basic"], "no transfer from pcf to babylon:basic")):
        r = subprocess.run([sys.executable, "-m", "shadowlab.cli", "transfer", "contact", *args],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
