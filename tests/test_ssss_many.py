"""``ssss`` on many lights [Tamás 2015]: the built-in 16-light scene ``many_lights`` and its committed
128² reference, the generator of 32 / 64 / 128 lights (:mod:`shadowlab.scene.generate`), the
comparison against per-light ``pcss`` / ``pcf`` and the truth, the fit of the parameters the source
chose by eye, and the bench's report (``shadowlab bench --only ssss``; speed is measured there,
never asserted here).

Measured on ``many_lights`` (128², committed reference, defaults): ssss 6 layers (max degree 15:
the sun meets every volume), shaded RMSE 0.0036, penumbra visibility RMSE 0.198 (pcss 0.118,
pcf 0.139), no leaks.
"""

import json

import numpy as np
import pytest

from shadowlab.scene.generate import many_lights_data, many_lights_spec, to_toml, write_many_lights
from shadowlab.scene.light_layers import colour, graph, lit_volume
from shadowlab.scene.spec import load_spec, parse, scene_spec
from shadowlab.techniques import get


# ------------------------------------------------------------------------------------------------
# the scenes

def test_many_lights_scene_has_sixteen_lights_some_overlapping_some_not():
    s = scene_spec("many_lights")
    assert len(s.lights) == 16 and s.camera.resolution == (128, 128) and s.description
    kinds = [l.kind for l in s.lights]
    assert kinds.count("directional") == 1 and kinds.count("spot") >= 3 and kinds.count("point") >= 3
    assert all(l.range for l in s.lights if l.kind != "directional")
    vols = [lit_volume(l) for l in s.lights]
    adj = graph(vols)
    deg = {v.name: len(a) for v, a in zip(vols, adj)}
    assert deg["sun"] == 15                                   # the sun meets every volume
    assert min(deg.values()) == 1                             # lights that meet only the sun's
    assert max(d for n, d in deg.items() if n != "sun") >= 4  # and clusters that overlap


@pytest.mark.parametrize("n", [32, 64, 128])
def test_generator_gives_n_lights_valid_and_reproducible(n, tmp_path):
    s = many_lights_spec(n, seed=3)
    assert len(s.lights) == n and all(l.range and l.kind in ("point", "spot") for l in s.lights)
    assert len({l.name for l in s.lights}) == n
    assert s.digest() == many_lights_spec(n, seed=3).digest()            # deterministic in the seed
    assert s.digest() != many_lights_spec(n, seed=4).digest()
    p = write_many_lights(tmp_path / f"m{n}.toml", n, seed=3)              # the TOML file parses to the same scene
    assert load_spec(p).digest() == s.digest()
    lay = colour(list(s.lights))
    assert 2 <= lay.layers_used <= lay.max_degree + 1 and lay.layers_used < n // 4


def test_generator_data_round_trips_through_toml():
    import tomllib
    d = many_lights_data(5, seed=1, resolution=(32, 24))
    assert tomllib.loads(to_toml(d)) == json.loads(json.dumps(d))
    assert parse(d).camera.resolution == (32, 24)
    with pytest.raises(ValueError, match="at least one light"):
        many_lights_data(0)


# ------------------------------------------------------------------------------------------------
# compare on the 16-light scene

@pytest.fixture(scope="module")
def many(frame_of):
    from shadowlab.reference import store
    from shadowlab.scene import load
    truth, meta = store.load(load("many_lights").spec)
    frame = frame_of("many_lights", seed=int(meta.get("seed", 0)))
    return frame.scene, truth, frame


#: the scene's maps (512², the sun 1024²): at 256² the point lights' cube maps leak (3.8 % of the
#: umbra shown lit); casting the 16 lights' maps is most of this test's time
MAPS = {}


