"""SDF representation ([Bán 2019, §2.4–2.6]): exact distances against closed forms and
brute force, Lipschitz ≤ 1 for every primitive, transform and CSG node, bounds where not exact,
the twins of Mitsuba primitives, and the ``[[sdf]]`` scene tables."""

import doctest
import math
import zlib

import numpy as np
import pytest

from shadowlab import backend
from shadowlab.errors import SceneError
from shadowlab.scene.spec import load_spec, parse, resolve
from shadowlab.sdf import field as F

backend.init()
import mitsuba as mi  # noqa: E402


def _pts(a) -> "mi.Vector3f":
    a = np.asarray(a, dtype=np.float64).reshape(-1, 3)
    return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, i], dtype=np.float32)) for i in range(3)))


def dist(sdf, pts) -> np.ndarray:
    return np.asarray(sdf.distance(_pts(pts)).numpy(), dtype=np.float64)


def test_examples_in_docstrings_run():
    from shadowlab.sdf import soft as SO
    from shadowlab.scene import sdf_spec as S
    from shadowlab.sdf import trace as T
    for mod in (F, T, S, SO):
        res = doctest.testmod(mod, extraglobs={"np": np})
        assert res.failed == 0, f"{mod.__name__}: {res.failed} of {res.attempted} examples failed"
    assert doctest.testmod(F).attempted >= 20


# --- exact distances at points with closed forms ------------------------------------------------

CLOSED = [
    # (sdf, point, exact signed distance)
    (F.Plane((0, 1, 0), 0.5), (3, 2, -1), 1.5),
    (F.Plane((1, 1, 0), 0.0), (1, 1, 7), math.sqrt(2)),
    (F.Sphere((1, 2, 3), 0.5), (1, 2, 5), 1.5),
    (F.Sphere((1, 2, 3), 0.5), (1, 2.2, 3), -0.3),
    (F.Box((1, 2, 3)), (0.5, 0.5, 0.5), -0.5),          # inside: nearest face x = 1
    (F.Box((1, 2, 3)), (3, 0, 0), 2.0),                   # face region
    (F.Box((1, 2, 3)), (4, 6, 0), 5.0),                   # edge region: √(3² + 4²)
    (F.Box((1, 2, 3)), (2, 4, 5), 3.0),                   # corner region: √(1 + 4 + 4)
    (F.Box((1, 1, 1), center=(5, 0, 0)), (5, 0, 0), -1.0),
    (F.Box((1, 1, 1), rounding=0.25), (3, 3, 0), math.hypot(2.25, 2.25) - 0.25),  # rounded edge
    (F.Box((1, 1, 1), rounding=0.25), (3, 0, 0), 2.0),    # faces stay where they were
    (F.Segment((0, 0, 0), (0, 2, 0)), (0, 5, 0), 3.0),
    (F.Segment((0, 0, 0), (0, 2, 0)), (3, 1, 4), 5.0),
    (F.Capsule((0, 0, 0), (2, 0, 0), 0.5), (1, 0, 0), -0.5),
    (F.Capsule((0, 0, 0), (2, 0, 0), 0.5), (-3, 4, 0), 4.5),
    (F.Cylinder((0, 0, 0), (0, 2, 0), 1.0), (3, 1, 0), 2.0),    # side
    (F.Cylinder((0, 0, 0), (0, 2, 0), 1.0), (0.5, 5, 0), 3.0),  # cap
    (F.Cylinder((0, 0, 0), (0, 2, 0), 1.0), (4, 6, 0), 5.0),    # rim
    (F.Cylinder((0, 0, 0), (0, 2, 0), 1.0), (0, 1.2, 0.5), -0.5),  # inside, nearest the side
    (F.Cylinder((1, 1, 1), (3, 3, 3), 0.5), (2, 2, 2), -0.5),   # oblique axis
    (F.Offset(F.Sphere((0, 0, 0), 1.0), -0.25), (2, 0, 0), 1.25),
    (F.Union(F.Sphere((-3, 0, 0), 1.0), F.Sphere((3, 0, 0), 1.0)), (0, 0, 0), 2.0),
    (F.Intersection(F.Box((1, 1, 1)), F.Sphere((0, 0, 0), 1.2)), (0, 0, 0), -1.0),
    (F.Difference(F.Box((1, 1, 1)), F.Sphere((0, 0, 0), 0.5)), (0, 0, 0), 0.5),
]


