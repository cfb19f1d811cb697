"""``csm`` against its source [Buljan 2020, §2.2, §4.1–4.4, Code A.13–A.14]: the pull-back λ of
p = c − λ·r·d places each cascade's light and near plane (and λ trades lost casters for depth
precision), the per-cascade filter scale, the last cascade beyond C_N, the sphere fit's invariance
under camera rotation, and the uniform split's worst case m̃ = n(f − n)/z."""

import math

import numpy as np
import pytest

from shadowlab.techniques import base

from outdoor_scene import OUTDOOR  # noqa: E402  (tests/ is on the path)
from scene_builder import floor, frame_from, scene  # noqa: E402

#: a camera looking down at a floor, a plate 20 m up casting a square shadow into the view; a sun
#: almost overhead
CAM = {"position": [0.0, 1.5, 0.0], "target": [0.0, 0.0, -5.0], "fov": 50, "near": 0.5, "far": 12.0}
SUN = {"name": "sun", "kind": "directional", "direction": [0.05, -1.0, 0.05], "irradiance": 3.0,
       "angular_diameter": 0.0, "shadow_map": 256}
PLATE = {"name": "plate", "type": "rectangle", "translate": [0.0, 20.0, -4.0], "rotate": [1, 0, 0, 90],
         "scale": 1.5}
HARD = {"cascades": 1, "fit": "sphere", "snap": False, "filter": "hard", "blend": 0.0, "shadow_near": 0.5,
        "shadow_far": 12.0}


@pytest.fixture(scope="module")
def roof(mitsuba_backend):
    return frame_from(scene("roof", camera=CAM, resolution=(64, 48), lights=[SUN],
                            shapes=[floor(30.0), PLATE]))


@pytest.fixture(scope="module")
def outdoor(mitsuba_backend):
    """tests/outdoor_scene.py: boxes and poles from 2 m to 40 m, shadows in every cascade."""
    return frame_from(OUTDOOR)


def _slice(frame, z0, z1):
    """(centre c, radius r rounded up to 1/8 m, corners) of the view slice [z0, z1] (Code A.13)."""
    from shadowlab.render.camera import Camera
    corners = Camera.from_scene(frame.scene).frustum_corners(z0, z1)
    c = corners.mean(axis=0)
    r = math.ceil(float(np.max(np.linalg.norm(corners - c, axis=1))) * 8.0) / 8.0
    return c, r, corners


def _proj(frame, **kw):
    from shadowlab.render.lightview import FrustumSlice, projection
    light = frame.lights[0]
    return projection(light, frame.scene, 256, FrustumSlice(0.5, 12.0, **kw))


# ----------------------------------------------------------------------------- pull (Code A.13)

@pytest.mark.parametrize("pull", [0.25, 1.0, 2.0, 5.0])
def test_pull_puts_the_light_at_c_minus_lambda_r_d_and_the_near_plane_there(roof, pull):
    """Code A.13: lightPos = c − DistanceFactor·radius·d; the view volume starts at the light (or,
    with λ < 1, at the slice's nearest corner) and ends at the slice's farthest corner."""
    from shadowlab.scene.lights import forward
    c, r, corners = _slice(roof, 0.5, 12.0)
    d = np.array(forward(roof.lights[0]))
    d /= np.linalg.norm(d)
    f = _proj(roof, pull=pull, near_plane="light").faces[0]
    assert np.allclose(f.origin, c - pull * r * d, atol=1e-9)
    zc = (corners - np.array(f.origin)) @ np.array(f.R[2])           # the corners' light-space depths
    margin = 1e-3 * roof.scene.radius
    assert f.near == pytest.approx(min(0.0, zc.min()) - margin, abs=1e-9)
    assert f.far == pytest.approx(zc.max() + margin, abs=1e-9)
    if pull >= 1.0:                                                   # every corner lies in front of p
        assert f.near == pytest.approx(-margin) and zc.min() >= 0.0
        assert f.far - f.near == pytest.approx(pull * r + float(((corners - c) @ d).max()) + 2 * margin)


