"""``shadowlab export SCENE --out DIR``: what another renderer needs to reproduce a scene.

Files (all geometry in world space, metres; matrices row-major, points are column vectors,
``p' = M @ [x, y, z, 1]``):

| file | content |
|---|---|
| ``scene.xml`` | Mitsuba 3 XML of exactly the scene the ground truth renders (analytic primitives, the same emitters, camera and the ``direct`` integrator); ``mitsuba scene.xml`` or ``mi.load_file``; every file it names is a relative path inside the export |
| ``scene_mesh.xml`` | the same scene with every shape and area light replaced by its PLY (what a rasteriser sees) |
| ``meshes/<shape>.ply`` | one triangle mesh per shape of the TOML (a capped cylinder = tube + two disks), ``meshes/light_<name>.ply`` per area light: binary PLY, positions, unit normals, uvs (:mod:`.ply`, :mod:`.mesh`) |
| ``meshes/source/<shape>.ply`` / ``.obj`` | a copy of each PLY / OBJ file the scene's ``ply`` / ``obj`` shapes load (object space; ``scene.xml`` references the copy with the shape's ``to_world``) |
| ``textures/<shape>_opacity.png`` | alpha-tested shapes: the thresholded binary opacity (0 / 255), nearest-texel lookup at the uv in the PLY |
| ``camera.json`` | position, target, up, field of view, resolution, pixel centres, world→camera, camera→clip (and an OpenGL pair) |
| ``lights.json`` | per light: kind, pose, physical size, colour, power, emitted radiance / intensity / irradiance; ``shadow_camera`` (the map ``hard`` samples: map size, depth format, near / far, per face Direct3D / OpenGL / Vulkan view and projection matrices, cube faces +X, −X, +Y, −Y, +Z, −Z with cube-map-sampling variants, :mod:`.shadow_camera`) and ``depth_bias`` (``hard``'s Direct3D bias and its ``glPolygonOffset`` / ``depthBias*`` equivalents for the depth format, :mod:`.bias`) |
| ``scene.json`` | manifest: scene name and hash (a reference stores the same hash), shapes with albedo and PLY, bounds, conventions |

Conventions (also written into the JSON files, key ``convention``):

* World: right-handed, y up in the built-in scenes, units metres, angles in degrees unless the
  key says ``_rad``.
* Camera space (Mitsuba's): the camera looks along +z, +y is up, +x points to the image's **left**
  (a right-handed frame). ``world_to_camera`` maps world points into it.
* ``camera_to_clip``: clip = P @ [x, y, z, 1], ndc = clip[:3] / clip[3] with ndc.x ∈ [−1, 1] from
  the image's left edge to its right edge, ndc.y ∈ [−1, 1] from bottom to top, ndc.z ∈ [0, 1] from
  the near to the far clip plane (Direct3D / Vulkan depth range); w = camera-space z.
  Pixel (i, j) (column i from the left, row j from the top) has its centre at
  ndc = (2(i + ½)/W − 1, 1 − 2(j + ½)/H): the ground truth shades exactly these points.
* ``opengl``: ``world_to_view`` (x right, y up, looking along −z) and ``view_to_clip``
  (gluPerspective, ndc.z ∈ [−1, 1]); the same pixels.
* Files are written mode 644 and directories 755 whatever the umask (an export is meant to be
  shared); the export moves as a whole: no path in it points outside it.
* Lights: ``pose`` is the rigid local→world frame (columns: x, y, z axes and origin); area lights
  (rect, disk, spot with a radius) emit from the +z side of their pose; ``to_world`` is Mitsuba's
  transform of the canonical primitive (rectangle [−1, 1]², disk and sphere of radius 1).
"""  # noqa: E501

from __future__ import annotations

import hashlib
import math
import os
import shutil
import tempfile
from importlib import metadata
from pathlib import Path

import mitsuba as mi
import numpy as np

