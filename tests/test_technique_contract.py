"""The one Technique contract: the base class owns ``render`` (parameters, the loop over lights,
AOV and stats bookkeeping, opaque and differentiable parameters); a family implements only its
per-light part. And the one light-size convention, ``light_scale``."""

import dataclasses

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.techniques import get, names
from shadowlab.techniques.base import LIGHT_SCALE, LightResult, Param, Pooled, Technique


class Toy(Technique):
    """A family written against the contract only: visibility = clip(gain · x), x the G-buffer
    point's x coordinate shifted per light; two maps per light, a pooled stat."""

    name = "toy"
    params = (Param("gain", 0.5, "float", 0.0, 4.0, differentiable=True, doc="gain"),
              Param("taps", 4, "int", 1, 16, doc="taps"))

    def prepare(self, frame, values, ctx):
        ctx.prepared = getattr(ctx, "prepared", 0) + 1
        ctx.gain = ctx.scalar("gain")

    def render_light(self, frame, light, values, ctx):
        import drjit as dr
        import mitsuba as mi
        gb = frame.gbuffer
        x = mi.Vector3f(gb.p).x + (0.25 if light.name == frame.lights[0].name else -0.25)
        v = dr.clip(ctx.gain * x + 0.5, 0.0, 1.0)
        return LightResult(v, {"x": x}, active=gb.valid & (x > 0.0), stats={"taps": values["taps"]},
                           maps=[{"near": 0.5, "far": 2.0}, {"near": 2.0, "far": 8.0}])

    def light_stats(self, frame, light, values, ctx, result):
        act = result.active.numpy()
        return {"lit_points": Pooled(float(result.visibility.numpy()[act].sum()), int(act.sum()))}

    def summarise(self, frame, values, ctx, lights):
        return {"maps_in_all": sum(len(st["maps"]) for st in lights.values())}


@pytest.fixture(scope="module")
def two(mitsuba_backend):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    return make_frame(load("two_lights", resolution=(48, 48)))


def test_the_base_loops_over_lights_and_keeps_the_books(two):
    import drjit as dr
    import mitsuba as mi
    frame, toy = two, Toy()
    r = toy.render(frame, {"gain": 0.8})
    gb = frame.gbuffer
    lights = [l.name for l in frame.lights]
    assert set(r.visibility) == set(lights) and set(r.aovs) == {f"{n}.x" for n in lights}
    x0 = mi.Vector3f(gb.p).x.numpy()
    for k, n in enumerate(lights):
        x = x0 + (0.25 if k == 0 else -0.25)
        act = gb.valid.numpy() & (x > 0)
        v = r.visibility[n].numpy()
        assert np.all(v[~act] == 1.0)                                   # visibility 1 outside `active`
        assert np.allclose(v[act], np.clip(np.float32(0.8) * x[act] + 0.5, 0, 1), atol=1e-6)
        aov = r.aovs[f"{n}.x"]
        act_img = gb.to_image(mi.Float(act.astype(np.float32)))
        assert aov.shape[:2] == (48, 48) and np.all(aov[act_img == 0] == 0)      # AOVs 0 outside `active`
        st = r.stats["lights"][n]
        assert st["taps"] == 4 and r.stats["taps"][n] == 4             # both layouts
        assert st["maps"] == [{"near": 0.5, "far": 2.0}, {"near": 2.0, "far": 8.0}]
        assert st["lit_points"] == pytest.approx(v[act].sum() / act.sum())
    tot = sum(r.visibility[n].numpy()[gb.valid.numpy() & ((x0 + (0.25 if k == 0 else -0.25)) > 0)].sum()
              for k, n in enumerate(lights))
    cnt = sum(int((gb.valid.numpy() & ((x0 + (0.25 if k == 0 else -0.25)) > 0)).sum()) for k in range(len(lights)))
    assert r.stats["lit_points"]["all"] == pytest.approx(tot / cnt)
    assert r.stats["maps_in_all"] == 2 * len(lights)
    # a Dr.Jit differentiable parameter is kept as is: gradients reach it through the loop
    g = mi.Float(0.8)
    dr.enable_grad(g)
    v = toy.render(frame, {"gain": g}).visibility[lights[0]]
    dr.backward(dr.sum(v))
    assert float(dr.grad(g)[0]) > 0
    with pytest.raises(InputError, match="differentiable"):
        toy.render(frame, {"taps": mi.Float(3.0)})
    with pytest.raises(InputError, match="one value"):
        toy.render(frame, {"gain": mi.Float([1.0, 2.0])})
    with pytest.raises(InputError, match="out of range"):
        toy.render(frame, {"gain": mi.Float(9.0)})


