"""A second, independent renderer for the exchange tests: plain numpy ray casting of an export.

It reads only the files ``shadowlab export`` writes (``scene.json``, ``camera.json``,
``lights.json`` and the PLY meshes, with its own PLY parser) and nothing of shadowlab, Mitsuba or
Dr.Jit: camera rays through the pixel centres from ``camera.json``'s ``world_to_clip`` matrix,
Möller–Trumbore ray/triangle tests, and k×k jittered samples on a rectangle or disk light (its
``to_world``) per round, R independent rounds. Per pixel it estimates

* ``A``: the visible fraction of the light's area (mean of v),
* ``V``: the ratio of shadowed to unshadowed direct light of a diffuse receiver,
  Σ G v / Σ G with G = max(0, n·ω) · max(0, −n_l·ω) / r²,
* ``U`` and ``shaded``: unshadowed and shadowed outgoing radiance of the diffuse receiver,
  ρ/π · L_e · area · mean(G [· v]) (uniform area sampling, pdf = 1/area),

each with the standard error of its mean over the R rounds.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


# ----------------------------------------------------------------------------------------- PLY
_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2", "ushort": "u2",
              "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4", "int32": "i4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path):
    """(positions V×3, normals V×3 or None, faces F×3) of a binary little-endian PLY with triangle
    faces, parsed from its own header (property names, types and order)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header") + len(b"end_header")
    end = data.index(b"\n", end) + 1
    header = data[:end].decode("ascii").splitlines()
    fmt = next(ln.split()[1] for ln in header if ln.startswith("format"))
    elements = []
    for ln in header:
        t = ln.split()
        if t and t[0] == "element":
            elements.append({"name": t[1], "count": int(t[2]), "props": []})
        elif t and t[0] == "property":
            elements[-1]["props"].append(t[1:])
    body = data[end:]
    assert fmt == "binary_little_endian", fmt  # what the export writes (scene.json's convention)
    offset = 0
    cols = {}
    faces = None
    for el in elements:
        if el["name"] == "face":
            (_, count_t, index_t, _name), = el["props"]
            dt = np.dtype([("n", "<" + _PLY_TYPES[count_t]), ("i", "<" + _PLY_TYPES[index_t], (3,))])
            f = np.frombuffer(body, dt, el["count"], offset)
            assert (f["n"] == 3).all(), "triangles only"
            faces = f["i"].astype(np.int64)
            offset += dt.itemsize * el["count"]
        else:
            dt = np.dtype([(p[-1], "<" + _PLY_TYPES[p[0]]) for p in el["props"]])
            v = np.frombuffer(body, dt, el["count"], offset)
            offset += dt.itemsize * el["count"]
            if el["name"] == "vertex":
                cols = {n: v[n].astype(np.float64) for n in dt.names}
    assert offset == len(body), "the header does not describe the body"
    names = list(cols)
    arr = np.stack([cols[n] for n in names], 1)
    ix = {n: i for i, n in enumerate(names)}
    P = arr[:, [ix["x"], ix["y"], ix["z"]]]
    N = arr[:, [ix["nx"], ix["ny"], ix["nz"]]] if "nx" in ix else None
    return P, N, faces