from .. import backend
from ..errors import EnvironmentProblem, InputError, SceneError
from ..io.jsonio import write_json_atomic
from ..io.png import encode_png
from ..reference import store
from ..render.camera import Camera
from ..io.outdir import claim_dir
from ..scene import lights as lights_mod
from ..scene.build import build, sensor_dict, shape_dicts
from ..scene.gltf import InvalidExport, report_lines, validate_glb, write_glb
from ..scene.spec import SceneSpec, load_spec, resolve
from ..scene.mesh import matrix_of, sagitta, shape_mesh, triangulate
from .mitsuba_xml import dict_to_xml
from .ply import write_ply
from .shadow_camera import depth_bias_info, hard_defaults, shadow_camera

__all__ = ["export_scene", "export_gltf", "GLTF_FILE", "FORMATS", "camera_info", "light_info", "EXPORT_FILES",
           "FORMAT_VERSION", "FILE_MODE", "DIR_MODE"]

FORMAT_VERSION = 1
#: the file ``shadowlab export --format gltf`` writes into ``--out``
GLTF_FILE = "scene.glb"
#: ``--format`` values: ``mitsuba`` (the files above, the default) and ``gltf`` (one .glb)
FORMATS = ("mitsuba", "gltf")
EXPORT_FILES = ("scene.xml", "scene_mesh.xml", "camera.json", "lights.json", "scene.json")
EXPORT_DIRS = ("meshes", "textures")
DEFAULT_SPP = 64
FILE_MODE, DIR_MODE = 0o644, 0o755  # whatever the umask: an export is meant to be shared

CAMERA_CONVENTION = {
    "world": "right-handed, metres; the built-in scenes have +y up",
    "matrices": "row-major 4x4, points are column vectors: p' = M @ [x, y, z, 1]",
    "camera_space": "Mitsuba's: the camera looks along +z, +y is up, +x points to the image's left (right-handed)",
    "camera_to_clip": "ndc = clip[:3] / clip[3]; ndc.x -1..1 = image left..right, ndc.y -1..1 = bottom..top, "
                      "ndc.z 0..1 = near..far (Direct3D/Vulkan range); clip w = camera-space z",
    "pixels": "pixel (i, j): column i from the left, row j from the top; its centre is at "
              "ndc = (2(i + 0.5)/W - 1, 1 - 2(j + 0.5)/H), film uv = ((i + 0.5)/W, (j + 0.5)/H); "
              "the ground truth is evaluated at these centres",
    "opengl": "world_to_view: x right, y up, looking along -z; view_to_clip: gluPerspective, ndc.z -1..1",
    "vectors": "position, target: world points (m); up: as the scene file gives it; up_used: the camera's actual +y "
               "axis in world space (up made orthogonal to forward); forward: unit view direction (camera +z)",
    "fov": "fov_deg: full horizontal field of view (fov_axis x, edge to edge of the image); fov_y_deg: the full "
           "vertical one, tan(fov_y/2) = tan(fov/2) H / W; square pixels, no lens shift",
}

LIGHT_CONVENTION = {
    "matrices": "row-major 4x4, points are column vectors: p' = M @ [x, y, z, 1]",
    "pose": "rigid local-to-world frame: columns 0-2 = local x, y, z axes, column 3 = origin; "
            "area lights with a front side (rect, disk, spot with a radius, directional with an angular size) "
            "emit from the +z side of their pose",
    "to_world": "Mitsuba's transform of the canonical primitive: rectangle [-1, 1]^2 in z = 0, disk of radius 1 "
                "in z = 0, sphere of radius 1 at the origin",
    "units": "metres, watts; radiance W m^-2 sr^-1, intensity W sr^-1, irradiance W m^-2, per RGB channel "
             "(= color x the scalar value)",
    "position": "pose origin in world space (m): the light's centre; for a directional light with an angular size "
                "the centre of its far-away disk, for a delta directional light (0, 0, 0) (only direction matters)",
    "direction": "unit world-space vector the light emits toward (pose +z); null for sphere and point lights",
    "physical_size": "the light's size as one number, what a technique's light_size starts from: rect sqrt(width x "
                     "height) in metres, disk / sphere / point / spot 2 x radius in metres, directional the angular "
                     "diameter in RADIANS; 0 = a delta light",
    "ply": "the emitting geometry (area lights only), world space, triangles wound counter-clockwise around the "
           "emitting side's normal; null for delta lights",
    "irradiance": "directional lights: the scene's irradiance (W m^-2, scalar and RGB) on a surface facing the "
                  "light: an engine's directional light intensity",
    "engine_draws": "false for a directional light's far disk (its ply, with ply_note): Mitsuba's stand-in for the "
                    "sun, never drawn by an engine",
    "shadow_camera": "the light camera of the depth map shadowlab's hard technique samples (default parameters, map "
                     "size = the light's shadow_map, depth format = its depth_bits): per face direct3d (left-handed "
                     "view looking down +z, clip z 0..1, viewport row 0 = ndc y +1 = shadowlab's texel row 0), opengl "
                     "(view looking down -z, clip z -1..1, window row 0 = ndc y -1) and vulkan (direct3d with clip y "
                     "negated) world_to_view / view_to_clip / world_to_clip; point and sphere lights: six faces in "
                     "the order +X, -X, +Y, -Y, +Z, -Z, each with cubemap matrices oriented for samplerCube / "
                     "TextureCube lookups with the direction p - position (same frustum and depths)",
    "depth_bias": "hard's Direct3D rasterizer depth bias (DepthBias, SlopeScaledDepthBias, DepthBiasClamp) for the "
                  "light's depth format, and the glPolygonOffsetClamp(factor, units, clamp) / Vulkan depthBias* "
                  "values that give the same bias for each minimum resolvable difference r an implementation may "
                  "use (units = DepthBias r_d3d / r); receiver: hard's shader-side biases",
}

