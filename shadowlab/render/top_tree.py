"""TOP trees: exact point-light visibility from partitioned shadow volumes [Gerhards 2015],
[Mora 2016], as [Wang 2022, §1.2] (Algorithms 1 and 2) uses them.

Every triangle T = (v0, v1, v2) of the scene gives four planes, 4-vectors (n, d) with
value(x) = n·x + d at a point x, unit n, and the light in homogeneous coordinates
L = (l, w) (w = 1: a point at l; w = 0: a light at infinity in direction l):

* three *shadow planes*, one per edge (a, b): the plane through a, b and the light,
  n ∝ (b − a) × (l − w·a), d = −n·a, oriented so that T lies on its negative side;
* one *capping plane*, T's own plane, oriented so that the light lies on its positive side.

"Positive" is the side the light can reach. T's shadow volume is the negative side of all four.

A node is a plane and three links, positive / intersecting / negative (−1: an empty leaf).
A triangle's subtree is the chain of its three shadow planes, each linked to the next by its
negative link, then its capping plane.

**Algorithm 1 (build).** A triangle descends from the root, taking at each node the link of its
side of that node's plane, until it reaches an empty link. It then hangs its subtree there.
A triangle that reaches a capping plane's negative side is dropped: it lies wholly in the shadow of
that plane's triangle and adds no shadow.

The build is level-synchronous: every pending triangle takes one step per round, all of them at
once, with no loop over triangles or nodes. Where several triangles reach the same empty link in
the same round, the first in insertion order takes it and the others descend into its subtree in
the next round. Every triangle that reaches a link reaches it in the round equal to the link's
depth, so the tree is the one sequential insertion in that order builds. :func:`build_top_tree`
runs the rounds as Dr.Jit kernels on the device (a frame's tree never passes through the host; the
count of triangles left is read once per :data:`ROUNDS_PER_READ` rounds on a GPU);
:func:`build_top_tree_numpy` runs them in numpy and is the reference the device build is tested
against, node for node.

Insertion order (``order``):

* ``random`` (the default): a fixed pseudo-random permutation. As with keys inserted into a binary
  search tree, a spatially coherent order builds a deep, list-like tree whose queries visit many
  nodes, and a random one a shallow tree.
* ``light``: nearest to the light first. It drops more triangles wholly in shadow, but on a
  heightfield it is a sweep across the scene.
* ``scene``: as given, usually a sweep as well.

The visibility does not depend on the order; the size and depth of the tree, and the nodes a query
visits, do (``shadowlab bench --only dpsv``).

A triangle's side of a plane is taken with a tolerance ε_b = 1e-9·R (R the largest |vertex|
about the tree's origin). Neighbours sharing an edge therefore see that edge's vertices as on
the plane, and are sorted by their third vertex.

**Algorithm 2 (query)**, per point with a stack, in one Dr.Jit loop over all points:

* pop a node;
* at a shadow plane, push the intersecting child and the child on the point's side;
* at a capping plane, a point on the negative side is in shadow (0); otherwise push the
  intersecting and positive children;
* an empty stack means lit (1).

Empty links are not pushed. The stack is a :func:`drjit.alloc_local` buffer with room for the
tree's depth + 1 entries (a pop pushes at most two children one level deeper), rounded up to a
power of two so that similar trees share a kernel.

The query point is the surface point moved off its surface toward the light by Mitsuba's own
shadow-ray offset, (1 + max|p_i|)·``RAY_EPSILON`` along the geometric normal. An occluder
closer to the surface than that is missed by both, so the visibility equals a Mitsuba shadow ray's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .replay import replayed

__all__ = ["TopTree", "Triangles", "build_top_tree", "build_top_tree_numpy", "upload_triangles", "triangle_planes",
           "query", "RAY_EPSILON", "ORDERS"]

#: Mitsuba's ``math::RayEpsilon<float>`` (1500 · 2⁻²⁴): a shadow ray leaves its surface this far
#: (times 1 + the largest coordinate) along the normal.
RAY_EPSILON = 1500.0 * 2.0 ** -24
#: insertion orders of :func:`build_top_tree`
ORDERS = ("random", "light", "scene")
#: seed of the ``random`` insertion order (fixed: the tree is part of the technique's definition)
ORDER_SEED = 0x70B
_LEAF = -1


class TopTree:
    """A built TOP tree. ``planes[k]`` = (n, d) of node k about ``origin`` (world = origin + x);
    ``cap[k]``: a capping plane; ``child[k]`` = (positive, intersecting, negative) node indices,
    −1 for an empty leaf; ``level[k]``: node k's depth (the root is 1); ``near[k]``: a lower bound
    of the light distance (point light) or light-space depth (directional) of every triangle in
    node k's subtree, the "deep" part of the query [Mora 2016] (None: not built). ``depth``: most
    nodes on a root-to-leaf path. Counts: ``triangles`` (inserted), ``dropped`` (wholly in another's
    shadow), ``degenerate`` (no area, or the light in their plane: no shadow volume); ``extent``:
    the largest |d| of its planes.

    The node arrays live where the tree was built: :func:`build_top_tree` leaves them on the device
    (numpy copies are read back when first asked for), :func:`build_top_tree_numpy` in numpy
    (uploaded by :meth:`arrays` when first queried)."""

    _FIELDS = ("planes", "cap", "child", "level", "near")

    def __init__(self, *, origin, light, depth: int, triangles: int, dropped: int, degenerate: int, rounds: int,
                 seconds: float, nodes: int, extent: float, host: dict | None = None, device: dict | None = None):
        self.origin, self.light = np.asarray(origin, np.float64), np.asarray(light, np.float64)
        self.depth, self.triangles, self.dropped, self.degenerate = int(depth), int(triangles), int(dropped), \
            int(degenerate)
        self.rounds, self.seconds, self.nodes, self.extent = int(rounds), float(seconds), int(nodes), float(extent)
        self._host, self._device, self._dr = host, device, None

    def _numpy(self, name: str):
        if self._host is None:
            d = self._device
            self._host = {"planes": np.stack([np.asarray(p.numpy(), np.float64) for p in d["planes"]], -1)
                          .reshape(-1, 4),
                          "cap": np.asarray(d["cap"].numpy(), bool).reshape(-1),
                          "child": np.stack([np.asarray(c.numpy(), np.int32) for c in d["child"]], -1).reshape(-1, 3),
                          "level": np.asarray(d["level"].numpy(), np.uint32).reshape(-1),
                          "near": np.asarray(d["near"].numpy(), np.float64).reshape(-1)}
        return self._host[name]

    planes = property(lambda self: self._numpy("planes"))
    cap = property(lambda self: self._numpy("cap"))
    child = property(lambda self: self._numpy("child"))
    level = property(lambda self: self._numpy("level"))
    near = property(lambda self: self._numpy("near"))

    def stats(self) -> dict:
        """JSON-able size and build figures."""
        return {"nodes": self.nodes, "depth": self.depth, "triangles": self.triangles, "dropped": self.dropped,
                "degenerate": self.degenerate, "build_rounds": self.rounds, "build_seconds": self.seconds}

    def arrays(self) -> dict:
        """The tree as the query reads it, Dr.Jit arrays (made once): plane components (float32),
        links, the capping flag, levels and the subtrees' nearest distances (float32)."""
        if self._dr is None:
            if self._device is not None:
                d = self._device
                pl, near = [mi.Float(p) for p in d["planes"]], d["near"]
                cap, child, level = d["cap"], d["child"], d["level"]
            else:
                h = self._host
                p32 = np.ascontiguousarray(h["planes"].astype(np.float32))
                pl = [mi.Float(np.ascontiguousarray(p32[:, c])) for c in range(4)]
                cap, level = mi.Bool(h["cap"]), mi.UInt32(h["level"])
                child = [mi.Int32(np.ascontiguousarray(h["child"][:, j])) for j in range(3)]
                near = None if h["near"] is None else mi.Float64(h["near"])
            self._dr = {"a": pl[0], "b": pl[1], "c": pl[2], "d": pl[3], "cap": cap,
                        "p": child[0], "i": child[1], "n": child[2], "level": level}
            if near is not None:
                self._dr["near"] = mi.Float(near)
            dr.eval(*self._dr.values())
        return self._dr


