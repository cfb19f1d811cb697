"""Input validation (issue 15, items 1b, 6 and 9): scene files, gate files and presets.

Unknown keys anywhere get a "did you mean" suggestion; keys of another light kind or shape type
name the kind's keys; booleans are TOML booleans; numbers are range-checked; a scene name is one
plain path component of the reference store; bad input given as a scene (a directory, a gate file,
an unusable up vector, a huge shadow map, a negative seed) exits 2 naming the file, the key and the
fix. The built-in scenes, the committed gate file and the presets the tests use still load, with
the scene hashes their committed references store.
"""

from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path

import pytest

from shadowlab.cli import main as cli_main
from shadowlab.errors import InputError, SceneError
from shadowlab.fit import preset as preset_mod
from shadowlab.gate.gatefile import load_gate_file, parse_gate_file
from shadowlab.reference import store
from shadowlab.reference.truth import SEED_MAX
from shadowlab.scene.reader import did_you_mean
from shadowlab.scene.spec import SHADOW_MAP_MAX, builtin_names, load_spec, parse, resolve
from shadowlab.techniques import base

ROOT = Path(__file__).resolve().parents[1]

BASE = {
    "name": "v",
    "camera": {"position": [0.0, 3.0, 5.0], "target": [0.0, 0.0, 0.0], "fov": 40, "resolution": [16, 16]},
    "lights": [{"name": "key", "kind": "rect", "position": [0.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0],
                "size": [1.0, 1.0], "power": 100.0}],
    "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0},
               {"name": "ball", "type": "sphere", "center": [0.0, 0.5, 0.0], "radius": 0.5},
               {"name": "pole", "type": "cylinder", "p0": [1, 0, 0], "p1": [1, 1, 0], "radius": 0.05}],
}


def _scene(edit) -> dict:
    d = copy.deepcopy(BASE)
    edit(d)
    return d


def _fails(d, *parts):
    with pytest.raises(SceneError) as e:
        parse(d, "s.toml")
    msg = str(e.value)
    assert msg.startswith("s.toml: "), msg
    for p in parts:
        assert p in msg, msg
    return msg


def test_the_base_scene_parses():
    spec = parse(copy.deepcopy(BASE), "s.toml")
    assert spec.name == "v" and [l.kind for l in spec.lights] == ["rect"] and len(spec.shapes) == 3


# ----------------------------------------------------------------------------- unknown keys
@pytest.mark.parametrize("edit, parts", [
    (lambda d: d.update(colour=1), ["colour: unknown key 'colour'", "a scene file (top level) takes"]),
    (lambda d: d.update(lihgts=[]), ["did you mean 'lights'?"]),
    (lambda d: d["camera"].update(field_of_view=50), ["camera.field_of_view", "did you mean 'fov'?", "[camera] takes"]),
    (lambda d: d["camera"].update(postion=[0, 1, 2]), ["camera.postion", "did you mean 'position'?"]),
    (lambda d: d["lights"][0].update(colour=[1, 0, 0]), ["lights[0].colour", "did you mean 'color'?",
                                                         "a rect light takes: casts_shadows, color,"]),
    (lambda d: d["lights"][0].update(shadowmap=1024), ["did you mean 'shadow_map'?"]),
    (lambda d: d["shapes"][1].update(albdo=[1, 1, 1]), ["shapes[1].albdo", "did you mean 'albedo'?"]),
    (lambda d: d.update(sdf=[{"type": "sphere", "radious": 1.0}]), ["sdf[0].radious", "did you mean 'radius'?"]),
    (lambda d: d.update(sdf=[{"type": "union", "children": [{"type": "box", "hafl": [1, 1, 1]}]}]),
     ["sdf[0].children[0].hafl", "did you mean 'half'?"]),
])
def test_unknown_keys_anywhere_in_a_scene_get_a_suggestion(edit, parts):
    msg = _fails(_scene(edit), *parts)
    assert "Fix the spelling or remove the key" in msg