SCENE_CONVENTION = {
    "units": "metres; world right-handed (the built-in scenes have +y up)",
    "ply": "binary little-endian PLY, world space: float x y z, unit shading normal nx ny nz (smooth on curved "
    "surfaces, flat on cubes and loaded meshes), float u v = Mitsuba's uv of the primitive "
    "(rectangle ((x+1)/2, (y+1)/2), disk (r, phi/2pi), sphere (phi/2pi, theta/pi), cylinder (phi/2pi, z)); "
    "faces are triangles wound counter-clockwise seen from the side the normal points to "
    "(cross(v1 - v0, v2 - v0) is the front geometric normal)",
    "albedo": "linear RGB reflectance of a Lambertian (diffuse) BSDF: outgoing radiance = albedo / pi x irradiance",
    "two_sided": "true: both sides reflect with the same albedo; false: the back side (against the normal) is black",
    "alpha": "opacity PNG looked up at the PLY's uv, nearest texel, PNG row 0 (top) at v = 0, clamped; 0 = the surface "
             "is "
    "not there (neither seen nor casting a shadow), 255 = opaque",
}


def _shadowlab_version() -> str | None:
    """The installed distribution's version (pyproject.toml's), read from its metadata, so that
    export depends on no package above it (the package's ``__init__`` is the API); None when
    shadowlab runs from a source tree that is not installed."""
    try:
        return metadata.version("shadowlab")
    except metadata.PackageNotFoundError:
        return None


def _rows(M) -> list:
    return [[float(x) for x in row] for row in np.asarray(M, np.float64).reshape(4, 4)]


def camera_info(scene) -> dict:
    """camera.json of a built :class:`shadowlab.scene.Scene`: its :class:`shadowlab.render.camera.Camera`,
    the truth's Mitsuba sensor written out (clip planes, field of view, matrices)."""
    cam = scene.spec.camera
    camera = Camera.from_scene(scene)
    W, H = camera.resolution
    c2w = camera.camera_to_world
    w2c = camera.world_to_camera
    near, far = camera.near, camera.far
    aspect = camera.aspect
    ty = camera.tan_y
    P = camera.camera_to_clip()
    gl_P = camera.proj_gl()
    gl_V = camera.view_gl
    up_used = [float(x) for x in c2w[:3, 1]]
    return {
        "convention": CAMERA_CONVENTION,
        "type": "perspective",
        "position": [float(x) for x in cam.position],
        "target": [float(x) for x in cam.target],
        "up": [float(x) for x in cam.up],
        "up_used": up_used,
        "forward": [float(x) for x in c2w[:3, 2]],
        "fov_axis": "x",
        "fov_deg": float(camera.fov),
        "fov_y_deg": math.degrees(2 * math.atan(ty)),
        "resolution": [W, H],
        "aspect": aspect,
        "near_clip": near,
        "far_clip": far,
        "camera_to_world": _rows(c2w),
        "world_to_camera": _rows(w2c),
        "camera_to_clip": _rows(P),
        "world_to_clip": _rows(P @ w2c),
        "opengl": {"world_to_view": _rows(gl_V), "view_to_clip": _rows(gl_P),
                   "world_to_clip": _rows(gl_P @ gl_V)},
    }


