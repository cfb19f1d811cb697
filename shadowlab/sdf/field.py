"""Signed distance functions and distance estimates in Dr.Jit ([Bán 2019, §2.4–2.6]).

An :class:`SDF` maps world points to a signed distance ``f`` whose zero set is the surface,
negative inside ([Bán 2019, §2.4.3]). Every class here is *Lipschitz with constant 1*
(``|f(p) − f(q)| ≤ |p − q|``) and a *bound*: ``|f(p)|`` never exceeds the Euclidean distance of
``p`` to the surface ([Bán 2019, §2.4.4], a distance estimate), which is all sphere tracing needs.
``exact`` says when it is the true signed distance (the primitives, similarity transforms,
offsets of exact fields); CSG results are bounds only ([Bán 2019, §2.6], Theorem 1).

* primitives (§2.4.1): :class:`Plane`, :class:`Sphere`, :class:`Box` (optionally rounded),
  :class:`Cylinder` (capped), :class:`Capsule`, :class:`Segment`;
* transforms (§2.5): :class:`Transformed` is ``f ∘ T⁻¹``; a similarity (rotation, translation,
  uniform scale s) gives ``s · f(T⁻¹x)``, exact; any other affine map multiplies by the smallest
  singular value of its linear part, which keeps a bound;
* CSG (§2.6, Theorem 1): :class:`Union` ``min``, :class:`Intersection` ``max``,
  :class:`Difference` ``max(f, −g)``; offset (§2.6.1): :class:`Offset` ``f − d``;
* :class:`Mandelbulb`: the power-8 distance estimator ([Bán 2019, §6, Fig. 6.9]; [Quílez 2009]), a
  symbolic loop with bailout.

:func:`twin_of` is the SDF of one of Mitsuba's canonical primitives (rectangle, disk, cube,
sphere, capped cylinder) under a ``to_world`` matrix; :mod:`shadowlab.scene.twins` applies it to
a scene's shapes, so one scene file gives the Mitsuba scene (ground truth) and its SDF.

Example (the backend must be initialised, ``shadowlab.backend.init()``):

>>> import mitsuba as mi
>>> ball = Sphere((0, 1, 0), 0.5)
>>> float(ball.distance(mi.Point3f(0, 3, 0))[0])
1.5
>>> scene = Union(ball, Plane((0, 1, 0), 0.0))
>>> round(float(scene.distance(mi.Point3f(0, 0.2, 0))[0]), 4)
0.2
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

GRAD_H = 1e-3        # central-difference step of SDF.gradient (scene units)
SLAB_THICKNESS = 0.02  # world thickness of the solid twins of Mitsuba rectangles and disks


def _v3(x) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"expected 3 finite numbers, got {x!r}")
    return a


def _vec(p):
    """Any Dr.Jit 3-vector (Point3f, Vector3f, Normal3f) as mi.Vector3f: Point3f + Vector3f is a
    Vector3f in Mitsuba's bindings, so arithmetic is done on vectors throughout."""
    return mi.Vector3f(p)


def _const(a) -> object:
    return mi.Vector3f(float(a[0]), float(a[1]), float(a[2]))


class SDF:
    """A signed distance function (or estimate) of a solid, in world coordinates ([Bán 2019, §2.4]).

    ``distance(p)`` (mi.Float), ``gradient(p)`` (normalised ∇f by central differences),
    ``convex`` (True iff this is one convex solid: what the convex-optimised cone trace of
    [Bán 2019, §4.4.3] may assume), ``primitives`` (the leaf objects: a union lists its members' leaves,
    any other node is one leaf), ``bbox_min`` / ``bbox_max`` (numpy world bounds; ±inf for
    unbounded solids such as a plane), ``exact`` (true signed distance, not just a bound),
    ``name`` and ``albedo`` (set by :meth:`named`; used by the cone-traced G-buffer).
    """

    convex: bool = False
    exact: bool = True
    name: str | None = None
    albedo: tuple = (0.5, 0.5, 0.5)

    def __init__(self):
        self.bbox_min = np.full(3, -np.inf)
        self.bbox_max = np.full(3, np.inf)

    @property
    def primitives(self) -> list:
        return [self]

    def distance(self, p):
        raise NotImplementedError

    def __call__(self, p):
        return self.distance(p)

    def gradient(self, p, h: float = GRAD_H):
        """Normalised ∇f at ``p`` by central differences with step ``h`` (six evaluations).

        >>> import mitsuba as mi
        >>> g = Sphere((0, 0, 0), 1.0).gradient(mi.Point3f(0, 2, 0))
        >>> [round(float(c[0]), 4) for c in g]
        [0.0, 1.0, 0.0]
        """
        q = _vec(p)
        comps = []
        for axis in range(3):
            e = [0.0, 0.0, 0.0]
            e[axis] = h
            e = mi.Vector3f(*e)
            comps.append(self.distance(q + e) - self.distance(q - e))
        return dr.normalize(mi.Vector3f(*comps))

    def named(self, name: str | None = None, albedo=None) -> "SDF":
        """Set the object's name and albedo (for the G-buffer); returns self."""
        if name is not None:
            self.name = name
        if albedo is not None:
            self.albedo = tuple(float(a) for a in albedo)
        return self

    @property
    def bounded(self) -> bool:
        return bool(np.all(np.isfinite(self.bbox_min)) and np.all(np.isfinite(self.bbox_max)))

    def __repr__(self):
        return f"{type(self).__name__}({self.name or ''})"