@pytest.mark.parametrize("edit, parts", [
    (lambda d: d["lights"].__setitem__(0, {"name": "b", "kind": "sphere", "position": [0, 4, 0], "radius": 0.3,
                                           "size": [1, 1], "power": 50}),
     ["lights[0].size: a sphere light has no 'size' (it is a key of rect lights)", "a sphere light's size is 'radius'",
      "a sphere light takes: casts_shadows, color, depth_bits, kind, name, near, position, power, radiance, radius, "
      "shadow_map"]),
    (lambda d: d["lights"][0].update(radius=0.5), ["a rect light has no 'radius'", "a rect light's size is 'size'"]),
    (lambda d: d["lights"][0].update(direction=[0, -1, 0]), ["a rect light has no 'direction'",
                                                             "directional lights"]),
    (lambda d: d["lights"].__setitem__(0, {"name": "s", "kind": "directional", "direction": [0, -1, 0],
                                           "irradiance": 2.0, "position": [0, 5, 0]}),
     ["a directional light has no 'position'"]),
    (lambda d: d["lights"].__setitem__(0, {"name": "p", "kind": "point", "position": [0, 4, 0], "power": 50,
                                           "target": [0, 0, 0]}), ["a point light has no 'target'"]),
    (lambda d: d["shapes"][0].update(radius=2.0), ["shapes[0].radius: a rectangle shape has no 'radius'",
                                                   "sphere, cylinder shapes"]),
    (lambda d: d["shapes"][1].update(caps=False), ["a sphere shape has no 'caps'"]),
    (lambda d: d.update(sdf=[{"type": "sphere", "half": [1, 1, 1]}]), ["type 'sphere' has no 'half'", "box"]),
    (lambda d: d.update(sdf=[{"type": "union", "children": [{"type": "box", "name": "x"}]}]),
     ["a CSG child has no 'name'"]),
])
def test_keys_of_another_kind_are_refused_naming_the_kinds_keys(edit, parts):
    _fails(_scene(edit), *parts)


def test_a_misspelt_kind_or_type_gets_a_suggestion():
    _fails(_scene(lambda d: d["lights"][0].update(kind="rec")), "lights[0].kind: expected one of rect,",
           "got 'rec' (did you mean 'rect'?)")
    _fails(_scene(lambda d: d["shapes"][1].update(type="sphre")), "got 'sphre' (did you mean 'sphere'?)")
    _fails(_scene(lambda d: d.update(sdf=[{"type": "mandelbub"}])), "(did you mean 'mandelbulb'?)")


def test_delta_and_area_emission_keys_must_match_the_radius():
    point = {"name": "p", "kind": "point", "position": [0, 4, 0]}
    _fails(_scene(lambda d: d["lights"].__setitem__(0, {**point, "radiance": 3.0})),
           "no radiance on a point light of radius 0")
    _fails(_scene(lambda d: d["lights"].__setitem__(0, {**point, "radius": 0.2, "intensity": 3.0})),
           "no intensity on a point light of radius 0.2")
    assert (
        parse(_scene(lambda d: d["lights"].__setitem__(0, {**point, "intensity": 3.0})), "s.toml").lights[0].intensity
        == 3.0
    )


# ----------------------------------------------------------------------------- booleans, numbers
@pytest.mark.parametrize("shape, key, value", [(0, "two_sided", "no"), (0, "two_sided", 0), (2, "caps", "false"),
                                               (2, "caps", 1)])
def test_booleans_are_booleans(shape, key, value):
    _fails(_scene(lambda d: d["shapes"][shape].update({key: value})), f"shapes[{shape}].{key}: expected true or false",
           repr(value))


def test_real_booleans_are_read_as_given():
    spec = parse(
        _scene(lambda d: (d["shapes"][0].update(two_sided=False), d["shapes"][2].update(caps=False))), "s.toml"
    )
    assert spec.shapes[0].two_sided is False and spec.shapes[2].caps is False
    assert parse(copy.deepcopy(BASE), "s.toml").shapes[0].two_sided is True