# ------------------------------------------------------------------------------------- geometry
class Triangles:
    """All triangles of a set of meshes, with per-vertex normals and the mesh each belongs to."""

    def __init__(self, meshes):
        self.names = [n for n, _ in meshes]
        tri, nrm, owner = [], [], []
        for k, (_, (P, N, F)) in enumerate(meshes):
            tri.append(P[F])
            if N is None:
                g = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
                N3 = np.repeat((g / np.linalg.norm(g, axis=1, keepdims=True))[:, None], 3, 1)
            else:
                N3 = N[F]
            nrm.append(N3)
            owner.append(np.full(len(F), k))
        self.tri = np.concatenate(tri)            # T×3×3
        self.nrm = np.concatenate(nrm)            # T×3×3
        self.owner = np.concatenate(owner)        # T
        self.v0 = self.tri[:, 0]
        self.e1 = self.tri[:, 1] - self.v0
        self.e2 = self.tri[:, 2] - self.v0
        g = np.cross(self.e1, self.e2)
        self.ng = g / np.linalg.norm(g, axis=1, keepdims=True)

    def intersect(self, o, d, tmax, chunk: int = 1 << 15, any_hit: bool = False):
        """Closest hit (t, triangle, b1, b2) per ray with eps < t < tmax (Möller–Trumbore);
        triangle −1 = miss. ``any_hit``: only whether there is one (bool array)."""
        n = len(o)
        best_t = np.full(n, np.inf)
        best_i = np.full(n, -1, np.int64)
        best_b = np.zeros((n, 2))
        hit_any = np.zeros(n, bool)
        eps = 1e-9
        for s in range(0, n, chunk):
            oo, dd, tm = o[s:s + chunk, None, :], d[s:s + chunk, None, :], tmax[s:s + chunk, None]
            p = np.cross(dd, self.e2[None])
            det = np.einsum("rtk,tk->rt", p, self.e1)
            ok = np.abs(det) > 1e-14
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tv = oo - self.v0[None]
            b1 = np.einsum("rtk,rtk->rt", tv, p) * inv
            q = np.cross(tv, self.e1[None])
            b2 = np.einsum("rtk,rtk->rt", np.broadcast_to(dd, q.shape), q) * inv
            t = np.einsum("tk,rtk->rt", self.e2, q) * inv
            good = ok & (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (t > eps) & (t < tm)
            if any_hit:
                hit_any[s:s + chunk] = good.any(1)
                continue
            t = np.where(good, t, np.inf)
            i = np.argmin(t, 1)
            r = np.arange(len(i))
            best_t[s:s + chunk] = t[r, i]
            hit = np.isfinite(t[r, i])
            best_i[s:s + chunk] = np.where(hit, i, -1)
            best_b[s:s + chunk] = np.stack([b1[r, i], b2[r, i]], 1)
        if any_hit:
            return hit_any
        return best_t, best_i, best_b


# ------------------------------------------------------------------------------------- the scene
def load_export(d):
    """Everything the caster needs from an export directory."""
    d = Path(d)
    manifest = json.loads((d / "scene.json").read_text())
    cam = json.loads((d / "camera.json").read_text())
    lights = {l["name"]: l for l in json.loads((d / "lights.json").read_text())["lights"]}
    shapes = [(s["name"], read_ply(d / s["ply"])) for s in manifest["shapes"]]
    light_meshes = [(f"light:{n}", read_ply(d / l["ply"])) for n, l in lights.items() if l["ply"]]
    albedo = np.array([s["albedo"] for s in manifest["shapes"]] + [[0.0, 0.0, 0.0]] * len(light_meshes))
    return {"manifest": manifest, "camera": cam, "lights": lights, "albedo": albedo,
            "n_shapes": len(shapes), "tris": Triangles(shapes + light_meshes)}


def camera_rays(cam, offset: float = 0.5):
    """Origins and unit directions of the rays through the pixel centres (``offset`` = 0.5; 0 =
    the pixels' top-left corners), row-major from the top left, from ``world_to_clip`` alone
    (two points per pixel: on the near and the far plane)."""
    W, H = cam["resolution"]
    j, i = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    x = 2 * (i.ravel() + offset) / W - 1
    y = 1 - 2 * (j.ravel() + offset) / H
    inv = np.linalg.inv(np.array(cam["world_to_clip"]))

    def unproject(z):
        c = np.stack([x, y, np.full_like(x, z), np.ones_like(x)], 1) @ inv.T
        return c[:, :3] / c[:, 3:]

    a, b = unproject(0.0), unproject(0.999)
    dvec = b - a
    return a, dvec / np.linalg.norm(dvec, axis=1, keepdims=True)


def sample_light(light, u):
    """Points, normals and the area of a rect or disk light for samples u ∈ [0, 1)²."""
    M = np.array(light["to_world"])
    if light["kind"] == "rect":
        local = np.stack([2 * u[..., 0] - 1, 2 * u[..., 1] - 1], -1)
    elif light["kind"] == "disk" or (light["kind"] == "spot" and light["size"]["radius"] > 0):
        r, phi = np.sqrt(u[..., 0]), 2 * np.pi * u[..., 1]
        local = np.stack([r * np.cos(phi), r * np.sin(phi)], -1)
    else:
        raise NotImplementedError(f"the numpy caster samples rect and disk lights, not {light['kind']}")
    p = local[..., 0:1] * M[:3, 0] + local[..., 1:2] * M[:3, 1] + M[:3, 3]
    nl = np.array(light["pose"])[:3, 2]
    return p, nl, float(light["area_m2"])


def render(export_dir, light_name: str, k: int = 8, rounds: int = 8, seed: int = 1, pixel_offset: float = 0.5):
    """Per-pixel estimates (H×W): V, V_se, A, A_se, U (H×W×3), shaded (H×W×3), shaded_se,
    mask (hit a non-emitting shape), depth (distance from the camera's position)."""
    sc = load_export(export_dir)
    cam, light, tris = sc["camera"], sc["lights"][light_name], sc["tris"]
    W, H = cam["resolution"]
    o, d = camera_rays(cam, pixel_offset)
    t, ti, b = tris.intersect(o, d, np.full(len(o), np.inf))
    hit = ti >= 0
    mask = hit & (tris.owner[np.maximum(ti, 0)] < sc["n_shapes"])
    idx = np.nonzero(mask)[0]
    p = o[idx] + t[idx, None] * d[idx]
    tri = ti[idx]
    ng = tris.ng[tri]
    bb = b[idx]
    ns = ((1 - bb[:, :1] - bb[:, 1:]) * tris.nrm[tri, 0] + bb[:, :1] * tris.nrm[tri, 1] + bb[:, 1:] * tris.nrm[tri, 2])
    ns /= np.linalg.norm(ns, axis=1, keepdims=True)
    facing = np.einsum("ij,ij->i", ng, d[idx]) > 0  # two-sided surfaces: the side the camera sees
    ng = np.where(facing[:, None], -ng, ng)
    ns = np.where((np.einsum("ij,ij->i", ns, d[idx]) > 0)[:, None], -ns, ns)
    albedo = sc["albedo"][tris.owner[tri]]
    Le = np.array(light["emission"]["rgb"])
    rng = np.random.default_rng(seed)
    n = len(idx)
    sv, sv2, sa, sa2, sg, sgv, sgv2 = (np.zeros(n) for _ in range(7))
    sj, sj2 = np.zeros(n), np.zeros(n)
    kk = k * k
    for r in range(rounds):
        cell = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2)
        u = (cell[None] + rng.random((n, kk, 2))) / k                  # n×kk×2 jittered strata
        y, nl, area = sample_light(light, u)
        w = y - p[:, None]
        dist = np.linalg.norm(w, axis=-1)
        wd = w / dist[..., None]
        G = (np.maximum(0, np.einsum("nk,nsk->ns", ns, wd)) * np.maximum(0, -wd @ nl) / dist ** 2)
        orig = np.repeat(p + 1e-5 * ng, kk, 0)
        blocked = tris.intersect(orig, wd.reshape(-1, 3), (dist * (1 - 1e-5)).reshape(-1), any_hit=True)
        v = (~blocked).reshape(n, kk).astype(np.float64)
        v = np.where(G > 0, v, 1.0)  # as Mitsuba: a sample carrying no light is not traced
        gsum = G.sum(1)
        Vr = np.where(gsum > 0, (G * v).sum(1) / np.where(gsum > 0, gsum, 1), 1.0)
        Ar = v.mean(1)
        Jr = area * (G * v).mean(1)   # ∫ G v dA for this round
        sv, sv2 = sv + Vr, sv2 + Vr * Vr
        sa, sa2 = sa + Ar, sa2 + Ar * Ar
        sg, sj, sj2 = sg + area * G.mean(1), sj + Jr, sj2 + Jr * Jr

    def mean_se(s, s2):
        m = s / rounds
        var = np.maximum(s2 / rounds - m * m, 0) * rounds / max(rounds - 1, 1)
        return m, np.sqrt(var / rounds)

    V, V_se = mean_se(sv, sv2)
    A, A_se = mean_se(sa, sa2)
    J, J_se = mean_se(sj, sj2)
    Ug = sg / rounds
    k_rad = albedo / np.pi * Le                                           # n×3: ρ/π · L_e
    eye = np.array(cam["camera_to_world"])[:3, 3]
    depth = np.zeros(H * W)
    depth[idx] = np.linalg.norm(p - eye, axis=1)
    out = {"mask": mask.reshape(H, W), "depth": depth.reshape(H, W)}

    def img(x, fill):
        a = np.full((H * W,) + x.shape[1:], fill, np.float64)
        a[idx] = x
        return a.reshape((H, W) + x.shape[1:])

    out.update(V=img(V, 1.0), V_se=img(V_se, 0.0), A=img(A, 1.0), A_se=img(A_se, 0.0),
               U=img(k_rad * Ug[:, None], 0.0), shaded=img(k_rad * J[:, None], 0.0),
               shaded_se=img(k_rad * J_se[:, None], 0.0))
    return out