class Plane(SDF):
    """Half-space ``⟨x, n⟩ ≤ height`` ([Bán 2019, §2.4.1]: ``f_n(x) = ⟨x, n⟩``, shifted by ``height``
    along the unit normal ``n``): the exact signed distance; unbounded.

    >>> import mitsuba as mi
    >>> float(Plane((0, 2, 0), 1.0).distance(mi.Point3f(5, 3, -7))[0])
    2.0
    """

    convex = True

    def __init__(self, normal=(0.0, 1.0, 0.0), height: float = 0.0):
        super().__init__()
        n = _v3(normal)
        if np.linalg.norm(n) == 0:
            raise ValueError("plane normal must be non-zero")
        self.normal = n / np.linalg.norm(n)
        self.height = float(height)

    def distance(self, p):
        return dr.dot(_vec(p), _const(self.normal)) - self.height


class Sphere(SDF):
    """Ball of radius ``r`` around ``center`` ([Bán 2019, §2.4.1] and §2.5: ``‖x − c‖ − r``), exact.

    >>> import mitsuba as mi
    >>> float(Sphere((1, 0, 0), 0.5).distance(mi.Point3f(1, 0, 0))[0])
    -0.5
    """

    convex = True

    def __init__(self, center=(0.0, 0.0, 0.0), radius: float = 1.0):
        super().__init__()
        self.center, self.radius = _v3(center), float(radius)
        if self.radius <= 0:
            raise ValueError("sphere radius must be positive")
        self.bbox_min, self.bbox_max = self.center - self.radius, self.center + self.radius

    def distance(self, p):
        return dr.norm(_vec(p) - _const(self.center)) - self.radius


class Box(SDF):
    """Axis-aligned box of half extents ``half`` around ``center``, edges rounded with radius
    ``rounding`` (the rounded box is the offset of [Bán 2019, §2.6.1, Fig. 2.5], of the box shrunk by
    ``rounding``, so its outer extents stay ``half``): exact
    ``‖max(q, 0)‖ + min(max_i q_i, 0) − rounding`` with ``q = |x − c| − (half − rounding)``.
    Rotate it with :class:`Transformed`.

    >>> import mitsuba as mi
    >>> float(Box((1, 1, 1)).distance(mi.Point3f(4, 5, 0))[0])  # corner region: √(3² + 4²)
    5.0
    """

    convex = True

    def __init__(self, half=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), rounding: float = 0.0):
        super().__init__()
        self.half, self.center, self.rounding = _v3(half), _v3(center), float(rounding)
        if np.any(self.half <= 0) or self.rounding < 0 or self.rounding > self.half.min():
            raise ValueError("box half extents must be positive and rounding in [0, min(half)]")
        self.bbox_min, self.bbox_max = self.center - self.half, self.center + self.half

    def distance(self, p):
        q = dr.abs(_vec(p) - _const(self.center)) - _const(self.half - self.rounding)
        outside = dr.norm(dr.maximum(q, 0.0))
        inside = dr.minimum(dr.maximum(q.x, dr.maximum(q.y, q.z)), 0.0)
        return outside + inside - self.rounding


