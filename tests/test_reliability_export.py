"""lights.json for a sun (issue 27, "Export"): it carries the irradiance the scene gave, and its
emitter disk (Mitsuba's far stand-in for the sun) is marked as not for drawing in an engine.

Closed form: the disk subtends the angular diameter θ at its distance, and its radiance L gives
the scene's irradiance E = L · π sin²(θ/2) on a surface facing it; disk_radius / disk_distance =
tan(θ/2). Exported through ``shadowlab export`` and checked against both.
"""

import json
import math
import sys
from pathlib import Path

import pytest

from shadowlab import cli
from shadowlab.exchange.ply import read_ply

sys.path.insert(0, str(Path(__file__).parent))
from scene_builder import floor, write_scene  # noqa: E402


@pytest.mark.parametrize("angle", [0.53, 0.0])
def test_the_suns_irradiance_is_exported_and_its_disk_is_not_for_drawing(angle, tmp_path, capsys, mitsuba_backend):
    E, color = 3.5, [1.0, 0.9, 0.8]
    lights = [{"name": "sun", "kind": "directional", "direction": [0.3, -1.0, 0.2], "angular_diameter": angle,
               "irradiance": E, "color": color}]
    toml = write_scene(tmp_path / "sunny.toml", name="sunny", lights=lights, shapes=[floor(3.0)], resolution=(16, 16),
                       camera={"position": [0.0, 5.0, 6.0], "target": [0.0, 0.0, 0.0], "fov": 50})
    out = tmp_path / "export"
    assert cli.main(["export", str(toml), "--out", str(out)]) == 0, capsys.readouterr().err
    lj = json.loads((out / "lights.json").read_text())
    (sun,) = lj["lights"]
    assert sun["irradiance"]["value"] == pytest.approx(E) and sun["irradiance"]["units"] == "W m^-2"
    assert sun["irradiance"]["rgb"] == pytest.approx([E * c for c in color])
    assert "irradiance" in lj["convention"] and "engine_draws" in lj["convention"]
    if angle == 0:                                     # a delta sun: no disk, nothing to hide
        assert sun["ply"] is None and "engine_draws" not in sun and sun["emission"]["quantity"] == "irradiance"
        return
    half = math.radians(angle) / 2
    L = sun["emission"]["value"]
    assert sun["emission"]["quantity"] == "radiance" and L * math.pi * math.sin(half) ** 2 == pytest.approx(E)
    size = sun["size"]
    assert size["disk_radius"] / size["disk_distance"] == pytest.approx(math.tan(half))
    assert sun["engine_draws"] is False and "must not draw it" in sun["ply_note"]
    assert f"{size['disk_radius']:.4g} m at {size['disk_distance']:.4g} m" in sun["ply_note"]
    ply = read_ply(out / sun["ply"])
    assert any("not for drawing in an engine" in c for c in ply["comments"]), ply["comments"]
    assert ply["positions"].shape[1] == 3
