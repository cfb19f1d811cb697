"""The shadow camera of a light, as lights.json writes it: what an engine needs to render the depth
map shadowlab's ``hard`` samples for that light, texel for texel.

The camera is :func:`shadowlab.render.lightview.projection` of the light with the default fit
(:class:`~shadowlab.render.lightview.SceneSphere`, the whole scene) at the technique's resolution
(``resolution`` 0: the light's ``shadow_map``) and depth format (``depth_bits`` 0: the light's
``depth_bits``), i.e. exactly the map ``hard`` with its defaults casts. Per face:

* ``direct3d``: ``world_to_view`` (left-handed light space: x right, y up, looking down +z) and
  ``view_to_clip`` (z ∈ [0, 1]); viewport row 0 is NDC y = +1, so texel (i, j) (column i from the
  left, row j from the top) is shadowlab's texel (i, j): the render target holds the same array.
* ``opengl``: ``world_to_view`` (right-handed, looking down −z) and ``view_to_clip`` (glFrustum /
  glOrtho, z ∈ [−1, 1]); with glDepthRange(0, 1) the window depth (ndc.z + 1)/2 is the same
  depth; window row 0 is the bottom (NDC y = −1): the texture's row N−1−j is shadowlab's row j,
  and t = (ndc.y + 1)/2 samples it.
* ``vulkan``: Direct3D's view and its projection with y negated (Vulkan's framebuffer y points
  down): the attachment holds shadowlab's array, row 0 at the top, z ∈ [0, 1].

Matrices are row-major, points are column vectors (p' = M @ [x, y, z, 1]): GLSL's column-major
``mat4`` wants the transpose of each row list, HLSL's ``mul(M, p)`` takes them as they are,
DirectXMath (row vectors, p' = p·M) takes the transpose.

Point and sphere lights have six faces in the order +X, −X, +Y, −Y, +Z, −Z (the order of OpenGL's
``GL_TEXTURE_CUBE_MAP_POSITIVE_X + k``, Direct3D's ``D3D11_TEXTURECUBE_FACE`` and Vulkan's cube
layers): face k looks down the k-th signed axis, 90° field of view, all faces share near and far.
shadowlab's own faces (right = forward × up, up +y, or +z for ±Y) are not oriented as a sampled
cube map expects, so each face also has ``cubemap`` matrices: the same frustum (same depths),
rotated in the image plane so that a map rendered into cube face k is sampled correctly by a
``samplerCube`` / ``TextureCube`` lookup with the direction p − light position (the face
selection table of the OpenGL and Vulkan specs: major axis, sc, tc; s = (sc/|ma| + 1)/2,
t = (tc/|ma| + 1)/2). ``cubemap.same_texels`` says how that face's texels relate to shadowlab's
(columns and / or rows reversed).

>>> sorted(CUBE_FACES)
['+X', '+Y', '+Z', '-X', '-Y', '-Z']
>>> CUBE_FACES["+X"]   # major axis, sc axis, tc axis
((1, 0, 0), (0, 0, -1), (0, -1, 0))
"""

from __future__ import annotations

import math

import numpy as np

from ..render.lightview import projection
from ..techniques import base as technique_registry
from ..techniques.shadow_map import GRAZING_MAX_COS, GRAZING_MAX_TAN
from .bias import bias_mapping

__all__ = ["shadow_camera", "depth_bias_info", "hard_defaults", "CUBE_FACE_ORDER", "CUBE_FACES", "DEPTH_FORMATS",
           "gl_projection"]

