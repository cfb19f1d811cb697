"""tests/scene_builder.py: the TOML it writes reads back as the scene document it was given (the
same SceneSpec digest), for every part of the scene format the tests use."""

import doctest
import math
import sys

import pytest

import scene_builder
from lightview_scene import SCENE as LIGHTVIEW
from scene_builder import floor, scene, scene_toml, spec_of, write_scene

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CAM = {"position": [0.0, 3.0, 5.0], "target": [0.0, 0.0, 0.0], "fov": 40}
SUN = {"name": "sun", "kind": "directional", "direction": [0.3, -1.0, 0.8], "irradiance": 3.0, "shadow_map": 64}

DOCS = {
    "lightview": LIGHTVIEW,
    "sdf": scene("csg", camera=CAM, resolution=(16, 12), lights=[SUN], sdf=[
        {"name": "ground", "type": "plane"},
        {"name": "nut", "type": "difference", "translate": [0, 0.5, 0],
         "children": [{"type": "box", "half": [1, 0.2, 1]},
                      {"type": "cylinder", "p0": [0, -1, 0], "p1": [0, 1, 0], "radius": 0.3}]}]),
    "path": scene("walk", camera={**CAM, "near": 0.1, "far": 300.0,
                                  "path": {"frames": 3, "interpolation": "linear",
                                           "keys": [{"frame": 0, "position": [0, 3, 5]},
                                                    {"frame": 2, "position": [1, 3, 5], "fov": 50}]}},
                  lights=[SUN], shapes=[floor(2.0, albedo=[0.7, 0.7, 0.7]),
                                        {"name": "pane", "type": "rectangle", "two_sided": True,
                                         "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "translate": [0, 1, 0]}],
                  description='quotes " and \\ and ünïcode'),
}


@pytest.mark.parametrize("name", sorted(DOCS))
def test_toml_reads_back_as_the_document_and_the_same_spec(name, tmp_path):
    d = DOCS[name]
    text = scene_toml(d)
    assert tomllib.loads(text) == d
    p = write_scene(tmp_path / "sub" / f"{name}.toml", d)
    assert p.read_text(encoding="utf-8") == text
    assert spec_of(tomllib.loads(text), p).digest() == spec_of(d, p).digest()


def test_scene_puts_the_resolution_into_a_copy_of_the_camera():
    d = scene("s", camera=CAM, resolution=(8, 6), lights=[SUN], shapes=[floor()])
    assert d["camera"]["resolution"] == [8, 6] and "resolution" not in CAM
    assert d["shapes"] == [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 4.0}]
    assert "sdf" not in d and spec_of(d).camera.resolution == (8, 6)


def test_values_toml_cannot_hold_are_refused():
    with pytest.raises(TypeError, match="cannot write"):
        scene_toml({"name": "x", "camera": {"position": None}})
    assert scene_toml({"x": math.inf, "y": -math.inf}) == "x = inf\ny = -inf\n"
    assert scene_toml({"x": math.nan}) == "x = nan\n"


def test_the_modules_example():
    assert doctest.testmod(scene_builder, optionflags=doctest.NORMALIZE_WHITESPACE).failed == 0
