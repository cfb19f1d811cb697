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

Three modules: this one reads a file (TOML or glTF), validates its top level and holds the
:class:`SceneSpec`; :mod:`shadowlab.scene.camera_spec` the camera and its path, and
:mod:`shadowlab.scene.elements` the lights and shapes, each with its tables' validation. Their
public names are importable from here as before.
"""

from __future__ import annotations

import hashlib
import json
import re
import sys
from dataclasses import asdict, dataclass, replace
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from ..errors import SceneError
from .reader import Reader
from .camera_spec import (CAMERA_FAR, CAMERA_KEYS, CAMERA_NEAR, FRAMES_MAX, INTERPOLATIONS, PATH_CAMERA_KEYS,
                          PATH_KEY_KEYS, PATH_KEYS, Camera, CameraKey, CameraPath, read_camera, read_camera_path)
from .elements import (DEPTH_BITS, LIGHT_KEYS, LIGHT_KINDS, SHADOW_MAP_MAX, SHAPE_KEYS, SHAPE_TYPES, LightSpec,
                       ShapeSpec, read_light, read_shape)
from .gltf_file import GLTF_SUFFIXES, scene_document, sidecar_path
from .sdf_spec import parse_sdf_tables

__all__ = ["CAMERA_FAR", "CAMERA_KEYS", "CAMERA_NEAR", "DEPTH_BITS", "FRAMES_MAX", "INTERPOLATIONS", "LIGHT_KEYS",
           "LIGHT_KINDS", "PATH_CAMERA_KEYS", "PATH_KEYS", "PATH_KEY_KEYS", "SCENE_NAME_RE", "SHADOW_MAP_MAX",
           "SHAPE_KEYS", "SHAPE_TYPES", "TOP_KEYS", "TRUTH_ALLOCATIONS", "Camera", "CameraKey", "CameraPath",
           "LightSpec", "SceneSpec", "ShapeSpec", "builtin_dir", "builtin_names", "load_spec", "parse", "resolve",
           "scene_spec"]


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


#: characters of a scene name: it names the scene's directory in the reference store
SCENE_NAME_RE = r"[A-Za-z0-9_.-]+"
TOP_KEYS = ("name", "description", "camera", "lights", "shapes", "sdf", "truth_allocation")
TRUTH_ALLOCATIONS = ("per_light", "contribution")


def _scene_name(top: Reader, data: dict, path: str) -> str:
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
    top = Reader(path, "", data)
    top.check_keys(TOP_KEYS, "a scene file (top level)")
    name = _scene_name(top, data, path)
    camera = read_camera(path, data, top)

    lights_raw = data.get("lights")
    if not isinstance(lights_raw, list) or not lights_raw:
        top.fail("lights", "a non-empty array of [[lights]] tables", lights_raw)
    names = set()
    lights = [read_light(path, i, lt, names) for i, lt in enumerate(lights_raw)]

    shapes_raw = data.get("shapes", [] if "sdf" in data else None)
    if not isinstance(shapes_raw, list) or not (shapes_raw or data.get("sdf")):
        top.fail("shapes", "a non-empty array of [[shapes]] tables (or [[sdf]] objects)", shapes_raw)
    snames = set()
    base = Path(path).parent
    shapes = [read_shape(path, i, st, names, snames, base) for i, st in enumerate(shapes_raw)]
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
    cam_path = read_camera_path(path, data["camera"], camera)
    spec = SceneSpec(name=name, camera=camera, lights=tuple(lights), shapes=tuple(shapes),
                     description=top.str("description", default=""), source=str(path), sdf=sdf, path=cam_path,
                     truth_allocation=top.str("truth_allocation", default="per_light", choices=TRUTH_ALLOCATIONS))
    if cam_path is not None:  # a path scene is at frame 0 until moved (at_frame)
        spec = replace(spec, frame=-1).at_frame(0)
    return spec

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
