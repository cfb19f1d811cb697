"""glTF 2.0 both ways: a loaded scene -> one ``.glb`` real-time engines load, and the glTF checks.

Written with pygltflib after [Khronos 2017] (the glTF 2.0 specification and its ``KHR_lights_punctual``
extension for lights); checked with the Khronos glTF validator (:func:`validate_glb`). The file
reads back as a scene through :mod:`shadowlab.scene.gltf_file` (``scene.load("x.glb")``), so an
exported ``.glb`` round-trips (docs/exchange.md, "glTF").

What :func:`write_glb` writes (world space, metres, +y up as the scene has it):

* **meshes**: one node and one mesh per shape of the scene (a capped cylinder is one mesh of its
  three parts), in world coordinates (identity node transforms), the triangulation of
  :func:`shadowlab.scene.mesh.triangulate` (curved primitives inscribed with ``segments``
  segments): ``POSITION``, unit ``NORMAL`` (smooth on curved primitives), ``TEXCOORD_0`` on
  alpha-tested shapes (Mitsuba's uv; glTF's v = 0 is the image's first row, as Mitsuba's);
* **materials**, one per shape: ``baseColorFactor`` = the albedo (linear RGB, alpha 1),
  metallic 0, roughness 1 (Lambertian as the truth's diffuse BSDF), ``doubleSided`` = the shape's
  ``two_sided``; an alpha-tested shape gets ``alphaMode: "MASK"``, its ``alphaCutoff`` and a
  ``baseColorTexture``: an embedded RGBA PNG, white, whose alpha is the shape's binary opacity
  (already thresholded at the cut-off: 0 or 255; sampled nearest, clamped, no mipmaps), so any
  cut-off in (0, 1] keeps exactly the texels the truth keeps;
* **the camera**: a perspective camera whose node looks along its −z with +y up and +x to the
  image's right (glTF's camera) -- Mitsuba's camera looks along +z with +x to the image's left, so
  the node's matrix is the truth sensor's ``to_world`` times diag(−1, 1, −1, 1). ``yfov`` is the
  full vertical field of view: tan(yfov/2) = tan(fov/2)·H/W (the scene's ``fov`` spans the
  width, Mitsuba's ``fov_axis = "x"``), ``aspectRatio`` = W/H, ``znear`` / ``zfar`` the clip
  planes; the node's extras hold the exact matrices and the pixel-centre convention;
* **lights** through ``KHR_lights_punctual``; a light node emits along its −z:

  | scene light | glTF light | intensity |
  |---|---|---|
  | directional (sun) | directional | lux = the irradiance E (W/m²) |
  | point, radius 0 | point | candela = I (W/sr) |
  | spot, radius 0 | spot, outer cone = ``angle``, inner = 0.999·angle (the truth's hard cone) | candela = I |
  | point / sphere with a radius r | point at the centre | candela = L·πr² (the sphere's intensity, Φ/4π) |
  | rect w×h, disk r | spot at the centre facing the emitting side, cones 0 and 90° | candela = L·A on the axis (A = wh or πr²) |
  | spot with a radius r | spot with the light's cone | candela = L·πr² |

  Photometric units are the scene's radiometric ones with a luminous efficacy of 1 (1 cd ≙
  1 W/sr, 1 lux ≙ 1 W/m²): an engine that shades ``albedo/π · intensity · cos/d²`` (three.js,
  Babylon.js with physical light units) then lights a point as the truth's emitter does. glTF's
  light ``color`` is in [0, 1]: a colour above 1 is divided by its largest channel and the
  intensity multiplied by it. ``range`` (point and spot) is the scene's ``range``: glTF's
  recommended window, the truth's windowed falloff.

What glTF cannot say goes into ``extras`` (key ``shadowlab``), so nothing is lost:

* the file (top level): the manifest of :func:`write_glb` (``lights``, ``camera_node``,
  ``resolution``) and ``shadowlab``: scene name, hash, description, truth settings, tessellation;
* each light node: ``light``, the light's table of the scene format (kind, pose, size, power,
  shadow map: what the import reads back exactly); ``emission`` (the quantity and value of the
  truth's emitter); ``emitter``, the area light's emitting shape (``rectangle`` / ``disk`` /
  ``sphere`` and its ``to_world``: it is **not** a drawable mesh, engines must not draw it); the
  sun's angular diameter, the spot's cone;
* the camera node: the camera table of the scene format and the exact matrices;
* each mesh node: the shape's name and type, and ``casts_shadows`` (false: drawn, casts no shadow);
* each material: the albedo, alpha cut-off and, for translucent casters, ``transmittance``,
  ``opacity`` and the per-crossing ``tau`` (glTF has no shadow-only transmission).
"""  # noqa: E501

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
from dataclasses import asdict
from importlib import metadata
from pathlib import Path

