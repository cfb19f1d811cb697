"""Triangle meshes of the scene's Mitsuba shapes, in world space (metres).

One function, :func:`triangulate`, takes one Mitsuba shape dict as :mod:`shadowlab.scene.build`
and :mod:`shadowlab.scene.lights` make it (so the transforms have one source of truth) and returns
world-space positions, unit normals, uvs and triangles:

| Mitsuba type | canonical shape (before ``to_world``)    | triangles                                   | uv (as Mitsuba's)       |
|--------------|------------------------------------------|---------------------------------------------|-------------------------|
| rectangle    | [−1, 1]² in z = 0, normal +z             | 2, exact                                    | ((x+1)/2, (y+1)/2)      |
| disk         | radius 1 in z = 0, normal +z             | ``segments`` (a fan), vertices on the rim   | (r, φ/2π)               |
| sphere       | radius 1 (or ``center`` + ``radius``)    | 2·s·(s/2) of a UV sphere (poles on ±z), s = ``segments``, vertices on the sphere | (φ/2π, θ/π) |
| cylinder     | radius 1, z ∈ [0, 1], open               | 2·``segments``, vertices on the surface     | (φ/2π, z)               |
| cube, ply, obj | Mitsuba's own mesh, read back after loading | as loaded (``face_normals``: unwelded, flat normals) | as loaded |
| gltf         | the file's primitive (:mod:`.gltf_file`)  | as in the file (its ``NORMAL``)              | its ``TEXCOORD_0``       |

Curved surfaces are inscribed (every vertex lies on the surface); the largest distance between
a tessellated sphere / cylinder / disk rim and the true surface is r·(1 − cos(π/s)) (the
sagitta of one segment: 0.12 % of the radius at s = 64). Normals: the exact surface normal
at each vertex (smooth shading), transformed by the inverse transpose of ``to_world``.
Triangles wind counter-clockwise around their normal (``cross(v1 − v0, v2 − v0)`` points the
same way as the surface normal).
"""  # noqa: E501

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from ..errors import SceneError

from .build import shape_dicts
from .gltf_file import mesh_arrays
from .lights import mitsuba_dict as light_dict

__all__ = ["triangulate", "matrix_of", "sagitta", "scene_triangles", "panel_triangles", "shape_mesh"]


def sagitta(segments: int) -> float:
    """Largest distance from an inscribed s-gon to its unit circle: 1 − cos(π/s)."""
    return 1.0 - math.cos(math.pi / segments)


def matrix_of(transform) -> np.ndarray:
    """A Mitsuba ScalarTransform4f (or a 4×4 array) -> numpy float64 4×4 (row-major: p' = M @ p)."""
    m = getattr(transform, "matrix", transform)
    return np.array(m, dtype=np.float64).reshape(4, 4)


def _apply(M, P, N):
    P = np.asarray(P, np.float64)
    N = np.asarray(N, np.float64)
    Pw = P @ M[:3, :3].T + M[:3, 3]
    Nw = N @ np.linalg.inv(M[:3, :3])  # inverse transpose, applied to row vectors
    Nw /= np.maximum(np.linalg.norm(Nw, axis=1, keepdims=True), 1e-30)
    return Pw, Nw


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a (rows+1)×(cols+1) vertex grid, index = r·(cols+1) + c (wound
    by :func:`_oriented` afterwards)."""
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a = (r * (cols + 1) + c).ravel()
    b, d, e = a + 1, a + cols + 1, a + cols + 2
    return np.concatenate([np.stack([a, b, d], 1), np.stack([b, e, d], 1)])


def _rectangle():
    P = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    N = np.tile([0.0, 0.0, 1.0], (4, 1))
    UV = (P[:, :2] + 1) / 2
    return P, N, UV, np.array([[0, 1, 2], [0, 2, 3]])


def _disk(s: int):
    phi = np.linspace(0.0, 2 * math.pi, s + 1)  # the seam vertex is duplicated (u = 0 and 1)
    rim = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], 1)
    P = np.concatenate([np.zeros((s, 3)), rim])  # a centre vertex per wedge (its uv's v = mid-wedge φ/2π)
    N = np.tile([0.0, 0.0, 1.0], (2 * s + 1, 1))
    mid = (phi[:-1] + phi[1:]) / 2
    UV = np.stack([np.concatenate([np.zeros(s), np.ones(s + 1)]), np.concatenate([mid, phi]) / (2 * math.pi)], 1)
    i = np.arange(s)
    return P, N, UV, np.stack([i, s + i, s + i + 1], 1)


def _sphere(s: int):
    nt = max(2, s // 2)
    theta = np.linspace(0.0, math.pi, nt + 1)
    phi = np.linspace(0.0, 2 * math.pi, s + 1)
    T, F = np.meshgrid(theta, phi, indexing="ij")
    P = np.stack([np.sin(T) * np.cos(F), np.sin(T) * np.sin(F), np.cos(T)], -1).reshape(-1, 3)
    UV = np.stack([F / (2 * math.pi), T / math.pi], -1).reshape(-1, 2)
    faces = _grid_faces(nt, s)
    # drop the degenerate triangles at the poles (two vertices at the same pole)
    A, B, C = P[faces[:, 0]], P[faces[:, 1]], P[faces[:, 2]]
    faces = faces[np.linalg.norm(np.cross(B - A, C - A), axis=1) > 1e-12]
    return P, P.copy(), UV, faces


def _cylinder(s: int):
    phi = np.linspace(0.0, 2 * math.pi, s + 1)
    Z, F = np.meshgrid(np.array([0.0, 1.0]), phi, indexing="ij")
    P = np.stack([np.cos(F), np.sin(F), Z], -1).reshape(-1, 3)
    N = np.stack([np.cos(F), np.sin(F), np.zeros_like(F)], -1).reshape(-1, 3)
    UV = np.stack([F / (2 * math.pi), Z], -1).reshape(-1, 2)
    return P, N, UV, _grid_faces(1, s)


def _oriented(P, N, F):
    """Wind every triangle counter-clockwise around its vertices' mean normal."""
    A, B, C = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    g = np.cross(B - A, C - A)
    flip = np.einsum("ij,ij->i", g, N[F].sum(1)) < 0
    F = F.copy()
    F[flip] = F[flip][:, [0, 2, 1]]
    return F