class Segment(SDF):
    """The segment from ``a`` to ``b`` ([Bán 2019, §2.4.1]:
    ``‖p − clamp(⟨b, p⟩ / ⟨b, b⟩) b‖`` relative to ``a``): exact unsigned distance (no interior).

    >>> import mitsuba as mi
    >>> float(Segment((0, 0, 0), (0, 2, 0)).distance(mi.Point3f(3, 1, 4))[0])
    5.0
    """

    convex = True
    radius = 0.0

    def __init__(self, a=(0.0, 0.0, 0.0), b=(0.0, 1.0, 0.0)):
        super().__init__()
        self.a, self.b = _v3(a), _v3(b)
        if np.linalg.norm(self.b - self.a) == 0:
            raise ValueError("segment end points must differ")
        r = self.radius
        self.bbox_min = np.minimum(self.a, self.b) - r
        self.bbox_max = np.maximum(self.a, self.b) + r

    def distance(self, p):
        ba = self.b - self.a
        pa = _vec(p) - _const(self.a)
        h = dr.clip(dr.dot(pa, _const(ba)) / float(ba @ ba), 0.0, 1.0)
        return dr.norm(pa - _const(ba) * h) - self.radius


class Capsule(Segment):
    """Capsule: the segment ``a``–``b`` offset by ``radius`` ([Bán 2019, §2.6.1, Fig. 2.6]a), exact.

    >>> import mitsuba as mi
    >>> float(Capsule((0, 0, 0), (0, 2, 0), 0.5).distance(mi.Point3f(0, 3, 0))[0])
    0.5
    """

    def __init__(self, a=(0.0, 0.0, 0.0), b=(0.0, 1.0, 0.0), radius: float = 0.5):
        if radius <= 0:
            raise ValueError("capsule radius must be positive")
        self.radius = float(radius)
        super().__init__(a, b)


class Cylinder(SDF):
    """Solid capped cylinder of ``radius`` with axis from ``a`` to ``b`` ([Bán 2019, §2.4], the cylinder
    among the primitives): with ``h`` the axial coordinate from the middle, ``ρ`` the distance
    from the axis and ``d = (ρ − r, |h| − L/2)``, ``f = min(max(d), 0) + ‖max(d, 0)‖``: exact.

    >>> import mitsuba as mi
    >>> float(Cylinder((0, 0, 0), (0, 2, 0), 1.0).distance(mi.Point3f(4, 6, 0))[0])  # rim: √(3² + 4²)
    5.0
    """

    convex = True

    def __init__(self, a=(0.0, 0.0, 0.0), b=(0.0, 1.0, 0.0), radius: float = 1.0):
        super().__init__()
        self.a, self.b, self.radius = _v3(a), _v3(b), float(radius)
        L = np.linalg.norm(self.b - self.a)
        if L == 0 or self.radius <= 0:
            raise ValueError("cylinder needs distinct end points and a positive radius")
        self.length, self.axis, self.mid = L, (self.b - self.a) / L, (self.a + self.b) / 2
        # box of the two end discs: per axis, the disc's extent is r·√(1 − u_i²)
        ext = self.radius * np.sqrt(np.clip(1 - self.axis ** 2, 0, 1))
        self.bbox_min = np.minimum(self.a, self.b) - ext
        self.bbox_max = np.maximum(self.a, self.b) + ext

    def distance(self, p):
        pm = _vec(p) - _const(self.mid)
        u = _const(self.axis)
        h = dr.dot(pm, u)
        rho = dr.norm(pm - u * h)
        dx = rho - self.radius
        dy = dr.abs(h) - 0.5 * self.length
        outside = dr.sqrt(dr.square(dr.maximum(dx, 0.0)) + dr.square(dr.maximum(dy, 0.0)))
        return dr.minimum(dr.maximum(dx, dy), 0.0) + outside