import numpy as np
import pygltflib as gl

from ..errors import INTERNAL_ERROR, EnvironmentProblem, InputError, SceneError, ShadowlabError
from ..io.png import encode_png, write_bytes_atomic
from . import lights as lights_mod
from .build import sensor_dict
from .mesh import matrix_of, sagitta, shape_mesh
from .gltf_file import GLTF_SUFFIXES
from .spec import LIGHT_KEYS, load_spec
from .textures import opacity_mask, read_alpha

__all__ = ["write_glb", "read_gltf", "build_gltf", "validate_glb", "InvalidExport", "report_lines", "gltf_matrices",
           "khr_light", "light_table", "camera_table", "FORMAT", "FORMAT_VERSION", "EXTRAS_KEY"]

FORMAT, FORMAT_VERSION = "shadowlab-gltf", 1
#: the key of shadowlab's own data in every ``extras`` object
EXTRAS_KEY = "shadowlab"
#: Mitsuba camera space -> glTF camera space (x to the image's right, looking along −z)
MI_TO_GLTF = np.diag([-1.0, 1.0, -1.0, 1.0])
_F32, _U32 = 5126, 5125
_NEAREST, _CLAMP = 9728, 33071
_ARRAY, _ELEMENTS = 34962, 34963
#: the validator's npm package, installed by ``make engines`` (package.json pins it)
VALIDATOR_PACKAGE = "gltf-validator"

CONVENTIONS = {
    "units": "metres; world right-handed (the built-in scenes have +y up)",
    "matrices": "extras matrices are row-major 4x4, points are column vectors: p' = M @ [x, y, z, 1] (glTF's own "
                "node.matrix is column-major, as the format says)",
    "camera": "glTF camera: looks along node -z, +y up, +x = image right; yfov = full vertical field of view, "
              "tan(yfov/2) = tan(fov_x/2) H / W; pixel (i, j) (column i from the left, row j from the top) has its "
              "centre at ndc = (2(i + 0.5)/W - 1, 1 - 2(j + 0.5)/H): the ground truth is evaluated there",
    "lights": "KHR_lights_punctual, emitting along node -z; 1 cd = 1 W/sr, 1 lux = 1 W/m^2 (luminous efficacy 1); "
              "extras.shadowlab.light is the scene-format table the import reads back",
    "materials": "baseColorFactor = Lambertian albedo (linear), metallic 0, roughness 1; alpha-tested shapes: MASK "
                 "with a binary opacity texture (nearest, clamped; alpha 0 = the surface is not there)",
}


class InvalidExport(ShadowlabError):
    """shadowlab's own glb fails the Khronos validator: a shadowlab bug (exit 4)."""

    exit_code = INTERNAL_ERROR


# -- small pieces -----------------------------------------------------------------------------


def _rows(M) -> list:
    return [[float(x) for x in row] for row in np.asarray(M, np.float64).reshape(4, 4)]


