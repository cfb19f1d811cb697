"""The TOP tree's query [Wang 2022, §1.2, Algorithm 2] on interpenetrating triangles: one triangle
pierces another, so in the tree it lies on both sides of the other's capping plane and hangs under
that plane's intersecting child; a query that loses a push there drops the piercing triangle's
shadow. Checked against brute-force segment–triangle tests (numpy, Möller–Trumbore)."""

import numpy as np
import pytest

#: a large horizontal triangle at y = 1 and a small ramp through it (from y = 0.6 to 1.6), inside
#: the first's shadow planes: it cuts only its capping plane
FLAT = [[-3.0, 1.0, -3.0], [3.5, 1.0, -2.5], [0.0, 1.0, 3.5]]
SPIKE = [[-0.6, 0.6, -0.5], [0.7, 0.6, -0.4], [0.05, 1.6, 0.6]]
LIGHTS = {"point": np.array([0.3, 4.0, 0.2, 1.0]), "directional": np.array([0.25, 1.0, -0.35, 0.0])}


def _occluded(V, x, light):
    """Bool per point: the segment from x toward the light (to the light, or to infinity for a
    directional light) crosses one of the triangles V (brute force, float64)."""
    if light[3] == 0.0:
        d = np.broadcast_to(light[:3] / np.linalg.norm(light[:3]), x.shape)
        tmax = np.full(len(x), np.inf)
    else:
        d = light[:3] - x
        tmax = np.ones(len(x))
    hit = np.zeros(len(x), bool)
    for a, b, c in V:                                                # two triangles, not pixels
        e1, e2 = b - a, c - a
        h = np.cross(d, e2)
        det = h @ e1
        with np.errstate(divide="ignore", invalid="ignore"):
            f = 1.0 / det
            s = x - a
            u = f * np.einsum("ij,ij->i", s, h)
            q = np.cross(s, e1)
            v = f * np.einsum("ij,ij->i", d, q)
            t = f * (q @ e2)
        hit |= (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < tmax)
    return hit


@pytest.mark.parametrize("kind", sorted(LIGHTS))
@pytest.mark.parametrize("first", ["flat", "spike"])
def test_a_piercing_triangle_hangs_under_a_capping_plane_and_keeps_its_shadow(mitsuba_backend, kind, first):
    """The ramp inserted after the large triangle cuts only its capping plane (Algorithm 1 hangs it
    under that capping node's intersecting child); inserted first, the large triangle cuts its
    shadow planes instead (an intersecting child of a shadow plane). Either way Algorithm 2 must
    push both children, and every point's visibility equals the brute force's, including the
    points above the large triangle that only the ramp shadows."""
    import mitsuba as mi

    from shadowlab.render.top_tree import build_top_tree, query
    V = np.array([FLAT, SPIKE] if first == "flat" else [SPIKE, FLAT], np.float64)
    light = LIGHTS[kind]
    tree = build_top_tree(V, light, origin=np.zeros(3), order="scene")
    cut = (tree.cap if first == "flat" else ~tree.cap) & (tree.child[:, 1] >= 0)
    assert cut.any() and tree.nodes == 8, "the second triangle must hang under an intersecting child"
    rng = np.random.default_rng(7)
    x = np.concatenate([rng.uniform([-2, -0.5, -2], [2, 0.39, 2], (3000, 3)),      # below both
                        rng.uniform([-0.8, 1.01, -0.4], [0.8, 1.59, 1.0], (3000, 3))])  # under the ramp's top
    ex = _occluded(V, x, light)
    vis, _, _ = query(tree, mi.Point3f(*x.astype(np.float32).T))
    got = vis.numpy() < 0.5
    # points within float32 rounding of a plane may go either way
    pl = tree.planes
    near = (np.abs(x @ pl[:, :3].T + pl[:, 3]) < 1e-5).any(1)
    assert np.array_equal(got[~near], ex[~near]), int((got != ex)[~near].sum())
    only_spike = _occluded(V[[1 if first == "flat" else 0]], x, light) & \
        ~_occluded(V[[0 if first == "flat" else 1]], x, light)
    assert only_spike.sum() > 100 and ex.mean() > 0.05               # the scene tells a lost shadow apart


# ----------------------------------------------------------------------------- the "deep" part

def _layers(seed=3):
    """Triangles of mixed sizes in layers from y = 0.3 to 2.4: small tiles and a few large sheets
    (a large one's vertices are far from the light while its middle is near)."""
    rng = np.random.default_rng(seed)
    c = np.column_stack([rng.uniform(-2, 2, 160), rng.choice([0.3, 0.9, 1.5, 2.1], 160), rng.uniform(-2, 2, 160)])
    s = np.where(np.arange(160) < 8, 3.0, 0.35)[:, None, None]
    offs = np.array([[-1.0, 0.0, -0.6], [1.0, 0.05, -0.5], [0.1, -0.05, 1.0]])
    return c[:, None, :] + s * (offs[None] + rng.normal(0, 0.15, (160, 3, 3)))


@pytest.mark.parametrize("kind", sorted(LIGHTS))
def test_deep_queries_skip_what_lies_beyond_the_point_and_keep_the_visibility(mitsuba_backend, kind):
    """[Mora 2016] (002 §1): a node whose subtree's triangles all lie farther from the light than
    the point cannot shadow it. ``near`` is a lower bound of every triangle's light distance (depth
    along the rays for a directional light) and the minimum over each subtree; with it the query
    visits fewer nodes and gives the brute force's visibility, as without."""
    import mitsuba as mi

    from shadowlab.render.top_tree import build_top_tree, light_distance, query, triangle_near
    V = _layers()
    light = LIGHTS[kind]
    tree = build_top_tree(V, light, origin=np.zeros(3))
    own = triangle_near(V, light)
    rng = np.random.default_rng(5)
    a, b = rng.random((2, 200, 1))
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    pts = V[:, None, 0] + a * (V[:, None, 1] - V[:, None, 0]) + b * (V[:, None, 2] - V[:, None, 0])
    assert np.all(light_distance(pts, light) >= own[:, None] - 1e-12)      # a lower bound
    k = np.arange(tree.nodes)
    for j in range(3):                                                       # the subtree minimum
        c = tree.child[:, j]
        assert np.all(tree.near[k[c >= 0]] <= tree.near[c[c >= 0]])
    x = rng.uniform([-2.5, 0.0, -2.5], [2.5, 2.4, 2.5], (6000, 3))
    ex = _occluded(V, x, light)
    P = mi.Point3f(*x.astype(np.float32).T)
    v_deep, n_deep, _ = query(tree, P, deep=True)
    v_flat, n_flat, _ = query(tree, P, deep=False)
    pl = tree.planes
    near = (np.abs(x @ pl[:, :3].T + pl[:, 3]) < 1e-5).any(1)
    assert np.array_equal(v_deep.numpy(), v_flat.numpy())
    assert np.array_equal(v_deep.numpy()[~near] < 0.5, ex[~near])
    assert 0.1 < ex.mean() < 0.9
    assert n_deep.numpy().mean() < 0.95 * n_flat.numpy().mean(), (n_deep.numpy().mean(), n_flat.numpy().mean())