class Transformed(SDF):
    """``f ∘ T⁻¹`` for an affine ``T(x) = A x + t`` given as a 4×4 world-from-local matrix
    ([Bán 2019, §2.5]). Distances are multiplied by the smallest singular value σ of ``A``: for a
    similarity (rotation, translation, uniform scale s) σ = s and the result is exact when the
    child is; otherwise (non-uniform scale) it is a bound: ``|f(T⁻¹x) − f(T⁻¹y)| ≤ ‖x − y‖ / σ``.

    >>> import mitsuba as mi
    >>> M = np.diag([2.0, 2.0, 2.0, 1.0]); M[:3, 3] = (0, 5, 0)   # scale 2, then move up 5
    >>> float(Transformed(Sphere((0, 0, 0), 1.0), M).distance(mi.Point3f(0, 0, 0))[0])
    3.0
    """

    def __init__(self, child: SDF, matrix):
        super().__init__()
        M = np.asarray(matrix, dtype=np.float64)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise ValueError("expected a finite 4×4 matrix")
        A = M[:3, :3]
        sv = np.linalg.svd(A, compute_uv=False)
        if sv.min() <= 1e-12 * max(sv.max(), 1e-300):
            raise ValueError("transform is singular")
        self.child, self.matrix = child, M
        self.inv = np.linalg.inv(A)
        self.t = M[:3, 3].copy()
        self.sigma = float(sv.min())
        self.similarity = bool(sv.max() - sv.min() <= 1e-6 * sv.max())
        self.exact = child.exact and self.similarity
        self.convex = child.convex
        self.name, self.albedo = child.name, child.albedo
        if child.bounded:
            lo, hi = child.bbox_min, child.bbox_max
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            w = corners @ A.T + self.t
            self.bbox_min, self.bbox_max = w.min(0), w.max(0)

    def distance(self, p):
        q = _vec(p) - _const(self.t)
        R = self.inv
        local = mi.Vector3f(*(q.x * float(R[i, 0]) + q.y * float(R[i, 1]) + q.z * float(R[i, 2]) for i in range(3)))
        return self.child.distance(local) * self.sigma


def rotation(axis, degrees: float) -> np.ndarray:
    """3×3 right-handed rotation by ``degrees`` about ``axis`` (Rodrigues), the same matrix as
    ``mi.ScalarTransform4f().rotate(axis, degrees)``."""
    a = _v3(axis)
    a = a / np.linalg.norm(a)
    th = math.radians(degrees)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def transform(child: SDF, translate=(0.0, 0.0, 0.0), rotate=(), scale=1.0) -> SDF:
    """``child`` moved like a scene shape: ``T = translate · rotate₁ · rotate₂ ⋯ · scale``
    (the convention of ``[[shapes]]``); ``rotate`` is a sequence of (ax, ay, az, degrees).
    Returns ``child`` itself for the identity.

    >>> import mitsuba as mi
    >>> s = transform(Sphere(), translate=(0, 2, 0), scale=0.5)
    >>> float(s.distance(mi.Point3f(0, 0, 0))[0])
    1.5
    """
    M = np.eye(4)
    M[:3, 3] = _v3(translate)
    R = np.eye(3)
    for ax, ay, az, deg in rotate:
        R = R @ rotation((ax, ay, az), deg)
    M[:3, :3] = R @ np.diag(_v3(scale))
    if np.allclose(M, np.eye(4), atol=0, rtol=0):
        return child
    return Transformed(child, M)


class Union(SDF):
    """``min`` of the children ([Bán 2019, §2.6], Theorem 1): a bound, exact outside all children when
    they do not overlap. ``primitives`` lists the children's leaves.

    >>> import mitsuba as mi
    >>> u = Union(Sphere((-2, 0, 0), 1.0), Sphere((2, 0, 0), 1.0))
    >>> float(u.distance(mi.Point3f(0, 0, 0))[0])
    1.0
    """

    def __init__(self, *children: SDF):
        super().__init__()
        if not children:
            raise ValueError("a union needs at least one child")
        self.children = list(children)
        self.convex = len(self.children) == 1 and self.children[0].convex
        self.exact = len(self.children) == 1 and self.children[0].exact
        self.bbox_min = np.min([c.bbox_min for c in self.children], 0)
        self.bbox_max = np.max([c.bbox_max for c in self.children], 0)

    @property
    def primitives(self) -> list:
        return [leaf for c in self.children for leaf in c.primitives]

    def distance(self, p):
        d = self.children[0].distance(p)
        for c in self.children[1:]:
            d = dr.minimum(d, c.distance(p))
        return d


class Intersection(SDF):
    """``max`` of the children ([Bán 2019, §2.6], Theorem 1): a bound; convex if every child is.

    >>> import mitsuba as mi
    >>> lens = Intersection(Sphere((-0.5, 0, 0), 1.0), Sphere((0.5, 0, 0), 1.0))
    >>> float(lens.distance(mi.Point3f(0, 0, 0))[0])
    -0.5
    """

    def __init__(self, *children: SDF):
        super().__init__()
        if not children:
            raise ValueError("an intersection needs at least one child")
        self.children = list(children)
        self.convex = all(c.convex for c in self.children)
        self.exact = len(self.children) == 1 and self.children[0].exact
        self.bbox_min = np.max([c.bbox_min for c in self.children], 0)
        self.bbox_max = np.min([c.bbox_max for c in self.children], 0)

    def distance(self, p):
        d = self.children[0].distance(p)
        for c in self.children[1:]:
            d = dr.maximum(d, c.distance(p))
        return d


