"""Reading a glTF 2.0 file (``.glb`` or ``.gltf``) as a scene [Khronos 2017].

:func:`scene_document` turns the file into the document a scene TOML parses to (the same dict
:func:`shadowlab.scene.spec.parse` validates), so a glTF goes through the one scene loader and every
command that takes a SCENE takes a ``.glb``. What comes from where:

* **shapes**: one ``gltf`` shape per triangle primitive of each mesh node of the file's scene
  (``filename``, ``node``, ``primitive``), its triangles read by :func:`mesh_arrays` in world space
  (the node's world matrix applied). Like ``ply`` and ``obj`` shapes they are shaded with flat face
  normals (the file's ``NORMAL`` is kept for a re-export, not used by the truth). The material
  gives ``albedo`` (``baseColorFactor``), ``two_sided`` (``doubleSided``) and, with ``alphaMode:
  "MASK"``, ``alpha_cutoff`` and an ``alpha_texture``: the ``baseColorTexture`` image (its alpha),
  stored once under ``$XDG_CACHE_HOME/shadowlab/gltf-images/`` by its SHA-256 (the scene's hash is
  the image's content, not that path). ``BLEND`` is read as opaque.
* **the camera**: the first perspective camera node: position, −z as the view direction, +y as up,
  ``znear`` / ``zfar`` as the clip planes; the horizontal field of view from ``yfov`` and the
  resolution's W/H (square pixels).
* **lights**: ``KHR_lights_punctual``: point → ``point`` (``intensity`` in W/sr = the candela),
  spot → ``spot`` (``angle`` = the outer cone), directional → ``directional`` (``irradiance`` in W/m²
  = the lux); all delta lights (glTF lights have no size).
* a file shadowlab wrote carries its own tables in ``extras.shadowlab`` (the light's table of the
  scene format, the camera's, the scene's name and truth settings, a translucent caster's
  transmittance): they are read instead, so an exported ``.glb`` round-trips without a sidecar.

**The sidecar** ``NAME.shadowlab.toml`` beside ``NAME.glb`` adds what glTF lacks, in the scene
format: top-level keys (``name``, ``description``, ``truth_allocation``) replace the file's;
``[camera]`` keys replace the camera's (``resolution``; a whole camera for a file without one);
a ``[[lights]]`` or ``[[shapes]]`` table with the ``name`` of one from the file changes that one's
keys (a light's ``kind`` and size make a glTF point light a sphere or rect light; emission keys
replace the file's intensity); one with a new name is added.

**Defaults** where neither says: the resolution is 128 pixels wide with the camera's aspect ratio
(128×128 without one), lights are delta lights with the format's shadow-map defaults, the scene is
named after the file. The defaults a file needed are printed once per file (stderr).

Not supported (exit 2, naming the feature): extensions a file *requires* other than
``KHR_lights_punctual`` (Draco, meshopt, quantisation, texture transforms), primitive modes other
than triangles, sparse accessors, orthographic cameras, images that are not PNG or JPEG. Ignored:
animations, skins and morph targets (the rest pose is read), other cameras.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import re
import struct
import sys
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np
import pygltflib as gl

from ..errors import SceneError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["GLTF_SUFFIXES", "scene_document", "mesh_arrays", "sidecar_path", "DEFAULT_WIDTH", "read_file"]

GLTF_SUFFIXES = (".glb", ".gltf")
#: the width of the camera's image when neither the file's extras nor the sidecar give a resolution
DEFAULT_WIDTH = 128
#: extensions a file may require: lights are read; every other required one is refused
READ_EXTENSIONS = ("KHR_lights_punctual",)
EXTRAS_KEY = "shadowlab"
_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES", 5: "TRIANGLE_STRIP",
          6: "TRIANGLE_FAN"}
_EMISSION_KEYS = ("power", "radiance", "irradiance", "intensity")
_shown_defaults: set = set()


def sidecar_path(path) -> Path:
    """``scene.glb`` -> ``scene.shadowlab.toml`` beside it."""
    p = Path(path)
    return p.with_name(p.stem + ".shadowlab.toml")


def _bad(path, what: str) -> SceneError:
    return SceneError(f"{path}: not a readable glTF 2.0 file ({what}); re-export it from its source, or check it "
                      "with the Khronos glTF validator")


def _parse_glb(path: Path, raw: bytes):
    if len(raw) < 20:
        raise _bad(path, f"{len(raw)} bytes, shorter than a GLB header")
    magic, version, length = struct.unpack_from("<4sII", raw, 0)
    if magic != b"glTF":
        raise _bad(path, "no 'glTF' magic at the start of the .glb")
    if version != 2:
        raise SceneError(f"{path}: a GLB of version {version}; shadowlab reads glTF 2.0: convert the file to glTF 2.0 "
                         "(e.g. re-export it from Blender)")
    if length != len(raw):
        raise _bad(path, f"the header says {length} bytes, the file has {len(raw)}: truncated or padded")
    off, chunks = 12, []
    while off + 8 <= len(raw):
        n, kind = struct.unpack_from("<II", raw, off)
        if off + 8 + n > len(raw):
            raise _bad(path, "a chunk runs past the end of the file")
        chunks.append((kind, raw[off + 8: off + 8 + n]))
        off += 8 + n
    if not chunks or chunks[0][0] != 0x4E4F534A:
        raise _bad(path, "the first GLB chunk is not JSON")
    blob = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == 0x004E4942 else None
    return chunks[0][1], blob


@lru_cache(maxsize=8)
def _read(path: str, mtime_ns: int, size: int):
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise SceneError(f"{p}: cannot read the glTF file ({e.strerror or e}); check its permissions") from None
    if p.suffix.lower() == ".glb":
        text, blob = _parse_glb(p, raw)
    else:
        text, blob = raw, None
    try:
        doc = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise _bad(p, f"its JSON does not parse: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
        raise _bad(p, "no 'asset' object in its JSON")
    ver = str(doc["asset"].get("version", ""))
    if not ver.startswith("2."):
        raise SceneError(f"{p}: glTF version {ver!r}; shadowlab reads glTF 2.0: convert the file to glTF 2.0")
    try:
        with warnings.catch_warnings():  # dataclasses_json warns of every optional field a file leaves out
            warnings.simplefilter("ignore")
            g = gl.GLTF2.gltf_from_json(text.decode("utf-8"))
    except Exception as e:  # pygltflib's schema mapping: a field of the wrong type
        raise _bad(p, f"its JSON does not follow the glTF schema: {e}") from None
    required = [x for x in (g.extensionsRequired or []) if x not in READ_EXTENSIONS]
    if required:
        raise SceneError(f"{p}: requires the glTF extension(s) {', '.join(required)}, which shadowlab does not read "
                         f"(it reads {', '.join(READ_EXTENSIONS)}); re-export the file without them (e.g. no Draco "
                         "or meshopt compression, no quantisation, no texture transforms)")
    return g, blob


def read_file(path):
    """(pygltflib GLTF2, GLB binary chunk or None) of a ``.glb`` / ``.gltf`` file, checked (SceneError,
    exit 2, naming the problem); cached per file version."""
    p = Path(path).resolve()
    if not p.is_file():
        raise SceneError(f"{path}: glTF file not found; give the path of a .glb or .gltf file")
    st = p.stat()
    return _read(str(p), st.st_mtime_ns, st.st_size)


def _buffer(path: Path, g, blob, i: int) -> bytes:
    b = g.buffers[i]
    uri = b.uri
    if uri is None:
        if blob is None:
            raise _bad(path, f"buffer {i} has no uri and there is no GLB binary chunk")
        return blob
    if uri.startswith("data:"):
        try:
            return base64.b64decode(uri.split(",", 1)[1])
        except (ValueError, IndexError) as e:
            raise _bad(path, f"buffer {i}'s data URI does not decode ({e})") from None
    f = path.parent / uri
    try:
        return f.read_bytes()
    except OSError as e:
        raise SceneError(f"{path}: buffer {i} reads {f}, which cannot be read ({e.strerror or e}); keep the .bin "
                         "file beside the .gltf") from None


def _view(path, g, blob, v: int) -> tuple[bytes, int | None]:
    bv = g.bufferViews[v]
    data = _buffer(path, g, blob, bv.buffer)
    off = bv.byteOffset or 0
    if off + bv.byteLength > len(data):
        raise _bad(path, f"bufferView {v} runs past the end of buffer {bv.buffer}")
    return data[off: off + bv.byteLength], bv.byteStride


def _accessor(path, g, blob, i: int) -> np.ndarray:
    a = g.accessors[i]
    if a.sparse is not None:
        raise SceneError(f"{path}: accessor {i} is sparse, which shadowlab does not read; re-export the file "
                         "without sparse accessors")
    dt = np.dtype(_COMPONENTS.get(a.componentType, np.float32)).newbyteorder("<")
    if a.componentType not in _COMPONENTS or a.type not in _WIDTH:
        raise _bad(path, f"accessor {i} has component type {a.componentType} / type {a.type}")
    n, w = int(a.count), _WIDTH[a.type]
    if a.bufferView is None:
        out = np.zeros((n, w), dt)
    else:
        data, stride = _view(path, g, blob, a.bufferView)
        off = a.byteOffset or 0
        stride = stride or dt.itemsize * w
        need = off + (n - 1) * stride + dt.itemsize * w if n else 0
        if need > len(data):
            raise _bad(path, f"accessor {i} runs past the end of its bufferView")
        out = np.ndarray((n, w), dt, buffer=data, offset=off, strides=(stride, dt.itemsize)).copy()
    if a.normalized and np.issubdtype(dt, np.integer):
        out = np.maximum(out.astype(np.float64) / np.iinfo(dt).max, -1.0)
    return out


def _local(node) -> np.ndarray:
    if node.matrix is not None and len(node.matrix) == 16:
        return np.array(node.matrix, np.float64).reshape(4, 4).T  # column-major in the file
    M = np.eye(4)
    if node.scale is not None:
        M = np.diag(list(node.scale) + [1.0])
    if node.rotation is not None:
        x, y, z, w = node.rotation
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3] = R
        M = T @ M
    if node.translation is not None:
        T = np.eye(4)
        T[:3, 3] = node.translation
        M = T @ M
    return M


def world_matrices(path, g) -> dict:
    """{node index: world matrix (row-major 4×4, p' = M p)} of the nodes of the file's scene (``scene``,
    else the first), in traversal order (depth first, the scene's root order)."""
    if not g.scenes:
        roots = [i for i in range(len(g.nodes)) if not any(i in (n.children or []) for n in g.nodes)]
    else:
        k = g.scene if g.scene is not None else 0
        if not 0 <= k < len(g.scenes):
            raise _bad(path, f"its default scene {k} does not exist")
        roots = list(g.scenes[k].nodes or [])
    out, stack = {}, [(i, np.eye(4)) for i in reversed(roots)]
    while stack:
        i, parent = stack.pop()
        if not 0 <= i < len(g.nodes) or i in out:
            raise _bad(path, f"node {i} is missing or appears twice in the node hierarchy")
        out[i] = parent @ _local(g.nodes[i])
        stack.extend((c, out[i]) for c in reversed(g.nodes[i].children or []))
    return out


def _node_index(path, g, node) -> int:
    if isinstance(node, int) and 0 <= node < len(g.nodes):
        return node
    if isinstance(node, str):
        hits = [i for i, n in enumerate(g.nodes) if n.name == node]
        if len(hits) == 1:
            return hits[0]
    meshes = ", ".join(str(n.name or i) for i, n in enumerate(g.nodes) if n.mesh is not None)
    raise SceneError(f"{path}: no node {node!r} with a mesh (give a node index, or the name of exactly one node); "
                     f"its mesh nodes: {meshes}")


def mesh_arrays(path, node, primitive=None, to_world=None):
    """(positions N×3, normals N×3, uvs N×2, faces M×3) of one mesh node's triangle primitive
    (``primitive`` None: all of them, concatenated), float64 in world space: the node's world
    matrix, then ``to_world`` (4×4, the scene shape's own transform) applied. Normals: the file's
    ``NORMAL`` (area-weighted face normals without one); uvs: ``TEXCOORD_0`` (zeros without)."""
    g, blob = read_file(path)
    p = Path(path)
    i = _node_index(p, g, node)
    mats = world_matrices(p, g)
    if i not in mats or g.nodes[i].mesh is None:
        raise SceneError(f"{p}: node {node!r} has no mesh in the file's scene")
    M = mats[i] if to_world is None else np.asarray(to_world, np.float64) @ mats[i]
    prims = g.meshes[g.nodes[i].mesh].primitives
    chosen = range(len(prims)) if primitive is None else [int(primitive)]
    P, N, UV, F, off = [], [], [], [], 0
    for k in chosen:
        if not 0 <= k < len(prims):
            raise SceneError(f"{p}: node {node!r} has {len(prims)} primitive(s), no primitive {k}")
        pr = prims[k]
        mode = 4 if pr.mode is None else pr.mode
        if mode != 4:
            raise SceneError(f"{p}: node {node!r} primitive {k} has mode {_MODES.get(mode, mode)}; shadowlab reads "
                             "triangle lists (mode TRIANGLES) only: re-export with triangulated meshes")
        if pr.attributes.POSITION is None:
            raise _bad(p, f"node {node!r} primitive {k} has no POSITION")
        pos = _accessor(p, g, blob, pr.attributes.POSITION).astype(np.float64)
        idx = (_accessor(p, g, blob, pr.indices).reshape(-1).astype(np.int64) if pr.indices is not None
               else np.arange(len(pos)))
        if len(idx) % 3 or (len(idx) and (idx.min() < 0 or idx.max() >= len(pos))):
            raise _bad(p, f"node {node!r} primitive {k} has indices that are not triangles of its vertices")
        f = idx.reshape(-1, 3)
        nrm = (_accessor(p, g, blob, pr.attributes.NORMAL).astype(np.float64) if pr.attributes.NORMAL is not None
               else _vertex_normals(pos, f))
        uv = (_accessor(p, g, blob, pr.attributes.TEXCOORD_0).astype(np.float64)
              if pr.attributes.TEXCOORD_0 is not None else np.zeros((len(pos), 2)))
        P.append(pos), N.append(nrm), UV.append(uv), F.append(f + off)
        off += len(pos)
    P, N = np.concatenate(P), np.concatenate(N)
    if not np.array_equal(M, np.eye(4)):  # identity: the file's float32 values exactly
        P = P @ M[:3, :3].T + M[:3, 3]
        N = N @ np.linalg.inv(M[:3, :3])
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
        if np.linalg.det(M[:3, :3]) < 0:  # a mirroring transform turns the winding around
            F = [f[:, [0, 2, 1]] for f in F]
    return P, N, np.concatenate(UV), np.concatenate(F)


def _vertex_normals(P, F) -> np.ndarray:
    g = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
    N = np.zeros_like(P)
    for c in range(3):
        np.add.at(N, F[:, c], g)
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)


# -- the scene document -------------------------------------------------------------------------


def _name(raw, fallback: str, taken: set) -> str:
    """A name of the scene format (letters, digits, '_', '-', starting with a letter, no '__'),
    unique among ``taken``."""
    s = re.sub(r"[^A-Za-z0-9_-]", "_", str(raw or ""))
    s = re.sub(r"_{2,}", "_", s).strip("_")
    if not s or not s[0].isalpha():
        s = fallback + (f"_{s}" if s else "")
    base, k = s, 2
    while s in taken:
        s, k = f"{base}_{k}", k + 1
    taken.add(s)
    return s


def _extras(obj) -> dict:
    e = getattr(obj, "extras", None)
    return e.get(EXTRAS_KEY, {}) if isinstance(e, dict) and isinstance(e.get(EXTRAS_KEY), dict) else {}


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "shadowlab" / "gltf-images"


def _image_file(path, g, blob, tex: int) -> str:
    """The file of texture ``tex``'s image: the file a .gltf names, or an embedded image stored once
    in the cache by its SHA-256 (content-addressed: the same bytes give the same path)."""
    t = g.textures[tex]
    img = g.images[t.source] if t.source is not None and 0 <= t.source < len(g.images) else None
    if img is None:
        raise _bad(path, f"texture {tex} has no image")
    if img.uri is not None and not img.uri.startswith("data:"):
        return str((Path(path).parent / img.uri).resolve())
    if img.uri is not None:
        head, _, b64 = img.uri.partition(",")
        data, mime = base64.b64decode(b64), head[5:].split(";")[0]
    else:
        data, _ = _view(path, g, blob, img.bufferView)
        mime = img.mimeType
    ext = {"image/png": ".png", "image/jpeg": ".jpg"}.get(mime)
    if ext is None:
        raise SceneError(f"{path}: texture {tex} is a {mime} image; shadowlab reads PNG and JPEG alpha textures: "
                         "re-export the file with PNG textures")
    d = _cache_dir()
    f = d / (hashlib.sha256(data).hexdigest() + ext)
    if not f.is_file():
        d.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=d, prefix=".img-", suffix=ext)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, f)
    return str(f)