@pytest.mark.parametrize("sdf,p,expected", CLOSED, ids=[f"{type(c[0]).__name__}{i}" for i, c in enumerate(CLOSED)])
def test_primitive_distances_match_closed_forms(sdf, p, expected):
    assert dist(sdf, p)[0] == pytest.approx(expected, abs=2e-6)


def _surface_samples(kind, n=120):
    """Dense points on the surface of canonical shapes (brute-force distance)."""
    g = np.linspace(-1, 1, n)
    A, B = np.meshgrid(g, g)
    A, B = A.ravel(), B.ravel()
    if kind == "box":  # half extents (1, 0.5, 0.75)
        h = np.array([1.0, 0.5, 0.75])
        faces = []
        for ax in range(3):
            o1, o2 = [i for i in range(3) if i != ax]
            for s in (-1, 1):
                P = np.zeros((A.size, 3))
                P[:, ax], P[:, o1], P[:, o2] = s * h[ax], A * h[o1], B * h[o2]
                faces.append(P)
        return np.concatenate(faces)
    if kind == "cylinder":  # axis (0,0,0)-(0,1.5,0), radius 0.6
        th = np.pi * A
        side = np.stack([0.6 * np.cos(th), 0.75 * (B + 1), 0.6 * np.sin(th)], 1)
        r = 0.6 * np.sqrt((B + 1) / 2)
        caps = [np.stack([r * np.cos(th), np.full_like(r, y), r * np.sin(th)], 1) for y in (0.0, 1.5)]
        return np.concatenate([side] + caps)
    raise ValueError(kind)


@pytest.mark.parametrize("kind,sdf", [("box", F.Box((1.0, 0.5, 0.75))),
                                      ("cylinder", F.Cylinder((0, 0, 0), (0, 1.5, 0), 0.6))])
def test_exact_primitives_agree_with_brute_force_distance(kind, sdf):
    surf = _surface_samples(kind)
    rng = np.random.default_rng(3)
    q = rng.uniform(-2, 2, size=(300, 3))
    brute = np.sqrt(((q[:, None, :] - surf[None]) ** 2).sum(-1)).min(1)
    f = dist(sdf, q)
    spacing = 0.06  # larger than the largest gap between samples on these surfaces
    assert np.all(np.abs(f) <= brute + 1e-5), "|f| exceeds the distance to the surface: not a bound"
    assert np.all(np.abs(f) >= brute - spacing), "|f| far below the sampled distance: not exact"
    # signs: negative inside (inside the box: all |q_i| < h_i)
    if kind == "box":
        inside = np.all(np.abs(q) < [1.0, 0.5, 0.75], axis=1)
        assert np.array_equal(f < 0, inside)


# --- Lipschitz ≤ 1 everywhere; bounds where not exact ---------------------------------------------

def _rot_translate(child, axis, deg, t, scale=1.0):
    return F.transform(child, translate=t, rotate=[(*axis, deg)], scale=scale)


