"""Frame stages traced once and replayed (render/replay.py): a replayed G-buffer or light view has the
bits of the stage traced afresh (``SHADOWLAB_REPLAY=0``), for every configuration the key tells
apart, for a second scene object and for a moved light, which replay one recording."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightview_scene import SCENE
from scene_builder import build_scene


def _arrays(obj) -> list:
    """Every Dr.Jit array of a frame's G-buffer and U_L, or of a light view's maps, as numpy."""
    from shadowlab.render.gbuffer import GBuffer
    if isinstance(obj, GBuffer):
        gb = obj
        out = [gb.p, gb.n, gb.ng, gb.valid, gb.distance, gb.forward_depth, gb.reflectance, gb.shape,
               gb.si.uv, gb.si.sh_frame.s, gb.rays.d]
    else:
        out = [obj.maps[k] for k in sorted(obj.maps)]
        if obj.translucent is not None:
            out += [obj.translucent.maps[k] for k in sorted(obj.translucent.maps)]
    return [np.asarray(a.numpy()) for a in out]


def _equal(a, b) -> bool:
    return len(a) == len(b) and all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, b))


def _traced(monkeypatch, fn):
    with monkeypatch.context() as m:
        m.setenv("SHADOWLAB_REPLAY", "0")
        return fn()


@pytest.fixture
def fresh(mitsuba_backend):
    from shadowlab.render import replay
    replay.clear()
    yield replay
    replay.clear()


@pytest.mark.parametrize("name", ["two_lights", "foliage"])
def test_a_replayed_frame_has_the_traced_bits(fresh, monkeypatch, name):
    """make_frame replayed equals make_frame traced, G-buffer and every light's U_L (alpha-tested
    casters included); a scene loaded anew gets its own recording, with the same bits."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    sc = load(name, resolution=(40, 24))
    want = _traced(monkeypatch, lambda: make_frame(sc, u_strata=2))
    again = load(name, resolution=(40, 24))
    frames = [make_frame(sc, u_strata=2) for _ in range(3)] + [make_frame(again, u_strata=2) for _ in range(2)]
    for f in frames:
        assert _equal(_arrays(f.gbuffer), _arrays(want.gbuffer))
        assert _equal([np.asarray(u.numpy()) for u in f.unshadowed.values()],
                      [np.asarray(u.numpy()) for u in want.unshadowed.values()])
    assert not fresh._failed
    assert [fresh.recordings("frame", (s.spec, 1, 2, 0), s) for s in (sc, again)] == [1, 1]
    # another seed is another key: its own trace, not the recording of seed 0
    other = make_frame(sc, u_strata=2, seed=1)
    assert not _equal([np.asarray(u.numpy()) for u in other.unshadowed.values()],
                      [np.asarray(u.numpy()) for u in want.unshadowed.values()])
    assert _equal(_arrays(other.gbuffer), _arrays(want.gbuffer))


def _configs():
    from shadowlab.render.lightview import FrustumSlice, TileRect
    return [("spot", {}), ("spot", {"bits": 16}), ("spot", {"backface": True}), ("spot", {"layers": 3}),
            ("spot", {"fit": TileRect(0.0, 0.0, 0.5, 0.5)}), ("panel", {}), ("bulb", {}), ("bulb", {"layers": 2}),
            ("sun", {}), ("sun", {"fit": FrustumSlice(0.5, 6.0, near_plane="light")}),
            ("sun", {"fit": FrustumSlice(0.5, 6.0, near_plane="pancake"), "res": 16}), ("spot", {"res": 16})]


def test_replayed_light_views_have_the_traced_bits(fresh, monkeypatch):
    """Every light kind (cube map, perspective, orthographic), depth format, back faces, layers,
    near-plane clipping and map size, each right after another configuration: replayed views equal
    the traced ones, and each configuration is recorded once however often it is asked for."""
    from shadowlab.render.lightview import light_view
    sc = build_scene(SCENE, "lightview.toml")
    configs = _configs()

    def view(light, kw):
        kw = {"res": 32, **kw}
        return light_view(sc, sc.spec.light(light), **kw)

    want = [_traced(monkeypatch, lambda: view(light, kw)) for light, kw in configs]
    for _ in range(3):                  # traced, recorded, replayed
        for (light, kw), w in zip(configs, want):
            assert _equal(_arrays(view(light, kw)), _arrays(w)), (light, kw)
    assert not fresh._failed
    assert all(s.frozen.n_recordings == 1 for s in fresh._stages.values())


