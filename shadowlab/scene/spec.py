"""Scene specifications: a TOML file -> validated plain-Python dataclasses.

The format (documented in README.md, "Scene format"):

```toml
name = "contact"
description = "..."
[camera]      position, target, up, fov (degrees, horizontal), resolution = [W, H],
              near, far (clip planes, m; default CAMERA_NEAR / CAMERA_FAR)
[camera.path] frames, interpolation = "linear" | "catmull-rom", [[camera.path.keys]] (frame,
              position, target, fov, up; missing ones default to [camera]'s) or
              [[camera.path.cameras]] (one camera per frame): see :class:`CameraPath`
[[lights]]    name, kind = rect|disk|sphere|spot|point|directional, colour and power, size ...
[[shapes]]    name, type = rectangle|disk|cube|sphere|cylinder|ply|obj|gltf, albedo, transform,
              alpha_texture = "textures/leaf.png", alpha_cutoff = 0.5 (alpha-tested casters)
[[sdf]]       SDF-only objects without a Mitsuba twin (Mandelbulb, CSG, ...): see shadowlab.scene.sdf_spec
```

A ``.glb`` / ``.gltf`` file loads as a scene too: :mod:`shadowlab.scene.gltf_file` turns it (and its
``NAME.shadowlab.toml`` sidecar) into this document, its meshes ``gltf`` shapes.

Every error names the file, the key and what was expected (exit 2): an unknown key (with the
closest known one), a key of another light kind or shape type (:data:`LIGHT_KEYS`,
:data:`SHAPE_KEYS`), a non-boolean ``two_sided`` / ``caps``, a number out of range, a scene name
that is not one plain directory name of the reference store. No Mitsuba backend here:
the spec is pure data, so it can be hashed, listed and validated without one (an
``alpha_texture`` is opened with ``mitsuba.Bitmap``, which needs no variant, to validate it).
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from ..errors import SceneError
from ._reader import _Reader, rotations
from .gltf_file import GLTF_SUFFIXES, scene_document, sidecar_path
from .sdf_spec import parse_sdf_tables
from .textures import AlphaTextureError, read_alpha

LIGHT_KINDS = ("rect", "disk", "sphere", "spot", "point", "directional")
SHAPE_TYPES = ("rectangle", "disk", "cube", "sphere", "cylinder", "ply", "obj", "gltf")
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


#: most frames of a camera path (each frame may get its own stored reference)
FRAMES_MAX = 100000
INTERPOLATIONS = ("linear", "catmull-rom")


@dataclass(frozen=True)
class CameraKey:
    """One keyframe of a camera path (or one camera of an explicit list): a frame index and the
    camera's position, target, fov and up there (each defaulting to ``[camera]``'s when not given)."""

    frame: int
    position: tuple
    target: tuple
    fov: float
    up: tuple


def _lerp(a, b, t):
    return tuple(x + (y - x) * t for x, y in zip(a, b))


def _catmull_rom(p0, p1, p2, p3, t):
    """Uniform Catmull-Rom between p1 (t = 0) and p2 (t = 1); p0, p3 are the neighbouring keys."""
    t2, t3 = t * t, t * t * t
    return tuple(0.5 * (2 * b + (-a + c) * t + (2 * a - 5 * b + 4 * c - d) * t2 + (-a + 3 * b - 3 * c + d) * t3)
                 for a, b, c, d in zip(p0, p1, p2, p3))


@dataclass(frozen=True)
class CameraPath:
    """A camera path of ``frames`` frames (README, "Scene format", camera paths).

    ``keys`` are keyframes at strictly increasing frame indices from 0 to frames − 1; frame i
    between keys k and k+1 is at t = (i − f_k)/(f_{k+1} − f_k). ``interpolation`` "linear"
    interpolates position, target and up linearly; "catmull-rom" uses the uniform Catmull-Rom
    spline through the keys (the first and last keys mirrored to give the end tangents), which
    passes through every key with a continuous velocity. fov is always interpolated linearly.
    ``explicit``: the path was given as ``[[camera.path.cameras]]``, one key per frame.

    >>> k0 = CameraKey(0, (0.0, 1.0, 5.0), (0.0, 0.0, 0.0), 40.0, (0.0, 1.0, 0.0))
    >>> k1 = CameraKey(4, (4.0, 1.0, 5.0), (0.0, 0.0, 0.0), 60.0, (0.0, 1.0, 0.0))
    >>> path = CameraPath(frames=5, keys=(k0, k1))
    >>> path.key_at(1).position, path.key_at(1).fov
    ((1.0, 1.0, 5.0), 45.0)
    """

    frames: int
    interpolation: str = "linear"
    keys: tuple = ()
    explicit: bool = False

    def key_at(self, i: int) -> CameraKey:
        """The camera of frame ``i`` (0 ≤ i < frames) as a :class:`CameraKey`."""
        ks = self.keys
        for k in ks:
            if k.frame == i:
                return k
        j = max(n for n, k in enumerate(ks) if k.frame < i)
        a, b = ks[j], ks[j + 1]
        t = (i - a.frame) / (b.frame - a.frame)
        fov = a.fov + (b.fov - a.fov) * t
        if self.interpolation == "catmull-rom":
            def pt(attr):
                p1, p2 = getattr(a, attr), getattr(b, attr)
                p0 = getattr(ks[j - 1], attr) if j > 0 else tuple(2 * x - y for x, y in zip(p1, p2))
                p3 = getattr(ks[j + 2], attr) if j + 2 < len(ks) else tuple(2 * y - x for x, y in zip(p1, p2))
                return _catmull_rom(p0, p1, p2, p3, t)
            return CameraKey(i, pt("position"), pt("target"), fov, pt("up"))
        return CameraKey(i, _lerp(a.position, b.position, t), _lerp(a.target, b.target, t), fov, _lerp(a.up, b.up, t))


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


@dataclass(frozen=True)
class SceneSpec:
    name: str
    camera: Camera
    lights: tuple
    shapes: tuple
    description: str = ""
    source: str = ""             # path of the TOML file (not part of the hash)
    sdf: tuple = ()              # [[sdf]] tables (shadowlab.scene.sdf_spec): SDF-only objects, no Mitsuba twin
    path: CameraPath | None = None   # [camera.path]: the camera moves; None: one static camera
    frame: int | None = None         # the frame this spec is at (None without a path); camera is that frame's
    #: how the ground truth spends its shadow rays across lights (reference/truth.py): "per_light",
    #: every light's visibility to the target error; "contribution", in proportion to its share of
    #: each pixel's unshadowed light
    truth_allocation: str = "per_light"

    @property
    def frames(self) -> int:
        """Frames of the camera path (1 for a scene without one)."""
        return 1 if self.path is None else self.path.frames

    def frame_range_text(self) -> str:
        """The valid frame indices, for error messages."""
        if self.path is None:
            return (f"scene {self.name!r} has no camera path ([camera.path]): only frame 0 is valid")
        return f"scene {self.name!r} has a camera path of {self.frames} frames: valid frames are 0..{self.frames - 1}"

    def check_frame(self, i) -> int:
        """``i`` as a frame index of this scene; SceneError (exit 2) naming the valid range otherwise."""
        if isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < self.frames:
            raise SceneError(f"frame {i!r} is out of range: {self.frame_range_text()}")
        return i

    def at_frame(self, i: int) -> "SceneSpec":
        """This scene with the camera of frame ``i`` (the resolution and clip planes are kept).
        A scene without a camera path has only frame 0, which is the scene itself."""
        self.check_frame(i)
        if self.path is None or i == self.frame:
            return self
        k = self.path.key_at(i)
        cam = replace(self.camera, position=k.position, target=k.target, fov=k.fov, up=k.up)
        return replace(self, camera=cam, frame=i)

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
        if d["truth_allocation"] == "per_light":  # absent unless set: scenes hash as before the key existed
            d.pop("truth_allocation")
        if not d["sdf"]:  # absent unless used: scenes without [[sdf]] hash as before the key existed
            d.pop("sdf")
        for l, spec in zip(d["lights"], self.lights):  # absent unless used: lights without a range hash as before
            if l["range"] is None:
                l.pop("range")
            # casts_shadows: hashed only where it changes the truth, i.e. a light's panel that could block another
            # light; a panel that casts is what every scene did before the key existed, so it hashes as then
            if l["casts_shadows"] or not spec.has_panel or len(self.lights) < 2:
                l.pop("casts_shadows")
        if d["path"] is None:  # absent unless used: a scene without a camera path hashes as before paths existed
            d.pop("path")
            d.pop("frame")
        # with a path, the whole path and the frame index are hashed: any change to the path makes
        # every frame's stored reference stale
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
            for k in ("node", "primitive"):  # gltf shapes only: absent otherwise, as before the keys existed
                if s[k] is None:
                    s.pop(k)
            # translucency: likewise absent unless used
            tr, op = s.pop("transmittance"), s.pop("opacity")
            if tr is not None:
                s["transmittance"], s["opacity"] = tr, op
            if s["casts_shadows"]:  # absent unless false: shapes hash as before the key existed
                s.pop("casts_shadows")
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


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


#: largest ``shadow_map`` (texels per side): the light view holds a float64 depth image of
#: res² texels per face while it is made (a 16384² face is 2 GiB; 200000² would be 298 GiB)
SHADOW_MAP_MAX = 16384
#: characters of a scene name: it names the scene's directory in the reference store
SCENE_NAME_RE = r"[A-Za-z0-9_.-]+"
TOP_KEYS = ("name", "description", "camera", "lights", "shapes", "sdf", "truth_allocation")
TRUTH_ALLOCATIONS = ("per_light", "contribution")
CAMERA_KEYS = ("position", "target", "up", "fov", "resolution", "near", "far", "path")
PATH_KEYS = ("frames", "interpolation", "keys", "cameras")
PATH_KEY_KEYS = ("frame", "position", "target", "fov", "up")
PATH_CAMERA_KEYS = ("position", "target", "fov", "up")
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


def _kind_keys(r: _Reader, kind: str, table: dict, keys: dict, label: str):
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


def _scene_name(top: _Reader, data: dict, path: str) -> str:
    """The scene's name: it names the scene's directory in the reference store, so it must be one
    plain path component (no '/', no '..', not empty, not hidden)."""
    explicit = "name" in data
    name = top.str("name", default=Path(path).stem)
    if not re.fullmatch(SCENE_NAME_RE, name) or name.startswith("."):
        why = ("letters, digits, '_', '-' or '.', not starting with '.' (it names the scene's directory in the "
               "reference store)")
        if explicit:
            top.fail("name", why, name)
        top.fail("name", f"{why}; the file name gives {name!r}: add name = \"...\" to the file or rename it", None)
    return name


def _camera(path: str, data: dict, top: _Reader) -> Camera:
    if "camera" not in data or not isinstance(data["camera"], dict):
        top.fail("camera", "a [camera] table with position, target, fov, resolution")
    c = _Reader(path, "camera", data["camera"])
    c.check_keys(CAMERA_KEYS, "[camera]")
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
    _check_view(c, camera.position, camera.target, camera.up, "camera.position")
    return camera


def _check_view(c: _Reader, position, target, up, where: str):
    """A camera (static, a key or a frame of a path) must look somewhere and have a usable up."""
    view = [a - b for a, b in zip(target, position)]
    if _norm(view) == 0:
        c.fail("target", f"a point different from {where}", list(target))
    if _norm(up) == 0:
        c.fail("up", "a non-zero vector (the camera's up direction; the default is [0, 1, 0])", list(up))
    if _norm(_cross(up, view)) <= 1e-6 * _norm(up) * _norm(view):
        c.fail("up", "a vector not parallel to the view direction target − position = "
               f"[{', '.join(f'{x:g}' for x in view)}] (up fixes the camera's roll, which a vector along the view "
               "does not); e.g. [0, 0, 1] when looking straight down", list(up))


def _camera_path(path: str, cam_table: dict, camera: Camera) -> CameraPath | None:
    """``[camera.path]``: keyframes with interpolation, or an explicit list of cameras (README,
    "Scene format"). Keys and cameras take position, target, fov and up, each defaulting to the
    static ``[camera]``'s; every frame's camera is checked like the static one."""
    if "path" not in cam_table:
        return None
    raw = cam_table["path"]
    top = _Reader(path, "camera", cam_table)
    if not isinstance(raw, dict):
        top.fail("path", "a [camera.path] table (frames, interpolation, [[camera.path.keys]] or "
                 "[[camera.path.cameras]])", raw)
    r = _Reader(path, "camera.path", raw)
    r.check_keys(PATH_KEYS, "[camera.path]")
    if ("keys" in raw) == ("cameras" in raw):
        r.fail("keys", "either [[camera.path.keys]] (keyframes: frame, position, target, fov, up) or "
               "[[camera.path.cameras]] (one camera per frame), not " + ("both" if "keys" in raw else "neither"))
    explicit = "cameras" in raw
    items = raw["cameras" if explicit else "keys"]
    label = "cameras" if explicit else "keys"
    if not isinstance(items, list) or not items or not all(isinstance(x, dict) for x in items):
        r.fail(label, f"a non-empty array of [[camera.path.{label}]] tables", items)
    if "frames" in raw or not explicit:
        v = raw.get("frames")
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= FRAMES_MAX:
            r.fail("frames", f"an integer in 1..{FRAMES_MAX} (the number of frames of the camera path; a path of N "
                   "frames has frames 0..N-1)" + (", or leave it out with [[camera.path.cameras]]" if explicit else ""),
                   v)
        frames = v
    else:
        frames = len(items)
    if explicit and frames != len(items):
        r.fail("frames", f"the number of [[camera.path.cameras]] tables ({len(items)}), one camera per frame; or "
               "leave frames out", frames)
    interp = r.str("interpolation", default="linear", choices=INTERPOLATIONS)
    keys = []
    for n, it in enumerate(items):
        k = _Reader(path, f"camera.path.{label}[{n}]", it)
        k.check_keys(PATH_CAMERA_KEYS if explicit else PATH_KEY_KEYS, f"[[camera.path.{label}]]")
        if explicit:
            fr = n
        else:
            fr = k.int("frame")
            prev = keys[-1].frame if keys else None
            if prev is None and fr != 0:
                k.fail("frame", "0 (the first key of a camera path is at frame 0)", fr)
            if prev is not None and fr <= prev:
                k.fail("frame", f"a frame after the previous key's {prev} (keys are strictly increasing)", fr)
            if fr > frames - 1:
                k.fail("frame", f"a frame in 0..{frames - 1} (the path has frames = {frames})", fr)
        keys.append(CameraKey(fr, k.vec("position", default=camera.position), k.vec("target", default=camera.target),
                              k.num("fov", default=camera.fov, lo=1.0, hi=170.0), k.vec("up", default=camera.up)))
        _check_view(k, keys[-1].position, keys[-1].target, keys[-1].up, "its position")
    if keys[-1].frame != frames - 1:
        r.fail("keys", f"a last key at frame {frames - 1} = frames − 1 (the path ends on a key); the last key is at "
               f"frame {keys[-1].frame}", None)
    cp = CameraPath(frames=frames, interpolation=interp, keys=tuple(keys), explicit=explicit)
    if not explicit:
        for i in range(frames):  # interpolated frames (a spline can overshoot): the same checks per frame
            k = cp.key_at(i)
            _check_view(_Reader(path, f"camera.path (frame {i})", {}), k.position, k.target, k.up, "its position")
    return cp


def _light(path: str, i: int, lt, names: set) -> LightSpec:
    if not isinstance(lt, dict):
        raise SceneError(f"{path}: lights[{i}]: expected a table, got {lt!r}")
    r = _Reader(path, f"lights[{i}]", lt)
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
    if r.has("up") and _norm(kw["up"]) == 0:
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


def _shape(path: str, i: int, st, names: set, snames: set, base: Path) -> ShapeSpec:
    if not isinstance(st, dict):
        raise SceneError(f"{path}: shapes[{i}]: expected a table, got {st!r}")
    r = _Reader(path, f"shapes[{i}]", st)
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


def _not_a_scene(path: str, data: dict):
    """A gate file or a preset given where a scene is expected: say what it is and what to run."""
    if "gate" in data and "camera" not in data:
        raise SceneError(f"{path}: this is a gate file ([[gate]] tables), not a scene; run it with "
                         f"`shadowlab gate {path}`, or give a scene (a built-in name or a scene .toml)")
    tables = [k for k, v in data.items() if isinstance(v, dict) and v and k != "meta"
              and all(isinstance(x, (bool, int, float, str)) for x in v.values())]
    if tables and not any(k in data for k in ("camera", "lights", "shapes", "sdf")):
        raise SceneError(f"{path}: this is a preset (parameter values of {', '.join(tables)}), not a scene; apply it "
                         f"with --preset {path} (`shadowlab compare SCENE --preset {path}`) and give a scene (a "
                         "built-in name or a scene .toml)")


def parse(data: dict, path: str = "<scene>") -> SceneSpec:
    """Validate a parsed TOML document and return a SceneSpec (raises SceneError)."""
    _not_a_scene(path, data)
    top = _Reader(path, "", data)
    top.check_keys(TOP_KEYS, "a scene file (top level)")
    name = _scene_name(top, data, path)
    camera = _camera(path, data, top)

    lights_raw = data.get("lights")
    if not isinstance(lights_raw, list) or not lights_raw:
        top.fail("lights", "a non-empty array of [[lights]] tables", lights_raw)
    names = set()
    lights = [_light(path, i, lt, names) for i, lt in enumerate(lights_raw)]

    shapes_raw = data.get("shapes", [] if "sdf" in data else None)
    if not isinstance(shapes_raw, list) or not (shapes_raw or data.get("sdf")):
        top.fail("shapes", "a non-empty array of [[shapes]] tables (or [[sdf]] objects)", shapes_raw)
    snames = set()
    base = Path(path).parent
    shapes = [_shape(path, i, st, names, snames, base) for i, st in enumerate(shapes_raw)]
    sdf = ()
    if "sdf" in data:
        sdf = parse_sdf_tables(data["sdf"], path, snames | names)
        meshy = [s.name for s in shapes if s.type in ("ply", "obj", "gltf") or s.alpha_tested]
        see_through = [s.name for s in shapes if s.translucent]
        if see_through:
            top.fail("sdf", "no [[sdf]] objects in a scene with translucent shapes (the SDF truth traces cones, "
                     f"without transmission): {', '.join(see_through)}", None)
        if meshy:
            top.fail("sdf", "no [[sdf]] objects in a scene with meshes or alpha-tested shapes (they have no "
                     f"signed distance field): {', '.join(meshy)}", None)
        switched = [s.name for s in shapes if not s.casts_shadows] + [l.name for l in lights if l.casts_shadows]
        if switched:
            top.fail("sdf", "no [[sdf]] objects in a scene with casts_shadows switched from its default (the cone "
                     "traced G-buffer and truth use one signed distance field for what is seen and what casts): "
                     f"{', '.join(switched)}", None)
    cam_path = _camera_path(path, data["camera"], camera)
    spec = SceneSpec(name=name, camera=camera, lights=tuple(lights), shapes=tuple(shapes),
                     description=top.str("description", default=""), source=str(path), sdf=sdf, path=cam_path,
                     truth_allocation=top.str("truth_allocation", default="per_light", choices=TRUTH_ALLOCATIONS))
    if cam_path is not None:  # a path scene is at frame 0 until moved (at_frame)
        spec = replace(spec, frame=-1).at_frame(0)
    return spec


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
    if p.suffix.lower() in GLTF_SUFFIXES and p.is_file():
        doc = scene_document(p, light_keys=LIGHT_KEYS)
        try:
            return parse(doc, str(p))
        except SceneError as e:
            side = sidecar_path(p)
            if side.is_file():  # the key may come from the sidecar: say where to look
                raise SceneError(f"{e} (the scene of {p.name} with its sidecar {side}, where the key may be)") from None
            raise
    if p.is_dir():
        inside = sorted(q.name for q in p.glob("*.toml"))[:5]
        raise SceneError(f"{p}: is a directory, not a scene file; give a .toml scene file"
                         + (f" such as {p / inside[0]} (it holds {', '.join(inside)})" if inside else "")
                         + " or the name of a built-in scene (`shadowlab scenes` lists them)")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{p}: not valid TOML ({e}); fix the syntax at the position given") from e
    except OSError as e:
        raise SceneError(f"{p}: cannot read the scene file ({e.strerror or e}); check its permissions") from None
    return parse(data, str(p))


def scene_spec(scene: str, resolution: tuple | None = None, frame: int | None = None) -> SceneSpec:
    """Built-in scene name or TOML path -> its spec, optionally at another resolution (W, H) and at
    frame ``frame`` of its camera path (None: the scene as it is)."""
    spec = load_spec(resolve(scene))
    if resolution:
        spec = spec.with_resolution(*resolution)
    if frame is not None:
        spec = spec.at_frame(frame)
    return spec


def builtin_dir() -> Path:
    """Directory of the built-in scenes and their textures: package data of an installed shadowlab
    (``shadowlab/builtin_scenes`` in a wheel), else ``scenes/`` at the top of the source checkout."""
    package = Path(__file__).resolve().parents[1]
    installed = package / "builtin_scenes"
    return installed if installed.is_dir() else package.parent / "scenes"


def builtin_names() -> list[str]:
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def resolve(scene: str) -> Path:
    """A built-in scene name or a path to a TOML file -> the file's path."""
    p = Path(scene)
    if p.suffix == ".toml" or p.suffix.lower() in GLTF_SUFFIXES or p.exists():
        return p
    cand = builtin_dir() / f"{scene}.toml"
    if cand.exists():
        return cand
    raise SceneError(f"unknown scene {scene!r}: not a file and not a built-in scene; built-in scenes: "
                     f"{', '.join(builtin_names())}")
