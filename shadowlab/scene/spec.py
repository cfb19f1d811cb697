"""Scene specifications: a TOML file -> validated plain-Python dataclasses.

The format (documented in README.md, "Scene format"):

```toml
name = "contact"
description = "..."
[camera]      position, target, up, fov (degrees, horizontal), resolution = [W, H],
              near, far (clip planes, m; default CAMERA_NEAR / CAMERA_FAR)
[[lights]]    name, kind = rect|disk|sphere|spot|point|directional, colour and power, size ...
[[shapes]]    name, type = rectangle|disk|cube|sphere|cylinder|ply|obj, albedo, transform,
              alpha_texture = "textures/leaf.png", alpha_cutoff = 0.5 (alpha-tested casters)
[[sdf]]       SDF-only objects without a Mitsuba twin (Mandelbulb, CSG, ...): see shadowlab.scene.sdf_spec
```

Every error names the file, the key and what was expected (exit 2). No Mitsuba backend here:
the spec is pure data, so it can be hashed, listed and validated without one (an
``alpha_texture`` is opened with ``mitsuba.Bitmap``, which needs no variant, to validate it).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from ..errors import SceneError
from ._reader import _Reader, rotations
from .sdf_spec import parse_sdf_tables
from .textures import AlphaTextureError, read_alpha

LIGHT_KINDS = ("rect", "disk", "sphere", "spot", "point", "directional")
SHAPE_TYPES = ("rectangle", "disk", "cube", "sphere", "cylinder", "ply", "obj")
DEPTH_BITS = (16, 24, 32)
#: default camera clip planes (m): the ground truth's Mitsuba sensor has always used these, so a
#: scene without ``camera.near`` / ``camera.far`` renders, exports and hashes as before they existed
CAMERA_NEAR = 1e-3
CAMERA_FAR = 1e5


@dataclass(frozen=True)
class Camera:
    position: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 40.0
    resolution: tuple = (128, 128)
    near: float | None = None    # clip planes (m); None = CAMERA_NEAR / CAMERA_FAR
    far: float | None = None

    @property
    def near_clip(self) -> float:
        return CAMERA_NEAR if self.near is None else float(self.near)

    @property
    def far_clip(self) -> float:
        return CAMERA_FAR if self.far is None else float(self.far)


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
    filename: str | None = None  # ply / obj, resolved relative to the scene file
    two_sided: bool = True
    alpha_texture: str | None = None  # alpha-tested caster: image file, resolved relative to the scene file
    alpha_cutoff: float = 0.5         # texels with alpha < cutoff are transparent (discarded)

    @property
    def alpha_tested(self) -> bool:
        return self.alpha_texture is not None


@dataclass(frozen=True)
class SceneSpec:
    name: str
    camera: Camera
    lights: tuple
    shapes: tuple
    description: str = ""
    source: str = ""             # path of the TOML file (not part of the hash)
    sdf: tuple = ()              # [[sdf]] tables (shadowlab.scene.sdf_spec): SDF-only objects, no Mitsuba twin

    @property
    def kind(self) -> str:
        """``"sdf"`` when the scene has SDF-only objects (``[[sdf]]``, which Mitsuba does not see:
        its G-buffer is cone traced and its truth is the Monte-Carlo cone reference), else
        ``"mitsuba"`` (Mitsuba's G-buffer and ground truth)."""
        return "sdf" if self.sdf else "mitsuba"

    def digest(self) -> str:
        """SHA-256 of the scene's content (not its path); a reference stores it."""
        d = asdict(self)
        d.pop("source")
        for k in ("near", "far"):  # absent unless set: scenes without them hash as before the keys existed
            if d["camera"][k] is None:
                d["camera"].pop(k)
        if not d["sdf"]:  # absent unless used: scenes without [[sdf]] hash as before the key existed
            d.pop("sdf")
        for s in d["shapes"]:
            if s["filename"]:
                p = Path(s["filename"])
                s["file_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest() if p.exists() else None
            # alpha testing: absent from the hashed dict unless used, so that the hash of a scene
            # without alpha textures is what it was before the keys existed (stored references
            # keep matching); when used, the texture's content is hashed, not its path
            tex = s.pop("alpha_texture")
            cutoff = s.pop("alpha_cutoff")
            if tex is not None:
                p = Path(tex)
                s["alpha_texture_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest() if p.exists() else None
                s["alpha_cutoff"] = cutoff
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()

    def light(self, name: str) -> LightSpec:
        for l in self.lights:
            if l.name == name:
                return l
        raise SceneError(f"scene {self.name!r} has no light {name!r}; its lights are "
                         f"{', '.join(l.name for l in self.lights)}")

    def with_resolution(self, w: int, h: int) -> "SceneSpec":
        return replace(self, camera=replace(self.camera, resolution=(int(w), int(h))))


def _norm(v):
    return math.sqrt(sum(x * x for x in v))


def parse(data: dict, path: str = "<scene>") -> SceneSpec:
    """Validate a parsed TOML document and return a SceneSpec (raises SceneError)."""
    top = _Reader(path, "", data)
    known_top = {"name", "description", "camera", "lights", "shapes", "sdf"}
    for k in data:
        if k not in known_top:
            top.fail(k, f"no such key (allowed: {', '.join(sorted(known_top))})", None)
    name = top.str("name", default=Path(path).stem)
    if "camera" not in data or not isinstance(data["camera"], dict):
        top.fail("camera", "a [camera] table with position, target, fov, resolution")
    c = _Reader(path, "camera", data["camera"])
    res = c.t.get("resolution", [128, 128])
    if (not isinstance(res, list) or len(res) != 2 or
            any(isinstance(x, bool) or not isinstance(x, int) or x < 1 or x > 8192 for x in res)):
        c.fail("resolution", "[width, height] with integers in 1..8192", res)
    clip = {}
    for k in ("near", "far"):
        if c.has(k):
            clip[k] = c.num(k)
            if clip[k] <= 0:
                c.fail(k, "a positive distance in metres (a clip plane in front of the camera)", clip[k])
    near, far = clip.get("near", CAMERA_NEAR), clip.get("far", CAMERA_FAR)
    if clip and near >= far:
        c.fail("far" if "far" in clip else "near",
               f"camera.near < camera.far (near {near:g}, far {far:g}; the defaults are near = {CAMERA_NEAR:g}, "
               f"far = {CAMERA_FAR:g})", clip.get("far", clip.get("near")))
    camera = Camera(position=c.vec("position"), target=c.vec("target"), up=c.vec("up", default=(0, 1, 0)),
                    fov=c.num("fov", default=40.0, lo=1.0, hi=170.0), resolution=tuple(res), **clip)
    if _norm([a - b for a, b in zip(camera.position, camera.target)]) == 0:
        c.fail("target", "a point different from camera.position", list(camera.target))

    lights_raw = data.get("lights")
    if not isinstance(lights_raw, list) or not lights_raw:
        top.fail("lights", "a non-empty array of [[lights]] tables", lights_raw)
    lights, names = [], set()
    for i, lt in enumerate(lights_raw):
        if not isinstance(lt, dict):
            top.fail(f"lights[{i}]", "a table", lt)
        r = _Reader(path, f"lights[{i}]", lt)
        kind = r.str("kind", choices=LIGHT_KINDS)
        lname = r.str("name", default=f"L{i}")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", lname):
            r.fail("name", "a name of letters, digits, '_' or '-' starting with a letter", lname)
        if lname in names:
            r.fail("name", "a name not used by another light", lname)
        names.add(lname)
        kw = dict(name=lname, kind=kind, color=r.vec("color", default=(1, 1, 1)),
                  shadow_map=r.int("shadow_map", default=512, lo=8),
                  depth_bits=r.int("depth_bits", default=32, choices=DEPTH_BITS),
                  up=r.vec("up", default=(0, 1, 0)))
        if any(x < 0 for x in kw["color"]):
            r.fail("color", "non-negative numbers", list(kw["color"]))
        for k in ("power", "radiance", "irradiance", "intensity"):
            if r.has(k):
                kw[k] = r.num(k, lo=0.0)
        if not any(k in kw for k in ("power", "radiance", "irradiance", "intensity")):
            r.fail("power", "a number (the light's power in watts; or radiance / irradiance / intensity)")
        if r.has("near"):
            kw["near"] = r.num("near", lo=1e-6)
        if kind == "directional":
            kw["direction"] = r.vec("direction")
            if _norm(kw["direction"]) == 0:
                r.fail("direction", "a non-zero vector", list(kw["direction"]))
            kw["angular_diameter"] = r.num("angular_diameter", default=0.0, lo=0.0, hi=30.0)
        else:
            kw["position"] = r.vec("position")
            if kind in ("rect", "disk", "spot"):
                kw["target"] = r.vec("target")
                if _norm([a - b for a, b in zip(kw["position"], kw["target"])]) == 0:
                    r.fail("target", "a point different from the light's position", list(kw["target"]))
            if kind == "rect":
                kw["size"] = r.vec("size", n=2, positive=True)
            elif kind in ("disk", "sphere"):
                kw["radius"] = r.num("radius", lo=1e-6)
            else:
                kw["radius"] = r.num("radius", default=0.0, lo=0.0)
            if kind == "spot":
                kw["angle"] = r.num("angle", default=30.0, lo=1.0, hi=80.0)
        lights.append(LightSpec(**kw))

    shapes_raw = data.get("shapes", [] if "sdf" in data else None)
    if not isinstance(shapes_raw, list) or not (shapes_raw or data.get("sdf")):
        top.fail("shapes", "a non-empty array of [[shapes]] tables (or [[sdf]] objects)", shapes_raw)
    shapes, snames = [], set()
    base = Path(path).parent
    for i, st in enumerate(shapes_raw):
        if not isinstance(st, dict):
            top.fail(f"shapes[{i}]", "a table", st)
        r = _Reader(path, f"shapes[{i}]", st)
        typ = r.str("type", choices=SHAPE_TYPES)
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
                  two_sided=bool(st.get("two_sided", True)))
        if typ == "sphere":
            kw["center"] = r.vec("center", default=(0, 0, 0))
            kw["radius"] = r.num("radius", default=1.0, lo=1e-6)
        elif typ == "cylinder":
            kw["p0"], kw["p1"] = r.vec("p0", default=(0, 0, 0)), r.vec("p1", default=(0, 1, 0))
            kw["radius"] = r.num("radius", default=1.0, lo=1e-6)
            kw["caps"] = bool(st.get("caps", True))
        elif typ in ("ply", "obj"):
            fn = r.str("filename")
            p = (base / fn).resolve()
            if not p.exists():
                r.fail("filename", f"an existing .{typ} file (looked for {p})", fn)
            kw["filename"] = str(p)
        if r.has("alpha_texture"):
            kw["alpha_texture"] = _alpha_texture(r, base)
            kw["alpha_cutoff"] = r.num("alpha_cutoff", default=0.5, lo=0.0, hi=1.0)
        elif r.has("alpha_cutoff"):
            r.fail("alpha_cutoff", "no alpha_cutoff without alpha_texture (the image whose alpha it tests)",
                   st["alpha_cutoff"])
        allowed = {"name", "type", "albedo", "translate", "rotate", "scale", "two_sided", "center", "radius",
                   "p0", "p1", "caps", "filename", "alpha_texture", "alpha_cutoff"}
        for k in st:
            if k not in allowed:
                r.fail(k, f"no such key (allowed: {', '.join(sorted(allowed))})", None)
        shapes.append(ShapeSpec(**kw))
    sdf = ()
    if "sdf" in data:
        sdf = parse_sdf_tables(data["sdf"], path, snames | names)
        meshy = [s.name for s in shapes if s.type in ("ply", "obj") or s.alpha_tested]
        if meshy:
            top.fail("sdf", "no [[sdf]] objects in a scene with meshes or alpha-tested shapes (they have no "
                     f"signed distance field): {', '.join(meshy)}", None)
    return SceneSpec(name=name, camera=camera, lights=tuple(lights), shapes=tuple(shapes),
                     description=top.str("description", default=""), source=str(path), sdf=sdf)


def _alpha_texture(r: _Reader, base: Path) -> str:
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


def load_spec(path) -> SceneSpec:
    """Read and validate a TOML scene file."""
    p = Path(path)
    if not p.exists():
        raise SceneError(f"{p}: scene file not found; give a path to a .toml scene or the name of a "
                         "built-in scene (`shadowlab scenes` lists them)")
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{p}: not valid TOML ({e}); fix the syntax at the position given") from e
    return parse(data, str(p))


def builtin_dir() -> Path:
    """Directory of the built-in scenes (``scenes/`` at the repository top level)."""
    return Path(__file__).resolve().parents[2] / "scenes"


def builtin_names() -> list[str]:
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def resolve(scene: str) -> Path:
    """A built-in scene name or a path to a TOML file -> the file's path."""
    p = Path(scene)
    if p.suffix == ".toml" or p.exists():
        return p
    cand = builtin_dir() / f"{scene}.toml"
    if cand.exists():
        return cand
    raise SceneError(f"unknown scene {scene!r}: not a file and not a built-in scene; built-in scenes: "
                     f"{', '.join(builtin_names())}")