def _rigid(M: np.ndarray) -> np.ndarray:
    R = M.copy()
    for k in range(3):
        n = np.linalg.norm(R[:3, k])
        if n > 0:
            R[:3, k] /= n
    return R


def _translate(p) -> np.ndarray:
    M = np.eye(4)
    M[:3, 3] = p
    return M


#: lights.json: what a directional light's ``irradiance`` is
SUN_IRRADIANCE = ("the scene's irradiance on a surface facing the light (normal along -direction), per RGB channel: "
                  "an engine's directional light intensity; the far disk's radiance (emission) is derived from it")
#: lights.json and the PLY's comment: the sun's emitter disk is Mitsuba's stand-in, not scene geometry
SUN_DISK_NOTE = ("Mitsuba's stand-in for the sun: a disk of radius {r:.4g} m at {d:.4g} m that subtends the angular "
                 "diameter, its radiance giving the irradiance; an engine must not draw it (light the scene with "
                 "direction and irradiance)")


def light_info(light, mitsuba_dict: dict, ply: str | None) -> dict:
    """lights.json entry of one LightSpec and the Mitsuba dict it becomes."""
    qty, value = lights_mod.emission(light)
    k = light.kind
    d = mitsuba_dict
    if "to_world" in d:
        to_world = matrix_of(d["to_world"])
    elif "center" in d:  # sphere emitter (sphere, point with a radius)
        r = float(d["radius"])
        to_world = _translate(d["center"]) @ np.diag([r, r, r, 1.0])
    elif "position" in d:  # delta point light
        to_world = _translate(d["position"])
    else:  # delta directional: a frame whose +z is the direction
        fwd = lights_mod.forward(light)
        up = lights_mod.up_for(fwd, light.up)
        to_world = matrix_of(mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=list(fwd), up=list(up)))
    pose = _rigid(to_world)
    info = {
        "name": light.name,
        "kind": k,
        "mitsuba_key": f"light_{light.name}",
        "mitsuba_emitter": ("area on a " + d["type"]) if "emitter" in d else d["type"],
        "delta": bool(light.is_delta),
        "pose": _rows(pose),
        "to_world": _rows(to_world),
        "position": [float(x) for x in pose[:3, 3]],
        "direction": [float(x) for x in pose[:3, 2]] if k in ("rect", "disk", "spot", "directional") else None,
        "physical_size": float(light.physical_size),
        "color": [float(c) for c in light.color],
        "power_W": None if light.power is None else float(light.power),
        "emission": {"quantity": qty, "value": float(value), "rgb": [float(c * value) for c in light.color]},
        "shadow_map": int(light.shadow_map),
        "depth_bits": int(light.depth_bits),
        "ply": ply,
    }
    if k == "rect":
        w, h = (float(x) for x in light.size)
        info["size"] = {"width": w, "height": h}
        info["area_m2"] = w * h
        info["emits"] = "+z side of pose (one-sided rectangle, width along pose x, height along pose y)"
    elif k in ("disk", "sphere", "point", "spot"):
        r = float(light.radius)
        info["size"] = {"radius": r}
        if k == "spot":
            info["size"]["cone_half_angle_deg"] = float(light.angle)
        if r > 0:
            info["area_m2"] = 4 * math.pi * r * r if k in ("sphere", "point") else math.pi * r * r
        info["emits"] = {
            "disk": "+z side of pose",
            "sphere": "outward",
            "point": "outward" if r > 0 else "all directions",
            "spot": (
                "+z side of pose, in every direction (Mitsuba has no area spot; the cone only "
                "sets the shadow map's field of view)"
            )
            if r > 0
            else "inside the cone around +z",
        }[k]
    else:  # directional
        a = float(light.angular_diameter)
        info["size"] = {"angular_diameter_deg": a, "angular_diameter_rad": math.radians(a)}
        info["direction"] = [float(x) for x in lights_mod.forward(light)]
        E = float(light.irradiance if light.irradiance is not None else light.power)
        info["irradiance"] = {"value": E, "rgb": [float(c * E) for c in light.color], "units": "W m^-2",
                              "meaning": SUN_IRRADIANCE}
        if a > 0:
            r = float(np.linalg.norm(to_world[:3, 0]))
            info["size"]["disk_radius"] = r
            info["size"]["disk_distance"] = r / math.tan(math.radians(a) / 2)
            info["emits"] = ("+z side of pose: a disk far away subtending the angular diameter "
                             "(radiance = irradiance / (pi sin^2(theta/2)))")
            info["engine_draws"] = False
            info["ply_note"] = SUN_DISK_NOTE.format(r=r, d=info["size"]["disk_distance"])
        else:
            info["emits"] = "parallel light along direction"
    return info


