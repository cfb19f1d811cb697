"""The report's light summary: each light's kind and size, and what its truth is.

A run may carry ``run["light_info"]`` = {light: {"kind", and the kind's size keys}}, made from the
scene's lights by :func:`light_info`; the report then lists the lights with a note where the
truth is not what the light's name suggests. The one such case: a **spot light with a radius**
has no cone in the truth. Mitsuba has no area spot light, so its truth is a disk area emitter
that emits in every direction in front of it; the cone only sets the shadow map's field of
view (``shadowlab.scene.lights``). A spot of radius 0 is Mitsuba's ``spot`` with a hard cone.

>>> from shadowlab.scene.spec import LightSpec
>>> info = light_info([LightSpec("lamp", "spot", radius=0.1, angle=25.0)])
>>> info
{'lamp': {'kind': 'spot', 'radius': 0.1, 'angle': 25.0}}
>>> light_notes(info["lamp"])[0][:28]
'no cone in the truth: Mitsub'
"""

from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["light_info", "light_notes", "light_rows"]

#: the size keys of each light kind (as in the scene format)
SIZE_KEYS = {"rect": ("size",), "disk": ("radius",), "sphere": ("radius",), "point": ("radius",),
             "spot": ("radius", "angle"), "directional": ("angular_diameter",)}


def light_info(lights) -> dict:
    """{name: {"kind", size keys}} of the scene's lights (``SceneSpec.lights``), JSON-ready."""
    out = {}
    for l in lights:
        d = {"kind": l.kind}
        for k in SIZE_KEYS.get(l.kind, ()):
            v = getattr(l, k)
            d[k] = [float(x) for x in v] if isinstance(v, (tuple, list)) else float(v)
        out[l.name] = d
    return out


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def light_notes(info: Mapping) -> list[str]:
    """What the truth of a light is, where that needs saying (see the module docstring)."""
    kind, r = info.get("kind"), _num(info.get("radius", 0.0))
    if kind == "spot" and r > 0:
        return [f"no cone in the truth: Mitsuba has no area spot light, so the truth is a disk of radius {r:g} m "
                "that emits in every direction in front of it (surfaces outside the cone are lit); the cone "
                f"(half-angle {_num(info.get('angle')):g}°) only sets the shadow map's field of view"]
    if kind == "spot":
        return [f"delta spot: Mitsuba's spot with a hard cone of half-angle {_num(info.get('angle')):g}°"]
    if kind in ("point", "directional") and _num(info.get("radius", info.get("angular_diameter", 0.0))) == 0:
        return ["delta light: hard shadows in the truth"]
    return []


def _size(info: Mapping) -> str:
    parts = []
    for k in SIZE_KEYS.get(info.get("kind"), ()):
        if k not in info:
            continue
        v = info[k]
        unit = "°" if k in ("angle", "angular_diameter") else " m"
        text = " × ".join(f"{_num(x):g}" for x in v) if isinstance(v, (list, tuple)) else f"{_num(v):g}"
        parts.append(f"{k} {text}{unit}")
    return ", ".join(parts)


def light_rows(names, info: Mapping | None) -> list[tuple[str, str, str, str]]:
    """(name, kind, size, notes) per light of ``names``; kind and size "?" when ``info`` lacks it.

    >>> light_rows(["key"], {"key": {"kind": "rect", "size": [1.0, 0.5]}})
    [('key', 'rect', 'size 1 × 0.5 m', '')]
    """
    rows = []
    for n in names:
        d = (info or {}).get(n)
        if not isinstance(d, Mapping):
            rows.append((n, "?", "?", ""))
            continue
        rows.append((n, str(d.get("kind", "?")), _size(d), "; ".join(light_notes(d))))
    return rows
