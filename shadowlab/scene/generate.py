"""Generated many-light scenes for benchmarks of layered shadows [Tamás 2015, §5]: ``n`` point and
spot lights with ranges over a floor with casters, deterministic in a seed.

:func:`many_lights_data` returns the scene as the TOML document's data (a dict that
:func:`shadowlab.scene.spec.parse` validates), :func:`many_lights_spec` the parsed
:class:`~shadowlab.scene.spec.SceneSpec`, :func:`write_many_lights` a ``.toml`` file that every
command takes as a scene (``shadowlab compare /tmp/many_64.toml -t ssss``).

Layout, for ``n`` lights: a g × g grid of cells (g = ⌈√n⌉) of :data:`CELL` metres each on a floor
of side g·CELL; light i sits in cell i at the cell's centre plus a uniform jitter of ±0.3 CELL,
1.3–2.2 m above the floor, with a range of 1.6–2.6 m (its lit volume a ball of that radius: the
volumes of neighbouring cells often meet, those of cells farther apart seldom do, so the layers
stay few as n grows). One light in three is
a disk spot (half-angle 70°) aimed at a point below it, the others spherical point lights; radii
0.06–0.12 m, powers 50–130 W, pale colours. Each cell holds one caster beside its light: a box
(a Mitsuba triangle mesh) or a sphere, 0.2–0.45 m. The camera looks down on the whole floor from
the front. One light cell in four (i mod 4 = 1) also holds a coloured translucent pane
(README, "Translucent casters"), a horizontal 0.6 m square halfway between the light and the
floor, offset toward the cell's centre, with a pale transmittance colour and opacity 0.6–1. Every
number is drawn from ``numpy.random.default_rng(seed)`` (the panes' from a second stream,
``default_rng(seed + 1)``, so the lights and opaque casters are those of the scene without panes),
so (n, seed) gives the same scene, and the same scene hash, on every machine.

>>> spec = many_lights_spec(32, seed=1)
>>> len(spec.lights), all(l.range for l in spec.lights), sum(s.translucent for s in spec.shapes)
(32, True, 8)
>>> many_lights_spec(32, seed=1).digest() == spec.digest()
True
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .spec import SceneSpec, parse

#: side of one light's cell (m)
CELL = 3.0


def many_lights_data(n: int, seed: int = 0, resolution: tuple = (128, 128)) -> dict:
    """The scene of ``n`` lights (module docstring) as TOML data: a dict for
    :func:`shadowlab.scene.spec.parse`."""
    n = int(n)
    if n < 1:
        raise ValueError(f"many_lights: n = {n}; expected at least one light")
    rng = np.random.default_rng(int(seed))
    glass = np.random.default_rng(int(seed) + 1)
    g = math.ceil(math.sqrt(n))
    half = 0.5 * g * CELL
    lights, shapes = [], [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": half,
                           "albedo": [0.8, 0.8, 0.8]}]
    r3 = lambda v: [round(float(x), 3) for x in v]  # noqa: E731  (short, exact numbers in the TOML)
    for i in range(g * g):
        cx = -half + CELL * (i % g + 0.5)
        cz = -half + CELL * (i // g + 0.5)
        if i < n:
            jx, jz = rng.uniform(-0.3, 0.3, 2) * CELL
            pos = [cx + jx, rng.uniform(1.3, 2.2), cz + jz]
            light = {
                "name": f"L{i:03d}",
                "radius": round(float(rng.uniform(0.06, 0.12)), 3),
                "power": round(float(rng.uniform(50.0, 130.0)), 1),
                "range": round(float(rng.uniform(1.6, 2.6)), 3),
                "color": r3(1.0 - 0.35 * rng.random(3)),
                "shadow_map": 512,
            }
            if i % 3 == 2:
                tx, tz = rng.uniform(-0.5, 0.5, 2)
                light.update(kind="spot", position=r3(pos), target=r3([pos[0] + tx, 0.0, pos[2] + tz]), angle=70)
            else:
                light.update(kind="point", position=r3(pos))
            lights.append(light)
            if i % 4 == 1:
                pane = [0.5 * (pos[0] + cx), 0.5 * pos[1], 0.5 * (pos[2] + cz)]
                shapes.append({"name": f"glass{i:03d}", "type": "rectangle", "translate": r3(pane),
                               "rotate": [1, 0, 0, -90], "scale": 0.3, "albedo": [0.6, 0.6, 0.6],
                               "transmittance": r3(0.15 + 0.85 * glass.random(3)),
                               "opacity": round(float(glass.uniform(0.6, 1.0)), 3)})
        # a caster beside the cell's centre, whether or not the cell has a light
        ox, oz = rng.uniform(-0.25, 0.25, 2) * CELL
        s = float(rng.uniform(0.2, 0.45))
        if rng.random() < 0.5:
            shapes.append({"name": f"box{i:03d}", "type": "cube", "translate": r3([cx + ox, s, cz + oz]),
                           "rotate": [0, 1, 0, round(float(rng.uniform(0, 90)), 1)], "scale": round(s, 3),
                           "albedo": [0.7, 0.7, 0.7]})
        else:
            shapes.append({"name": f"ball{i:03d}", "type": "sphere", "center": r3([cx + ox, s, cz + oz]),
                           "radius": round(s, 3), "albedo": [0.7, 0.7, 0.7]})
    d = 1.05 * g * CELL
    return {"name": f"many_lights_{n}", "truth_allocation": "contribution",
            "description": f"{n} generated point and spot lights with ranges over a {2 * half:g} m floor with "
                           f"casters (shadowlab.scene.generate, seed {int(seed)}).",
            "camera": {"position": [0.0, round(0.95 * d, 3), round(0.85 * d, 3)], "target": [0.0, 0.0, 0.0],
                       "fov": 55, "resolution": [int(resolution[0]), int(resolution[1])]},
            "lights": lights, "shapes": shapes}


def many_lights_spec(n: int, seed: int = 0, resolution: tuple = (128, 128)) -> SceneSpec:
    """The parsed scene of ``n`` lights (validated like a scene file)."""
    return parse(many_lights_data(n, seed, resolution), f"<many_lights_{int(n)}>")


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def to_toml(data: dict) -> str:
    """Scene data (top-level scalars, ``camera``, ``[[lights]]``, ``[[shapes]]``) as TOML text."""
    out = [f"{k} = {_toml_value(v)}" for k, v in data.items() if not isinstance(v, (dict, list))]
    out += ["", "[camera]"] + [f"{k} = {_toml_value(v)}" for k, v in data["camera"].items()]
    for table in ("lights", "shapes"):
        for item in data[table]:
            out += ["", f"[[{table}]]"] + [f"{k} = {_toml_value(v)}" for k, v in item.items()]
    return "\n".join(out) + "\n"


def write_many_lights(path, n: int, seed: int = 0, resolution: tuple = (128, 128)) -> Path:
    """Write the scene of ``n`` lights to ``path`` (a ``.toml`` file); return the path."""
    p = Path(path)
    p.write_text(to_toml(many_lights_data(n, seed, resolution)), encoding="utf-8")
    return p