def _find(d, pred):
    """The first nested dict of ``d`` (depth first) for which ``pred`` holds, or None."""
    if isinstance(d, dict):
        if pred(d):
            return d
        for v in d.values():
            r = _find(v, pred)
            if r is not None:
                return r
    return None


def _texture_files(d, owner: str, save_bitmap):
    """Replace every bitmap texture holding a tensor (``data``) inside ``d`` by one reading the file
    ``save_bitmap(owner, data)`` writes; same filtering, wrap mode and raw flag."""
    if isinstance(d, dict):
        for k, v in list(d.items()):
            if isinstance(v, dict) and v.get("type") == "bitmap" and "data" in v:
                d[k] = {"type": "bitmap", "filename": save_bitmap(owner, v["data"]),
                        **{kk: vv for kk, vv in v.items() if kk not in ("type", "data")}}
            else:
                _texture_files(v, owner, save_bitmap)
    return d


def _scene_dicts(sc, spp: int, mesh_files: dict | None, save_bitmap, source_mesh=None):
    """(dict for scene.xml, per-shape Mitsuba dicts, per-light dicts); with ``mesh_files`` the shapes
    and area lights are PLY shapes (scene_mesh.xml). Opacity tensors become files (``save_bitmap``);
    the XML's ``ply`` / ``obj`` shapes read ``source_mesh(shape, type, path)`` (the copy beside it),
    the returned per-shape dicts keep the scene's own path."""
    d = {"type": "scene"}
    shapes = {}
    for s in sc.spec.shapes:
        sd = _texture_files(shape_dicts(s), s.name, save_bitmap)
        shapes[s.name] = sd
        if mesh_files is None:
            for key, v in sd.items():
                if source_mesh is not None and v.get("type") in ("ply", "obj") and v.get("filename"):
                    v = {**v, "filename": source_mesh(s.name, v["type"], v["filename"])}
                elif v.get("type") == "gltf":  # a glTF's primitive: its world-space triangles as a PLY
                    v = {"type": "ply", "filename": source_mesh(s.name, "gltf", v), "bsdf": v["bsdf"],
                         "face_normals": True}
                d[key] = v
        else:
            d[s.name] = {"type": "ply", "filename": mesh_files[s.name], "bsdf": next(iter(sd.values()))["bsdf"]}
    sensor = sensor_dict(sc.spec.camera, spp=spp)
    sensor["film"]["width"], sensor["film"]["height"] = "$resx", "$resy"
    sensor["sampler"]["sample_count"] = "$spp"
    d["sensor"] = sensor
    lights = {}
    for l in sc.spec.lights:
        key, ld = lights_mod.mitsuba_dict(l, sc.center, sc.radius)
        lights[l.name] = ld
        if mesh_files is not None and "emitter" in ld:
            d[key] = {"type": "ply", "filename": mesh_files[key], "emitter": ld["emitter"]}
        else:
            d[key] = ld
    d["integrator"] = {"type": "direct"}
    return d, shapes, lights


def _publish_modes(root: Path) -> None:
    """Files FILE_MODE (644), directories DIR_MODE (755) below and including ``root``: temporary
    files (mkstemp) are 600 and directories made under a restrictive umask 700."""
    os.chmod(root, DIR_MODE)
    for dirpath, dirnames, filenames in os.walk(root):
        for n in dirnames:
            os.chmod(os.path.join(dirpath, n), DIR_MODE)
        for n in filenames:
            os.chmod(os.path.join(dirpath, n), FILE_MODE)