def _shapes(path, g, blob, mats: dict) -> list:
    out, taken = [], set()
    for i, M in mats.items():
        node = g.nodes[i]
        if node.mesh is None:
            continue
        ex = _extras(node)
        prims = g.meshes[node.mesh].primitives
        for k, pr in enumerate(prims):
            raw = ex.get("shape") or node.name or g.meshes[node.mesh].name
            name = _name(raw if len(prims) == 1 else f"{raw}_{k}", f"mesh{i}", taken)
            t = {"name": name, "type": "gltf", "filename": str(Path(path).resolve()), "node": i}
            if len(prims) > 1:
                t["primitive"] = k
            t.update(_material(path, g, blob, pr.material, name))
            if ex.get("casts_shadows") is False:  # drawn but casting no shadow (shadowlab's own export)
                t["casts_shadows"] = False
            if t.pop("_invisible", False):
                continue
            out.append(t)
    return out


def _material(path, g, blob, m, name: str) -> dict:
    """The shape keys a primitive's material gives (glTF's default material without one)."""
    if m is None:
        return {"albedo": [1.0, 1.0, 1.0], "two_sided": False}
    mat = g.materials[m]
    ex = _extras(mat)
    pbr = mat.pbrMetallicRoughness
    f = list(pbr.baseColorFactor) if pbr is not None and pbr.baseColorFactor else [1.0, 1.0, 1.0, 1.0]
    t = {"albedo": ex.get("albedo") or [min(1.0, max(0.0, float(c))) for c in f[:3]],
         "two_sided": bool(mat.doubleSided)}
    if mat.alphaMode == "MASK":
        cut = 0.5 if mat.alphaCutoff is None else float(mat.alphaCutoff)
        tex = pbr.baseColorTexture if pbr is not None else None
        if tex is None:  # a constant alpha: all there, or nothing
            if len(f) > 3 and f[3] < cut:
                return {"_invisible": True}
        else:
            if (tex.texCoord or 0) != 0:
                raise SceneError(f"{path}: material {mat.name or m} (shape {name}) reads its alpha at TEXCOORD_"
                                 f"{tex.texCoord}; shadowlab reads alpha textures at TEXCOORD_0")
            t["alpha_texture"] = _image_file(path, g, blob, tex.index)
            t["alpha_cutoff"] = min(1.0, max(0.0, cut))
    for k in ("transmittance", "opacity"):
        if k in ex:
            t[k] = ex[k]
    return t