def test_a_new_parameter_value_reuses_the_compiled_kernels(two):
    import drjit as dr
    toy = Toy()
    toy.render(two, {"gain": 0.3})
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        for g in (0.7, 1.9):
            toy.render(two, {"gain": g})
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert jit and all(k["cache_hit"] for k in jit)


def test_every_family_implements_only_its_per_light_part():
    """The render loop is written once: no registered technique overrides ``render`` or
    handles Dr.Jit parameters itself."""
    for n in names():
        t = get(n)
        assert type(t).render is Technique.render, n
        assert type(t).render_light is not Technique.render_light, n
        assert "resolve" not in vars(type(t)) or n in ("esm", "evsm"), n       # range checks only


def test_light_scale_is_the_one_light_size_convention():
    found = []
    for n in names():
        ps = {p.name: p for p in get(n).params}
        assert "light_size" not in ps, n
        if "light_scale" in ps:
            p = ps["light_scale"]
            same = dataclasses.replace(p, source=LIGHT_SCALE.source, differentiable=LIGHT_SCALE.differentiable,
                                       doc=LIGHT_SCALE.doc)
            assert same == LIGHT_SCALE and p.doc.startswith(LIGHT_SCALE.doc), n
            found.append(n)
    assert "pcss" in found and "sdf_linear" in found
    assert get("pcss").param("light_scale").differentiable


def test_pcss_light_scale_scales_every_light_by_its_own_size(two):
    """light_scale 1 is each light's own size (pcss: the side of its equal-area square), and a
    scale multiplies each in proportion; the stats report it per light and per map."""
    from shadowlab.techniques.blocker_search import scene_light_size
    t = get("pcss")
    r1 = t.render(two, {})
    r2 = t.render(two, {"light_scale": 0.5})
    sizes = {l.name: scene_light_size(l) for l in two.lights}
    assert len(set(sizes.values())) == 2                               # the two lights differ in size
    for n, s in sizes.items():
        assert r1.stats["light_size"][n] == pytest.approx(s, rel=1e-7)
        assert r2.stats["light_size"][n] == pytest.approx(0.5 * s, rel=1e-7)
        m = r1.stats["lights"][n]["maps"]
        assert len(m) == 1 and m[0]["resolution"] == 1024 and 0 < m[0]["near"] < m[0]["far"]
    assert r1.stats["shadow_map_texels"] == sum(m["texels"] for st in r1.stats["lights"].values()
                                                for m in st["maps"])
    # scale 1 is the default: the same bits
    r1b = t.render(two, {"light_scale": 1.0})
    for n in sizes:
        assert np.array_equal(r1.visibility[n].numpy(), r1b.visibility[n].numpy())


def test_stats_tables_for_the_report():
    from shadowlab.report.tables import NA as _NA, stats_markdown, stats_tables
    st = {"lights": {"a": {"resolution": 512, "light_size": 0.25, "maps": [{"near": 0.5, "far": 4.0}]},
                     "b": {"resolution": 256, "maps": [{"near": 0.5, "far": 2.0}, {"near": 2.0, "far": 9.0}]}}}
    (t1, c1, r1), (t2, c2, r2) = stats_tables(st)
    assert t1 == "lights" and c1 == ["light", "resolution", "light_size", "maps"]
    assert r1 == [["a", "512", "0.25", "1"], ["b", "256", _NA, "2"]]
    assert t2 == "maps" and c2 == ["light", "map", "near", "far"] and len(r2) == 3 and r2[2] == ["b", "1", "2", "9"]
    assert stats_tables({"resolution": {"a": 1}}) == []
    md = stats_markdown({"techniques": {"hard": {"stats": st}}})
    assert "### hard: stats per light" in md and "### hard: stats per map" in md and "| b | 1 | 2 | 9 |" in md


def test_numbers_are_not_taken_for_drjit_inputs():
    """``Technique.resolve`` keeps only Dr.Jit arrays as arrays: a numpy scalar is parsed as a number."""
    v = get("pcss").resolve({"light_scale": np.float32(0.5)})["light_scale"]
    assert type(v) is float and v == 0.5