def _unit_planes(n, d):
    """Normalise planes (n, d) to unit normals; returns (n, d, |n| before)."""
    ln = np.linalg.norm(n, axis=-1)
    s = 1.0 / np.maximum(ln, 1e-300)
    return n * s[..., None], d * s, ln


def triangle_planes(V: np.ndarray, light: np.ndarray):
    """(planes T×4×4: shadow planes of edges v0v1, v1v2, v2v0 then the capping plane, degenerate T
    bool) of triangles ``V`` (T×3×3, about the tree's origin) for the homogeneous ``light`` (l, w)."""
    V = np.asarray(V, np.float64)
    l, w = np.asarray(light[:3], np.float64), float(light[3])
    out = np.zeros((len(V), 4, 4))
    bad = np.zeros(len(V), bool)
    scale = max(float(np.abs(V).max(initial=0.0)), 1e-30)
    for e in range(3):
        a, b, c = V[:, e], V[:, (e + 1) % 3], V[:, (e + 2) % 3]
        n = np.cross(b - a, l[None] - w * a)
        d = -np.einsum("ij,ij->i", n, a)
        n, d, ln = _unit_planes(n, d)
        side = np.einsum("ij,ij->i", n, c) + d
        flip = side > 0
        n[flip], d[flip] = -n[flip], -d[flip]
        bad |= (ln <= 1e-24 * scale * scale) | (np.abs(side) <= 1e-12 * scale)
        out[:, e, :3], out[:, e, 3] = n, d
    n = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    d = -np.einsum("ij,ij->i", n, V[:, 0])
    n, d, ln = _unit_planes(n, d)
    at_light = n @ l + d * w
    flip = at_light < 0
    n[flip], d[flip] = -n[flip], -d[flip]
    bad |= (ln <= 1e-24 * scale * scale) | (np.abs(at_light) <= 1e-12 * (scale if w else 1.0))
    out[:, 3, :3], out[:, 3, 3] = n, d
    return out, bad