def test_a_moved_light_camera_replays_the_recording(fresh, monkeypatch):
    """Light cameras that move (cascades' slices, virtual maps' tiles, the scene's other lights of a
    kind) are inputs of one recording: each view equals the view traced afresh for its camera."""
    from shadowlab.render.lightview import FrustumSlice, TileRect, light_view
    sc = build_scene(SCENE, "lightview.toml")
    slices = [FrustumSlice(0.5, 2.0, near_plane="light"), FrustumSlice(2.0, 6.0, 0.5, near_plane="light"),
              FrustumSlice(1.0, 3.0, 1.0, near_plane="light"), FrustumSlice(0.2, 1.0, near_plane="light")]
    for light, fits in (("sun", slices),
                        ("spot", [TileRect(-1.0, -1.0, 0.0, 0.0), TileRect(0.0, 0.0, 0.5, 0.5), None,
                                  TileRect(-0.5, 0.0, 0.0, 0.5)])):
        fresh.clear()
        views = []
        for fit in fits:
            got = light_view(sc, sc.spec.light(light), res=32, fit=fit)
            want = _traced(monkeypatch, lambda: light_view(sc, sc.spec.light(light), res=32, fit=fit))
            assert _equal(_arrays(got), _arrays(want)), (light, fit)
            views.append(_arrays(got))
        assert not _equal(views[0], views[1])
        assert len(fresh._stages) == 1 and next(iter(fresh._stages.values())).frozen.n_recordings == 1


def test_translucent_views_replay(fresh, monkeypatch):
    """The translucent casters' τ product and nearest-caster view replay with their bits."""
    from shadowlab.render.lightview import light_view
    from shadowlab.scene import load
    sc = load("many_lights", resolution=(32, 18))
    lights = [l for l in sc.spec.lights][:3]
    want = [_traced(monkeypatch, lambda: light_view(sc, l, res=32, translucent=True)) for l in lights]
    for _ in range(3):
        for l, w in zip(lights, want):
            got = light_view(sc, l, res=32, translucent=True)
            assert got.translucent is not None and _equal(_arrays(got), _arrays(w))
    assert not fresh._failed


def test_objects_made_after_a_recording_make_it_record_again(fresh, monkeypatch):
    """A recording that calls through pointers (the alpha test of foliage's leaf cards reads their
    BSDFs) cannot be replayed once more objects are registered with Dr.Jit (another scene loaded):
    the stage records again and keeps its bits."""
    from shadowlab.render.lightview import light_view
    from shadowlab.scene import load
    sc = load("foliage", resolution=(32, 18))
    light = sc.spec.lights[0]
    want = _traced(monkeypatch, lambda: light_view(sc, light, res=32))
    for _ in range(2):
        assert _equal(_arrays(light_view(sc, light, res=32)), _arrays(want))
    others = [load("two_lights", resolution=(8, 6)), load("contact", resolution=(8, 6))]
    for _ in range(2):
        assert _equal(_arrays(light_view(sc, light, res=32)), _arrays(want))
    assert not fresh._failed and len(others) == 2


def test_a_stage_that_reads_an_array_it_was_not_given_is_traced_each_time(fresh):
    """Dr.Jit refuses to record a stage that reads an array from outside its inputs; the stage then
    runs traced, with the right values each time (a recording would have kept the first call's).
    Recording is tried once: with no Mitsuba scene among its inputs there is no larger walk to retry
    with (the stage runs traced, in the refused recording, traced, traced: four calls)."""
    import drjit as dr
    import mitsuba as mi
    outside = mi.Float(1.0, 2.0)
    dr.eval(outside)
    calls = []

    def stage(x):
        calls.append(1)
        return x + outside

    for v in (3.0, 5.0, 7.0):
        x = mi.Float(v)
        got = fresh.replayed("reads_outside", (), stage, fresh, x)
        assert got.numpy().tolist() == [v + 1.0, v + 2.0]
    assert ("reads_outside", (), id(fresh)) in fresh._failed
    assert len(calls) == 4