def _column_major(M) -> list:
    return [float(x) for x in np.asarray(M, np.float64).reshape(4, 4).T.reshape(-1)]


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _frame(origin, forward, up) -> np.ndarray:
    """Rigid node matrix whose −z is ``forward`` and whose +y is ``up`` made orthogonal to it (glTF's
    camera and light orientation)."""
    z = -_unit(forward)
    x = np.cross(_unit(lights_mod.up_for(tuple(forward), tuple(up))), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = x, y, z, np.asarray(origin, np.float64)
    return M


def _table(obj, keys) -> dict:
    """The scene-format table of a spec dataclass: its ``keys`` that are set (None left out), lists
    for tuples; parsing the table gives the same object back."""
    d = asdict(obj)
    out = {}
    for k in keys:
        v = d.get(k)
        if v is None:
            continue
        out[k] = [list(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, (tuple, list)) else v
    return out


def light_table(light) -> dict:
    """A LightSpec as its ``[[lights]]`` table (the keys of its kind that are set)."""
    return _table(light, LIGHT_KEYS[light.kind])


def camera_table(cam) -> dict:
    """A scene ``Camera`` as its ``[camera]`` table (a camera path is not written: one frame)."""
    return _table(cam, ("position", "target", "up", "fov", "resolution", "near", "far"))


def gltf_matrices(cam) -> dict:
    """The glTF camera of a scene ``Camera`` (spec): node matrix (camera → world, glTF axes), view
    (world → glTF camera), the glTF perspective projection and its parameters.

    The node matrix is the truth sensor's own ``to_world`` (``build.sensor_dict``: Mitsuba's
    ``look_at``) times diag(−1, 1, −1, 1).

    >>> from shadowlab.scene.spec import Camera
    >>> m = gltf_matrices(Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), fov=90.0, resolution=(4, 2)))
    >>> round(math.degrees(m["yfov"]), 4), m["aspectRatio"]      # tan(yfov/2) = tan(45°)·2/4
    (53.1301, 2.0)
    >>> np.round(m["node"][:3, 2], 6).tolist()      # the node's +z points back, away from the target
    [0.0, 0.0, 1.0]
    """
    W, H = cam.resolution
    tan_x = math.tan(math.radians(cam.fov) / 2)
    tan_y = tan_x * H / W
    n, f = cam.near_clip, cam.far_clip
    node = matrix_of(sensor_dict(cam)["to_world"]) @ MI_TO_GLTF
    proj = np.array([[1 / tan_x, 0, 0, 0], [0, 1 / tan_y, 0, 0],
                     [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)], [0, 0, -1, 0]], np.float64)
    view = np.linalg.inv(node)
    return {"node": node, "view": view, "projection": proj, "yfov": 2 * math.atan(tan_y), "aspectRatio": W / H,
            "znear": n, "zfar": f, "tan_x": tan_x, "tan_y": tan_y}


def _emitter_area(light) -> float:
    """Projected area the on-axis intensity of an area light is radiance times."""
    if light.kind == "rect":
        return light.size[0] * light.size[1]
    return math.pi * light.radius ** 2  # disk, spot, and the cross-section of a sphere / point


def khr_light(light) -> tuple[dict, dict]:
    """(KHR_lights_punctual light, what of it glTF cannot say) of one LightSpec (the module's table)."""
    qty, value = lights_mod.emission(light)
    k = light.kind
    extra = {"emission": {"quantity": qty, "value": float(value)}}
    if k == "directional":
        typ = "directional"
        half = math.radians(light.angular_diameter) / 2
        intensity = value if qty == "irradiance" else value * math.pi * math.sin(half) ** 2
        extra["angular_diameter_deg"] = float(light.angular_diameter)
    elif light.is_delta:
        typ, intensity = ("spot" if k == "spot" else "point"), value
    else:
        typ = "point" if k in ("sphere", "point") else "spot"
        intensity = value * _emitter_area(light)
    out = {"name": light.name, "type": typ}
    color = [float(c) for c in light.color]
    peak = max(color)
    if peak > 1.0:
        color = [c / peak for c in color]
        intensity *= peak
    out["color"] = color
    out["intensity"] = float(intensity)
    if typ == "spot":
        if k == "spot":
            outer = math.radians(light.angle)
            inner = outer * 0.999 if light.is_delta else 0.0
            extra["cone_half_angle_deg"] = float(light.angle)
        else:  # a rect or disk area light: its hemisphere
            outer, inner = math.pi / 2, 0.0
        out["spot"] = {"innerConeAngle": inner, "outerConeAngle": outer}
    if light.range is not None and typ != "directional":
        out["range"] = float(light.range)
    return out, extra


def _light_node(light, mitsuba_dict: dict, scene) -> tuple[np.ndarray, dict]:
    """(node matrix, emitter extras): the node sits at the light's centre with −z along the
    direction it emits toward; an area light's emitting shape is described, not drawn."""
    fwd = lights_mod.forward(light)
    if light.kind == "directional":
        origin = np.asarray(scene.center, np.float64)
    else:
        origin = np.asarray(light.position, np.float64)
    M = _frame(origin, fwd, light.up)
    emitter = None
    if "emitter" in mitsuba_dict:
        d = mitsuba_dict
        if "to_world" in d:
            to_world = matrix_of(d["to_world"])
        else:  # sphere: centre + radius
            r = float(d["radius"])
            to_world = np.diag([r, r, r, 1.0])
            to_world[:3, 3] = d["center"]
        emitter = {"shape": d["type"], "to_world": _rows(to_world),
                   "canonical": {"rectangle": "[-1, 1]^2 in z = 0, emitting along +z",
                                 "disk": "radius 1 in z = 0, emitting along +z",
                                 "sphere": "radius 1 at the origin, emitting outward"}[d["type"]],
                   "drawable": False}
    return M, emitter


class _Blob:
    """The glb's binary chunk: bufferViews appended at 4-byte offsets."""

    def __init__(self, g: gl.GLTF2):
        self.g, self.data = g, bytearray()

    def view(self, raw: bytes, target=None) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        self.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.data), byteLength=len(raw),
                                                target=target))
        self.data.extend(raw)
        return len(self.g.bufferViews) - 1

    def accessor(self, a: np.ndarray, typ: str, *, indices: bool = False, bounds: bool = False) -> int:
        a = np.ascontiguousarray(a, np.uint32 if indices else np.float32)
        v = self.view(a.tobytes(), _ELEMENTS if indices else _ARRAY)
        acc = gl.Accessor(bufferView=v, componentType=_U32 if indices else _F32, count=int(a.size if indices
                                                                                            else len(a)), type=typ)
        if indices:
            acc.min, acc.max = [int(a.min())], [int(a.max())]
        elif bounds:
            acc.min, acc.max = [float(x) for x in a.min(0)], [float(x) for x in a.max(0)]
        self.g.accessors.append(acc)
        return len(self.g.accessors) - 1


