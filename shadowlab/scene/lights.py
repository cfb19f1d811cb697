"""Lights: how each kind of the scene format becomes exactly one Mitsuba emitter.

| kind        | size parameter        | Mitsuba emitter (ground truth)                         | emission from ``power`` Φ |
|-------------|-----------------------|--------------------------------------------------------|---------------------------|
| rect        | size = [w, h] (m)     | ``rectangle`` shape + ``area`` emitter, facing target  | L = Φ / (π w h)           |
| disk        | radius (m)            | ``disk`` shape + ``area``, facing target               | L = Φ / (π · π r²)        |
| sphere      | radius (m)            | ``sphere`` shape + ``area``                            | L = Φ / (π · 4π r²)       |
| point       | radius (m), 0 = delta | sphere as above; r = 0: ``point``                      | r = 0: I = Φ / 4π         |
| spot        | radius (m), angle (°) | disk as above (the cone sets the light camera);        | r = 0: I = Φ / (2π(1−cos θ)) |
|             |                       | r = 0: ``spot`` with a hard cone                       |                           |
| directional | angular_diameter (°)  | a disk 1000 scene radii away subtending that angle;    | ``irradiance`` E (W/m²):  |
|             | 0 = delta             | 0: ``directional``                                     | L = E / (π sin²(θ/2))     |

Mitsuba has no area spot light, so a spot with a radius emits like a disk of that radius
everywhere in front of it; its cone only sets the shadow map's field of view.
"""  # noqa: E501

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from ..errors import SceneError
from .spec import LightSpec

SUN_DISTANCE = 1000.0  # in scene bounding radii


def unit(v):
    """``v`` scaled to length 1 (a tuple)."""
    n = math.sqrt(sum(x * x for x in v))
    return tuple(x / n for x in v)


def forward(light: LightSpec) -> tuple:
    """Unit vector the light faces (emits toward)."""
    if light.kind == "directional":
        return unit(light.direction)
    if light.kind in ("rect", "disk", "spot"):
        return unit([t - p for t, p in zip(light.target, light.position)])
    return (0.0, -1.0, 0.0)


def up_for(fwd, up):
    """An up vector not parallel to ``fwd``."""
    c = abs(sum(a * b for a, b in zip(fwd, unit(up))))
    if c > 0.999:
        return (1.0, 0.0, 0.0) if abs(fwd[0]) < 0.9 else (0.0, 0.0, 1.0)
    return up


def emission(light: LightSpec) -> tuple[str, float]:
    """(quantity, scalar) the Mitsuba emitter gets: ('radiance', L), ('intensity', I) or
    ('irradiance', E). Multiplied by ``light.color`` per channel."""
    P = light.power
    k = light.kind
    if k == "directional":
        E = light.irradiance if light.irradiance is not None else P
        if E is None:
            raise SceneError(f"light {light.name!r}: a directional light needs `irradiance` (W/m²)")
        if light.angular_diameter == 0:
            return "irradiance", E
        half = math.radians(light.angular_diameter) / 2
        return "radiance", E / (math.pi * math.sin(half) ** 2)
    if light.is_delta:
        if light.intensity is not None:
            return "intensity", light.intensity
        if P is None:
            raise SceneError(f"light {light.name!r}: a point/spot light of radius 0 needs `power` or `intensity`")
        if k == "spot":
            return "intensity", P / (2 * math.pi * (1 - math.cos(math.radians(light.angle))))
        return "intensity", P / (4 * math.pi)
    if light.radiance is not None:
        return "radiance", light.radiance
    if P is None:
        raise SceneError(f"light {light.name!r}: an area light needs `power` (W) or `radiance`")
    if k == "rect":
        area = light.size[0] * light.size[1]
    elif k in ("disk", "spot"):
        area = math.pi * light.radius ** 2
    else:  # sphere, point with radius
        area = 4 * math.pi * light.radius ** 2
    return "radiance", P / (math.pi * area)