def _camera(path, g, mats: dict, notes: list):
    for i, M in mats.items():
        node = g.nodes[i]
        if node.camera is None:
            continue
        ex = _extras(node)
        if isinstance(ex.get("camera"), dict):
            return dict(ex["camera"])
        cam = g.cameras[node.camera]
        if cam.type != "perspective" or cam.perspective is None:
            raise SceneError(f"{path}: camera {cam.name or node.camera} is {cam.type}; shadowlab's truth has a "
                             "perspective camera: give the file a perspective camera, or a [camera] table in "
                             f"{sidecar_path(path).name}")
        pe = cam.perspective
        aspect = pe.aspectRatio
        W = DEFAULT_WIDTH
        H = max(1, round(W / aspect)) if aspect else DEFAULT_WIDTH
        R = M[:3, :3]
        pos = M[:3, 3]
        fwd = -R[:, 2] / np.linalg.norm(R[:, 2])
        up = R[:, 1] / np.linalg.norm(R[:, 1])
        t = {"position": pos.tolist(), "target": (pos + fwd).tolist(), "up": up.tolist(), "yfov": float(pe.yfov),
             "near": float(pe.znear)}
        if pe.zfar is not None:
            t["far"] = float(pe.zfar)
        t["resolution"] = [W, H]
        notes.append(f"camera.resolution = [{W}, {H}]")
        return t
    return None