def _opacity_png(shape) -> bytes:
    """RGBA PNG, white, alpha = the shape's binary opacity (255 where alpha ≥ cut-off)."""
    try:
        m = opacity_mask(read_alpha(shape.alpha_texture), shape.alpha_cutoff)
    except ValueError as e:
        raise SceneError(f"shape {shape.name!r}: alpha_texture {shape.alpha_texture} {e}") from e
    a = (np.asarray(m, np.float64).reshape(m.shape[0], m.shape[1]) > 0.5).astype(np.uint8) * 255
    rgba = np.full(a.shape + (4,), 255, np.uint8)
    rgba[..., 3] = a
    return encode_png(rgba)


def _material(g, blob, s, textures: dict) -> int:
    pbr = gl.PbrMetallicRoughness(baseColorFactor=[float(x) for x in s.albedo] + [1.0], metallicFactor=0.0,
                                  roughnessFactor=1.0)
    extra = {"albedo": [float(x) for x in s.albedo], "two_sided": bool(s.two_sided)}
    mat = gl.Material(name=s.name, pbrMetallicRoughness=pbr, doubleSided=bool(s.two_sided))
    if s.alpha_tested:
        png = _opacity_png(s)
        if png not in textures:
            if not g.samplers:
                g.samplers.append(gl.Sampler(magFilter=_NEAREST, minFilter=_NEAREST, wrapS=_CLAMP, wrapT=_CLAMP))
            g.images.append(gl.Image(bufferView=blob.view(png), mimeType="image/png", name=f"{s.name}_opacity"))
            g.textures.append(gl.Texture(sampler=0, source=len(g.images) - 1))
            textures[png] = len(g.textures) - 1
        pbr.baseColorTexture = gl.TextureInfo(index=textures[png])
        mat.alphaMode, mat.alphaCutoff = "MASK", float(s.alpha_cutoff)
        extra["alpha_cutoff"] = float(s.alpha_cutoff)
        extra["alpha_texture"] = ("binary opacity of " + Path(s.alpha_texture).name + " thresholded at the cut-off "
                                  "(alpha 255 = opaque, 0 = not there); nearest texel at TEXCOORD_0, clamped")
    if s.translucent:
        extra["transmittance"] = [float(x) for x in s.transmittance]
        extra["opacity"] = float(s.opacity)
        extra["tau"] = [float(x) for x in s.tau]
        extra["translucent"] = ("a translucent shadow caster: drawn opaque, shadow rays are multiplied by tau at "
                                "each crossing (straight-line transmission)")
    mat.extras = {EXTRAS_KEY: extra}
    g.materials.append(mat)
    return len(g.materials) - 1