def test_a_lights_cascades_are_cast_in_one_stage(fresh, monkeypatch):
    """``light_views`` casts the cascades of a light in one stage and one kernel (one walk of the scene
    per replay, not one per cascade); each map equals the one ``light_view`` traces for it alone."""
    import drjit as dr

    from shadowlab.render.lightview import FrustumSlice, light_view, light_views
    sc = build_scene(SCENE, "lightview.toml")
    sun = sc.spec.light("sun")
    fits = [FrustumSlice(0.5, 1.5, near_plane="light"), FrustumSlice(1.5, 3.0, near_plane="light"),
            FrustumSlice(3.0, 6.0, near_plane="light")]
    want = [_traced(monkeypatch, lambda: light_view(sc, sun, res=32, fit=f)) for f in fits]
    for call in range(3):               # traced, recorded, replayed
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.sync_thread()
            dr.kernel_history()
            got = light_views(sc, sun, fits, res=32)
            dr.sync_thread()
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        # a scene of another test still alive makes the first recording (given the scene's accel arrays
        # and objects) fail after its kernel ran; the stage is then recorded with the whole scene
        again = call == 1 and bool(fresh._whole)
        assert len(jit) == 1 + again and all(k["size"] == 32 * 32 for k in jit)
        assert all(_equal(_arrays(g), _arrays(w)) for g, w in zip(got, want))
    assert len(fresh._stages) == 1 and next(iter(fresh._stages.values())).frozen.n_recordings == 1


@pytest.mark.parametrize("name, variants", [("vtsm", [{"t_max": 32, "grid": 4}, {"t_max": 16, "grid": 2}]),
                                             ("fvsm", [{"t_max": 64}, {"t_max": 32}])])
def test_replayed_tiles_of_a_virtual_map_have_the_traced_bits(fresh, monkeypatch, name, variants):
    """A virtual map's tiles (cast inside the technique at every render) replay their wavefront:
    visibility, the tile each point read and the hit count equal the traced render's, for two
    tile plans (other tile counts and texels) rendered in turn on one frame."""
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    from shadowlab.techniques import base
    frame = make_frame(load("street", resolution=(48, 27)), u_strata=1)
    t = base.get(name)
    light = frame.lights[0].name

    def result(params):
        r = t.render(frame, t.resolve(params))
        return ([np.asarray(r.visibility[light].numpy()), np.asarray(r.aovs[f"{light}.tile"])],
                r.stats["lights"][light]["hit_texels"])

    want = [_traced(monkeypatch, lambda: result(p)) for p in variants]
    assert not _equal(want[0][0], want[1][0])
    for _ in range(3):                  # traced, recorded, replayed
        for p, w in zip(variants, want):
            got = result(p)
            assert _equal(got[0], w[0]) and got[1] == w[1], p
    stages = {k: s for k, s in fresh._stages.items() if k[0] == "tiles"}
    assert len(stages) >= 2 and all(s.frozen.n_recordings == 1 for s in stages.values()) and not fresh._failed


def test_a_scenes_lights_are_cast_in_one_stage(fresh, monkeypatch):
    """A shadow-map technique's first light casts every light of the frame with the same map settings
    in one stage: each view equals the one light_view traces for its light alone, the lights' own
    panels skipped in their own maps only."""
    import drjit as dr

    from shadowlab.render.frame import make_frame
    from shadowlab.render.lightview import light_view
    from shadowlab.scene import load
    from shadowlab.techniques.shadow_map import view_for
    sc = load("many_lights", resolution=(32, 18))
    lights = sc.spec.lights
    want = [_traced(monkeypatch, lambda: light_view(sc, l, res=64)) for l in lights]
    for _ in range(3):                  # traced, recorded, replayed
        frame = make_frame(sc, u_strata=1)
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.sync_thread()
            dr.kernel_history()
            got = [view_for(frame, l.name, {"resolution": 64}) for l in lights]
            dr.sync_thread()
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        assert len(jit) < len(lights)   # one kernel per configuration, not per light
        assert all(_equal(_arrays(g), _arrays(w)) for g, w in zip(got, want))
    assert not fresh._failed