@pytest.mark.parametrize("edit, parts", [
    (lambda d: d["lights"][0].update(shadow_map=200000), [f"shadow_map: expected an integer <= {SHADOW_MAP_MAX}",
                                                          "GiB per face", "got 200000"]),
    (lambda d: d["lights"][0].update(shadow_map=4), ["shadow_map: expected an integer >= 8"]),
    (lambda d: d["lights"][0].update(power=-1.0), ["power: expected a number >= 0, got -1.0"]),
    (lambda d: d["lights"][0].update(power=float("nan")), ["power: expected a finite number"]),
    (lambda d: d["lights"][0].update(up=[0, 0, 0]), ["lights[0].up: expected a non-zero vector"]),
    (lambda d: d["camera"].update(fov=0.0), ["camera.fov: expected a number in [1.0, 170.0]"]),
    (lambda d: d["camera"].update(up=[0, 0, 0]), ["camera.up: expected a non-zero vector"]),
    (lambda d: d["camera"].update(up=[0.0, -3.0, -5.0]), ["camera.up: expected a vector not parallel to the view "
                                                          "direction target − position = [0, -3, -5]", "[0, 0, 1]"]),
    (lambda d: d["shapes"][2].update(p1=[1, 0, 0]), ["shapes[2].p1: expected a point different from p0"]),
    (lambda d: d["shapes"][0].update(rotate=[1, 0, 0, float("inf")]), ["rotate: expected finite numbers"]),
    (lambda d: d.update(sdf=[{"type": "mandelbulb", "iterations": 10 ** 9}]),
     ["iterations: expected an integer <= 64"]),
])
def test_numbers_are_range_checked(edit, parts):
    _fails(_scene(edit), *parts)


# ----------------------------------------------------------------------------- scene names (item 1b)
@pytest.mark.parametrize("name", ["../x", "", ".", "..", ".hidden", "a/b", "a\\b", "a b", "/abs"])
def test_a_scene_name_is_one_plain_path_component(name):
    _fails(_scene(lambda d: d.update(name=name)), "name: expected letters, digits, '_', '-' or '.'",
           "names the scene's directory in the reference store", repr(name))


def test_a_bad_name_from_the_file_name_asks_for_a_name_key():
    d = _scene(lambda d: d.pop("name"))
    with pytest.raises(SceneError, match=r"the file name gives 'my scene': add name = "):
        parse(d, "dir/my scene.toml")
    assert parse(d, "dir/my_scene-2.v1.toml").name == "my_scene-2.v1"


def test_a_bad_name_writes_nothing_outside_the_store_even_with_force(tmp_path, monkeypatch, capsys, mitsuba_backend):
    store = tmp_path / "store"
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store))
    victim = tmp_path / "x"
    victim.mkdir()
    (victim / "keep.txt").write_text("precious")
    for name in ("../x", ""):
        f = tmp_path / "s.toml"
        f.write_text(_toml(_scene(lambda d: d.update(name=name))))
        rc = cli_main(["reference", str(f), "--force", "--resolution", "8x8"])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith(f"error: {f}: name: expected letters"), err
    assert (victim / "keep.txt").read_text() == "precious"
    assert not store.exists() or not any(store.rglob("*"))


# ----------------------------------------------------------------------------- not a scene (item 6)
def _toml(d: dict) -> str:
    """A small TOML writer for the scene dicts above (tables and arrays of tables)."""
    def val(v):
        return json.dumps(v) if not isinstance(v, bool) else ("true" if v else "false")
    lines = [f"{k} = {val(v)}" for k, v in d.items() if not isinstance(v, (dict, list)) or
             (isinstance(v, list) and not (v and isinstance(v[0], dict)))]
    for k, v in d.items():
        if isinstance(v, dict):
            lines += [f"[{k}]"] + [f"{kk} = {val(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for t in v:
                lines += [f"[[{k}]]"] + [f"{kk} = {val(vv)}" for kk, vv in t.items()]
    return "\n".join(lines) + "\n"


def test_the_toml_writer_round_trips():
    assert parse(tomllib.loads(_toml(BASE)), "s.toml") == parse(copy.deepcopy(BASE), "s.toml")


@pytest.mark.parametrize("case", ["directory", "gate_file", "up_zero", "up_parallel", "shadow_map", "seed",
                                  "seed_big", "unreadable"])
def test_bad_scene_input_exits_2_naming_file_key_and_fix(case, tmp_path, monkeypatch, capsys, mitsuba_backend):
    store = tmp_path / "store"
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store))
    f = tmp_path / "s.toml"
    args = ["--resolution", "8x8"]
    if case == "directory":
        f = tmp_path / "scenes"
        f.mkdir()
        (f / "a.toml").write_text(_toml(BASE))
        want = [f"error: {f}: is a directory, not a scene file", f"such as {f / 'a.toml'}"]
    elif case == "gate_file":
        f = ROOT / "references" / "gates.toml"
        want = [f"error: {f}: this is a gate file", f"`shadowlab gate {f}`"]
    elif case == "unreadable":
        f.write_bytes(b"name = \"\xff\xfe\"\n")
        want = [f"error: {f}: not valid TOML"]
    else:
        edits = {"up_zero": lambda d: d["camera"].update(up=[0, 0, 0]),
                 "up_parallel": lambda d: d["camera"].update(up=[0, 3, 5]),
                 "shadow_map": lambda d: d["lights"][0].update(shadow_map=200000)}
        f.write_text(_toml(_scene(edits.get(case, lambda d: None))))
        want = {"up_zero": [f"error: {f}: camera.up: expected a non-zero vector"],
                "up_parallel": [f"error: {f}: camera.up: expected a vector not parallel"],
                "shadow_map": [f"error: {f}: lights[0].shadow_map: expected an integer <= 16384"],
                "seed": ["--seed", f"-1 is out of range; expected a seed in [0, {SEED_MAX}]"],
                "seed_big": ["--seed", f"{SEED_MAX + 1} is out of range; expected a seed in [0, {SEED_MAX}]"]}[case]
        args += {"seed": ["--seed", "-1"], "seed_big": ["--seed", str(SEED_MAX + 1)]}.get(case, [])
    rc = cli_main(["reference", str(f)] + args)
    captured = capsys.readouterr()
    err = captured.err + captured.out
    assert rc == 2, err
    assert "Traceback" not in err
    for w in want:
        assert w in err, err
    assert not store.exists() or not any(store.rglob("*"))