CUBE_FACE_ORDER = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")
#: per face: (major axis, sc axis, tc axis) of the cube-map face selection table (OpenGL 4.6 §8.13,
#: Vulkan "Cube Map Face Selection"): sc = sc_axis · d, tc = tc_axis · d for a direction d
CUBE_FACES = {
    "+X": ((1, 0, 0), (0, 0, -1), (0, -1, 0)),
    "-X": ((-1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "+Y": ((0, 1, 0), (1, 0, 0), (0, 0, 1)),
    "-Y": ((0, -1, 0), (1, 0, 0), (0, 0, -1)),
    "+Z": ((0, 0, 1), (1, 0, 0), (0, -1, 0)),
    "-Z": ((0, 0, -1), (-1, 0, 0), (0, -1, 0)),
}
DEPTH_FORMATS = {
    16: {"type": "unorm", "bits": 16, "direct3d": "DXGI_FORMAT_D16_UNORM", "vulkan": "VK_FORMAT_D16_UNORM",
         "opengl": "GL_DEPTH_COMPONENT16", "stored": "round(d * 65535) / 65535"},
    24: {"type": "unorm", "bits": 24, "direct3d": "DXGI_FORMAT_D24_UNORM_S8_UINT",
         "vulkan": "VK_FORMAT_X8_D24_UNORM_PACK32", "opengl": "GL_DEPTH_COMPONENT24",
         "stored": "round(d * 16777215) / 16777215"},
    32: {"type": "float", "bits": 32, "direct3d": "DXGI_FORMAT_D32_FLOAT", "vulkan": "VK_FORMAT_D32_SFLOAT",
         "opengl": "GL_DEPTH_COMPONENT32F", "stored": "float32(d)"},
}
FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])   # Direct3D light space -> OpenGL view space
FLIP_Y = np.diag([1.0, -1.0, 1.0, 1.0])   # Direct3D clip -> Vulkan clip (y down)


def _rows(M) -> list:
    return [[float(x) + 0.0 for x in row] for row in np.asarray(M, np.float64).reshape(4, 4)]  # no -0.0


def hard_defaults() -> dict:
    """``hard``'s resolved default parameters (the technique the exported camera and bias are for)."""
    return technique_registry.get("hard").resolve({})


def gl_projection(face) -> np.ndarray:
    """OpenGL view → clip of a :class:`~shadowlab.render.lightview.Face` (view space looks down −z;
    ndc.z ∈ [−1, 1], (ndc.z + 1)/2 = the face's NDC depth; same NDC x, y as Direct3D's)."""
    s, (sx, sy), n, f = face.scale, face.shift, face.near, face.far
    if face.ortho:
        return np.array([[1 / s, 0, 0, -sx], [0, 1 / s, 0, -sy],
                         [0, 0, -2 / (f - n), -(f + n) / (f - n)], [0, 0, 0, 1]], np.float64)
    return np.array([[1 / s, 0, sx, 0], [0, 1 / s, sy, 0],
                     [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)], [0, 0, -1, 0]], np.float64)


def _pair(V, P) -> dict:
    return {"world_to_view": _rows(V), "view_to_clip": _rows(P), "world_to_clip": _rows(P @ V)}


def _view(rows, origin) -> np.ndarray:
    R = np.asarray(rows, np.float64)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, -R @ np.asarray(origin, np.float64)
    return M


def _cubemap(face, name: str) -> dict:
    """Matrices of cube face ``name`` oriented for cube-map sampling, and how its texels relate to
    shadowlab's face (same frustum: only the image-plane axes differ, by sign)."""
    axis, sc, tc = (np.array(v, np.float64) for v in CUBE_FACES[name])
    P = face.proj_matrix
    V_d3d = _view([sc, -tc, axis], face.origin)          # D3D: row 0 at the top = t = 0
    V_gl = _view([sc, tc, -axis], face.origin)           # OpenGL: window row 0 = t = 0
    R = np.array(face.R)
    cols = "same" if float(R[0] @ sc) > 0 else "reversed"
    rows = "same" if float(R[1] @ -tc) > 0 else "reversed"
    return {"direct3d": _pair(V_d3d, P), "opengl": _pair(V_gl, gl_projection(face)),
            "vulkan": _pair(V_d3d, FLIP_Y @ P),
            "same_texels": {"columns": cols, "rows": rows,
                            "note": "cube texel (column c, row r from t = 0) holds shadowlab's face texel "
                                    "(i, j) with c = i or N-1-i, r = j or N-1-j as given"}}