def test_views_of_every_size_and_translucency_are_cast_in_one_stage(fresh, monkeypatch):
    """``FrameContext.views`` casts what it is asked for in one stage whatever the map sizes and
    translucency (one recording, one replay per frame): each view has the bits ``light_view`` traces
    for it alone, and a view asked for again is not cast again."""
    from shadowlab.render.frame import ViewKey, make_frame
    from shadowlab.render.lightview import light_view
    from shadowlab.scene import load
    sc = load("many_lights", resolution=(32, 18))
    lights = sc.spec.lights[:3]
    asks = [(l, res, tr) for l, res in zip(lights, (16, 24, 32)) for tr in (False, True)]
    want = [_traced(monkeypatch, lambda: light_view(sc, l, res=res, translucent=tr)) for l, res, tr in asks]
    for _ in range(3):                  # traced, recorded, replayed
        frame = make_frame(sc, u_strata=1)
        casts = []
        monkeypatch.setattr(frame, "cast", lambda reqs, cast=frame.cast: casts.append(len(reqs)) or cast(reqs))
        keys = [ViewKey(l.name, res, None, False, None, 1, tr) for l, res, tr in asks]
        got = frame.views(keys)
        again = frame.views(keys[::-1])
        assert casts == [len(asks)]
        assert all(_equal(_arrays(g), _arrays(w)) for g, w in zip(got, want))
        assert all(a is g for a, g in zip(again[::-1], got))
    views = [k for k in fresh._stages if k[0] == "light_view"]
    assert len(views) == 1 and fresh._stages[views[0]].frozen.n_recordings == 1
    assert not fresh._failed


def test_lights_cast_together_each_skip_their_own_panel(fresh, monkeypatch):
    """Two panel lights whose panels cast shadows, cast in one stage: each map skips its own panel and
    sees the other's, as the map light_view traces for that light alone."""
    import copy

    from shadowlab.render.lightview import light_view, light_views
    d = copy.deepcopy(SCENE)
    d["lights"].append({"name": "panel2", "kind": "rect", "position": [-1.0, 2.6, 0.8], "target": [0.0, 0.0, 0.0],
                        "size": [0.6, 0.6], "power": 100.0, "casts_shadows": True})
    sc = build_scene(d, "two_panels.toml")
    lights = [sc.spec.light("panel"), sc.spec.light("panel2")]
    want = [_traced(monkeypatch, lambda: light_view(sc, l, res=32)) for l in lights]
    for _ in range(3):                  # traced, recorded, replayed
        got = light_views(sc, lights, [None, None], res=32)
        assert all(_equal(_arrays(g), _arrays(w)) for g, w in zip(got, want))
    assert len(fresh._stages) == 1 and not fresh._failed