class Difference(SDF):
    """``a \\ b``: ``max(f_a, −f_b)`` ([Bán 2019, §2.6], Theorem 1), a bound; not convex in general.

    >>> import mitsuba as mi
    >>> cup = Difference(Box((1, 1, 1)), Sphere((0, 1, 0), 0.8))
    >>> round(float(cup.distance(mi.Point3f(0, 1, 0))[0]), 4)   # inside the removed ball
    0.8
    """

    def __init__(self, a: SDF, b: SDF):
        super().__init__()
        self.a, self.b = a, b
        self.exact = False
        self.bbox_min, self.bbox_max = a.bbox_min.copy(), a.bbox_max.copy()

    def distance(self, p):
        return dr.maximum(self.a.distance(p), -self.b.distance(p))


class Offset(SDF):
    """The offset ``S_d`` of [Bán 2019, §2.6.1]: ``f − d`` grows the solid by ``d > 0`` (rounded edges)
    and erodes it for ``d < 0``; exact for exact ``f`` and ``d ≥ 0``. Erosion is only a bound:
    the eroded solid's edges and corners lie √2·|d| and √3·|d| inside the original ones
    ([Bán 2019, Fig. 6.20]), farther than ``f`` + |d| says. Convexity is kept either way.

    >>> import mitsuba as mi
    >>> float(Offset(Segment((0, 0, 0), (0, 1, 0)), 0.25).distance(mi.Point3f(1, 0.5, 0))[0])
    0.75
    """

    def __init__(self, child: SDF, d: float):
        super().__init__()
        self.child, self.d = child, float(d)
        self.exact, self.convex = child.exact and self.d >= 0, child.convex
        self.name, self.albedo = child.name, child.albedo
        grow = max(self.d, 0.0)
        self.bbox_min, self.bbox_max = child.bbox_min - grow, child.bbox_max + grow

    def distance(self, p):
        return self.child.distance(p) - self.d


class Mandelbulb(SDF):
    """Distance estimator of the power-``power`` Mandelbulb ([Bán 2019, §6, Fig. 6.9], after [Quílez 2009]):
    iterate ``w ← w^power + p`` in spherical (triplex) form with the running derivative
    ``dr ← power · |w|^(power−1) · dr + 1`` until ``|w| > bailout`` or ``iterations``, then
    ``DE = ½ · ln|w| · |w| / dr``, negative inside. The set lies in the ball of radius
    ``bound_radius`` (1.2 for power 8), whose distance ``|p| − bound_radius`` is taken when larger
    (both are bounds, so their maximum is). The estimator is not a strict bound in every
    point; ``step`` (< 1) shrinks it (tests compare sphere tracing with dense marching).
    Defined in the unit frame; place it with :func:`transform`.

    >>> import mitsuba as mi
    >>> m = Mandelbulb()
    >>> round(float(m.distance(mi.Point3f(0, 0, 3))[0]), 4)   # far away: the bounding sphere
    1.8
    >>> float(m.distance(mi.Point3f(0, 0, 0))[0]) < 0   # the origin is inside the set
    True
    """

    convex = False
    exact = False

    def __init__(self, power: float = 8.0, iterations: int = 8, bailout: float = 2.0,
                 bound_radius: float = 1.2, step: float = 1.0):
        super().__init__()
        self.power, self.iterations, self.bailout = float(power), int(iterations), float(bailout)
        self.bound_radius, self.step = float(bound_radius), float(step)
        if self.power < 2 or self.iterations < 1 or self.bailout <= 1 or not 0 < self.step <= 1:
            raise ValueError("mandelbulb: power ≥ 2, iterations ≥ 1, bailout > 1, step in (0, 1]")
        self.bbox_min, self.bbox_max = np.full(3, -self.bound_radius), np.full(3, self.bound_radius)

    def distance(self, p):
        q = _vec(p)
        return dr.maximum(dr.norm(q) - self.bound_radius, _mandelbulb_de(q, self.power, self.iterations,
                                                                         self.bailout) * self.step)