def _fov_x(cam: dict) -> dict:
    """Turn a glTF ``yfov`` into the scene format's horizontal ``fov`` at the camera's resolution."""
    if "yfov" in cam:
        W, H = cam["resolution"]
        cam["fov"] = math.degrees(2 * math.atan(math.tan(cam.pop("yfov") / 2) * W / H))
    return cam


def _lights(path, g, mats: dict, fixed=frozenset()) -> list:
    """The file's lights as ``[[lights]]`` tables; ``fixed``: names whose sidecar table sets the
    cone (``angle``) or another ``kind``, so a spot cone shadowlab cannot take is not refused."""
    khr = ((g.extensions or {}).get("KHR_lights_punctual") or {}).get("lights") or []
    out, taken = [], set()
    for i, M in mats.items():
        node = g.nodes[i]
        ref = ((node.extensions or {}).get("KHR_lights_punctual") or {}).get("light")
        if ref is None:
            continue
        if not isinstance(ref, int) or not 0 <= ref < len(khr):
            raise _bad(path, f"node {i} names KHR_lights_punctual light {ref!r}, which does not exist")
        ex = _extras(node)
        if isinstance(ex.get("light"), dict):
            t = dict(ex["light"])
            t["name"] = _name(t.get("name"), f"light{i}", taken)
            out.append(t)
            continue
        lt = khr[ref]
        typ = lt.get("type")
        name = _name(node.name or lt.get("name"), f"light{i}", taken)
        pos = M[:3, 3]
        fwd = -M[:3, 2] / np.linalg.norm(M[:3, 2])
        color = [float(c) for c in lt.get("color", [1.0, 1.0, 1.0])]
        value = float(lt.get("intensity", 1.0))
        if typ == "directional":
            t = {"name": name, "kind": "directional", "direction": fwd.tolist(), "irradiance": value}
        elif typ == "point":
            t = {"name": name, "kind": "point", "position": pos.tolist(), "intensity": value}
        elif typ == "spot":
            outer = math.degrees(float((lt.get("spot") or {}).get("outerConeAngle", math.pi / 4)))
            if not 1.0 <= outer <= 80.0 and name not in fixed:
                raise SceneError(f"{path}: spot light {name!r} has an outer cone of {outer:.1f}°; shadowlab's spot "
                                 f"lights take 1-80°: set angle in a [[lights]] table named {name!r} in "
                                 f"{sidecar_path(path).name}, or change the cone in the file")
            t = {"name": name, "kind": "spot", "position": pos.tolist(), "target": (pos + fwd).tolist(),
                 "angle": outer, "intensity": value}
        else:
            raise SceneError(f"{path}: KHR_lights_punctual light {ref} has type {typ!r}; shadowlab reads directional, "
                             "point and spot lights")
        t["color"] = color
        if "range" in lt and typ != "directional":
            t["range"] = float(lt["range"])
        t["_from_gltf"] = True
        out.append(t)
    return out