def test_the_largest_seed_renders(tmp_path, monkeypatch, capsys, mitsuba_backend):
    """SEED_MAX is the largest seed mi.render's 32-bit seed (seed·1000 + i) takes."""
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(tmp_path / "store"))
    f = tmp_path / "s.toml"
    f.write_text(_toml(BASE))
    assert cli_main(["reference", str(f), "--resolution", "4x4", "--seed", str(SEED_MAX), "--spp", "4"]) == 0
    assert json.loads((tmp_path / "store" / "v" / "4x4" / "meta.json").read_text())["seed"] == SEED_MAX


# ----------------------------------------------------------------------------- gate files
_GATE = """version = 1
references = "."
[defaults.statistical]
alpha = 0.001
[[gate]]
name = "g"
scene = "contact"
target = "visibility"
candidate = { technique = "pcf", params = { kernel = 3 } }
budget = { rmse = 0.5 }
"""


@pytest.mark.parametrize("old, new, parts", [
    ("references =", "referenses =", ["unknown key(s) 'referenses' (did you mean 'references'?)"]),
    ('target = "visibility"', 'target = "visibilty"', ["target = 'visibilty' (did you mean 'visibility'?)"]),
    ('target = "visibility"', 'target = "visibility"\ncandiate = 1', ["did you mean 'candidate'?"]),
    ('technique = "pcf"', 'technique = "pfc"', ["unknown technique 'pfc' (did you mean 'pcf'?)"]),
    ('technique = "pcf"', 'tecnique = "pcf"', ["exactly one of technique, exr, truth (got none)",
                                               "unknown key 'tecnique' (did you mean 'technique'?)"]),
    ("kernel = 3", "kernal = 3", ["has no parameter 'kernal' (did you mean 'kernel'?)"]),
    ("kernel = 3", 'kernel = "3"', ["pcf.kernel: expected a number (without quotes), got '3'"]),
    ("kernel = 3", "kernel = true", ["pcf.kernel: expected a number"]),
    ("alpha = 0.001", "alpah = 0.001", ["[defaults.statistical]: unknown statistical setting(s) alpah",
                                        "did you mean 'alpha'?"]),
    ("budget = { rmse = 0.5 }", "budget = { rmes = 0.5 }", ["unknown budget metric 'rmes' (did you mean 'rmse'?)"]),
    ("budget = { rmse = 0.5 }", "statistical = { alpah = 0.1 }", ["did you mean 'alpha'?"]),
    ("version = 1", "version = true", ["version = True is not supported"]),
])
def test_gate_file_typos_get_a_suggestion(tmp_path, old, new, parts):
    p = tmp_path / "gates.toml"
    text = _GATE.replace(old, new)
    assert text != _GATE
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_gate_file(p)
    for part in parts:
        assert part in str(e.value), str(e.value)