LIPSCHITZ = {
    "plane": F.Plane((0.3, 1, -0.2), 0.4),
    "sphere": F.Sphere((0.2, -0.1, 0.3), 0.7),
    "box": F.Box((0.8, 0.3, 0.5)),
    "rounded_box": F.Box((0.8, 0.3, 0.5), rounding=0.2),
    "segment": F.Segment((-0.5, 0, 0), (0.4, 0.6, 0.2)),
    "capsule": F.Capsule((-0.5, 0, 0), (0.4, 0.6, 0.2), 0.3),
    "cylinder": F.Cylinder((0, -0.5, 0.1), (0.2, 0.7, -0.3), 0.4),
    "rotated_box": _rot_translate(F.Box((0.8, 0.3, 0.5)), (1, 2, 0.5), 37, (0.3, 0.2, -0.1)),
    "uniform_scale": _rot_translate(F.Cylinder((0, 0, 0), (0, 1, 0), 0.3), (0, 0, 1), 20, (0, 0, 0), 1.7),
    "nonuniform_scale": F.transform(F.Sphere((0, 0, 0), 1.0), scale=(1.5, 0.4, 0.8)),
    "union": F.Union(F.Sphere((-0.6, 0, 0), 0.5), F.Box((0.3, 0.6, 0.3), center=(0.5, 0, 0))),
    "intersection": F.Intersection(F.Box((0.7, 0.7, 0.7)), F.Sphere((0, 0, 0), 0.9)),
    "difference": F.Difference(F.Box((0.7, 0.7, 0.7)), F.Cylinder((0, -1, 0), (0, 1, 0), 0.4)),
    "offset_grow": F.Offset(F.Box((0.5, 0.2, 0.3)), 0.15),
    "offset_erode": F.Offset(F.Box((0.5, 0.4, 0.3)), -0.1),
    "nested": F.Offset(F.transform(F.Difference(F.Union(F.Sphere((0, 0, 0), 0.6), F.Capsule((0, 0, 0), (1, 0, 0), 0.2)),
                                                F.Plane((0, 1, 0), 0.2)), rotate=[(1, 0, 0, 30)], scale=0.8), 0.05),
}


@pytest.mark.parametrize("name", sorted(LIPSCHITZ))
def test_lipschitz_at_most_one(name):
    sdf = LIPSCHITZ[name]
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    p = rng.uniform(-2, 2, size=(20000, 3))
    # pairs at every scale: far apart, and close (where a wrong derivative shows)
    q = p + rng.normal(size=p.shape) * rng.choice([1.0, 0.05, 0.002], size=(len(p), 1))
    lhs = np.abs(dist(sdf, p) - dist(sdf, q))
    rhs = np.linalg.norm(p - q, axis=1)
    ratio = lhs / np.maximum(rhs, 1e-12)
    assert np.all(lhs <= rhs * (1 + 1e-4) + 2e-6), f"{name}: Lipschitz ratio up to {ratio.max():.4f}"
    # and it is not trivially small: a distance field has slope 1 almost everywhere
    assert np.quantile(ratio, 0.9) > 0.5