def _insertion_order(V, light, order):
    if isinstance(order, np.ndarray):
        return np.asarray(order, np.int64)
    if order == "scene":
        return np.arange(len(V))
    if order == "random":
        return np.random.default_rng(ORDER_SEED).permutation(len(V))
    l, w = light[:3], light[3]
    if w:
        key = np.linalg.norm(V - l, axis=-1).min(1)
    else:
        key = -(V @ l).max(1)  # farthest along the direction toward the light first
    return np.argsort(key, kind="stable")


def build_top_tree_numpy(V: np.ndarray, light, *, origin=None, order="random") -> TopTree:
    """Algorithm 1 over the triangles ``V`` (T×3×3 world-space vertices) for ``light`` in numpy on
    the host: the reference :func:`build_top_tree` (on the device) is tested against, node for node.
    ``light``: a point (x, y, z, 1) or a direction toward a light at infinity (x, y, z, 0).
    ``order``: ``random`` (a fixed permutation), ``light`` (nearest first), ``scene`` (as given) or
    an array permutation of the triangles."""
    t0 = time.perf_counter()
    light = np.asarray(light, np.float64)
    V = np.asarray(V, np.float64)
    if origin is None:
        origin = light[:3] if light[3] else (V.reshape(-1, 3).min(0) + V.reshape(-1, 3).max(0)) / 2
    origin = np.asarray(origin, np.float64)
    Vo = V - origin
    lo = np.concatenate([light[:3] - origin * light[3], light[3:]])
    planes, bad = triangle_planes(Vo, lo)
    seq = _insertion_order(Vo, lo, order)
    seq = seq[~bad[seq]]
    eps = 1e-9 * max(float(np.abs(Vo).max(initial=0.0)), 1e-30)
    cap_n = 4 * len(seq)
    P = np.zeros((cap_n, 4))
    is_cap = np.zeros(cap_n, bool)
    child = np.full((cap_n, 3), _LEAF, np.int64)
    depth = np.zeros(cap_n, np.int64)
    owner = np.zeros(cap_n, np.int64)
    used = 0

    def hang(tri, parent_depth):
        """Allocate the 4-node subtrees of triangles ``tri``; returns their roots."""
        nonlocal used
        k = len(tri)
        base = used + 4 * np.arange(k)
        for j in range(4):
            P[base + j] = planes[tri, j]
            depth[base + j] = parent_depth + 1 + j
            owner[base + j] = tri
        for j in range(3):
            child[base + j, 2] = base + j + 1
        is_cap[base + 3] = True
        used += 4 * k
        return base

    rounds = dropped = 0
    if len(seq):
        hang(seq[:1], 0)
        pend = seq[1:]
        node = np.zeros(len(pend), np.int64)
        while len(pend):
            rounds += 1
            pl = P[node]
            vals = np.einsum("tvk,tk->tv", Vo[pend], pl[:, :3]) + pl[:, 3:4]
            pos = (vals > eps).any(1)
            neg = (vals < -eps).any(1)
            link = np.where(pos & ~neg, 0, np.where(neg & ~pos, 2, 1))
            drop = is_cap[node] & (link == 2)
            nxt = child[node, link]
            down = (nxt != _LEAF) & ~drop
            node[down] = nxt[down]
            c = np.nonzero((nxt == _LEAF) & ~drop)[0]
            done = drop.copy()
            if len(c):
                key = node[c] * 3 + link[c]
                uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
                win = c[first]
                roots = hang(pend[win], depth[uk // 3])
                child[uk // 3, uk % 3] = roots
                node[c] = roots[inv.ravel()]
                done[win] = True
            dropped += int(drop.sum())
            pend, node = pend[~done], node[~done]
    near = subtree_near(triangle_near(Vo, lo)[owner[:used]], child[:used], depth[:used])
    return TopTree(host={"planes": P[:used].copy(), "cap": is_cap[:used].copy(), "child": child[:used].astype(np.int32),
                         "level": depth[:used].astype(np.uint32), "near": near},
                   nodes=used, extent=float(np.abs(P[:used, 3]).max(initial=0.0)), origin=origin, light=lo,
                   depth=int(depth[:used].max(initial=0)), triangles=used // 4, dropped=dropped,
                   degenerate=int(bad.sum()), rounds=rounds, seconds=time.perf_counter() - t0)


def light_distance(x, light):
    """The distance from the light (a point light, w = 1) or the depth along its rays (a light at
    infinity, w = 0) of points ``x`` (numpy (…, 3) or Dr.Jit Point3f, about the tree's origin)."""
    l, w = light[:3], float(light[3])
    if isinstance(x, np.ndarray):
        return np.linalg.norm(x - l, axis=-1) if w else -(x @ (l / np.linalg.norm(l)))
    if w:
        return dr.norm(x - mi.Point3f(*[float(c) for c in l]))
    d = l / np.linalg.norm(l)
    return -dr.dot(mi.Vector3f(x), mi.Vector3f(*[float(c) for c in d]))


def triangle_near(V: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Per triangle a lower bound of :func:`light_distance` over its points: for a light at infinity
    the smallest of its vertices' depths (exact: the depth is linear), for a point light the distance
    to its bounding sphere about the centroid."""
    if light[3] == 0.0:
        return light_distance(V, light).min(axis=1)
    c = V.mean(axis=1)
    r = np.linalg.norm(V - c[:, None], axis=-1).max(axis=1)
    return np.maximum(light_distance(c, light) - r, 0.0)


def subtree_near(own: np.ndarray, child: np.ndarray, level: np.ndarray) -> np.ndarray:
    """The minimum of ``own`` over each node and its descendants (children sit one level deeper:
    a pass per level, deepest first, over all the nodes of that level at once)."""
    near = own.astype(np.float64).copy()
    for lv in range(int(level.max(initial=0)), 0, -1):
        k = np.nonzero(level == lv)[0]
        for j in range(3):
            c = child[k, j]
            has = c >= 0
            near[k[has]] = np.minimum(near[k[has]], near[c[has]])
    return near


def stack_size(tree: TopTree) -> int:
    """Room the query's stack needs (depth + 1), rounded up to a power of two (≥ 16)."""
    return max(16, 1 << int(tree.depth).bit_length())        # 2^bits(depth) > depth


def offset_point(tree: TopTree, p, ng):
    """The query point of surface point ``p`` (world, Dr.Jit) with geometric normal ``ng``:
    moved by Mitsuba's shadow-ray offset toward the light, about the tree's origin. The origin and
    the light enter opaquely: another light reuses the kernel."""
    def vec(a, kind):
        return kind(*[dr.opaque(mi.Float, float(x)) for x in a])

    o = vec(tree.origin, mi.Point3f)
    if tree.light[3]:
        to_light = o + vec(tree.light[:3], mi.Vector3f) - p
    else:
        to_light = vec(tree.light[:3], mi.Vector3f)
    ng = mi.Vector3f(ng)
    mag = (1.0 + dr.max(dr.abs(p))) * RAY_EPSILON
    mag = dr.mulsign(mag, dr.dot(ng, to_light))
    return mi.Point3f(dr.fma(mag, ng, p)) - o


def query(tree: TopTree, x, active=True, deep: bool = True):
    """Algorithm 2 at points ``x`` (Dr.Jit Point3f about ``tree.origin``, e.g. from
    :func:`offset_point`) where ``active``: (visibility Float, 1 lit / 0 shadowed; nodes visited
    UInt32; the deepest level visited, UInt32). Inactive points and an empty tree give 1, 0, 0.
    ``deep``: a node whose subtree's triangles all lie farther from the light than the point
    (:attr:`TopTree.near`) cannot shadow it and is skipped with its subtree [Mora 2016]."""
    m = dr.width(x)
    if tree.nodes == 0:
        return dr.full(mi.Float, 1.0, m), dr.zeros(mi.UInt32, m), dr.zeros(mi.UInt32, m)
    A = tree.arrays()
    size = stack_size(tree)
    stack = dr.alloc_local(mi.Int32, size, dr.zeros(mi.Int32, m))
    sp = dr.select(active, dr.full(mi.UInt32, 1, m), 0)  # width m: loop state must not broadcast
    vis = dr.full(mi.Float, 1.0, m)
    visits = dr.zeros(mi.UInt32, m)
    deepest = dr.zeros(mi.UInt32, m)
    deep = deep and "near" in A
    if deep:   # a margin of float rounding: prune only what lies clearly beyond the point
        dx = light_distance(x, tree.light) + 1e-6 * (1.0 + tree.extent)

    def body(sp, vis, visits, deepest, stack):
        sp = dr.maximum(sp, 1) - 1  # lanes already done still run the body in a packet: keep indices in range
        n = stack.read(sp)
        val = (dr.gather(mi.Float, A["a"], n) * x.x + dr.gather(mi.Float, A["b"], n) * x.y
               + dr.gather(mi.Float, A["c"], n) * x.z + dr.gather(mi.Float, A["d"], n))
        cap = dr.gather(mi.Bool, A["cap"], n)
        live = (dx >= dr.gather(mi.Float, A["near"], n)) if deep else mi.Bool(True)
        shadow = live & cap & (val < 0.0)
        vis = dr.select(shadow, 0.0, vis)
        ci = dr.gather(mi.Int32, A["i"], n)
        side = dr.select(cap | (val > 0.0), dr.gather(mi.Int32, A["p"], n), dr.gather(mi.Int32, A["n"], n))
        push_i = live & ~shadow & (ci >= 0)
        stack.write(ci, sp, push_i)
        sp = dr.select(push_i, sp + 1, sp)
        push_s = live & ~shadow & (side >= 0)
        stack.write(side, sp, push_s)
        sp = dr.select(push_s, sp + 1, sp)
        sp = dr.select(shadow, 0, sp)
        deepest = dr.maximum(deepest, dr.gather(mi.UInt32, A["level"], n))
        return sp, vis, visits + 1, deepest, stack

    _, vis, visits, deepest, _ = dr.while_loop((sp, vis, visits, deepest, stack), lambda sp, *_: sp > 0, body,
                                               labels=("sp", "vis", "visits", "deepest", "stack"),
                                               label="top_tree_query")
    return vis, visits, deepest


# ----------------------------------------------------------------------------------------------
# Algorithm 1 on the device

@dataclass(frozen=True)
class Triangles:
    """Triangles uploaded once (:func:`upload_triangles`): ``v[i]`` the world position of vertex i
    of every triangle (mi.Point3d), ``host`` the same T×3×3 float64 numpy array (the ``light``
    insertion order sorts on it), ``lo`` / ``hi`` their bounds."""

    v: tuple
    host: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return len(self.host)


def upload_triangles(V) -> Triangles:
    """``V`` (T×3×3 world vertices) as :class:`Triangles` on the device, made once per scene."""
    V = np.ascontiguousarray(np.asarray(V, np.float64).reshape(-1, 3, 3))
    v = tuple(mi.Point3d(*(mi.Float64(np.ascontiguousarray(V[:, i, c])) for c in range(3))) for i in range(3))
    dr.eval(v)
    flat = V.reshape(-1, 3)
    lo, hi = (flat.min(0), flat.max(0)) if len(flat) else (np.zeros(3), np.zeros(3))
    return Triangles(v, V, lo, hi)


def _dot(a, b):
    """a·b summed x, y, z in turn (numpy's order for three terms; no fused multiply-add on LLVM)."""
    return (a.x * b.x + a.y * b.y) + a.z * b.z


def _cross(a, b):
    """a × b written out as numpy's ``cross`` computes it (Dr.Jit's own uses fused multiply-subtracts)."""
    return type(a)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x)


def _device_planes(v, l, w: float, scale):
    """:func:`triangle_planes` on the device: ([[n.x, n.y, n.z, d] for each of the 4 planes], degenerate)
    of the triangles ``v`` (3 mi.Point3d about the tree's origin); ``scale``: their largest |coordinate|."""
    F = mi.Float64
    lv = mi.Vector3d(*[F(float(c)) for c in l])
    out, bad = [], dr.zeros(mi.Bool, dr.width(v[0]))

    def unit(n, d):
        ln = dr.sqrt(_dot(n, n))
        s = 1.0 / dr.maximum(ln, 1e-300)
        return n * s, d * s, ln

    for e in range(3):
        a, b, c = v[e], v[(e + 1) % 3], v[(e + 2) % 3]
        n = _cross(mi.Vector3d(b - a), lv - w * mi.Vector3d(a))
        n, d, ln = unit(n, -_dot(n, a))
        side = _dot(n, c) + d
        flip = side > 0
        n, d = dr.select(flip, -n, n), dr.select(flip, -d, d)
        bad |= (ln <= 1e-24 * scale * scale) | (dr.abs(side) <= 1e-12 * scale)
        out.append([n.x, n.y, n.z, d])
    n = _cross(mi.Vector3d(v[1] - v[0]), mi.Vector3d(v[2] - v[0]))
    n, d, ln = unit(n, -_dot(n, v[0]))
    at_light = _dot(n, lv) + d * w
    flip = at_light < 0
    n, d = dr.select(flip, -n, n), dr.select(flip, -d, d)
    bad |= (ln <= 1e-24 * scale * scale) | (dr.abs(at_light) <= 1e-12 * (scale if w else 1.0))
    out.append([n.x, n.y, n.z, d])
    return out, bad


def _device_near(v, light):
    """:func:`triangle_near` on the device (Float64 per triangle)."""
    l, w = np.asarray(light[:3], np.float64), float(light[3])
    if w == 0.0:
        u = l / np.linalg.norm(l)
        uv = mi.Vector3d(*[float(c) for c in u])
        return dr.minimum(dr.minimum(-_dot(mi.Vector3d(v[0]), uv), -_dot(mi.Vector3d(v[1]), uv)),
                          -_dot(mi.Vector3d(v[2]), uv))
    c = (v[0] + v[1] + v[2]) / 3.0

    def norm(a):
        a = mi.Vector3d(a)
        return dr.sqrt(_dot(a, a))
    r = dr.maximum(dr.maximum(norm(v[0] - c), norm(v[1] - c)), norm(v[2] - c))
    return dr.maximum(norm(c - mi.Point3d(*[float(x) for x in l])) - r, 0.0)


def _read(*values) -> list:
    """Width-1 device values read back together (one wait): Python ints."""
    return [int(x) for x in dr.concat([mi.Float64(x) for x in values]).numpy()]


def _hang(tree, planes, tri, base, parent_depth, active, key=None):
    """Write the 4-node subtrees of triangles ``tri`` (where ``active``) at nodes base … base + 3:
    its three shadow planes chained by their negative links, then its capping plane; and, given the
    ``key`` of the empty link each was taken at, the link to its subtree. ``planes``: the four
    planes' (n.x, n.y, n.z, d) as 4 arrays of 4·T, plane j of triangle t at j·T + t.

    One scatter per array of the tree over the 4 nodes of every triangle (lane j·m + i: node j of
    triangle i): Dr.Jit evaluates pending work before a second scatter into an array, so a scatter
    per node would be a kernel per node."""
    Pn, is_cap, child, depth, owner = tree
    I32, U32 = mi.Int32, mi.UInt32
    m = dr.width(tri)
    lane = dr.arange(U32, 4 * m)
    j = lane // m
    i = lane - j * m
    t, b = dr.gather(I32, tri, i), dr.gather(I32, base, i)
    act = dr.gather(mi.Bool, active, i)
    k = U32(b + I32(j))
    src = j * U32(dr.width(planes[0]) // 4) + U32(t)
    for c in range(4):
        dr.scatter(Pn[c], dr.gather(mi.Float64, planes[c], src, act), k, act)
    dr.scatter(depth, dr.gather(I32, parent_depth, i) + 1 + I32(j), k, act)
    dr.scatter(owner, t, k, act)
    dr.scatter(is_cap, True, k, act & (j == 3))
    # nodes 0-2 link on to the next by their negative link; lane 3 writes the parent's link to node 0
    chain = j < 3
    if key is None:
        dr.scatter(child, b + I32(j) + 1, U32(b + I32(j)) * 3 + 2, act & chain)
    else:
        dr.scatter(child, dr.select(chain, b + I32(j) + 1, b),
                   dr.select(chain, U32(b + I32(j)) * 3 + 2, U32(dr.gather(I32, key, i))), act)


def _round(tree, planes, win, links, lane, tri, Vp, node, alive, used, eps):
    """One round of the build: every pending triangle (``alive``) steps down one link of ``tree``;
    the first in insertion order (the lowest ``lane``) to reach an empty link takes it; ``used``:
    the nodes in use (width 1). Returns the triangles' nodes and pending flags after the round,
    (dropped, 0, triangles left) as a UInt32 array of 3 on the device, and the subtrees hung (a
    width-1 UInt32 not yet evaluated: the caller's read or totals evaluate it). A round with nothing
    pending changes nothing."""
    I32, U32, F = mi.Int32, mi.UInt32, mi.Float64
    Pn, is_cap, child, depth, _ = tree
    counts = dr.zeros(U32, 3)
    pl = [dr.gather(F, Pn[c], node, alive) for c in range(4)]
    n_pl = mi.Vector3d(pl[0], pl[1], pl[2])
    vals = [_dot(p, n_pl) + pl[3] for p in Vp]
    pos = (vals[0] > eps) | (vals[1] > eps) | (vals[2] > eps)
    neg = (vals[0] < -eps) | (vals[1] < -eps) | (vals[2] < -eps)
    link = dr.select(pos & ~neg, I32(0), dr.select(neg & ~pos, I32(2), I32(1)))
    drop = alive & dr.gather(mi.Bool, is_cap, node, alive) & (link == 2)
    key = node * 3 + link
    nxt = dr.gather(I32, child, key, alive)
    cand = alive & ~drop & (nxt == _LEAF)
    node = dr.select(alive & ~drop & (nxt != _LEAF), nxt, node)
    dr.scatter_reduce(dr.ReduceOp.Min, win, lane, U32(key), cand)
    dr.scatter_reduce(dr.ReduceOp.Add, counts, U32(1), U32(0), drop)
    alive = alive & ~drop
    dr.eval(node, alive, key, cand, win, counts)
    # nothing pending may still read the tree when it is written below: Dr.Jit would copy every array
    # a pending gather reads before scattering into it (copy on write), megabytes per round
    del pl, n_pl, vals, pos, neg, link, drop, nxt
    # the links taken this round (a winner, still empty) in index order: their subtrees' slots
    taken = U32((win != 0xFFFFFFFF) & (dr.gather(I32, child, links) == _LEAF))
    slot = dr.prefix_sum(taken)
    last = dr.width(links) - 1
    hung = dr.gather(U32, slot, U32(last)) + dr.gather(U32, taken, U32(last))   # read with the caller's totals
    base = used + 4 * I32(dr.gather(U32, slot, U32(key), cand))
    first = cand & (dr.gather(U32, win, U32(key), cand) == lane)
    parent_depth = dr.gather(I32, depth, node, cand)
    dr.eval(base, first, parent_depth)
    _hang(tree, planes, tri, base, parent_depth, first, key)
    node = dr.select(cand, base, node)
    alive = alive & ~first
    dr.scatter_reduce(dr.ReduceOp.Add, counts, U32(1), U32(2), alive)
    dr.eval(node, alive, tree, counts)
    return node, alive, counts, hung


def _rounds(k: int, tree, planes, win, links, lane, tri, Vp, node, alive, totals, eps):
    """``k`` rounds (:func:`_round`) in a row with nothing read on the host: ``totals`` (UInt32, 4)
    carries (dropped, nodes in use, rounds with a triangle pending, triangles left) from round to
    round on the device. Returns the nodes, pending flags and totals after the ``k`` rounds."""
    U32 = mi.UInt32
    for _ in range(k):
        busy = dr.gather(U32, totals, U32(3)) > 0
        node, alive, counts, hung = _round(tree, planes, win, links, lane, tri, Vp, node, alive,
                                           mi.Int32(dr.gather(U32, totals, U32(1))), eps)
        dropped, left = dr.gather(U32, counts, U32(0)), dr.gather(U32, counts, U32(2))
        totals = dr.ravel(mi.Vector4u(dr.gather(U32, totals, U32(0)) + dropped,
                                      dr.gather(U32, totals, U32(1)) + 4 * hung,
                                      dr.gather(U32, totals, U32(2)) + dr.select(busy, U32(1), U32(0)), left))
        dr.eval(totals)
    return node, alive, totals


def _subtree_near(top: int, near, depth, child):
    """Each node's ``near`` lowered to the least over its subtree: level by level from the deepest
    (``top``) up, one kernel a level."""
    F = mi.Float64
    for lv in range(top, 0, -1):
        here = depth == lv
        m = near
        for j in range(3):
            has = here & (child[j] >= 0)
            m = dr.select(has, dr.minimum(m, dr.gather(F, near, child[j], has)), m)
        near = dr.select(here, m, near)
        dr.eval(near)
    return near


#: rounds run between two reads of the triangles left: on a GPU, one replayed stage (a round with
#: nothing pending launches its kernels but changes nothing); on the CPU rounds are traced, one by one
ROUNDS_PER_READ = 8
#: rounds the last GPU build of a tree of each capacity took: the next build of that capacity runs as
#: many (rounded up to ROUNDS_PER_READ) before its first read, so a tree built again (a new frame, a
#: light moved a little) waits for the device once rather than once per ROUNDS_PER_READ
_LAST_ROUNDS: dict = {}


class _Builds:
    """The owner of the build rounds' recordings (:func:`~shadowlab.render.replay.replayed`): they read
    no Mitsuba scene, only the tree's own arrays, so they live with the process (least recently used
    dropped first)."""


_BUILDS = _Builds()


def build_top_tree(V, light, *, origin=None, order="random") -> TopTree:
    """Algorithm 1 over the triangles ``V`` (T×3×3 world-space vertices, or :class:`Triangles`
    already on the device) for ``light``: a point (x, y, z, 1) or a direction toward a light at
    infinity (x, y, z, 0), on the device. ``order``: ``random`` (a fixed permutation), ``light``
    (nearest first), ``scene`` (as given) or an array permutation of the triangles.

    The rounds of :func:`build_top_tree_numpy` as Dr.Jit kernels over every pending triangle at
    once: a triangle descends one link per round; the first in insertion order to reach an empty
    link takes it (a ``Min`` scatter-reduction over the links), and the links taken in a round get
    their subtrees in the order of their index (a prefix sum over the links), as numpy's sorted
    ``unique`` gives them, so the tree is the reference's node for node. One wait per
    :data:`ROUNDS_PER_READ` rounds on a GPU (the first after as many rounds as the last build of the
    tree's capacity took), per round on the CPU (how many triangles are left), and one at the start
    (which triangles are degenerate)."""
    t0 = time.perf_counter()
    tris = V if isinstance(V, Triangles) else upload_triangles(V)
    light = np.asarray(light, np.float64)
    if origin is None:
        origin = light[:3] if light[3] else (tris.lo + tris.hi) / 2
    origin = np.asarray(origin, np.float64)
    lo = np.concatenate([light[:3] - origin * light[3], light[3:]])
    T = len(tris)
    I32, U32, F = mi.Int32, mi.UInt32, mi.Float64
    o = mi.Point3d(*[float(c) for c in origin])
    v = tuple(p - o for p in tris.v)
    if T:
        scale = dr.max(dr.maximum(dr.maximum(dr.max(dr.abs(v[0])), dr.max(dr.abs(v[1]))), dr.max(dr.abs(v[2]))))
        scale_h = float(dr.maximum(scale, 1e-30)[0])
    else:
        scale_h = 1e-30
    planes, bad = _device_planes(v, lo[:3], float(lo[3]), scale_h)
    planes = [dr.concat([planes[j][c] for j in range(4)]) for c in range(4)]   # plane j of triangle t at j·T + t
    if isinstance(order, np.ndarray):
        perm = I32(np.asarray(order, np.int32))
    elif order == "random":
        perm = I32(np.random.default_rng(ORDER_SEED).permutation(T).astype(np.int32))
    elif order == "scene":
        perm = dr.arange(I32, T)
    else:
        perm = I32(_insertion_order(tris.host - origin, lo, order).astype(np.int32))
    seq = dr.gather(I32, perm, dr.compress(~dr.gather(mi.Bool, bad, perm)))
    n_seq = dr.width(seq) if T else 0
    eps = 1e-9 * scale_h
    cap_n = 4 * n_seq
    Pn = [dr.zeros(F, cap_n) for _ in range(4)]
    is_cap = dr.zeros(mi.Bool, cap_n)
    child = dr.full(I32, _LEAF, 3 * cap_n)
    depth = dr.zeros(I32, cap_n)
    owner = dr.zeros(I32, cap_n)

    rounds = dropped = used = 0
    tree = (Pn, is_cap, child, depth, owner)
    if n_seq:
        _hang(tree, planes, dr.gather(I32, seq, I32(0)), I32(0), I32(0), mi.Bool(True))
        used = 4
    if n_seq > 1:
        M = n_seq - 1
        lane = dr.arange(U32, M)
        tri = dr.gather(I32, seq, lane + 1)
        Vp = [dr.gather(mi.Point3d, p, tri) for p in v]
        # opaque, not literal: the first round then has the inputs' layout of the later ones (one recording)
        node = dr.opaque(I32, 0, M)
        alive = dr.opaque(mi.Bool, True, M)
        win = dr.opaque(U32, 0xFFFFFFFF, 3 * cap_n)
        links = dr.arange(I32, 3 * cap_n)
        eps_dr = dr.opaque(F, eps)
        dr.eval(planes, tri, Vp, node, alive, win, links, tree)
        # on a GPU ROUNDS_PER_READ rounds are one recording per tree size, replayed for the later rounds and
        # frames (the tree's arrays are its only inputs: a replay walks no Mitsuba scene), which spares the
        # host the tracing that costs more there than the rounds' kernels, and the host reads how many
        # triangles are left once per recording; on the CPU a replay copies the arrays it writes (Dr.Jit
        # protects a frozen function's inputs): the traced round is the faster, its counts read after each
        if mi.variant().startswith("cuda"):
            k = ROUNDS_PER_READ
            totals = dr.opaque(U32, 0, 4) + U32(0, 4, 0, M)   # dropped, nodes in use, rounds, triangles left
            dr.eval(totals)
            left, run = M, 0
            ahead = max(k, -(-_LAST_ROUNDS.get(cap_n, 0) // k) * k)
            while left:
                node, alive, totals = replayed("top_tree_round", (cap_n, ahead), _rounds, _BUILDS, ahead, tree,
                                               planes, win, links, lane, tri, Vp, node, alive, totals, eps_dr)
                run += ahead
                ahead = k
                if run > cap_n + k:   # each round takes every pending triangle one level down a tree of cap_n nodes
                    raise RuntimeError(f"TOP tree build: {left} triangles still pending after {run} rounds")
                dropped, used, rounds, left = (int(x) for x in totals.numpy())   # the stage's one read
            _LAST_ROUNDS[cap_n] = rounds
        else:
            left = M
            while left:
                rounds += 1
                node, alive, counts, hung = _round(tree, planes, win, links, lane, tri, Vp, node, alive,
                                                   dr.opaque(I32, used), eps_dr)
                dr.scatter(counts, hung, U32(1))
                d, new, left = (int(x) for x in counts.numpy())
                if rounds > cap_n:
                    raise RuntimeError(f"TOP tree build: {left} triangles still pending after {rounds} rounds")
                dropped += d
                used += 4 * new
    k = dr.arange(I32, used)
    Pn = [dr.gather(F, p, k) for p in Pn]
    child = [dr.gather(I32, child, k * 3 + j) for j in range(3)]
    is_cap, depth, owner = dr.gather(mi.Bool, is_cap, k), dr.gather(I32, depth, k), dr.gather(I32, owner, k)
    near = dr.gather(F, _device_near(v, lo), owner)
    dr.eval(Pn, child, is_cap, depth, near)
    top = _read(dr.max(depth))[0] if used else 0
    if top and mi.variant().startswith("cuda"):  # one recording per tree shape: the levels' tracing is the host's
        near = replayed("top_tree_near", (used, top), _subtree_near, _BUILDS, top, near, depth, child)
    elif top:
        near = _subtree_near(top, near, depth, child)
    extent = float(dr.max(dr.abs(Pn[3]))[0]) if used else 0.0
    return TopTree(
        device={"planes": Pn, "cap": is_cap, "child": child, "level": U32(depth), "near": near},
        nodes=used, extent=extent, origin=origin, light=lo, depth=top, triangles=used // 4, dropped=dropped,
        degenerate=T - n_seq, rounds=rounds, seconds=time.perf_counter() - t0)
