"""A technique per light (``sun=csm,*=pcf``): each light rendered by its own technique, through the
base class's loop, with per-light parameters that compare, fit, sweep and the CLI accept.

What must hold: a light's visibility in a mix is, bit for bit, what its technique gives that light
alone (the mix adds nothing and loses nothing); a light's parameters change that light only; a
technique that cannot render the whole scene (csm with point lights) renders its own light in a
mix; every light needs a technique; a fit finds each light's own values."""

from __future__ import annotations

import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from shadowlab import cli
from shadowlab.errors import GateFailure, InputError
from shadowlab.techniques import base, get
from shadowlab.techniques.light_mix import LightMix


def _vis(res, light):
    return np.asarray(res.visibility[light].numpy(), np.float64)


def test_names_parse_into_one_technique_with_per_light_parameters():
    mix = get("warm = pcss, cool=hard")
    assert isinstance(mix, LightMix) and mix.name == "warm=pcss,cool=hard"
    assert get("warm=pcss,cool=hard") is mix
    names = {p.name for p in mix.params}
    assert {"warm.light_scale", "cool.depth_bias"} <= names and not {"light_scale", "depth_bias"} & names
    assert mix.param("warm.light_scale").lo == get("pcss").param("light_scale").lo
    assert "warm.light_scale" in mix.fit_params(mix.resolve({}))
    assert "warm=pcss,cool=hard" not in base.names()                 # made from its name, not registered
    for bad, why in [("warm=pcss,warm=hard", "given twice"), ("warm=nope", "unknown technique"),
                     ("warm=,cool=hard", "not LIGHT=TECHNIQUE"), ("*=pcf,*=hard", "'*' is given twice")]:
        with pytest.raises(InputError, match=why):
            get(bad)


def test_each_light_is_its_own_technique_bit_for_bit(frame_of):
    frame = frame_of("two_lights", (64, 48), u_strata=1)
    mix = get("warm=pcss,cool=hard").render(frame)
    alone = {"pcss": get("pcss").render(frame), "hard": get("hard").render(frame)}
    assert np.array_equal(_vis(mix, "warm"), _vis(alone["pcss"], "warm"))
    assert np.array_equal(_vis(mix, "cool"), _vis(alone["hard"], "cool"))
    assert not np.array_equal(_vis(mix, "cool"), _vis(alone["pcss"], "cool"))   # the scene tells them apart
    assert mix.stats["lights"]["warm"]["technique"] == "pcss" and mix.stats["lights"]["cool"]["technique"] == "hard"
    # a light's parameter changes that light only, as its technique's own parameter would
    big = get("warm=pcss,cool=hard").render(frame, {"warm.light_scale": 2.0})
    assert np.array_equal(_vis(big, "cool"), _vis(mix, "cool"))
    assert np.array_equal(_vis(big, "warm"), _vis(get("pcss").render(frame, {"light_scale": 2.0}), "warm"))
    assert not np.array_equal(_vis(big, "warm"), _vis(mix, "warm"))
    # *= covers the lights not named
    star = get("cool=hard,*=pcss").render(frame)
    assert np.array_equal(_vis(star, "warm"), _vis(alone["pcss"], "warm"))


def test_gradients_reach_each_lights_own_parameter(frame_of):
    frame = frame_of("two_lights", (48, 36), u_strata=1)
    s = mi.Float(1.0)
    dr.enable_grad(s)
    res = get("warm=pcss,cool=pcss").render(frame, {"warm.light_scale": s})
    dr.backward(dr.sum(res.visibility["warm"]) + dr.sum(res.visibility["cool"]))
    g = float(dr.grad(s)[0])
    assert g != 0.0 and np.isfinite(g)


def test_a_technique_limited_to_suns_renders_the_sun_of_a_mixed_scene(frame_of):
    """many_lights: a sun and point lights. csm alone refuses the scene; in a mix it renders the
    sun (what a user wants: cascades for the sun, PCF for the rest)."""
    frame = frame_of("many_lights", (48, 48), u_strata=1)
    assert get("csm").unsupported(frame.scene.spec)
    mix = get("sun=csm,*=hard")
    assert mix.unsupported(frame.scene.spec) is None
    assert "no technique for light" in get("sun=csm").unsupported(frame.scene.spec)
    assert "has no light 'moon'" in get("moon=csm,*=hard").unsupported(frame.scene.spec)
    assert "light 'c1_warm'" in get("c1_warm=csm,*=hard").unsupported(frame.scene.spec)
    res = mix.render(frame)
    sun = frame.for_lights(["sun"])
    assert np.array_equal(_vis(res, "sun"), _vis(get("csm").render(sun), "sun"))
    assert np.array_equal(_vis(res, "c1_warm"), _vis(get("hard").render(frame), "c1_warm"))
    assert {"cascade"} <= {k.split(".", 1)[1] for k in res.aovs if k.startswith("sun.")}   # csm's AOVs kept