@dr.syntax
def _mandelbulb_de(p, power, iterations, bailout):
    """The escape-time loop of :class:`Mandelbulb` (a Dr.Jit symbolic loop: lanes leave it at
    the bailout). ``p`` is a mi.Vector3f; y is the pole axis as in Quílez's shader."""
    w = mi.Vector3f(p)
    m = dr.squared_norm(w)
    dz = mi.Float(1.0)
    i = mi.UInt32(0)
    b2 = bailout * bailout
    while (i < iterations) & (m <= b2):
        r = dr.maximum(dr.sqrt(m), 1e-20)
        dz = power * dr.power(r, power - 1.0) * dz + 1.0
        th = power * dr.acos(dr.clip(w.y / r, -1.0, 1.0))
        ph = power * dr.atan2(w.x, w.z)
        rp = dr.power(r, power)
        sth = dr.sin(th)
        w = p + rp * mi.Vector3f(sth * dr.sin(ph), dr.cos(th), sth * dr.cos(ph))
        m = dr.squared_norm(w)
        i += 1
    r = dr.maximum(dr.sqrt(m), 1e-20)
    return 0.5 * dr.log(r) * r / dz


# ----------------------------------------------------------------------------------------------
# SDF twins of Mitsuba's canonical primitives (the scene-level twins: shadowlab.scene.twins)

def _columns(M):
    return M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3]


def _orthogonal(*cols, tol=1e-6) -> bool:
    for i in range(len(cols)):
        for j in range(i + 1, len(cols)):
            a, b = cols[i], cols[j]
            if abs(a @ b) > tol * np.linalg.norm(a) * np.linalg.norm(b):
                return False
    return True


def _frame_matrix(R: np.ndarray, origin: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, origin
    return M


def twin_of(kind: str, to_world) -> SDF:
    """The SDF twin of one canonical Mitsuba primitive under its ``to_world`` matrix (4×4):

    * ``rectangle`` ([−1, 1]² in z = 0, normal +z): a box of thickness ``SLAB_THICKNESS`` behind
      its front face (so the visible face is exactly Mitsuba's);
    * ``disk`` (unit disc in z = 0): a flat capped cylinder of that thickness behind its face;
    * ``cube`` ([−1, 1]³), ``sphere`` (unit ball), ``cylinder`` (radius 1, z ∈ [0, 1], with its
      caps: a solid).

    Exact where ``to_world`` keeps the primitive's shape (rotation, translation, scale with
    orthogonal axes, uniform across a round section); otherwise a :class:`Transformed` bound.

    >>> import mitsuba as mi
    >>> M = np.diag([2.0, 2.0, 2.0, 1.0])                  # a 4 × 4 m rectangle in z = 0
    >>> float(twin_of("rectangle", M).distance(mi.Point3f(0, 0, 1))[0])
    1.0
    """
    M = np.asarray(to_world, dtype=np.float64)
    u, v, w, c = _columns(M)
    lu, lv, lw = (float(np.linalg.norm(x)) for x in (u, v, w))
    if kind in ("rectangle", "disk"):
        if not _orthogonal(u, v):
            raise ValueError(f"{kind} with a sheared transform has no SDF twin")
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        R = np.stack([u / lu, v / lv, n], 1)
        T = SLAB_THICKNESS
        if kind == "rectangle":
            return Transformed(Box((lu, lv, T / 2)), _frame_matrix(R, c - n * T / 2))
        if abs(lu - lv) <= 1e-6 * max(lu, lv):
            return Cylinder(c - n * T, c, lu)
        # an ellipse: scale a unit disc slab non-uniformly (a bound)
        A = np.eye(4)
        A[:3, :3], A[:3, 3] = np.stack([u, v, n * T], 1), c
        return Transformed(Cylinder((0, 0, -1), (0, 0, 0), 1.0), A)
    if kind == "cube":
        if _orthogonal(u, v, w):
            return Transformed(Box((lu, lv, lw)), _frame_matrix(np.stack([u / lu, v / lv, w / lw], 1), c))
        return Transformed(Box((1, 1, 1)), M)
    if kind == "sphere":
        if _orthogonal(u, v, w) and max(lu, lv, lw) - min(lu, lv, lw) <= 1e-6 * max(lu, lv, lw):
            return Sphere(c, lu)
        return Transformed(Sphere((0, 0, 0), 1.0), M)
    if kind == "cylinder":
        if _orthogonal(u, v, w) and abs(lu - lv) <= 1e-6 * max(lu, lv):
            return Cylinder(c, c + w, lu)
        return Transformed(Cylinder((0, 0, 0), (0, 0, 1), 1.0), M)
    raise ValueError(f"no SDF twin for Mitsuba shape type {kind!r}")
