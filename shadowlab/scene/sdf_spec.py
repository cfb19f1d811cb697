"""The ``[[sdf]]`` tables of a scene file: SDF-only objects [Bán 2019, §2.4–2.6, §6].

Objects that have no Mitsuba twin (a Mandelbulb, CSG solids, capsules, planes) are declared in
the scene TOML under ``[[sdf]]``; they join the SDF twins of the ``[[shapes]]``
(:func:`shadowlab.scene.twins.sdf_of`). Mitsuba does not see them, so such a scene's G-buffer is
cone traced and its ground truth is the Monte-Carlo cone reference, not Mitsuba: its
:attr:`~shadowlab.scene.spec.SceneSpec.kind` is ``"sdf"``.

```toml
[[sdf]]
name = "bulb"                 # letters, digits, '_' or '-' (default sdf<i>)
type = "mandelbulb"           # sphere | box | cylinder | capsule | segment | plane | mandelbulb
                              # | union | intersection | difference
albedo = [0.7, 0.6, 0.4]      # diffuse reflectance (top-level objects only)
translate = [0.0, 1.2, 0.0]   # placement, as for [[shapes]]: T = translate · rotate… · scale
rotate = [0, 1, 0, 30]        # [ax, ay, az, degrees] or a list of them
scale = 1.0                   # a number keeps distances exact; [sx, sy, sz] gives a bound
offset = 0.0                  # f − offset: grows (> 0, rounds edges) or erodes (< 0) the solid
# sphere:    center = [0, 0, 0], radius = 1
# box:       half = [1, 1, 1] (half extents), rounding = 0 (edge radius, ≤ min(half))
# cylinder:  p0, p1 (axis end points), radius     (capped, solid)
# capsule:   p0, p1, radius;   segment: p0, p1
# plane:     normal = [0, 1, 0], height = 0       (half-space ⟨x, n⟩ ≤ height; unbounded)
# mandelbulb: power = 8, iterations = 8, bailout = 2, step = 1 (DE scale, ≤ 1)
# union / intersection / difference: children = [{ type = "box", ... }, { type = "sphere", ... }]
#            (inline tables with the keys above except name and albedo; difference: exactly two,
#             the second is removed from the first)
```

Validation needs no Mitsuba backend (errors name the file, the key and what was expected);
:func:`build_objects` turns the validated tables into :mod:`shadowlab.sdf.field` objects.
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import SceneError
from ..sdf import field as F
from .reader import Reader, rotations

PRIMITIVES = ("sphere", "box", "cylinder", "capsule", "segment", "plane", "mandelbulb")
OPERATIONS = ("union", "intersection", "difference")
TYPES = PRIMITIVES + OPERATIONS
#: cap of a Mandelbulb's ``iterations``: more only costs time (the estimate converges in float32 long before)
MANDELBULB_MAX_ITERATIONS = 64

_COMMON = {"type", "translate", "rotate", "scale", "offset"}
_KEYS = {
    "sphere": {"center", "radius"},
    "box": {"half", "rounding"},
    "cylinder": {"p0", "p1", "radius"},
    "capsule": {"p0", "p1", "radius"},
    "segment": {"p0", "p1"},
    "plane": {"normal", "height"},
    "mandelbulb": {"power", "iterations", "bailout", "step"},
    "union": {"children"},
    "intersection": {"children"},
    "difference": {"children"},
}


def _object(path: str, where: str, st, top: bool, depth: int = 0) -> dict:
    if not isinstance(st, dict):
        raise SceneError(f"{path}: {where}: expected a table, got {st!r}")
    r = Reader(path, where, st)
    typ = r.str("type", choices=TYPES)
    allowed = _COMMON | _KEYS[typ] | ({"name", "albedo"} if top else set())
    for k in st:
        if k not in allowed:
            others = [t for t, ks in _KEYS.items() if k in ks] if k not in _COMMON | {"name", "albedo"} else []
            if others:
                r.refuse(k, f"type {typ!r} has no {k!r} (it is a key of {', '.join(others)}); type {typ!r} takes: "
                         f"{', '.join(sorted(allowed))}. Remove the key or change the type")
            if k in ("name", "albedo"):
                r.refuse(k, f"a CSG child has no {k!r} (only top-level [[sdf]] objects have a name and an albedo); "
                         "remove it")
            r.unknown(k, allowed, f"an [[sdf]] object of type {typ!r}")
    scale = st.get("scale", 1.0)
    if isinstance(scale, (int, float)) and not isinstance(scale, bool):
        scale = r.num("scale", default=1.0, lo=1e-9)
    else:
        scale = list(r.vec("scale", positive=True))
    out = {
        "type": typ,
        "translate": list(r.vec("translate", default=(0, 0, 0))),
        "rotate": [[float(x) for x in q] for q in rotations(r, st)],
        "scale": scale,
        "offset": r.num("offset", default=0.0),
    }
    if typ == "sphere":
        out["center"] = list(r.vec("center", default=(0, 0, 0)))
        out["radius"] = r.num("radius", default=1.0, lo=1e-9)
    elif typ == "box":
        out["half"] = list(r.vec("half", default=(1, 1, 1), positive=True))
        out["rounding"] = r.num("rounding", default=0.0, lo=0.0, hi=min(out["half"]))
    elif typ in ("cylinder", "capsule", "segment"):
        out["p0"], out["p1"] = list(r.vec("p0", default=(0, 0, 0))), list(r.vec("p1", default=(0, 1, 0)))
        if out["p0"] == out["p1"]:
            r.fail("p1", "a point different from p0", out["p1"])
        if typ != "segment":
            out["radius"] = r.num("radius", default=1.0 if typ == "cylinder" else 0.5, lo=1e-9)
    elif typ == "plane":
        out["normal"] = list(r.vec("normal", default=(0, 1, 0)))
        if not any(out["normal"]):
            r.fail("normal", "a non-zero vector", out["normal"])
        out["height"] = r.num("height", default=0.0)
    elif typ == "mandelbulb":
        out["power"] = r.num("power", default=8.0, lo=2.0, hi=16.0)
        out["iterations"] = r.int("iterations", default=8, lo=1, hi=MANDELBULB_MAX_ITERATIONS,
                                  why=" (each iteration is a step of every distance evaluation; float32 "
                                      "gains nothing past ~30)")
        out["bailout"] = r.num("bailout", default=2.0, lo=1.0 + 1e-6)
        out["step"] = r.num("step", default=1.0, lo=1e-3, hi=1.0)
    else:
        kids = st.get("children")
        n_ok = (lambda n: n == 2) if typ == "difference" else (lambda n: n >= 1)
        if not isinstance(kids, list) or not n_ok(len(kids)):
            r.fail("children", "exactly two inline tables (the solid and what is removed from it)"
                   if typ == "difference" else "a non-empty list of inline tables", kids)
        if depth > 16:
            r.fail("children", "CSG nested at most 16 levels deep", None)
        out["children"] = [_object(path, f"{where}.children[{i}]", k, False, depth + 1) for i, k in enumerate(kids)]
    if top:
        out["albedo"] = list(r.vec("albedo", default=(0.5, 0.5, 0.5)))
        if any(a < 0 or a > 1 for a in out["albedo"]):
            r.fail("albedo", "three numbers in [0, 1]", out["albedo"])
    return out


def parse_sdf_tables(raw, path: str, taken: set) -> tuple:
    """Validate the ``[[sdf]]`` array of a scene document; returns a tuple of plain dicts
    (JSON-serialisable, so they enter the scene hash). ``taken``: names of lights and shapes."""
    if not isinstance(raw, list):
        raise SceneError(f"{path}: sdf: expected an array of [[sdf]] tables, got {raw!r}")
    out, names = [], set(taken)
    for i, st in enumerate(raw):
        d = _object(path, f"sdf[{i}]", st, top=True)
        name = st.get("name", f"sdf{i}")
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name) or "__" in name:
            raise SceneError(f"{path}: sdf[{i}].name: expected a name of letters, digits, '_' or '-' starting "
                             f"with a letter (no '__'), got {name!r}")
        if name in names:
            raise SceneError(f"{path}: sdf[{i}].name: expected a name not used by a light, shape or other sdf "
                             f"object, got {name!r}")
        names.add(name)
        out.append({"name": name, **d})
    return tuple(out)


def _build(d: dict):
    t = d["type"]
    if t == "sphere":
        obj = F.Sphere(d["center"], d["radius"])
    elif t == "box":
        obj = F.Box(d["half"], rounding=d["rounding"])
    elif t == "cylinder":
        obj = F.Cylinder(d["p0"], d["p1"], d["radius"])
    elif t == "capsule":
        obj = F.Capsule(d["p0"], d["p1"], d["radius"])
    elif t == "segment":
        obj = F.Segment(d["p0"], d["p1"])
    elif t == "plane":
        obj = F.Plane(d["normal"], d["height"])
    elif t == "mandelbulb":
        obj = F.Mandelbulb(d["power"], d["iterations"], d["bailout"], step=d["step"])
    else:
        kids = [_build(k) for k in d["children"]]
        obj = {"union": F.Union, "intersection": F.Intersection, "difference": F.Difference}[t](*kids)
    obj = F.transform(obj, d["translate"], d["rotate"], d["scale"])
    if d["offset"]:
        obj = F.Offset(obj, d["offset"])
    return obj


def build_objects(tables) -> list:
    """The SDF objects of validated ``[[sdf]]`` tables, named and with their albedo."""
    return [_build(d).named(d["name"], d["albedo"]) for d in tables]


def bounds(tables):
    """World bounding box (lo, hi) of the bounded ``[[sdf]]`` objects, or None if there is none
    (planes are unbounded and left out)."""
    objs = [o for o in build_objects(tables) if o.bounded]
    if not objs:
        return None
    return np.min([o.bbox_min for o in objs], 0), np.max([o.bbox_max for o in objs], 0)