def test_set_and_ranges_name_a_lights_parameter():
    sets = base.parse_sets(["warm.light_scale=1.5", "pcf.kernel=5"], ["warm=pcss,cool=hard", "pcf"])
    assert sets == {"warm=pcss,cool=hard": {"warm.light_scale": 1.5}, "pcf": {"kernel": 5}}
    with pytest.raises(InputError, match="out of range"):
        base.parse_sets(["warm.light_scale=-1"], ["warm=pcss,cool=hard"])
    from shadowlab.fit.run import parse_ranges
    assert parse_ranges(["cool.light_scale=0.5:2"], ["warm=pcss,cool=pcss"]) == \
        {"warm=pcss,cool=pcss": {"cool.light_scale": (0.5, 2.0)}}
    from shadowlab.sweep.points import parse_range
    assert parse_range("warm.light_scale=0.5:2:3", "warm=pcss,cool=hard").values == (0.5, 1.25, 2.0)
    assert cli._technique_list("sun=csm, softbox=pcss,pcss;a=hard,b=pcf") == \
        ["sun=csm,softbox=pcss", "pcss", "a=hard,b=pcf"]


def test_compare_and_fit_through_the_cli(mitsuba_backend, tmp_path, capsys):
    def run(*args):
        try:
            cli.app([str(a) for a in args], standalone_mode=False)
            return 0
        except SystemExit as e:
            return e.code
    assert run("compare", "two_lights", "-t", "warm=pcss,cool=hard,pcss", "--set", "warm.light_scale=1.5",
               "--out", tmp_path / "cmp") == 0
    m = json.loads((tmp_path / "cmp" / "metrics.json").read_text())
    assert list(m["techniques"]) == ["warm=pcss,cool=hard", "pcss"]
    assert m["techniques"]["warm=pcss,cool=hard"]["params"]["warm.light_scale"] == 1.5
    assert (tmp_path / "cmp" / "index.html").is_file()
    # a fit of each light's own light_scale: two values, never worse than the start
    assert run("fit", "two_lights", "-t", "warm=pcss,cool=pcss", "--steps", 4, "--out", tmp_path / "fit",
               "--save-preset", tmp_path / "p.toml") == 0
    f = json.loads((tmp_path / "fit" / "fit.json").read_text())["techniques"]["warm=pcss,cool=pcss"]
    assert {"warm.light_scale", "cool.light_scale"} <= set(f["params"])
    assert f["loss_after"] <= f["loss_before"] + 1e-9
    assert run("compare", "two_lights", "--preset", tmp_path / "p.toml", "--out", tmp_path / "cmp2") == 0


def test_a_gate_file_names_a_technique_per_light(mitsuba_backend, tmp_path):
    from pathlib import Path
    store = Path(__file__).resolve().parents[1] / "references"
    gate = tmp_path / "gates.toml"
    gate.write_text(f'''version = 1
references = "{store}"

[[gate]]
name = "mix/loose"
scene = "two_lights"
candidate = {{ technique = "warm=pcss,cool=hard", params = {{ "warm.light_scale" = 1.0 }} }}
budget = {{ rmse = 0.5 }}

[[gate]]
name = "mix/tight"
scene = "two_lights"
candidate = {{ technique = "warm=pcss,cool=hard" }}
budget = {{ rmse = 0.0001 }}
''')
    with pytest.raises(GateFailure, match="1 gate\\(s\\) failed: mix/tight"):       # exit 1
        cli.app(["gate", str(gate), "--out", str(tmp_path / "g")], standalone_mode=False)
    junit = (tmp_path / "g" / "junit.xml").read_text()
    assert 'name="mix/loose"' in junit and junit.count("<failure") == 1, junit