def test_ssss_against_pcss_pcf_and_the_truth_per_light(many):
    from shadowlab.pipeline import technique_metrics
    scene, truth, frame = many
    out = {}
    for n in ("ssss", "pcss"):            # pcf: `shadowlab compare many_lights -t ssss,pcss,pcf`
        r = get(n).render(frame, MAPS)
        m, per_light, _ = technique_metrics(frame, truth, r)
        out[n] = (r, m, per_light)
    r, m, per = out["ssss"]
    assert set(per) == {l.name for l in scene.spec.lights}          # a metrics row per light
    assert all(np.isfinite(per[l]["rmse"]) for l in per)
    assert m["rmse"] < 0.0045 and m["vis_rmse_penumbra"] < 0.23, (m["rmse"], m["vis_rmse_penumbra"])
    assert m["leak_rate"] < 0.002
    assert m["vis_rmse_penumbra"] < 2.0 * out["pcss"][1]["vis_rmse_penumbra"]
    st = r.stats
    for k in ("layers_used", "max_degree", "layer_conflicts", "layer_edges", "words_per_pixel"):
        assert k in st
    assert st["layers_used"] <= st["max_degree"] + 1 and st["max_degree"] == 15
    assert st["layers_used"] == 6 and st["layer_conflicts"] == 0 and st["words_per_pixel"] == 1
    assert {st["lights"][l]["layer"] for l in st["lights"]} == set(range(6))


def test_fit_light_size_depth_threshold_and_exp_k(many):
    """The three parameters the source set by eye are fittable (declared ranges, no gradients: the
    blur crosses a numpy stage, so they are golden-section searches) and a short fit never ends
    worse than its start."""
    from shadowlab.fit import run as R
    scene, truth, frame = many
    tech = get("ssss")
    for name in ("light_scale", "depth_threshold", "exp_k"):
        p = tech.param(name)
        assert p.kind == "float" and p.lo is not None and p.hi is not None and not p.differentiable
    plan = R.plan("ssss", frame, params=["light_scale", "depth_threshold", "exp_k"],
                  sets={"layer_packing": "exponential", **MAPS})
    assert [d.method for d in plan.dims] == ["golden"] * 3
    f = R.execute(plan, frame, truth, R.Budget(evals=3, rounds=1))
    assert f["loss_after"] <= f["loss_before"]
    assert set(f["params"]) == {"light_scale", "depth_threshold", "exp_k"}


# ------------------------------------------------------------------------------------------------
# the bench's report (no timing asserted)

def test_bench_part_is_registered_and_its_report_has_both_tables():
    from shadowlab.bench import core, ssss
    from shadowlab.docs import BENCH_PARTS
    from shadowlab.errors import InputError
    assert "ssss" in core.ONLY and "ssss" in BENCH_PARTS
    wide = ssss.wide_pcf()
    assert wide.resolve({"kernel": 23})["kernel"] == 23 and wide.name == "pcf"
    with pytest.raises(InputError, match="out of range"):
        get("pcf").resolve({"kernel": 23})                       # the registered pcf is unchanged
    row = lambda s, **k: {"warm_s": s, "first_run_s": s, "runs_s": [s], **k}  # noqa: E731
    kern = {"hard": {"kernel": None, **row(0.01)}}
    for v in ssss.VARIANTS:
        for k in ssss.KERNELS:
            kern[f"{v}/{k}"] = {"kernel": k, **row(0.02 + 0.001 * k, layers_used=6)}
    lights = {str(n): {"lights": n, "map_cast_s": 0.0, **{v: row(0.001 * n, layers_used=min(n, 6))
                                                          for v in ssss.LIGHT_ROWS}} for n in (1, 4, 16)}
    res = {"date": "d", "machine": {"cpu": "cpu", "cores": 2, "mitsuba": "3.9.1", "drjit": "1.5.0",
                                    "variant": "llvm_ad_rgb"}, "quick": True, "config_name": "quick",
           "config": {"res": 48, "gen_res": 48}, "wall_s": 1.0,
           "kernel": {"scene": "many_lights", "resolution": [48, 48], "lights": 16, "map_cast_s": 0.1,
                      "shadow_map": 128, "rows": kern},
           "lights": {"scene": "many_lights", "resolution": [48, 48], "rows": lights},
           "generated": {"resolution": [48, 48], "shadow_map": 64, "seed": 0,
                         "rows": {"32": {"lights": 32, "map_cast_s": 0.0, **{v: row(0.05, layers_used=5)
                                                                              for v in ssss.LIGHT_ROWS}}}}}
    md = ssss.markdown(res)
    for s in ("Cost against kernel (Table 1)", "Cost against lights (Table 2)", "5×5 + 23×23", "31.9 ms", "19.1 ms",
              "59.4", "*generated*", "Machine: cpu, 2 cores", "--quick"):
        assert s in md, s