def _install(tmp: Path, out: Path) -> None:
    """Move the exported files from ``tmp`` into ``out``; in an existing directory only the files
    an export writes are replaced, other files stay."""
    if not out.exists():
        os.rename(tmp, out)
        return
    for name in EXPORT_DIRS:
        old = out / f".{name}.old-{os.getpid()}"
        if (out / name).exists():
            os.rename(out / name, old)
        if (tmp / name).exists():
            os.rename(tmp / name, out / name)
        shutil.rmtree(old, ignore_errors=True)
    for name in EXPORT_FILES:
        os.replace(tmp / name, out / name)
    shutil.rmtree(tmp, ignore_errors=True)


def export_scene(scene, out, *, resolution=None, segments: int = 64, spp: int = DEFAULT_SPP,
                 force: bool = False, verify: bool = True, protected=None) -> dict:
    """Export ``scene`` (built-in name, TOML path or SceneSpec) to the directory ``out``; returns
    the manifest (scene.json). ``resolution`` = (W, H) overrides the scene's camera resolution.

    An existing non-empty ``out`` is refused unless ``force`` (then only the exported files and the
    ``meshes/``, ``textures/`` directories are replaced). Everything is written to a temporary sibling
    directory first, checked by loading both XML files with ``mi.load_file`` (``verify``), and only
    then moved into place: a failed export leaves ``out`` as it was. ``out`` never lies inside the
    reference store (``protected``, default the store's root): exit 2, even with ``force``."""
    if not isinstance(segments, int) or not 3 <= segments <= 4096:
        raise InputError(f"--segments {segments!r}: expected an integer in 3..4096 (tessellation of curved shapes)")
    if not isinstance(spp, int) or spp < 1:
        raise InputError(f"--spp {spp!r}: expected a positive integer")
    spec = scene if isinstance(scene, SceneSpec) else load_spec(resolve(scene))
    if resolution:
        spec = spec.with_resolution(*resolution)
    sdf = getattr(spec, "sdf", ())
    if sdf:
        raise InputError(f"scene {spec.name!r} has [[sdf]] objects, which have no triangle mesh or Mitsuba shape to "
                         "export; export a scene made of [[shapes]] only")
    out = Path(out)
    # inside the store, an existing file, or below a file: refused (the non-empty rule follows)
    claim_dir(out, "export", force=True, protected=[store.root()] if protected is None else protected)
    if out.exists() and any(out.iterdir()) and not force:
        raise InputError(f"export output {out} exists and is not empty; pass --force to replace the exported "
                         f"files in it ({', '.join(EXPORT_FILES)}, meshes/, textures/) or choose another --out")
    backend.init()
    sc = build(spec)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.export-", dir=out.parent))
    try:
        textures = {}  # sha256 of the PNG -> relative file name

        def save_bitmap(owner, data):
            """Write an alpha-tested shape's opacity tensor (build.opacity_texture: H×W×1 of 0/1) as
            an 8-bit grey PNG (0 / 255, read back raw as 0 / 1); identical textures share one file."""
            a = np.asarray(data, np.float64)
            png = encode_png((np.clip(a.reshape(a.shape[0], a.shape[1]), 0, 1) * 255 + 0.5).astype(np.uint8))
            digest = hashlib.sha256(png).hexdigest()
            if digest not in textures:
                textures[digest] = f"textures/{owner}_opacity.png"
                (tmp / "textures").mkdir(exist_ok=True)
                (tmp / textures[digest]).write_bytes(png)
            return textures[digest]

        sources = {}  # the scene's PLY / OBJ file -> its copy (relative), one copy per file

        def source_mesh(owner, kind, path):
            """Copy a mesh file the scene loads into meshes/source/ (scene.xml reads the copy); a glTF
            primitive (``kind`` "gltf", ``path`` its shape dict) is written there as a world-space PLY."""
            if kind == "gltf":
                rel = f"meshes/source/{owner}.ply"
                (tmp / "meshes" / "source").mkdir(parents=True, exist_ok=True)
                write_ply(tmp / rel, *triangulate(path, segments), comment=f"shape {owner}: glTF {path['filename']} "
                          f"node {path['node']}, world space")
                sources[f"gltf:{owner}"] = rel
                return rel
            key = str(Path(path).resolve())
            if key not in sources:
                rel = f"meshes/source/{owner}.{kind}"
                (tmp / "meshes" / "source").mkdir(parents=True, exist_ok=True)
                shutil.copyfile(key, tmp / rel)
                sources[key] = rel
            return sources[key]

        mesh_files, shapes_meta = {}, []
        exact_d, shape_d, light_d = _scene_dicts(sc, spp, None, save_bitmap, source_mesh)
        for s in spec.shapes:
            P, N, UV, F = shape_mesh(s, segments)
            off = len(P)
            rel = f"meshes/{s.name}.ply"
            write_ply(tmp / rel, P, N, UV, F,
                      comment=f"shadowlab export of scene {spec.name}, shape {s.name} ({s.type}), world space, metres")
            mesh_files[s.name] = rel
            entry = {"name": s.name, "type": s.type, "ply": rel, "mitsuba_keys": list(shape_d[s.name]),
                     "albedo": [float(a) for a in s.albedo], "two_sided": bool(s.two_sided),
                     "triangles": int(len(F)), "vertices": int(off)}
            if s.type in ("ply", "obj") and s.filename:
                entry["source_mesh"] = sources[str(Path(s.filename).resolve())]
            if s.alpha_texture is not None:
                tex = _find(shape_d[s.name], lambda x: x.get("type") == "bitmap")
                entry["alpha"] = {"opacity_texture": tex["filename"], "source_texture": s.alpha_texture,
                                  "cutoff": float(s.alpha_cutoff),
                                  "lookup": "nearest texel at the PLY's uv, row 0 at v = 0; opacity 0 = discard"}
            shapes_meta.append(entry)
        lights_meta = []
        hard = hard_defaults()
        for l in spec.lights:
            ld = light_d[l.name]
            rel = None
            if "emitter" in ld:  # area light: its emitting geometry
                rel = f"meshes/light_{l.name}.ply"
                P, N, UV, F = triangulate(ld, segments)
                write_ply(
                    tmp / rel,
                    P,
                    N,
                    UV,
                    F,
                    comment=f"shadowlab export of scene {spec.name}, light {l.name} ({l.kind}), emits along the "
                            f"normals" + ("; not for drawing in an engine: the far disk standing in for the sun"
                                          if l.kind == "directional" else ""),
                )
                mesh_files[f"light_{l.name}"] = rel
            info = light_info(l, ld, rel)
            info["shadow_camera"] = shadow_camera(l, sc, hard)
            info["depth_bias"] = depth_bias_info(l, hard)
            lights_meta.append(info)

        W, H = spec.camera.resolution
        defaults = {"spp": spp, "resx": W, "resy": H}
        xml_exact = dict_to_xml(exact_d, defaults=defaults)
        xml_mesh = dict_to_xml(_scene_dicts(sc, spp, mesh_files, save_bitmap)[0], defaults=defaults)
        (tmp / "scene.xml").write_text(xml_exact, encoding="utf-8")
        (tmp / "scene_mesh.xml").write_text(xml_mesh, encoding="utf-8")
        cam = camera_info(sc)
        write_json_atomic(tmp / "camera.json", cam)
        write_json_atomic(tmp / "lights.json", {"convention": LIGHT_CONVENTION, "lights": lights_meta})
        manifest = {
            "format": "shadowlab-export", "format_version": FORMAT_VERSION, "convention": SCENE_CONVENTION,
            "scene": spec.name, "scene_hash": spec.digest(), "source": spec.source,
            "description": spec.description, "resolution": [int(W), int(H)],
            "shadowlab": _shadowlab_version(), "mitsuba": mi.MI_VERSION,
            "units": "metres",
            "files": {"mitsuba_xml": "scene.xml", "mitsuba_xml_meshes": "scene_mesh.xml", "camera": "camera.json",
                      "lights": "lights.json", "meshes": sorted(mesh_files.values()),
                      "source_meshes": sorted(sources.values()),
                      "textures": sorted(textures.values())},
            "shapes": shapes_meta,
            "lights": [l.name for l in spec.lights],
            "bounds": {"min": list(sc.bbox_min), "max": list(sc.bbox_max), "center": list(sc.center),
                       "radius": float(sc.radius)},
            "tessellation": {"segments": segments, "max_relative_deviation": sagitta(segments),
                             "note": "curved surfaces are inscribed: every vertex lies on the surface, the largest "
                                     "gap is radius x max_relative_deviation"},
            "truth": {"visibility": "V_L = integral of f v / integral of f over the light, f = BSDF Le cos / pdf "
                                    "(for a diffuse receiver and an area light: the cos_r cos_l / r^2 weighted visible "
                                    "fraction); A_L = plain visible area (solid-angle for spheres) fraction",
                      "shaded": "sum over lights of U_L V_L at the pixel centres (U_L = unshadowed direct light)",
                      "compare_with": "shadowlab ingest SCENE IMAGE.exr --channel NAME | --shaded"},
        }
        write_json_atomic(tmp / "scene.json", manifest)
        if verify:
            for name in ("scene.xml", "scene_mesh.xml"):
                try:
                    loaded = mi.load_file(str(tmp / name), optimize=False)
                except Exception as e:  # our own output must load; say so plainly
                    raise SceneError(f"the exported {name} does not load in Mitsuba ({e}); this is a shadowlab "
                                     "bug, please report it with the scene file") from e
                n_exp = len(sc.mi_scene.shapes()) if name == "scene.xml" else \
                    len(spec.shapes) + sum(1 for l in light_d.values() if "emitter" in l)
                if len(loaded.shapes()) != n_exp:
                    raise SceneError(f"the exported {name} has {len(loaded.shapes())} shapes, expected {n_exp}; "
                                     "this is a shadowlab bug")
        _publish_modes(tmp)
        _install(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def export_gltf(scene, out, *, resolution=None, segments: int = 64, force: bool = False, validate: bool = True,
                protected=None) -> dict:
    """``shadowlab export SCENE --format gltf``: write ``out/scene.glb`` (:func:`shadowlab.scene.gltf.write_glb`)
    and check it with the Khronos validator when it is installed (``make engines``).

    Returns ``{"path", "manifest", "validation"}``; ``validation`` is the validator's counts and its
    error and warning lines, or ``{"skipped": why}`` without node or the npm package. The file is
    written beside ``out/scene.glb`` first and replaces it only once it is valid: an export whose own
    glb has validator errors raises :class:`~shadowlab.scene.gltf.InvalidExport` (exit 4, a shadowlab
    bug) and leaves ``out`` as it was. ``out`` is refused as :func:`export_scene` refuses it."""
    spec = scene if isinstance(scene, SceneSpec) else load_spec(resolve(scene))
    if resolution:
        spec = spec.with_resolution(*resolution)
    out = Path(out)
    claim_dir(out, "export", force=True, protected=[store.root()] if protected is None else protected)
    target = out / GLTF_FILE
    if target.exists() and not force:
        raise InputError(f"export output {target} exists; pass --force to replace it or choose another --out")
    backend.init()
    sc = build(spec)
    out.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out, prefix=f".{GLTF_FILE}.", suffix=".tmp")
    os.close(fd)
    try:
        manifest = write_glb(sc, tmp, segments=segments)
        validation = {"skipped": None}
        if validate:
            try:
                rep = validate_glb(tmp)
            except EnvironmentProblem as e:
                validation = {"skipped": str(e)}
            else:
                issues = rep.get("issues", {})
                validation = {"errors": int(issues.get("numErrors", 0)), "warnings": int(issues.get("numWarnings", 0)),
                              "infos": int(issues.get("numInfos", 0)), "lines": report_lines(rep),
                              "validator": rep.get("validatorVersion")}
                if validation["errors"]:
                    raise InvalidExport(f"the exported glTF of scene {spec.name!r} has {validation['errors']} "
                                        "Khronos validator errors (" + "; ".join(validation["lines"][:3]) + "); this "
                                        f"is a shadowlab bug, please report it with the scene file ({out} is as it "
                                        "was)")
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return {"path": str(target), "scene": spec.name, "manifest": manifest, "validation": validation}