def _merge_light(t: dict, s: dict, light_keys: dict) -> dict:
    """A sidecar ``[[lights]]`` table ``s`` over the file's light ``t``: its keys win; emission keys
    replace the file's; keys the (new) kind does not take, which came from the file, are dropped."""
    t = dict(t)
    if any(k in s for k in _EMISSION_KEYS):
        for k in _EMISSION_KEYS:
            t.pop(k, None)
    t.update(s)
    kind = t.get("kind")
    if kind in light_keys and t.get("_from_gltf"):
        t = {k: v for k, v in t.items() if k in light_keys[kind] or k in s or k == "_from_gltf"}
    return t


def _read_sidecar(path: Path) -> dict:
    sc = sidecar_path(path)
    if not sc.is_file():
        return {}
    try:
        data = tomllib.loads(sc.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{sc}: not valid TOML ({e}); fix the syntax at the position given") from None
    allowed = ("name", "description", "truth_allocation", "camera", "lights", "shapes")
    for k in data:
        if k not in allowed:
            raise SceneError(f"{sc}: key {k!r} is not taken by a glTF's sidecar; it takes {', '.join(allowed)} "
                             "(in the scene format)")
    for k in ("lights", "shapes"):
        if k in data and (not isinstance(data[k], list) or not all(isinstance(x, dict) for x in data[k])):
            raise SceneError(f"{sc}: {k}: expected [[{k}]] tables")
    if "camera" in data and not isinstance(data["camera"], dict):
        raise SceneError(f"{sc}: camera: expected a [camera] table")
    return data


def _by_name(items: list, extra: list, merge) -> list:
    out = [dict(x) for x in items]
    index = {x.get("name"): n for n, x in enumerate(out)}
    for s in extra:
        n = index.get(s.get("name"))
        if n is None:
            out.append(dict(s))
        else:
            out[n] = merge(out[n], s)
    return out


def scene_document(path, *, light_keys: dict) -> dict:
    """The scene-format document of a ``.glb`` / ``.gltf`` file and its sidecar (the module's
    docstring says what comes from where); ``light_keys``: the keys each light kind takes
    (:data:`shadowlab.scene.spec.LIGHT_KEYS`). SceneError (exit 2) for a file without lights or
    camera that its sidecar does not give, and for what shadowlab cannot read."""
    p = Path(path)
    g, blob = read_file(p)
    mats = world_matrices(p, g)
    top = _extras(g)
    side = _read_sidecar(p)
    notes: list = []
    doc = {"name": f"{top['scene']}-gltf" if top.get("scene") else p.stem}
    if not top.get("scene") and "name" not in side:
        notes.append(f"name = {p.stem!r}")
    for k in ("description", "truth_allocation"):
        if k in top:
            doc[k] = top[k]
    for k in ("name", "description", "truth_allocation"):
        if k in side:
            doc[k] = side[k]
    cam = _camera(p, g, mats, notes)
    if "camera" in side:
        if cam is not None and "resolution" in side["camera"]:
            notes[:] = [n for n in notes if not n.startswith("camera.resolution")]
        cam = {**(cam or {}), **side["camera"]}
    if cam is None:
        raise SceneError(f"{p}: the glTF has no camera (no node with a camera in its scene); add a perspective camera "
                         f"to the file, or a [camera] table (position, target, fov, resolution) to "
                         f"{sidecar_path(p)}")
    doc["camera"] = _fov_x(cam)
    fixed = {t.get("name") for t in side.get("lights", []) if "angle" in t or t.get("kind", "spot") != "spot"}
    from_file = _lights(p, g, mats, fixed)
    named = {s.get("name") for s in side.get("lights", [])}
    delta = [t["name"] for t in from_file if t.get("_from_gltf") and t["name"] not in named]
    if delta:
        notes.append(f"lights {', '.join(delta)} are delta lights (glTF lights have no size)")
    lights = _by_name(from_file, side.get("lights", []), lambda t, s: _merge_light(t, s, light_keys))
    if not lights:
        raise SceneError(f"{p}: the glTF has no lights (no KHR_lights_punctual light on a node of its scene); add "
                         f"lights to the file (KHR_lights_punctual), or [[lights]] tables to {sidecar_path(p)}")
    doc["lights"] = [{k: v for k, v in t.items() if k != "_from_gltf"} for t in lights]
    shapes = _by_name(_shapes(p, g, blob, mats), side.get("shapes", []), lambda t, s: {**t, **s})
    if not shapes:
        raise SceneError(f"{p}: the glTF has no triangle meshes in its scene; add meshes to the file, or [[shapes]] "
                         f"to {sidecar_path(p)}")
    doc["shapes"] = shapes
    _show_defaults(p, notes)
    return doc


def _show_defaults(path: Path, notes: list) -> None:
    key = str(path.resolve())
    if notes and key not in _shown_defaults:
        _shown_defaults.add(key)
        print(f"note: {path}: defaults used ({'; '.join(notes)}); set them in {sidecar_path(path).name} "
              "(docs/exchange.md, glTF)", file=sys.stderr)