def mitsuba_dict(light: LightSpec, scene_center, scene_radius) -> tuple[str, dict]:
    """(key, Mitsuba dict) of the light's emitter, as a shape carrying an area emitter or as a
    delta emitter. The key is ``light_<name>``; shadowlab finds the emitter by it."""
    T = mi.ScalarTransform4f
    qty, value = emission(light)
    rgb = {"type": "rgb", "value": [c * value for c in light.color]}
    key = f"light_{light.name}"
    k = light.kind
    if k == "directional":
        d = forward(light)
        if light.angular_diameter == 0:
            return key, {"type": "directional", "direction": list(d), "irradiance": rgb}
        dist = SUN_DISTANCE * scene_radius
        pos = [c - dist * x for c, x in zip(scene_center, d)]
        r = dist * math.tan(math.radians(light.angular_diameter) / 2)
        to_world = T().look_at(origin=pos, target=list(scene_center), up=list(up_for(d, light.up))) @ T().scale(
            [r, r, 1]
        )
        return key, {"type": "disk", "to_world": to_world, "emitter": {"type": "area", "radiance": rgb}}
    if light.is_delta:
        if k == "spot":
            return key, {"type": "spot", "to_world": T().look_at(origin=list(light.position), target=list(light.target),
                                                                   up=list(up_for(forward(light), light.up))),
                         "cutoff_angle": light.angle, "beam_width": light.angle * 0.999, "intensity": rgb}
        return key, {"type": "point", "position": list(light.position), "intensity": rgb}
    if k in ("sphere", "point"):
        return key, {"type": "sphere", "center": list(light.position), "radius": light.radius,
                     "emitter": {"type": "area", "radiance": rgb}}
    look = T().look_at(
        origin=list(light.position), target=list(light.target), up=list(up_for(forward(light), light.up))
    )
    if k == "rect":
        to_world = look @ T().scale([light.size[0] / 2, light.size[1] / 2, 1])
        return key, {"type": "rectangle", "to_world": to_world, "emitter": {"type": "area", "radiance": rgb}}
    to_world = look @ T().scale([light.radius, light.radius, 1])  # disk, spot
    return key, {"type": "disk", "to_world": to_world, "emitter": {"type": "area", "radiance": rgb}}


def light_sphere(scene, light, fit: str = "equal_area") -> tuple:
    """(centre (3,), radius) of the sphere that stands for ``light`` (a LightSpec) in the SDF
    soft-shadow algorithms of :mod:`shadowlab.sdf.soft` [Bán 2019, §3.2, §5.4].

    | light kind | centre | radius, ``fit="equal_area"`` | radius, ``fit="bounding"`` |
    |---|---|---|---|
    | sphere, point (r) | position | r | r |
    | disk, spot (r) | position | r (the disk seen face-on) | r |
    | rect w × h | position | √(w·h/π) (the disk of equal area) | ½√(w² + h²) [Bán 2019, §5.4] |
    | directional (θ) | scene centre − D·direction | D·tan(θ/2) | D·tan(θ/2) |

    with D = ``SUN_DISTANCE`` scene radii, where the ground truth puts the sun's disk. Delta
    lights (radius 0, θ = 0) give radius 0."""
    if fit not in ("equal_area", "bounding"):
        raise ValueError(f"fit must be equal_area or bounding, not {fit!r}")
    k = light.kind
    if k == "directional":
        D = SUN_DISTANCE * float(scene.radius)
        d = np.asarray(forward(light), dtype=np.float64)
        c = np.asarray(scene.center, dtype=np.float64) - D * d
        return c, D * math.tan(math.radians(light.angular_diameter) / 2)
    c = np.asarray(light.position, dtype=np.float64)
    if k == "rect":
        w, h = light.size
        return c, (math.sqrt(w * h / math.pi) if fit == "equal_area" else 0.5 * math.hypot(w, h))
    return c, float(light.radius)