def test_a_gate_bool_parameter_takes_only_booleans(tmp_path):
    tech, name = _bool_param()
    for bad in ('"no"', "0"):
        with pytest.raises(InputError, match=rf"{tech}\.{name}: expected true or false"):
            parse_gate_file(tomllib.loads(_GATE.replace('technique = "pcf", params = { kernel = 3 }',
                                                        f'technique = "{tech}", params = {{ {name} = {bad} }}')),
                            tmp_path / "g.toml")
    gf = parse_gate_file(tomllib.loads(_GATE.replace('technique = "pcf", params = { kernel = 3 }',
                                                     f'technique = "{tech}", params = {{ {name} = false }}')),
                         tmp_path / "g.toml")
    assert gf.gates[0].candidate.params == {name: False}


def _bool_param():
    for n in base.names():
        for p in base.get(n).params:
            if p.kind == "bool":
                return n, p.name
    pytest.skip("no technique has a boolean parameter")


def test_a_scene_given_as_a_gate_file_says_so(tmp_path):
    with pytest.raises(InputError, match="this is a scene file .* not a gate file"):
        load_gate_file(ROOT / "scenes" / "contact.toml")


def test_a_truth_seed_past_the_range_is_refused(tmp_path):
    text = _GATE.replace('{ technique = "pcf", params = { kernel = 3 } }', f"{{ truth = true, seed = {SEED_MAX + 1} }}")
    with pytest.raises(InputError, match=rf"integer in 0\.\.{SEED_MAX}"):
        parse_gate_file(tomllib.loads(text.replace("budget = { rmse = 0.5 }", "statistical = {}")), tmp_path / "g.toml")


# ----------------------------------------------------------------------------- presets
@pytest.mark.parametrize("data, parts", [
    ({"pfc": {"kernel": 3}}, ["unknown technique 'pfc' (did you mean 'pcf'?)"]),
    ({"pcf": {"kernal": 3}}, ["[pcf]: technique 'pcf' has no parameter 'kernal' (did you mean 'kernel'?)"]),
    ({"pcf": {"kernel": "3"}}, ["pcf.kernel: expected a number (without quotes)"]),
    ({"pcf": {"kernel": True}}, ["pcf.kernel: expected a number"]),
    ({"pcf": {"kernel": 99}}, ["pcf.kernel=99 is out of range"]),
    ({"descripton": "x", "pcf": {"kernel": 3}}, ["did you mean 'description'?"]),
    ({"description": 5, "pcf": {"kernel": 3}}, ["`description` must be a string"]),
    ({"camera": {}, "lights": []}, ["this is a scene file", "not a preset"]),
])
def test_preset_typos_and_types(data, parts):
    with pytest.raises(InputError) as e:
        preset_mod.from_dict(data, "p.toml")
    for part in parts:
        assert part in str(e.value), str(e.value)


def test_a_preset_bool_parameter_takes_only_booleans():
    tech, name = _bool_param()
    for bad in ("no", 0, 1):
        with pytest.raises(InputError, match=rf"{tech}\.{name}: expected true or false"):
            preset_mod.from_dict({tech: {name: bad}}, "p.toml")
    assert preset_mod.from_dict({tech: {name: False}}, "p.toml").values == {tech: {name: False}}


def test_a_directory_given_as_a_preset_says_so(tmp_path):
    with pytest.raises(InputError, match="is a directory; give a preset file such as"):
        preset_mod.load(tmp_path)


def test_a_saved_preset_loads(tmp_path):
    p = preset_mod.save(tmp_path / "p.toml", "p", {"pcf": {"kernel": 5}}, meta={"scene": "contact"})
    assert preset_mod.load(p).values == {"pcf": {"kernel": 5}}


# ----------------------------------------------------------------------------- what must keep loading
def test_every_builtin_scene_loads_with_the_hash_of_its_committed_reference():
    for n in builtin_names():
        spec = load_spec(resolve(n))
        # committed at the scene's default resolution; a camera path's scene is at frame 0, stored per frame
        d = store.path_for(n, spec.camera.resolution, ROOT / "references", frame=spec.frame)
        meta = json.loads((d / "meta.json").read_text())
        assert spec.digest() == meta["scene_hash"], n


def test_the_committed_gate_file_loads():
    assert len(load_gate_file(ROOT / "references" / "gates.toml").gates) >= 4


def test_did_you_mean_is_case_insensitive_and_quiet_when_nothing_is_close():
    assert did_you_mean("FOV", ["fov", "up"]) == " (did you mean 'fov'?)"
    assert did_you_mean("colour", ["color"]) == " (did you mean 'color'?)"
    assert did_you_mean("qqqq", ["fov", "up"]) == ""
    assert did_you_mean("kind", ["type", "name"]) == " (did you mean 'type'?)"
