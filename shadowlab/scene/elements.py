"""The lights and shapes of a scene file: :class:`LightSpec` (``[[lights]]``) and :class:`ShapeSpec`
(``[[shapes]]``), the keys each kind and type takes (:data:`LIGHT_KEYS`, :data:`SHAPE_KEYS`) and the
validation of their tables. Part of the scene format of :mod:`shadowlab.scene.spec`, which re-exports
these names.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

from ..errors import SceneError
from .reader import Reader, norm, rotations
from .textures import AlphaTextureError, read_alpha

LIGHT_KINDS = ("rect", "disk", "sphere", "spot", "point", "directional")
SHAPE_TYPES = ("rectangle", "disk", "cube", "sphere", "cylinder", "ply", "obj", "gltf")
DEPTH_BITS = (16, 24, 32)
#: largest ``shadow_map`` (texels per side): the light view holds a float64 depth image of
#: res² texels per face while it is made (a 16384² face is 2 GiB; 200000² would be 298 GiB)
SHADOW_MAP_MAX = 16384
_LIGHT_COMMON = ("name", "kind", "color", "power", "shadow_map", "depth_bits", "casts_shadows")
#: the keys each light kind takes (README, "Scene format"); a key of another kind is refused
LIGHT_KEYS = {
    "rect": _LIGHT_COMMON + ("position", "target", "up", "size", "radiance", "near"),
    "disk": _LIGHT_COMMON + ("position", "target", "up", "radius", "radiance", "near"),
    "sphere": _LIGHT_COMMON + ("position", "radius", "radiance", "near"),
    "spot": _LIGHT_COMMON + ("position", "target", "up", "radius", "angle", "radiance", "intensity", "near", "range"),
    "point": _LIGHT_COMMON + ("position", "radius", "radiance", "intensity", "near", "range"),
    "directional": _LIGHT_COMMON + ("direction", "up", "angular_diameter", "irradiance"),
}
_LIGHT_SIZE_KEY = {"rect": "size", "disk": "radius", "sphere": "radius", "spot": "radius", "point": "radius",
                   "directional": "angular_diameter"}
_SHAPE_COMMON = ("name", "type", "albedo", "translate", "rotate", "scale", "two_sided", "alpha_texture",
                 "alpha_cutoff", "transmittance", "opacity", "casts_shadows")
#: the keys each shape type takes; a key of another type (``radius`` on a cube) is refused
SHAPE_KEYS = {
    "rectangle": _SHAPE_COMMON, "disk": _SHAPE_COMMON, "cube": _SHAPE_COMMON,
    "sphere": _SHAPE_COMMON + ("center", "radius"),
    "cylinder": _SHAPE_COMMON + ("p0", "p1", "radius", "caps"),
    "ply": _SHAPE_COMMON + ("filename",), "obj": _SHAPE_COMMON + ("filename",),
    "gltf": _SHAPE_COMMON + ("filename", "node", "primitive"),
}


@dataclass(frozen=True)
class LightSpec:
    """One light. Sizes in scene units (metres), angles in degrees, power in watts.

    size: rect (width, height); radius: disk, sphere, spot and point (0 = a delta light);
    angular_diameter: directional (0 = a delta light). ``radiance`` (area kinds),
    ``intensity`` (delta point/spot) and ``irradiance`` (directional) are derived from
    ``power`` unless given; see :func:`shadowlab.scene.lights.emission`.
    """

    name: str
    kind: str
    position: tuple = (0.0, 0.0, 0.0)
    target: tuple = (0.0, 0.0, 0.0)
    up: tuple = (0.0, 1.0, 0.0)
    direction: tuple = (0.0, -1.0, 0.0)
    size: tuple = (0.0, 0.0)
    radius: float = 0.0
    angle: float = 30.0
    angular_diameter: float = 0.0
    color: tuple = (1.0, 1.0, 1.0)
    power: float | None = None
    radiance: float | None = None
    irradiance: float | None = None
    intensity: float | None = None
    shadow_map: int = 512
    depth_bits: int = 32
    near: float | None = None
    range: float | None = None   # point / spot: influence radius (m), windowed falloff; None = unbounded
    casts_shadows: bool = False  # the emitter's own panel blocks the other lights (engines: no)

    @property
    def physical_size(self) -> float:
        """The light's size as one number: rect diagonal-equivalent width (sqrt of area for the
        side of the equal-area square), 2*radius for disk/sphere/spot/point, the angular
        diameter in radians for directional. ``light_size`` parameters start from this."""
        if self.kind == "rect":
            return math.sqrt(self.size[0] * self.size[1])
        if self.kind == "directional":
            return math.radians(self.angular_diameter)
        return 2.0 * self.radius

    @property
    def is_delta(self) -> bool:
        return self.physical_size == 0.0

    @property
    def has_panel(self) -> bool:
        """The light is a surface in the scene that could block another light: an area light
        (rect, disk, sphere; spot and point of radius > 0). A delta light has none, and a
        directional light's emitter is a disk far outside the scene, on no other light's path."""
        return not self.is_delta and self.kind != "directional"


@dataclass(frozen=True)
class ShapeSpec:
    name: str
    type: str
    albedo: tuple = (0.5, 0.5, 0.5)
    translate: tuple = (0.0, 0.0, 0.0)
    rotate: tuple = ()           # sequence of (ax, ay, az, degrees), applied in order
    scale: tuple = (1.0, 1.0, 1.0)
    center: tuple | None = None  # sphere
    radius: float = 1.0          # sphere, cylinder
    p0: tuple = (0.0, 0.0, 0.0)  # cylinder
    p1: tuple = (0.0, 1.0, 0.0)
    caps: bool = True            # cylinder: close the tube with two disks
    filename: str | None = None  # ply / obj / gltf, resolved relative to the scene file
    node: int | str | None = None    # gltf: the mesh node (index or name)
    primitive: int | None = None     # gltf: one primitive of its mesh (None: all)
    two_sided: bool = True
    alpha_texture: str | None = None  # alpha-tested caster: image file, resolved relative to the scene file
    alpha_cutoff: float = 0.5         # texels with alpha < cutoff are transparent (discarded)
    transmittance: tuple | None = None  # translucent caster: RGB fraction of light let through, in [0, 1]
    opacity: float = 1.0                # share of the surface that filters (the rest lets all light through)
    casts_shadows: bool = True          # false: seen and lit, but never blocks a light (shadow rays, light views)

    @property
    def alpha_tested(self) -> bool:
        return self.alpha_texture is not None

    @property
    def translucent(self) -> bool:
        return self.transmittance is not None

    @property
    def tau(self) -> tuple:
        """The straight-line transmittance of one crossing of the surface, per RGB channel:
        τ = 1 − opacity·(1 − transmittance) (README, "Translucent casters"); an opaque shape
        has τ = (0, 0, 0).

        >>> ShapeSpec("pane", "rectangle", transmittance=(1.0, 0.5, 0.0), opacity=0.5).tau
        (1.0, 0.75, 0.5)
        """
        if self.transmittance is None:
            return (0.0, 0.0, 0.0)
        return tuple(1.0 - self.opacity * (1.0 - t) for t in self.transmittance)


def _kind_keys(r: Reader, kind: str, table: dict, keys: dict, label: str):
    """Refuse a key the light kind / shape type does not take, naming the kinds that take it."""
    allowed = keys[kind]
    for k in table:
        if k in allowed:
            continue
        others = [o for o, ks in keys.items() if k in ks]
        if others:
            size = (f"; a {kind} light's size is {_LIGHT_SIZE_KEY[kind]!r}"
                    if label == "light" and k in _LIGHT_SIZE_KEY.values() else "")
            r.refuse(k, f"a {kind} {label} has no {k!r} (it is a key of {', '.join(others)} {label}s){size}; a "
                     f"{kind} {label} takes: {', '.join(sorted(allowed))}. Remove the key or change the {label}'s "
                     f"{'kind' if label == 'light' else 'type'}")
        r.unknown(k, allowed, f"a {kind} {label}")


def read_light(path: str, i: int, lt, names: set) -> LightSpec:
    if not isinstance(lt, dict):
        raise SceneError(f"{path}: lights[{i}]: expected a table, got {lt!r}")
    r = Reader(path, f"lights[{i}]", lt)
    kind = r.str("kind", choices=LIGHT_KINDS)
    _kind_keys(r, kind, lt, LIGHT_KEYS, "light")
    lname = r.str("name", default=f"L{i}")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", lname):
        r.fail("name", "a name of letters, digits, '_' or '-' starting with a letter", lname)
    if lname in names:
        r.fail("name", "a name not used by another light", lname)
    names.add(lname)
    kw = dict(name=lname, kind=kind, color=r.vec("color", default=(1, 1, 1)),
              shadow_map=r.int("shadow_map", default=512, lo=8, hi=SHADOW_MAP_MAX,
                               why=f" (texels per side; making a {SHADOW_MAP_MAX}² map takes 2 GiB per face, "
                                   "and the memory grows with the square of the size)"),
              depth_bits=r.int("depth_bits", default=32, choices=DEPTH_BITS),
              up=r.vec("up", default=(0, 1, 0)))
    if any(x < 0 for x in kw["color"]):
        r.fail("color", "non-negative numbers", list(kw["color"]))
    if r.has("up") and norm(kw["up"]) == 0:
        r.fail("up", "a non-zero vector (the light's up direction; the default is [0, 1, 0])", list(kw["up"]))
    for k in ("power", "radiance", "irradiance", "intensity"):
        if r.has(k):
            kw[k] = r.num(k, lo=0.0)
    if not any(k in kw for k in ("power", "radiance", "irradiance", "intensity")):
        r.fail("power", "a number (the light's power in watts; or radiance / irradiance / intensity)")
    if r.has("near"):
        kw["near"] = r.num("near", lo=1e-6)
    if kind == "directional":
        kw["direction"] = r.vec("direction")
        if norm(kw["direction"]) == 0:
            r.fail("direction", "a non-zero vector", list(kw["direction"]))
        kw["angular_diameter"] = r.num("angular_diameter", default=0.0, lo=0.0, hi=30.0)
    else:
        kw["position"] = r.vec("position")
        if kind in ("rect", "disk", "spot"):
            kw["target"] = r.vec("target")
            if norm([a - b for a, b in zip(kw["position"], kw["target"])]) == 0:
                r.fail("target", "a point different from the light's position", list(kw["target"]))
        if kind == "rect":
            kw["size"] = r.vec("size", n=2, positive=True)
        elif kind in ("disk", "sphere"):
            kw["radius"] = r.num("radius", lo=1e-6)
        else:
            kw["radius"] = r.num("radius", default=0.0, lo=0.0)
        if kind == "spot":
            kw["angle"] = r.num("angle", default=30.0, lo=1.0, hi=80.0)
        if r.has("range"):  # only point and spot take it (_kind_keys refused it on the other kinds)
            kw["range"] = r.num("range")
            if kw["range"] <= 0:
                r.fail("range", "a number > 0 (the light's influence radius in metres; leave it out for an "
                       "unbounded light)", kw["range"])
        if kind in ("spot", "point"):  # radius 0: a delta light, which has an intensity and no radiance
            if kw["radius"] == 0 and r.has("radiance"):
                r.fail("radiance", f"no radiance on a {kind} light of radius 0 (a delta light has no area): give "
                       "intensity (W/sr) or power, or a radius > 0", kw["radiance"])
            if kw["radius"] > 0 and r.has("intensity"):
                r.fail("intensity", f"no intensity on a {kind} light of radius {kw['radius']:g} (an area light): "
                       "give radiance or power, or radius = 0 for a delta light", kw["intensity"])
    light = LightSpec(**kw)
    if r.bool("casts_shadows", False):
        if not light.has_panel:
            r.fail("casts_shadows", f"false or no key: a {'directional' if kind == 'directional' else 'delta'} "
                   "light has no surface in the scene that could block another light", True)
        light = replace(light, casts_shadows=True)
    return light


def read_shape(path: str, i: int, st, names: set, snames: set, base: Path) -> ShapeSpec:
    if not isinstance(st, dict):
        raise SceneError(f"{path}: shapes[{i}]: expected a table, got {st!r}")
    r = Reader(path, f"shapes[{i}]", st)
    typ = r.str("type", choices=SHAPE_TYPES)
    _kind_keys(r, typ, st, SHAPE_KEYS, "shape")
    sname = r.str("name", default=f"{typ}{i}")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", sname) or "__" in sname:
        r.fail("name", "a name of letters, digits, '_' or '-' starting with a letter (no '__')", sname)
    if sname in snames or sname in names:
        r.fail("name", "a name not used by another shape or light", sname)
    snames.add(sname)
    alb = r.vec("albedo", default=(0.5, 0.5, 0.5))
    if any(a < 0 or a > 1 for a in alb):
        r.fail("albedo", "three numbers in [0, 1]", list(alb))
    rot = rotations(r, st)
    kw = dict(name=sname, type=typ, albedo=alb, translate=r.vec("translate", default=(0, 0, 0)),
              rotate=tuple(tuple(float(x) for x in q) for q in rot),
              scale=r.vec("scale", default=(1, 1, 1), positive=True),
              two_sided=r.bool("two_sided", True), casts_shadows=r.bool("casts_shadows", True))
    if typ == "sphere":
        kw["center"] = r.vec("center", default=(0, 0, 0))
        kw["radius"] = r.num("radius", default=1.0, lo=1e-6)
    elif typ == "cylinder":
        kw["p0"], kw["p1"] = r.vec("p0", default=(0, 0, 0)), r.vec("p1", default=(0, 1, 0))
        if kw["p0"] == kw["p1"]:
            r.fail("p1", "a point different from p0 (the cylinder's axis runs from p0 to p1)", list(kw["p1"]))
        kw["radius"] = r.num("radius", default=1.0, lo=1e-6)
        kw["caps"] = r.bool("caps", True)
    elif typ in ("ply", "obj", "gltf"):
        fn = r.str("filename")
        p = (base / fn).resolve()
        if not p.is_file():
            r.fail("filename", f"an existing .{'glb / .gltf' if typ == 'gltf' else typ} file, relative to the scene "
                   f"file (looked for {p})", fn)
        kw["filename"] = str(p)
        if typ == "gltf":
            node = st.get("node")
            if isinstance(node, bool) or not (isinstance(node, str) or (isinstance(node, int) and node >= 0)):
                r.fail("node", "the glTF node of the mesh: its index (an integer >= 0) or its name", node)
            kw["node"] = node
            if r.has("primitive"):
                kw["primitive"] = r.int("primitive", lo=0)
    if r.has("alpha_texture"):
        kw["alpha_texture"] = _alpha_texture(r, base)
        kw["alpha_cutoff"] = r.num("alpha_cutoff", default=0.5, lo=0.0, hi=1.0)
    elif r.has("alpha_cutoff"):
        r.fail("alpha_cutoff", "no alpha_cutoff without alpha_texture (the image whose alpha it tests)",
               st["alpha_cutoff"])
    if r.has("transmittance"):
        tr = r.vec("transmittance")
        if any(not 0.0 <= t <= 1.0 for t in tr):
            r.fail("transmittance", "three numbers in [0, 1] (the RGB fraction of light a translucent caster "
                   "lets through; 0 blocks, 1 lets all through)", list(tr))
        if "alpha_texture" in kw:
            r.fail("transmittance", "a translucent shape of a supported type: an alpha-tested shape "
                   "(alpha_texture) cannot also be translucent; drop one of the two keys", list(tr))
        kw["transmittance"] = tr
        kw["opacity"] = r.num("opacity", default=1.0, lo=0.0, hi=1.0)
    elif r.has("opacity"):
        r.fail("opacity", "no opacity without transmittance (the colour the opaque share filters with)",
               st["opacity"])
    return ShapeSpec(**kw)

def _alpha_texture(r: Reader, base: Path) -> str:
    """Validate ``alpha_texture`` (a readable image with an alpha channel, or greyscale; see
    :mod:`shadowlab.scene.textures`) and return its resolved path."""
    fn = r.str("alpha_texture")
    p = (base / fn).resolve()
    if not p.is_file():
        r.fail("alpha_texture", f"an existing image file, relative to the scene file (looked for {p})", fn)
    try:
        read_alpha(p)
    except AlphaTextureError as e:
        r.fail("alpha_texture", f"an image with an alpha channel or a greyscale mask: {p} {e}", fn)
    return str(p)