def test_csg_and_nonuniform_scale_are_bounds_of_the_true_distance():
    """Theorem 1 of [Bán 2019, §2.6] and the σ_min rule of Transformed: |f| ≤ distance to the surface
    (brute force on the surface of an ellipsoid, a box with a hole drilled through)."""
    rng = np.random.default_rng(5)
    u = rng.normal(size=(40000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    radii = np.array([1.5, 0.4, 0.8])
    ell = F.transform(F.Sphere((0, 0, 0), 1.0), scale=tuple(radii))
    assert not ell.exact
    surf = u * radii
    q = rng.uniform(-2.5, 2.5, size=(400, 3))
    brute = np.sqrt(((q[:, None] - surf[None]) ** 2).sum(-1)).min(1)
    f = dist(ell, q)
    assert np.all(np.abs(f) <= brute + 2e-3)
    assert np.all(np.sign(f) == np.sign(((q / radii) ** 2).sum(1) - 1))
    # difference: box minus a sphere at its centre; its surface is the box faces outside the ball
    # plus the sphere inside the box
    box, ball = F.Box((1, 1, 1)), F.Sphere((0, 0, 0), 0.7)
    diff = F.Difference(box, ball)
    assert not diff.exact and not diff.convex
    faces = _surface_samples("box", 100) * [1, 2, 4 / 3]
    faces = faces[np.linalg.norm(faces, axis=1) >= 0.7]
    sph = u * 0.7
    surf = np.concatenate([faces, sph])
    brute = np.sqrt(((q[:, None] - surf[None]) ** 2).sum(-1)).min(1)
    f = dist(diff, q)
    assert np.all(np.abs(f) <= brute + 1e-5)


def test_negative_offset_is_a_bound_that_erodes_corners_by_more_than_d():
    """[Bán 2019, §6.6, Fig. 6.20]: eroding a box by d gives the box with half extents shrunk by d, whose
    corner lies √3·d inside the original corner; f + d is a bound of its distance (too small off
    the corner by (√3 − 1)·d), exact off a face."""
    d = 0.1
    eroded = F.Offset(F.Box((0.5, 0.4, 0.3)), -d)
    assert not eroded.exact and eroded.convex and F.Offset(F.Box((0.5, 0.4, 0.3)), d).exact
    truth = F.Box((0.5 - d, 0.4 - d, 0.3 - d))
    rng = np.random.default_rng(6)
    q = rng.uniform(-2, 2, size=(2000, 3))
    assert np.all(dist(eroded, q) <= dist(truth, q) + 1e-5)
    corner = np.array([[1.5, 1.4, 1.3]])                      # (1, 1, 1) beyond the original corner
    assert dist(truth, corner)[0] - dist(eroded, corner)[0] == pytest.approx((math.sqrt(3) - 1) * d, abs=2e-3)
    assert dist(eroded, [[1.5, 0, 0]])[0] == pytest.approx(dist(truth, [[1.5, 0, 0]])[0], abs=1e-6)


def test_transform_matches_mitsuba_rotation_and_keeps_distances_exact():
    T = mi.ScalarTransform4f
    for axis, deg in [((1, 0, 0), -90), ((0, 1, 0), 25), ((0.3, -0.5, 0.8), 71)]:
        a = np.asarray(axis) / np.linalg.norm(axis)
        M = np.array((T().rotate(list(a), deg)).matrix)[:3, :3]
        assert np.allclose(F.rotation(axis, deg), M, atol=1e-6)
    box = F.Box((0.5, 0.2, 0.3))
    moved = F.transform(box, translate=(1, 2, 3), rotate=[(0.3, -0.5, 0.8, 71)], scale=2.0)
    assert moved.exact and moved.convex
    rng = np.random.default_rng(2)
    q = rng.uniform(-2, 2, size=(500, 3))
    M = moved.matrix
    world = q @ M[:3, :3].T + M[:3, 3]
    # f_T(T q) = 2 · f(q): distances scale with the uniform scale
    assert np.allclose(dist(moved, world), 2 * dist(box, q), atol=1e-5)


def test_flags_convexity_primitives_and_bounds():
    s = F.Sphere((0, 1, 0), 0.5).named("ball", (0.1, 0.2, 0.3))
    b = F.transform(F.Box((1, 1, 1)), translate=(3, 0, 0)).named("box")
    u = F.Union(s, F.Union(b, F.Capsule((0, 0, 0), (1, 0, 0), 0.1)))
    assert [p.name for p in u.primitives] == ["ball", "box", None]
    assert all(p.convex for p in u.primitives) and not u.convex
    assert F.Union(s).convex and s.convex
    assert not F.Difference(s, b).convex and F.Intersection(s, b).convex
    assert np.allclose(u.bbox_min, [-0.5, -1, -1]) and np.allclose(u.bbox_max, [4, 1.5, 1])
    m = F.transform(F.Mandelbulb(), translate=(0, 2, 0), scale=0.5)
    assert not m.convex and np.allclose(m.bbox_min, [-0.6, 1.4, -0.6]) and np.allclose(m.bbox_max, [0.6, 2.6, 0.6])
    assert not F.Plane().bounded


def test_gradient_is_the_unit_normal():
    sdf = F.Union(F.Sphere((0, 0, 0), 1.0), F.Box((0.5, 0.5, 0.5), center=(3, 0, 0)))
    rng = np.random.default_rng(4)
    d = rng.normal(size=(1000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    p = d * rng.uniform(1.05, 1.4, size=(1000, 1))       # near the sphere, outside
    g = np.asarray(sdf.gradient(_pts(p)).numpy()).T
    assert np.allclose(g, d, atol=1e-3)
    g = np.asarray(sdf.gradient(_pts([[3.9, 0.1, -0.2]])).numpy()).T[0]  # box face x = 3.5
    assert np.allclose(g, [1, 0, 0], atol=1e-4)


# --- the Mandelbulb distance estimator -----------------------------------------------------------

def test_mandelbulb_estimator_outside_inside_and_bounding_sphere():
    m = F.Mandelbulb()
    rng = np.random.default_rng(7)
    far = rng.normal(size=(200, 3))
    far *= (rng.uniform(1.5, 4, size=(200, 1)) / np.linalg.norm(far, axis=1, keepdims=True))
    f = dist(m, far)
    r = np.linalg.norm(far, axis=1)
    assert np.all(f >= r - 1.2 - 1e-5) and np.all(f > 0)
    assert np.all(f <= r)   # the origin is in the set: no point is farther from it than |p|
    # a point of the set (the origin; points on the y axis near it) has a negative estimate
    assert np.all(dist(m, [[0, 0, 0], [0, 0.3, 0], [0.2, 0.0, 0.1]]) < 0)


# --- twins of Mitsuba primitives, and the scene tables ---------------------------------------------

def test_twins_of_the_mitsuba_primitives_have_the_same_surface():
    """Points on each Mitsuba shape's surface (Mitsuba's own sample_position) are on the twin's
    zero set, and its normals agree with the twin's gradient (outside of rectangle edges)."""
    from shadowlab.scene import load
    from shadowlab.scene.twins import sdf_of
    sc = load("sdf_composite")
    sdf = sdf_of(sc)
    by_name = {p.name: p for p in sdf.primitives}
    rng = np.random.default_rng(1)
    checked = set()
    for sh in sc.mi_scene.shapes():
        name = sh.id().split("__")[0]
        if name not in by_name or sh.is_emitter():
            continue
        u = mi.Point2f(*(mi.Float(rng.uniform(0.02, 0.98, 2000).astype(np.float32)) for _ in range(2)))
        ps = sh.sample_position(0.0, u)
        twin = by_name[name]
        f = np.asarray(twin.distance(ps.p).numpy())
        assert np.abs(f).max() < 2e-5 * max(1.0, float(np.abs(np.asarray(ps.p.numpy())).max())), name
        g = np.asarray(twin.gradient(mi.Vector3f(ps.p) + mi.Vector3f(ps.n) * 2e-3).numpy()).T
        n = np.asarray(ps.n.numpy()).T
        agree = np.abs((g * n).sum(1)) > 0.999   # rectangles are two-sided: ±n
        assert agree.mean() > 0.97, name
        checked.add(name)
    assert len(checked) == len(sdf.primitives) == 26


def test_scenes_with_meshes_or_alpha_have_no_sdf_and_twin_scenes_do(tmp_path):
    from shadowlab.scene import load
    from shadowlab.scene.twins import sdf_of
    assert sdf_of(load("foliage")) is None          # alpha-tested cards
    for name in ("contact", "analytic_sphere", "sdf_simple", "sdf_thin", "sdf_pointed"):
        s = sdf_of(load(name))
        assert s is not None and len(s.primitives) == len(load_spec(resolve(name)).shapes)
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    p = tmp_path / "m.toml"
    p.write_text(_SCENE_HEAD + '[[shapes]]\nname = "m"\ntype = "obj"\nfilename = "tri.obj"\n')
    assert sdf_of(load(str(p))) is None


_SCENE_HEAD = """
name = "t"
[camera]
position = [0, 2, 5]
target = [0, 0, 0]
[[lights]]
name = "L"
kind = "sphere"
position = [0, 4, 0]
radius = 0.5
power = 100
"""


def _parse(text):
    import tomllib
    return parse(tomllib.loads(_SCENE_HEAD + text), "scene.toml")


def test_sdf_tables_parse_build_and_hash():
    spec = _parse("""
[[sdf]]
name = "nut"
type = "difference"
albedo = [0.2, 0.3, 0.4]
translate = [0, 1, 0]
scale = 0.5
offset = 0.01
children = [{ type = "box", half = [1, 0.3, 1], rounding = 0.1 },
            { type = "cylinder", p0 = [0, -1, 0], p1 = [0, 1, 0], radius = 0.4 }]
[[sdf]]
type = "mandelbulb"
translate = [3, 1, 0]
""")
    assert spec.shapes == () and len(spec.sdf) == 2 and spec.sdf[1]["name"] == "sdf1"
    from shadowlab.scene.sdf_spec import build_objects
    nut, bulb = build_objects(spec.sdf)
    assert nut.name == "nut" and nut.albedo == (0.2, 0.3, 0.4) and isinstance(bulb.child, F.Mandelbulb)
    # the hole: centre of the nut is outside the solid by 0.5·0.4 − 0.01
    assert dist(nut, [0, 1, 0])[0] == pytest.approx(0.5 * 0.4 - 0.01, abs=1e-6)
    # the tables enter the scene hash; scenes without them hash as before the key existed
    spec2 = _parse("""
[[sdf]]
name = "nut"
type = "sphere"
""")
    assert spec.digest() != spec2.digest()
    from shadowlab.reference import store
    store.load(load_spec(resolve("contact")))  # committed reference: its hash still matches


@pytest.mark.parametrize("text,key", [
    ('[[sdf]]\ntype = "torus"\n', "sdf[0].type"),
    ('[[sdf]]\ntype = "sphere"\nradius = -1\n', "sdf[0].radius"),
    ('[[sdf]]\ntype = "sphere"\nhalf = [1, 1, 1]\n', "sdf[0].half"),
    ('[[sdf]]\ntype = "difference"\nchildren = [{ type = "box" }]\n', "sdf[0].children"),
    ('[[sdf]]\ntype = "union"\nchildren = [{ type = "box", albedo = [1, 1, 1] }]\n', "sdf[0].children[0].albedo"),
    ('[[sdf]]\ntype = "box"\nrotate = [0, 0, 0, 30]\n', "sdf[0].rotate"),
    ('[[sdf]]\ntype = "capsule"\np0 = [0, 0, 0]\np1 = [0, 0, 0]\n', "sdf[0].p1"),
    ('[[sdf]]\nname = "L"\ntype = "box"\n', "sdf[0].name"),
    ('[[sdf]]\ntype = "mandelbulb"\npower = 1\n', "sdf[0].power"),
])
def test_bad_sdf_tables_name_the_key(text, key):
    with pytest.raises(SceneError, match=key.replace("[", r"\[").replace("]", r"\]")):
        _parse(text)


def test_non_unit_rotation_axes_are_normalised():
    """Mitsuba's rotate() does not normalise its axis; the scene builder does, so [0, 2, 0] is a
    rotation (not a shear) and the twin matches."""
    from shadowlab.scene.build import _transform
    a = _parse('[[shapes]]\ntype = "cube"\nrotate = [0, 2, 0, 30]\n').shapes[0]
    b = _parse('[[shapes]]\ntype = "cube"\nrotate = [0, 1, 0, 30]\n').shapes[0]
    assert np.allclose(np.array(_transform(a).matrix), np.array(_transform(b).matrix), atol=1e-7)
    with pytest.raises(SceneError, match=r"shapes\[0\]\.rotate"):
        _parse('[[shapes]]\ntype = "cube"\nrotate = [0, 0, 0, 30]\n')


def test_sdf_tables_refused_next_to_meshes(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    p = tmp_path / "s.toml"
    p.write_text(_SCENE_HEAD + '[[shapes]]\nname = "m"\ntype = "obj"\nfilename = "tri.obj"\n'
                 '[[sdf]]\ntype = "sphere"\n')
    with pytest.raises(SceneError, match="sdf"):
        load_spec(p)