def _version() -> str:
    try:
        return metadata.version("shadowlab")
    except metadata.PackageNotFoundError:  # a source tree that was never installed
        return "source"


# -- the writer -------------------------------------------------------------------------------


def build_gltf(scene, *, resolution=None, segments: int = 64) -> tuple[gl.GLTF2, dict]:
    """(pygltflib document with its binary blob set, manifest) of a loaded Scene (:func:`write_glb`)."""
    spec = scene.spec
    if resolution:
        spec = spec.with_resolution(*resolution)
    if spec.sdf:
        raise InputError(f"scene {spec.name!r} has [[sdf]] objects, which have no triangle mesh to write to glTF; "
                         "export a scene made of [[shapes]] only")
    if not isinstance(segments, int) or isinstance(segments, bool) or not 3 <= segments <= 4096:
        raise InputError(f"--segments {segments!r}: expected an integer in 3..4096 (tessellation of curved shapes)")
    g = gl.GLTF2(asset=gl.Asset(version="2.0", generator=f"shadowlab {_version()} (pygltflib {gl.__version__})"))
    blob = _Blob(g)
    roots, textures = [], {}
    for s in spec.shapes:
        P, N, UV, F = shape_mesh(s, segments)
        attrs = gl.Attributes(POSITION=blob.accessor(P, "VEC3", bounds=True), NORMAL=blob.accessor(N, "VEC3"))
        if s.alpha_tested:
            attrs.TEXCOORD_0 = blob.accessor(UV, "VEC2")
        prim = gl.Primitive(attributes=attrs, indices=blob.accessor(F.reshape(-1), "SCALAR", indices=True),
                            material=_material(g, blob, s, textures), mode=4)
        g.meshes.append(gl.Mesh(name=s.name, primitives=[prim]))
        g.nodes.append(gl.Node(name=s.name, mesh=len(g.meshes) - 1,
                               extras={EXTRAS_KEY: {"shape": s.name, "type": s.type, "triangles": int(len(F)),
                                                    "vertices": int(len(P)),
                                                    "casts_shadows": bool(getattr(s, "casts_shadows", True))}}))
        roots.append(len(g.nodes) - 1)

    cam = spec.camera
    m = gltf_matrices(cam)
    W, H = cam.resolution
    g.cameras.append(gl.Camera(name="camera", type="perspective", perspective=gl.Perspective(
        yfov=float(m["yfov"]), aspectRatio=float(m["aspectRatio"]), znear=float(m["znear"]), zfar=float(m["zfar"]))))
    cam_extra = {"camera": camera_table(cam), "fov_axis": "x", "fov_x_deg": float(cam.fov),
                 "fov_y_deg": math.degrees(m["yfov"]), "resolution": [int(W), int(H)],
                 "camera_to_world": _rows(m["node"]), "world_to_view": _rows(m["view"]),
                 "view_to_clip": _rows(m["projection"]), "world_to_clip": _rows(m["projection"] @ m["view"]),
                 "pixels": CONVENTIONS["camera"]}
    g.nodes.append(gl.Node(name="camera", camera=0, matrix=_column_major(m["node"]), extras={EXTRAS_KEY: cam_extra}))
    camera_node = len(g.nodes) - 1
    roots.append(camera_node)

    khr, manifest_lights = [], []
    for l in spec.lights:
        light, extra = khr_light(l)
        _, md = lights_mod.mitsuba_dict(l, scene.center, scene.radius)
        M, emitter = _light_node(l, md, scene)
        extra = {"light": light_table(l), **extra, "physical_size": float(l.physical_size)}
        if emitter is not None:
            extra["emitter"] = emitter
        khr.append(light)
        g.nodes.append(gl.Node(name=l.name, matrix=_column_major(M),
                               extensions={"KHR_lights_punctual": {"light": len(khr) - 1}},
                               extras={EXTRAS_KEY: extra}))
        manifest_lights.append({"name": l.name, "node": len(g.nodes) - 1, "kind": l.kind, "type": light["type"],
                                "light": len(khr) - 1})
        roots.append(len(g.nodes) - 1)
    if khr:
        g.extensionsUsed = ["KHR_lights_punctual"]
        g.extensions = {"KHR_lights_punctual": {"lights": khr}}
    g.scenes.append(gl.Scene(name=spec.name, nodes=roots))
    g.scene = 0
    manifest = {"lights": manifest_lights, "camera_node": camera_node, "resolution": [int(W), int(H)]}
    g.extras = {**manifest, EXTRAS_KEY: {
        "format": FORMAT, "format_version": FORMAT_VERSION, "scene": spec.name, "scene_hash": spec.digest(),
        "description": spec.description, "truth_allocation": spec.truth_allocation, "units": "metres",
        "tessellation": {"segments": segments, "max_relative_deviation": sagitta(segments)},
        "conventions": CONVENTIONS}}
    while len(blob.data) % 4:
        blob.data.append(0)
    g.buffers.append(gl.Buffer(byteLength=len(blob.data)))
    g.set_binary_blob(bytes(blob.data))
    return g, manifest