def test_a_larger_pull_spends_depth_precision_linearly_the_caster_plane_does_not_move(roof):
    """The λ trade-off's second half (§2.2): the depth range, hence the step of a 16-bit depth
    format in metres, grows by r per unit of λ; with ``caster`` both planes move with p."""
    _, r, _ = _slice(roof, 0.5, 12.0)
    span = {lam: (lambda f: f.far - f.near)(_proj(roof, pull=lam, near_plane="light").faces[0]) for lam in (1, 3)}
    assert span[3] - span[1] == pytest.approx(2.0 * r, rel=1e-9)
    step = {lam: s / (2 ** 16 - 1) for lam, s in span.items()}
    assert step[3] > step[1] * 1.1
    cas = [_proj(roof, pull=lam, near_plane="caster").faces[0] for lam in (1, 3)]
    assert cas[0].far - cas[0].near == pytest.approx(cas[1].far - cas[1].near, rel=1e-9)


def _plate_shadow(frame, values):
    v = base.get("csm").render(frame, {**HARD, **values}).visibility["sun"].numpy()
    return float(np.mean(v < 0.5))


def test_a_pull_too_low_clips_a_caster_toward_the_light_and_pancaking_keeps_it(roof):
    """The λ trade-off's first half (§2.2: "if λ is too low the view volume may not hold every
    caster"): the plate 20 m up is in the map exactly when its light-space depth from p is past the
    near plane (closed form from the face); ``pancake`` clamps it onto the plane, ``caster`` starts
    at it: both keep its shadow for every λ."""
    from shadowlab.scene.lights import forward
    d = np.array(forward(roof.lights[0]))
    d /= np.linalg.norm(d)
    seen = {}
    for lam in (0.25, 8.0):
        f = _proj(roof, pull=lam, near_plane="light").faces[0]
        plate_depth = float((np.array([0.0, 20.0, -4.0]) - np.array(f.origin)) @ d)
        seen[lam] = plate_depth > f.near
    assert seen == {0.25: False, 8.0: True}                          # the scene tells the λ apart
    ref = _plate_shadow(roof, {"near_plane": "caster"})
    assert 0.02 < ref < 0.5
    assert _plate_shadow(roof, {"near_plane": "light", "pull": 0.25}) == 0.0
    assert _plate_shadow(roof, {"near_plane": "light", "pull": 8.0}) == pytest.approx(ref, abs=0.01)
    for lam in (0.25, 8.0):
        assert _plate_shadow(roof, {"near_plane": "pancake", "pull": lam}) == pytest.approx(ref, abs=0.01)
    assert _plate_shadow(roof, {"near_plane": "caster", "pull": 0.25}) == ref


def test_pull_is_fitted_only_where_it_acts():
    csm = base.get("csm")
    assert "pull" in csm.fit_params(csm.resolve({}))
    assert "pull" in csm.fit_params(csm.resolve({"near_plane": "pancake"}))
    assert "pull" not in csm.fit_params(csm.resolve({"near_plane": "caster"}))


# ----------------------------------------------------------------------------- filter per cascade

def _recorded(frame, monkeypatch, values):
    """(texel world size, softness) of every cascade's pcf evaluation."""
    fam = type(base.get("pcf"))
    seen, evaluate = [], fam.evaluate

    def spy(self, sub, light, view, cv, ctx):
        seen.append((2.0 * view.proj.faces[0].scale / view.res, float(cv["softness"])))
        return evaluate(self, sub, light, view, cv, ctx)

    monkeypatch.setattr(fam, "evaluate", spy)
    r = base.get("csm").render(frame, {"cascades": 3, "filter": "pcf", "pcf_softness": 2.0, "blend": 0.0, **values})
    monkeypatch.setattr(fam, "evaluate", evaluate)
    return seen, r.visibility["sun"].numpy(), r.aovs["sun.cascade"]