@pytest.mark.parametrize("plane", [True, False])
def test_replayed_ssss_blurs_have_the_traced_bits(fresh, monkeypatch, plane):
    """ssss's two blur passes replayed equal them traced, for four calls with one camera and for
    another camera (whose axes the tangent-plane depths compile in: its own recording), each call
    with new layer values."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.render.camera import Camera
    from shadowlab.render.frame import make_frame
    from shadowlab.render.screen import Screen
    from shadowlab.scene import load
    from shadowlab.techniques import ssss
    scr = make_frame(load("two_lights", resolution=(40, 24)), u_strata=1).screen
    c = scr.camera
    moved = Camera(c.position + 0.3, c.target, up=c.up_given, fov=c.fov, width=c.width, height=c.height)
    rng = np.random.default_rng(1)
    thr = dr.opaque(mi.Float, 0.05)
    for screen in (scr, Screen(moved, scr.ss, scr.position, scr.normal, scr.valid)):
        for k in range(4):           # traced, recorded, replayed twice: each with its own layer values
            n = dr.width(screen.depth)
            vals = [mi.Float(rng.random(n).astype(np.float32)) for _ in range(2)]
            sig = [mi.Float((3.0 * rng.random(n)).astype(np.float32)) for _ in range(2)]
            got = [np.asarray(v.numpy()) for v in ssss.blur_full(screen, vals, sig, 9, thr, plane)]
            want = _traced(monkeypatch, lambda: [np.asarray(v.numpy())
                                                 for v in ssss.blur_full(screen, vals, sig, 9, thr, plane)])
            assert _equal(got, want), k
            assert not np.array_equal(got[0], np.asarray(vals[0].numpy()))     # the blur changed something
    assert not fresh._failed
    assert len([k for k in fresh._stages if k[0] == "ssss_blur"]) == 2          # one recording per camera


def test_tree_rounds_replay_across_trees_of_one_size(fresh):
    """On a GPU the build's rounds (ROUNDS_PER_READ of them a stage; a later build's first stage as many
    as the last build of the size took) are recorded once per tree size and replayed by every later
    stage and build, trees of other lights over the same triangles included
    (on the CPU they are traced: a replay copies the arrays it writes); each tree equals the numpy
    reference's, in its rounds too (a stage's rounds past the last pending triangle are not counted)."""
    from conftest import CUDA
    from shadowlab.render import replay
    from shadowlab.render.top_tree import _BUILDS, ROUNDS_PER_READ, build_top_tree, build_top_tree_numpy
    V = np.random.default_rng(4).uniform(-1, 1, (60, 3, 3))
    sizes = set()
    for k, light in enumerate(([0.2, 3.0, 0.1, 1.0], [-0.5, 2.5, 0.4, 1.0], [0.3, -1.0, 0.2, 0.0])):
        a = build_top_tree_numpy(V, np.array(light))
        b = build_top_tree(V, np.array(light))
        assert b.rounds > 3 and np.array_equal(a.child, b.child) and np.array_equal(a.level, b.level), k
        assert (b.rounds, b.dropped, b.nodes) == (a.rounds, a.dropped, a.nodes), k
        sizes.add(4 * (len(V) - b.degenerate))
    for _ in range(3):                  # the subtrees' nearest distances: traced, recorded, replayed
        b = build_top_tree(V, np.array(light))
        assert np.allclose(a.near, b.near, rtol=1e-12, atol=1e-12)
    assert len(sizes) == 1
    size = sizes.pop()
    assert replay.recordings("top_tree_round", (size, ROUNDS_PER_READ), _BUILDS) == (1 if CUDA else 0)
    # a build after the first runs as many rounds as the last of its size took before its first read
    ahead = -(-b.rounds // ROUNDS_PER_READ) * ROUNDS_PER_READ
    if ahead > ROUNDS_PER_READ:
        assert replay.recordings("top_tree_round", (size, ahead), _BUILDS) == (1 if CUDA else 0)
    assert not fresh._failed


ALONE = """
import numpy as np, os, sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
from shadowlab.render import replay
from shadowlab.render.frame import make_frame
from shadowlab.render.lightview import light_view
from shadowlab.scene import load
sc = load("two_lights", resolution=(40, 24))
def arrays(f):
    views = [light_view(sc, light, res=32) for light in sc.spec.lights]
    return [np.asarray(a.numpy()) for a in (f.gbuffer.p, f.gbuffer.n, f.gbuffer.shape, *f.unshadowed.values())] + \\
        [np.asarray(v.maps[k].numpy()) for v in views for k in sorted(v.maps)]
os.environ["SHADOWLAB_REPLAY"] = "0"
want = arrays(make_frame(sc, u_strata=2))
os.environ["SHADOWLAB_REPLAY"] = "1"
for call in range(3):
    got = arrays(make_frame(sc, u_strata=2))
    assert all(np.array_equal(a, b) for a, b in zip(got, want)), call
assert replay.recordings("frame", (sc.spec, 1, 2, 0), sc) == 1
print("whole" if replay._whole else "arrays", *sorted({k[0] for k in replay._stages}), len(replay._failed))
"""


def test_a_scene_alone_is_replayed_over_its_arrays_with_the_traced_bits(mitsuba_backend):
    """With one scene alive (a fresh process: in this one other tests' scenes are), a stage hands
    Dr.Jit the scene's acceleration arrays and objects, not the scene: no stage falls back to the
    whole scene or to tracing, and the G-buffer, U_L and light views replayed equal the traced ones."""
    r = subprocess.run([sys.executable, "-c", ALONE, mitsuba_backend], capture_output=True, text=True,
                       cwd=Path(__file__).parent.parent, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["arrays", "frame", "light_view", "0"], r.stdout