def write_glb(scene, path, *, resolution=None, segments: int = 64) -> dict:
    """Write ``scene`` (a loaded :class:`shadowlab.scene.Scene`) as one binary glTF at ``path``
    (atomically: a reader never sees half a file); returns the manifest ``{"lights": [{"name",
    "node", "kind", "type", "light"}, ...] in the scene's light order, "camera_node", "resolution":
    [W, H]}``, also the file's top-level ``extras``. ``resolution`` = (W, H) overrides the
    camera's; ``segments`` tessellates curved primitives."""
    g, manifest = build_gltf(scene, resolution=resolution, segments=segments)
    write_bytes_atomic(Path(path), b"".join(g.save_to_bytes()))
    return manifest


def read_gltf(path, *, resolution=None):
    """The :class:`~shadowlab.scene.spec.SceneSpec` of a ``.glb`` / ``.gltf`` file and its
    ``NAME.shadowlab.toml`` sidecar (what ``scene.load(path)`` builds; :mod:`.gltf_file` says what
    comes from where), optionally at another resolution (W, H)."""
    p = Path(path)
    if p.suffix.lower() not in GLTF_SUFFIXES:
        raise InputError(f"{p}: not a glTF file name; expected a {' or '.join(GLTF_SUFFIXES)} file")
    spec = load_spec(p)
    return spec.with_resolution(*resolution) if resolution else spec