def shadow_camera(light, scene, values: dict | None = None) -> dict:
    """lights.json's ``shadow_camera`` of ``light`` (a LightSpec) in the built ``scene``, for the
    shadow-map technique parameters ``values`` (default: ``hard``'s)."""
    values = hard_defaults() if values is None else values
    res = int(values.get("resolution") or light.shadow_map)
    bits = int(values.get("depth_bits") or light.depth_bits)
    proj = projection(light, scene, res)
    f0 = proj.faces[0]
    faces = []
    for k, f in enumerate(proj.faces):
        R = np.array(f.R)
        V, P = f.view_matrix, f.proj_matrix
        entry = {"index": k, "name": CUBE_FACE_ORDER[k] if proj.cube else None,
                 "origin": [float(x) + 0.0 for x in f.origin], "right": [float(x) + 0.0 for x in R[0]],
                 "up": [float(x) + 0.0 for x in R[1]], "forward": [float(x) + 0.0 for x in R[2]],
                 "near": f.near, "far": f.far,
                 "direct3d": _pair(V, P), "opengl": _pair(FLIP_Z @ V, gl_projection(f)),
                 "vulkan": _pair(V, FLIP_Y @ P)}
        if f.ortho:
            entry["half_extent"] = f.scale
        else:
            entry["fov_deg"] = math.degrees(2 * math.atan(f.scale))
            entry["tan_half_fov"] = f.scale
        if proj.cube:
            entry["cubemap"] = _cubemap(f, CUBE_FACE_ORDER[k])
        faces.append(entry)
    backface = bool(values.get("backface", False))
    return {
        "technique": "hard",
        "fit": "the whole scene (shadowlab.render.lightview.SceneSphere): " +
               ("orthographic, fitted to the scene's bounding sphere" if f0.ortho else
                "six 90-degree faces (a cube map)" if proj.cube else
                "perspective from the light's centre" + (", field of view 2 x cone angle" if light.kind == "spot"
                                                         else ", fitted to the scene's boxes")),
        "projection": "orthographic" if f0.ortho else "perspective",
        "map_size": [res, res],
        "faces_count": len(proj.faces),
        "near": f0.near, "far": f0.far,
        "depth_format": DEPTH_FORMATS[bits],
        "depth": ("stored per texel: NDC depth d in [0, 1] of the first surface at the texel centre "
                  "(perspective d = f/(f - n) (1 - n/z), orthographic d = (z - n)/(f - n), z = light-space "
                  "depth along forward), in the depth format; cleared to 1 (nothing hit); depth test LESS"),
        "depth_clamp": ("on: casters nearer than near are stored at depth 0 and farther than far at 1, not clipped "
                        "(OpenGL glEnable(GL_DEPTH_CLAMP), Direct3D DepthClipEnable = FALSE, Vulkan "
                        "depthClampEnable = VK_TRUE)"),
        "cull": "front faces (the map holds the first surfaces facing away from the light)" if backface
                else "none (the first surface of either facing)",
        "draw": "every shape of scene.json (alpha-tested shapes discard texels of opacity 0) and the other lights' "
                "emitting geometry; not this light's own (meshes/light_<name>.ply)",
        "lookup": ("project p with direct3d.world_to_clip: u = (ndc.x + 1)/2 N, v = (1 - ndc.y)/2 N (texel "
                   "centres at i + 0.5), nearest texel; lit when ndc.z <= stored depth + bias (comparison "
                   "LESS_EQUAL); outside the face or the near/far range: lit"),
        "cube_face_order": list(CUBE_FACE_ORDER) if proj.cube else None,
        "faces": faces,
    }


def depth_bias_info(light, values: dict | None = None) -> dict:
    """lights.json's ``depth_bias``: ``hard``'s (or ``values``') Direct3D rasterizer bias for the
    light's depth format and its OpenGL / Vulkan equivalents (:mod:`.bias`), and the receiver-side
    biases a shader applies."""
    values = hard_defaults() if values is None else values
    bits = int(values.get("depth_bits") or light.depth_bits)
    out = {"technique": "hard"}
    out.update(bias_mapping(values["depth_bias"], values["slope_scaled_depth_bias"], values["depth_bias_clamp"],
                            bits))
    out["receiver"] = {"constant_bias": float(values["constant_bias"]), "slope_bias": float(values["slope_bias"]),
                       "max_slope_bias": float(values["max_slope_bias"]),
                       "normal_offset_texels": float(values["normal_offset"]),
                       "note": "shader side, world units: z' = z - constant_bias - min(slope_bias tan(angle(n, l)), "
                               "max_slope_bias) after moving p by normal_offset texel widths along its normal"}
    out["receiver"]["grazing"] = {
        "grazing_slope_bias": float(values.get("grazing_slope_bias", 0.0)), "max_cos": GRAZING_MAX_COS,
        "max_tan": GRAZING_MAX_TAN,
        "note": "shader side, receivers with 0 <= cos(n, l) < max_cos: texel t is tested with z'_t = z' - max(0, "
                "-grazing_slope_bias (g_u du + g_v dv)), g the receiver's tangent-plane NDC depth gradient per texel "
                "(tan(n, l) capped at max_tan), (du, dv) = t's centre - the receiver's texel position; 0 = off"}
    return out