def test_the_filter_keeps_its_texels_or_its_world_size_per_cascade(outdoor, monkeypatch):
    """``texel`` (Code A.14): softness 2 texels in every cascade; ``world``: cascade i taps at
    2·t_0/t_i of its own texels, the same world footprint 2·t_0. Cascade 0 is the same either way,
    the others differ."""
    tex, v_tex, sel = _recorded(outdoor, monkeypatch, {"filter_scale": "texel"})
    world, v_world, _ = _recorded(outdoor, monkeypatch, {"filter_scale": "world"})
    assert len(tex) == len(world) == 3                                # every cascade holds points
    t0 = world[0][0]
    assert world[2][0] > 2.0 * t0                                      # the ratio matters here
    assert all(s == 2.0 for _, s in tex)
    for t, s in world:
        assert s * t == pytest.approx(2.0 * t0, rel=1e-6)
    sel = np.asarray(sel).reshape(-1)
    assert np.array_equal(v_tex[sel == 0], v_world[sel == 0])
    assert np.abs(v_tex - v_world)[sel >= 1].max() > 0.05


# ----------------------------------------------------------------------------- beyond C_N (Code A.14)

BOXES = [{"name": f"b{i}", "type": "cube", "translate": [x, 0.3, -z], "scale": 0.3}
         for i, (x, z) in enumerate([(-1.0, 5.5), (0.5, 6.5), (-0.5, 7.5), (1.0, 8.5)])]


def test_points_beyond_the_last_split_take_the_last_cascade(mitsuba_backend):
    """Code A.14 (blending branch): i == MAX_CASCADES_NUM − 1 takes every point past the splits.
    With C_N = 5 m the boxes at 5.5–8.5 m still cast the shadows the last map holds, where a
    range to 30 m puts them too; a point outside that map stays lit."""
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.render.lightview import FrustumSlice
    cam = {**CAM, "far": 30.0}
    sun = {**SUN, "direction": [0.3, -1.0, 0.2]}
    frame = frame_from(scene("beyond", camera=cam, resolution=(64, 48), lights=[sun], shapes=[floor(30.0)] + BOXES))
    csm = base.get("csm")
    p = {"cascades": 2, "shadow_near": 0.5, "blend": 0.0, "filter": "hard", "snap": False}
    short = csm.render(frame, {**p, "shadow_far": 5.0})
    z = frame.camera.view_depth(vec_numpy(frame.gbuffer.p))
    beyond = frame.gbuffer.valid.numpy() & (z > 5.0)
    sel = np.asarray(short.aovs["sun.cascade"]).reshape(-1)
    assert np.all(sel[beyond] == 1)
    v = short.visibility["sun"].numpy()
    last = FrustumSlice(*short.stats["lights"]["sun"]["maps"][-1]["split"], 2.0, False, "sphere", "light")
    inside = frame.light_view("sun", res=256, fit=last).lookup(frame.gbuffer.p)["inside"].numpy()
    assert (beyond & ~inside).sum() > 100 and np.all(v[beyond & ~inside] == 1.0)
    dark = beyond & inside & (v < 0.5)
    assert dark.sum() > 40                                           # shadows go on past C_N
    full = csm.render(frame, {**p, "shadow_far": 30.0}).visibility["sun"].numpy()
    assert np.mean(full[dark] < 0.5) > 0.8                           # where a longer range puts them too


# ----------------------------------------------------------------------------- rotation (§4.2)