# -- validation -------------------------------------------------------------------------------

_VALIDATE_JS = r"""
const fs = require('fs');
const validator = require(process.argv[1]);
const path = process.argv[2];
validator.validateBytes(new Uint8Array(fs.readFileSync(path)), {uri: path, maxIssues: 1000,
    externalResourceFunction: (uri) => Promise.reject(new Error('external resource ' + uri))})
  .then((report) => { process.stdout.write(JSON.stringify(report)); })
  .catch((e) => { process.stderr.write(String(e && e.message || e)); process.exit(5); });
"""


def project_root() -> Path:
    """The checkout's top directory (``package.json`` and ``node_modules/`` live there)."""
    return Path(__file__).resolve().parents[2]


def node_modules() -> Path:
    """``$SHADOWLAB_NODE_MODULES``, else the checkout's ``node_modules`` (where ``make engines``
    installs the pinned npm packages)."""
    env = os.environ.get("SHADOWLAB_NODE_MODULES")
    return Path(env) if env else project_root() / "node_modules"


def validator_path() -> Path:
    """The installed Khronos validator package; EnvironmentProblem (exit 3) naming ``make engines``
    when node or the package is missing."""
    if shutil.which("node") is None:
        raise EnvironmentProblem("node (Node.js) not found; the glTF validator runs on it. Install Node.js >= 18 "
                                 "and npm (sudo apt-get install nodejs npm), then run `make engines`")
    p = node_modules() / VALIDATOR_PACKAGE
    if not (p / "package.json").is_file():
        raise EnvironmentProblem(f"the Khronos glTF validator (npm package {VALIDATOR_PACKAGE}) is not installed in "
                                 f"{p.parent}; run `make engines` (npm ci from the committed package-lock.json)")
    return p


def validate_glb(path) -> dict:
    """The Khronos glTF validator's report of the file at ``path`` (its JSON: ``issues`` with
    ``numErrors``, ``numWarnings``, ``numInfos``, ``numHints`` and ``messages``, each with
    ``code``, ``message``, ``severity`` 0 error … 3 hint, ``pointer``). Runs
    ``require('gltf-validator').validateBytes`` with node; EnvironmentProblem (exit 3) naming
    ``make engines`` when node or the package is missing."""
    pkg = validator_path()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such glTF file to validate")
    try:
        r = subprocess.run(["node", "-e", _VALIDATE_JS, str(pkg), str(p.resolve())], capture_output=True, text=True,
                           timeout=300, env={**os.environ, "NODE_OPTIONS": ""})
    except (OSError, subprocess.TimeoutExpired) as e:
        raise EnvironmentProblem(f"the glTF validator could not run ({e}); check `node --version` and run "
                                 "`make engines`") from e
    if r.returncode != 0:
        raise EnvironmentProblem(f"the glTF validator failed on {p} ({(r.stderr or r.stdout).strip()[-300:]}); "
                                 "run `make engines` to reinstall it")
    return json.loads(r.stdout)


def report_lines(report: dict, *, severities=(0, 1)) -> list[str]:
    """One line per validator message of the given severities (0 error, 1 warning, 2 info, 3 hint)."""
    names = {0: "error", 1: "warning", 2: "info", 3: "hint"}
    return [f"{names.get(m.get('severity'), '?')} {m.get('code')}: {m.get('message')} at {m.get('pointer', '')}"
            for m in report.get("issues", {}).get("messages", []) if m.get("severity") in severities]