def _mitsuba_mesh(d: dict):
    """Load one mesh shape (cube / ply / obj) with Mitsuba and read its world-space buffers."""
    dd = {k: v for k, v in d.items() if k not in ("bsdf", "emitter")}
    try:
        mesh = mi.load_dict(dd)
    except Exception as e:
        raise SceneError(f"Mitsuba could not load the {d.get('type')} shape for export: {e}") from e
    P = np.array(mesh.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    F = np.array(mesh.faces_buffer(), np.int64).reshape(-1, 3)
    UV = (np.array(mesh.vertex_texcoords_buffer(), np.float64).reshape(-1, 2)
          if mesh.has_vertex_texcoords() else np.zeros((len(P), 2)))
    if mesh.has_vertex_normals() and not d.get("face_normals", False):
        N = np.array(mesh.vertex_normals_buffer(), np.float64).reshape(-1, 3)
        return P, N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30), UV, F
    # flat shading: one vertex per corner, the face normal on all three
    A, B, C = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    g = np.cross(B - A, C - A)
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-30)
    idx = F.reshape(-1)
    return P[idx], np.repeat(g, 3, axis=0), UV[idx], np.arange(len(idx)).reshape(-1, 3)


def triangulate(d: dict, segments: int = 64):
    """(positions N×3, normals N×3, uvs N×2, faces M×3) of one Mitsuba shape dict, world space."""
    if segments < 3:
        raise SceneError(f"tessellation needs at least 3 segments, got {segments}")
    t = d.get("type")
    if t in ("cube", "ply", "obj"):
        return _mitsuba_mesh(d)
    if t == "gltf":  # the glTF's own triangles and normals, wound as the file winds them
        return mesh_arrays(d["filename"], d["node"], d.get("primitive"), matrix_of(d["to_world"]))
    if t == "rectangle":
        P, N, UV, F = _rectangle()
    elif t == "disk":
        P, N, UV, F = _disk(segments)
    elif t == "sphere":
        P, N, UV, F = _sphere(segments)
    elif t == "cylinder":
        P, N, UV, F = _cylinder(segments)
    else:
        raise SceneError(f"cannot triangulate a Mitsuba shape of type {t!r}")
    if "to_world" in d:
        M = matrix_of(d["to_world"])
    else:
        M = np.eye(4)
    if t == "sphere" and ("center" in d or "radius" in d):  # Mitsuba: to_world · translate(center) · scale(radius)
        c, r = np.asarray(d.get("center", (0, 0, 0)), np.float64), float(d.get("radius", 1.0))
        S = np.diag([r, r, r, 1.0])
        S[:3, 3] = c
        M = M @ S
    Pw, Nw = _apply(M, P, N)
    return Pw, Nw, UV, _oriented(Pw, Nw, F)


def shape_mesh(shape, segments: int = 64):
    """(positions, normals, uvs, faces) of one ShapeSpec as one mesh, world space: the triangulation
    of each Mitsuba shape it becomes (a capped cylinder: tube and two caps), concatenated in that
    order (what ``export`` writes as the shape's PLY and glTF mesh)."""
    P, N, UV, F, off = [], [], [], [], 0
    for d in shape_dicts(shape).values():
        p, n, uv, f = triangulate(d, segments)
        P.append(p), N.append(n), UV.append(uv), F.append(f + off)
        off += len(p)
    return np.concatenate(P), np.concatenate(N), np.concatenate(UV), np.concatenate(F)


def scene_triangles(spec, segments: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Every triangle of the scene's shapes that cast shadows (``spec.shapes`` with ``casts_shadows``;
    the lights' own emitting shapes are not among them: :func:`panel_triangles`), world space:
    (T×3×3 float64 vertices, T int shape index into ``spec.shapes``). Rectangles and cubes are exact,
    PLY/OBJ meshes as Mitsuba loads them, curved primitives inscribed with ``segments`` segments (the
    table above)."""
    tris, owner = [], []
    for k, s in enumerate(spec.shapes):
        if not s.casts_shadows:
            continue
        for d in shape_dicts(s).values():
            P, _, _, F = triangulate(d, segments)
            tris.append(P[F])
            owner.append(np.full(len(F), k, np.int32))
    if not tris:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int32)
    return np.concatenate(tris), np.concatenate(owner)


def panel_triangles(spec, segments: int = 64, *, exclude: str | None = None) -> np.ndarray:
    """The triangles (T×3×3, world) of the panels of the lights that cast shadows (``casts_shadows``),
    but light ``exclude``'s own (a light never shadows itself); none by default."""
    tris = []
    for light in spec.lights:
        if light.casts_shadows and light.has_panel and light.name != exclude:
            P, _, _, F = triangulate(light_dict(light, (0.0, 0.0, 0.0), 1.0)[1], segments)
            tris.append(P[F])
    return np.concatenate(tris) if tris else np.zeros((0, 3, 3))