def test_the_sphere_fit_does_not_change_when_the_camera_turns_about_its_position(mitsuba_backend):
    """§4.2: the slice's bounding sphere is invariant under rotation of the camera: turned about
    its position, every cascade keeps its map's half size (its texel size: with and without
    snapping), its light frame and near plane, and its sphere centre c = p + λ·r·d keeps its
    distance to the camera (the sphere turns with the view); the box fit's size changes."""
    from outdoor_scene import CAMERA
    from scene_builder import build_scene
    from shadowlab.render.lightview import FrustumSlice, projection
    from shadowlab.scene.lights import forward
    got = {}
    for yaw in (0.0, 35.0, 120.0):
        a = math.radians(yaw)
        t = np.subtract(CAMERA["target"], CAMERA["position"])
        t = [t[0] * math.cos(a) - t[2] * math.sin(a), t[1], t[0] * math.sin(a) + t[2] * math.cos(a)]
        sc = build_scene({**OUTDOOR, "camera": {**CAMERA, "target": list(np.add(CAMERA["position"], t))}})
        light = sc.lights[0]
        d = np.array(forward(light))
        d /= np.linalg.norm(d)
        for bound in ("sphere", "box"):
            for snap in (False, True):
                f = projection(light, sc, 256, FrustumSlice(2.0, 9.0, 2.0, snap, bound, "light")).faces[0]
                c = np.array(f.origin) + 2.0 * f.scale * (255.0 / 256.0 if snap else 1.0) * d
                got.setdefault((bound, snap), []).append(
                    (f.scale, f.near, np.ravel(f.R), np.linalg.norm(c - CAMERA["position"])))
    for snap in (False, True):
        s0, n0, R0, c0 = got[("sphere", snap)][0]
        for s, n, R, c in got[("sphere", snap)][1:]:
            assert s == s0 and n == n0 and np.array_equal(R, R0)
            if not snap:                                             # snapping moves c across d by < 1 texel
                assert c == pytest.approx(c0, rel=1e-9)
    box = [g[0] for g in got[("box", False)]]
    assert abs(box[1] / box[0] - 1.0) > 1e-3                         # the box's half size changes


# ----------------------------------------------------------------------------- splits (§4.1)

def _m_tilde(C, n):
    """§4.1's m̃ = n·dz/(z·ds) at the start z = C_i of each cascade, with the cascade's own
    parameterisation: s spans 1/N over [C_i, C_{i+1}], so dz/ds = N·(C_{i+1} − C_i)."""
    C = np.asarray(C, np.float64)
    N = len(C) - 1
    return n * N * np.diff(C) / C[:-1]


@pytest.mark.parametrize("n, f, N", [(0.1, 150.0, 3), (1.0, 1000.0, 8), (0.5, 40.0, 4)])
def test_uniform_splits_have_the_worst_case_m_tilde_and_lambda_trades_it_against_the_first_cascade(n, f, N):
    """§4.1: with uniform splits dz/ds = f − n, so m̃ = n(f − n)/z, largest (f − n) at z = n: the
    theoretical worst split; log splits make m̃ the same n·N((f/n)^(1/N) − 1) in every cascade;
    the practical split's λ trades the worst m̃ (falling as λ grows) against the length of the
    nearest cascade (shrinking: "near cascades too short")."""
    from shadowlab.techniques.cascades import splits
    uni = splits("uniform", n, f, N)
    assert np.allclose(_m_tilde(uni, n), n * (f - n) / uni[:-1], rtol=1e-12)
    assert _m_tilde(uni, n).max() == pytest.approx(f - n, rel=1e-12)
    log = splits("log", n, f, N)
    assert np.allclose(_m_tilde(log, n), n * N * ((f / n) ** (1.0 / N) - 1.0), rtol=1e-9)
    lams = np.linspace(0.0, 1.0, 11)
    worst = [_m_tilde(splits("practical", n, f, N, lam), n).max() for lam in lams]
    first = [splits("practical", n, f, N, lam)[1] - n for lam in lams]
    assert worst[0] == pytest.approx(f - n) and np.all(np.diff(worst) < 0)
    assert np.all(np.diff(first) < 0)
    assert min(worst) == pytest.approx(_m_tilde(log, n).max(), rel=1e-9)
