"""TOP trees and the fused shadow map + DPSV family [Wang 2022] (``dpsv``, ``sm_dpsv``, ``sm_dpsv_soft``).

Exact visibility of a delta light is one Mitsuba shadow ray per G-buffer point
(:func:`shadowlab.reference.truth.centre_visibility`). The mesh scene holds only geometry the
tree holds exactly: a floor rectangle, two rotated cubes and a PLY "canopy", a bumpy sheet whose
triangles share edges.
"""

import numpy as np
import pytest

from shadowlab import cli
from shadowlab.techniques.base import get

RES = [112, 112]
CAMERA = {"position": [0.0, 4.5, 4.5], "target": [0.0, 0.0, 0.3], "fov": 50, "resolution": RES}
LIGHTS = {
    "point": {"name": "L", "kind": "point", "position": [0.4, 3.2, 0.5], "power": 100.0, "shadow_map": 512},
    "spot": {"name": "L", "kind": "spot", "position": [-0.4, 3.0, -2.0], "target": [0.1, 0.0, 0.6], "angle": 40.0,
             "power": 100.0, "shadow_map": 512},
    "directional": {"name": "L", "kind": "directional", "direction": [0.3, -1.0, 0.8], "irradiance": 3.0,
                    "shadow_map": 512},
}


def _canopy(path, n=9):
    """A bumpy n×n-cell sheet (2n² triangles sharing edges) as a PLY file."""
    from shadowlab.exchange.ply import write_ply
    g = np.linspace(-0.6, 0.6, n + 1)
    X, Z = np.meshgrid(g, g)
    Y = 0.15 * np.sin(5 * X) * np.cos(4 * Z)
    P = np.stack([X, Y, Z], -1).reshape(-1, 3)
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (r * (n + 1) + c).ravel()
    F = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a + 1, a + n + 2, a + n + 1], 1)])
    N = np.tile([0.0, 1.0, 0.0], (len(P), 1))
    UV = np.zeros((len(P), 2))
    write_ply(path, P.astype(np.float32), N.astype(np.float32), UV.astype(np.float32), F.astype(np.int32))


def _scene(tmp_path, light, shapes=None, camera=CAMERA):
    from scene_builder import frame_from, scene
    ply = tmp_path / "canopy.ply"
    if not ply.exists():
        _canopy(ply)
    shapes = shapes or [
        {"name": "floor", "type": "rectangle", "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "scale": 3.0},
        {"name": "box", "type": "cube", "translate": [-0.9, 0.4, -0.2], "rotate": [0, 1, 0, 30], "scale": 0.4},
        {"name": "box2", "type": "cube", "translate": [1.0, 0.5, 0.6], "rotate": [1, 1, 0, 40], "scale": 0.3},
        {"name": "canopy", "type": "ply", "filename": "canopy.ply", "translate": [0.1, 1.3, -0.3]},
    ]
    return frame_from(scene("dpsv_test", camera=camera, lights=[light], shapes=shapes), tmp_path / "scene.toml")


@pytest.fixture(scope="module", params=sorted(LIGHTS))
def mesh_frame(request, tmp_path_factory, mitsuba_backend):
    return request.param, _scene(tmp_path_factory.mktemp(request.param), LIGHTS[request.param])


def _exact(frame):
    from shadowlab.reference.truth import centre_visibility
    return centre_visibility(frame, "L").numpy() > 0.5


def _near_a_plane(frame, idx, tol):
    """Of the points ``idx``, those whose query point lies within ``tol`` of any plane of the tree."""
    from shadowlab.render.top_tree import offset_point
    from shadowlab.render.gbuffer import vec_numpy
    tree = frame.top_tree("L")
    x = vec_numpy(offset_point(tree, frame.gbuffer.p, frame.gbuffer.ng))[idx].astype(np.float64)
    d = np.abs(x @ tree.planes[:, :3].T + tree.planes[:, 3])
    return d.min(1) <= tol


# ---------------------------------------------------------------------------------------------
# the tree

def test_one_triangle_planes_and_its_shadow_volume(mitsuba_backend):
    """Closed form for one triangle under a point light: each shadow plane holds the light and its
    edge and has the third vertex on its negative side; the capping plane has the light on its
    positive side; points below the triangle are shadowed, points beside it or above it are lit."""
    import mitsuba as mi
    from shadowlab.render.top_tree import build_top_tree, query, triangle_planes
    V = np.array([[[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 1.0]]])
    light = np.array([0.2, 3.0, 0.2, 1.0])
    planes, bad = triangle_planes(V, light)
    assert not bad.any()
    for e in range(3):
        n, d = planes[0, e, :3], planes[0, e, 3]
        a, b, c = V[0, e], V[0, (e + 1) % 3], V[0, (e + 2) % 3]
        assert abs(n @ light[:3] + d) < 1e-12 and abs(n @ a + d) < 1e-12 and abs(n @ b + d) < 1e-12
        assert n @ c + d < 0
    cap = planes[0, 3]
    assert cap[:3] @ light[:3] + cap[3] > 0 and np.allclose(np.abs(cap[:3]), [0, 1, 0])
    tree = build_top_tree(V, light, origin=np.zeros(3))
    assert tree.nodes == 4 and tree.depth == 4 and list(tree.child[:3, 2]) == [1, 2, 3] and tree.cap[3]
    # below the centroid (on the line from the light through it), beside it, above it
    c = V[0].mean(0)
    below = light[:3] + 2.0 * (c - light[:3])
    pts = np.array([below, below + [3.0, 0, 0], c + [0, 0.5, 0]], np.float32)
    vis, visits, deepest = query(tree, mi.Point3f(*pts.T))
    assert list(vis.numpy()) == [0.0, 1.0, 1.0]
    assert visits.numpy()[0] == 4 and deepest.numpy()[0] == 4


def test_directional_planes_are_parallel_to_the_light(mitsuba_backend):
    from shadowlab.render.top_tree import triangle_planes
    V = np.array([[[0.0, 1.0, 0.0], [1.0, 1.2, 0.0], [0.0, 0.9, 1.0]]])
    d = np.array([0.3, 1.0, -0.2])
    d /= np.linalg.norm(d)
    planes, bad = triangle_planes(V, np.concatenate([d, [0.0]]))
    assert not bad.any()
    assert np.allclose(planes[0, :3, :3] @ d, 0.0, atol=1e-12)   # shadow planes contain the direction
    assert planes[0, 3, :3] @ d > 0                              # the light's side is positive


def test_dpsv_equals_exact_visibility(mesh_frame):
    """Every valid pixel agrees with a Mitsuba shadow ray, except points within the ray epsilon of
    one of the tree's planes: a vanishing fraction (≤ 0.01 %)."""
    kind, frame = mesh_frame
    gb = frame.gbuffer
    valid = gb.valid.numpy()
    r = get("dpsv").render(frame, {})
    v = r.visibility["L"].numpy() > 0.5
    ex = _exact(frame)
    bad = np.nonzero((v != ex) & valid)[0]
    scale = 1.0 + float(np.abs(frame.top_tree("L").origin).max()) + 4.0
    assert _near_a_plane(frame, bad, 1e-4 * scale).all(), (kind, len(bad))
    assert len(bad) <= 1e-4 * valid.sum(), (kind, len(bad), valid.sum())
    assert 0.02 < 1.0 - v[valid].mean() < 0.9, "the scene must have shadows to test"
    assert r.stats["tree_triangles"]["L"] > 150 and r.stats["nodes_per_query"]["L"] > 1
    dv = r.aovs["L.depth_visited"]
    assert 4 <= dv.max() <= r.stats["tree_depth"]["L"] and dv.max() <= r.aovs["L.nodes_visited"].max()


def test_fused_equals_exact_except_the_classifiers_misses(mesh_frame):
    """``sm_dpsv`` is exact at every edge point; where it is wrong, the point was not marked (all
    four one-texel offsets agree with the centre's test) and the shadow map's answer is wrong:
    the classifier's misses, counted here, far fewer than ``hard``'s errors."""
    kind, frame = mesh_frame
    valid = frame.gbuffer.valid.numpy()
    ex = _exact(frame)
    r = get("sm_dpsv").render(frame, {})
    v = r.visibility["L"].numpy() > 0.5
    edge = _flat(frame, r.aovs["L.edge"]) > 0.5
    h = get("hard").render(frame, {}).visibility["L"].numpy() > 0.5
    wrong = (v != ex) & valid
    misses = wrong & ~edge
    assert not (wrong & edge).any() or _near_a_plane(frame, np.nonzero(wrong & edge)[0], 1e-3).all()
    assert (v[misses] == h[misses]).all()            # a miss keeps the shadow map's answer
    hard_wrong = int(((h != ex) & valid).sum())
    print(f"{kind}: edge points {int(edge.sum())}, classifier misses {int(misses.sum())}, hard wrong {hard_wrong}")
    assert hard_wrong > 0 and misses.sum() <= 0.5 * hard_wrong
    assert 0 < r.stats["edge_fraction"]["L"] < 0.2
    nv = _flat(frame, r.aovs["L.nodes_visited"])      # counted on the device: the AOVs' mean over the edge points
    assert r.stats["nodes_per_query"]["L"] == pytest.approx(float(nv[edge].sum()) / int(edge.sum()), rel=1e-12)


def _flat(frame, img):
    """(H, W) AOV image -> flat G-buffer order (the inverse of ``gbuffer.to_image``)."""
    gb = frame.gbuffer
    idx = np.arange(gb.size)
    pos = gb.to_image(idx.astype(np.float64)).astype(np.int64)
    out = np.empty(gb.size, img.dtype)
    out[pos.ravel()] = np.asarray(img).ravel()
    return out


def test_insertion_order_does_not_change_the_visibility(mesh_frame):
    import drjit as dr
    from shadowlab.render.top_tree import build_top_tree, offset_point, query
    kind, frame = mesh_frame
    V = frame.triangles()
    light = frame.top_tree("L").light + np.concatenate([frame.top_tree("L").origin * frame.top_tree("L").light[3], [0]])
    rng = np.random.default_rng(7)
    results, sizes = [], set()
    for order in ("random", "light", "scene", rng.permutation(len(V))):
        tree = build_top_tree(V, light, order=order, origin=frame.top_tree("L").origin)
        vis, _, _ = query(tree, offset_point(tree, frame.gbuffer.p, frame.gbuffer.ng), frame.gbuffer.valid)
        dr.eval(vis)
        results.append(vis.numpy())
        sizes.add((tree.nodes, tree.depth))
    assert len(sizes) > 1, "the orders must build different trees"
    for v in results[1:]:
        assert np.array_equal(v, results[0]), kind


def test_the_device_build_is_the_numpy_reference_node_for_node(mesh_frame):
    """Algorithm 1 on the device (what frames use) builds the tree the level-synchronous numpy
    reference builds: the same links, capping flags and levels node for node, the same counts, and the
    same visibility and nodes visited at every point. The planes' offsets d agree to float64 rounding
    (numpy's einsum may use fused multiply-adds; the device sums x, y, z in turn)."""
    import drjit as dr
    from shadowlab.render.top_tree import build_top_tree, build_top_tree_numpy, offset_point, query
    kind, frame = mesh_frame
    ref = frame.top_tree("L")
    light = ref.light + np.concatenate([ref.origin * ref.light[3], [0]])
    V = frame.triangles()
    for order in ("random", "light", "scene", np.random.default_rng(3).permutation(len(V))):
        a = build_top_tree_numpy(V, light, order=order, origin=ref.origin)
        b = build_top_tree(V, light, order=order, origin=ref.origin)
        assert {**a.stats(), "build_seconds": 0} == {**b.stats(), "build_seconds": 0}, kind
        assert a.rounds == b.rounds and a.nodes > 4 * len(V) // 2
        for f in ("child", "cap", "level"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), (kind, f)
        assert np.allclose(a.planes, b.planes, rtol=0, atol=1e-14 * (1 + a.extent)), kind
        assert np.allclose(a.near, b.near, rtol=1e-12, atol=1e-12), kind
        out = []
        for tree in (a, b):
            x = offset_point(tree, frame.gbuffer.p, frame.gbuffer.ng)
            vis, visits, deepest = query(tree, x, frame.gbuffer.valid)
            dr.eval(vis, visits, deepest)
            out.append((vis.numpy(), visits.numpy(), deepest.numpy()))
        for x, y in zip(*out):
            assert np.array_equal(x, y), kind


# ---------------------------------------------------------------------------------------------
# the edge classifier

def test_classifier_marks_points_within_a_texel_of_a_planar_edge(tmp_path, mitsuba_backend):
    """A square plate over a floor under a sun straight above: the shadow edge on the floor is the
    plate's outline. Floor points whose light-space distance to it is under ½ texel / √2 are all
    marked; none farther than 1.6 texels is (the four offsets reach 1.5 texels at most)."""
    from shadowlab.render.gbuffer import vec_numpy
    sun = {"name": "L", "kind": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 3.0, "shadow_map": 256}
    shapes = [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0},
              {"name": "plate", "type": "rectangle", "rotate": [[0, 1, 0, 20], [1, 0, 0, -90]],
               "translate": [0.2, 1.0, 0.1], "scale": 0.8}]
    frame = _scene(tmp_path, sun, shapes, camera={**CAMERA, "position": [0.0, 5.0, 3.0], "resolution": [128, 128]})
    r = get("sm_dpsv").render(frame, {})
    edge = _flat(frame, r.aovs["L.edge"]) > 0.5
    texel = _flat(frame, r.aovs["L.texel"])
    p = vec_numpy(frame.gbuffer.p).astype(np.float64)
    floor = frame.gbuffer.valid.numpy() & (np.abs(p[:, 1]) < 1e-3)
    # the plate's outline in the floor plane: a square of half side 0.8 rotated 20° about y
    a = np.radians(20.0)
    rel = p[:, [0, 2]] - [0.2, 0.1]
    lx = rel[:, 0] * np.cos(a) - rel[:, 1] * np.sin(a)
    lz = rel[:, 0] * np.sin(a) + rel[:, 1] * np.cos(a)
    inside = np.maximum(np.abs(lx), np.abs(lz)) - 0.8
    outside_d = np.hypot(np.maximum(np.abs(lx) - 0.8, 0), np.maximum(np.abs(lz) - 0.8, 0))
    dist = np.where(inside > 0, outside_d, -inside) / np.maximum(texel, 1e-9)
    near, far = floor & (dist < 0.5 / np.sqrt(2)), floor & (dist > 1.6)
    assert near.sum() > 20 and far.sum() > 1000
    assert edge[near].all(), int((~edge[near]).sum())
    assert not edge[far].any(), int(edge[far].sum())


# ---------------------------------------------------------------------------------------------
# soft shadows

@pytest.fixture(scope="module")
def planes(frame_of):
    from shadowlab.reference import store
    frame = frame_of("parallel_planes")
    truth, _ = store.load(frame.scene.spec)
    return frame, truth


def test_soft_matches_the_truth_like_pcss(planes):
    """On ``parallel_planes`` (square light, closed-form penumbra) the filtered visibility map is
    within a small RMSE of the truth in the penumbra, close to ``pcss`` and far below ``hard``."""
    from shadowlab.pipeline import technique_metrics
    frame, truth = planes
    m = {n: technique_metrics(frame, truth, get(n).render(frame, {}))[0] for n in ("sm_dpsv_soft", "pcss", "hard")}
    assert m["sm_dpsv_soft"]["vis_rmse_penumbra"] < 0.025, m["sm_dpsv_soft"]["vis_rmse_penumbra"]
    assert m["sm_dpsv_soft"]["vis_rmse_penumbra"] < 0.1 * m["hard"]["vis_rmse_penumbra"]
    assert m["sm_dpsv_soft"]["leak_rate"] == 0.0


PANEL = {"name": "L", "kind": "rect", "position": [0.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0],
         "up": [0.0, 0.0, 1.0], "size": [1.0, 1.0], "power": 100.0, "shadow_map": 1024}
EDGE_SHAPES = [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 4.0},
               {"name": "blocker", "type": "rectangle", "rotate": [1, 0, 0, -90], "translate": [-2.0, 2.0, 0.0],
                "scale": [2.0, 3.0, 1.0]}]


def test_soft_penumbra_has_the_same_world_width_from_any_camera_distance(mitsuba_backend, tmp_path):
    """``filter_size = world`` (the default): the filter is fixed in world units, so the shadow
    edge's 10–90 % width along the floor is the same seen from near and from far. The source's
    ``light_distance`` size has no camera term: its filter spans the same pixels from both, so twice
    the world width from twice the distance."""
    from shadowlab.render.gbuffer import vec_numpy
    widths, pixels = {}, {}
    for dist in (3.0, 6.0):
        cam = {"position": [0.0, 1.5, dist], "target": [0.0, 0.0, 0.0], "fov": 40,
               "resolution": [128, 128]}
        frame = _scene(tmp_path, PANEL, EDGE_SHAPES, camera=cam)
        p = vec_numpy(frame.gbuffer.p).astype(np.float64)
        sel = frame.gbuffer.valid.numpy() & (np.abs(p[:, 1]) < 1e-3) & (np.abs(p[:, 2]) < 0.5)
        for mode in ("world", "light_distance"):
            r = get("sm_dpsv_soft").render(frame, {"filter_size": mode})
            v, px = r.visibility["L"].numpy(), _flat(frame, r.aovs["L.filter_pixels"])
            s = sel & (v > 0.2) & (v < 0.8)
            assert s.sum() > 10
            slope, _ = np.polyfit(p[s, 0], v[s], 1)
            widths.setdefault(mode, []).append(0.8 / slope)
            pixels.setdefault(mode, []).append(np.median(px[sel & (px > 0)]))
    w, ld = widths["world"], widths["light_distance"]
    # the closed form: a straight edge under a square light of side 1 at (4 − 2)/2 · 1 = 1
    assert abs(w[0] - w[1]) < 0.1 * w[0], w
    assert 0.65 < w[0] < 1.0, w
    assert 1.7 < pixels["world"][0] / pixels["world"][1] < 2.3, pixels
    assert abs(pixels["light_distance"][0] / pixels["light_distance"][1] - 1.0) < 0.02, pixels
    assert 1.6 < ld[1] / ld[0] < 2.4, ld


SUN = {"name": "L", "kind": "directional", "direction": [0.0, -1.0, 0.0], "angular_diameter": 14.0,
       "irradiance": 3.0, "shadow_map": 1024}


@pytest.mark.parametrize("light", [PANEL, SUN], ids=["rect", "directional"])
def test_soft_filter_size_closed_forms(mitsuba_backend, tmp_path, light):
    """The filter's width in visibility-map pixels at receivers 4 m and 3 m below the blocker's light
    (a floor and a platform under the same blocker edge), against its closed form from the
    G-buffer. ``light_distance`` [Wang 2022, §1.4]: the penumbra w_p divided by the distance to the
    light, in widths of the light's map: w_p / (2·z̃·tan θ) × H (z̃ = 4 − y under the downward rect
    light), so at equal w_p the platform's filter has 4/3 of the floor's pixels; under the sun's
    orthographic map, w_p / (2·half extent) × H, the same at both. ``world``: w_p / (2 d tan θ_y / H),
    d the view depth."""
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.techniques.shadow_map import view_for
    platform = {"name": "platform", "type": "rectangle", "rotate": [1, 0, 0, -90], "translate": [0.0, 1.0, 1.5],
                "scale": [2.0, 1.0, 1.0]}
    cam = {"position": [0.0, 3.0, 6.0], "target": [0.0, 0.5, 0.5], "fov": 40, "resolution": [128, 128]}
    frame = _scene(tmp_path, light, EDGE_SHAPES + [platform], camera=cam)
    p = vec_numpy(frame.gbuffer.p).astype(np.float64)
    H = frame.screen.height
    face = view_for(frame, "L", get("sm_dpsv_soft").resolve({})).proj.faces[0]
    assert face.ortho == (light is SUN)
    across = np.full(len(p), 2.0 * face.scale) if face.ortho else 2.0 * face.scale * (4.0 - p[:, 1])
    pixel_world = np.maximum(2.0 * frame.screen.depth.numpy() * frame.camera.tan_y / H, 1e-12)
    floor, plat = np.abs(p[:, 1]) < 1e-3, np.abs(p[:, 1] - 1.0) < 1e-3
    for mode in ("light_distance", "world"):
        aovs = get("sm_dpsv_soft").render(frame, {"filter_size": mode}).aovs
        wp, px = (_flat(frame, aovs[f"L.{k}"]).astype(np.float64) for k in ("penumbra_width", "filter_pixels"))
        on = px > 0
        assert (on & floor).sum() > 20 and (on & plat).sum() > 20, mode
        expect = wp / across * H if mode == "light_distance" else wp / pixel_world
        np.testing.assert_allclose(px[on], expect[on], rtol=0.02, err_msg=mode)
        per_wp = px / np.maximum(wp, 1e-9)
        ratio = np.median(per_wp[on & plat]) / np.median(per_wp[on & floor])
        if mode == "light_distance":
            assert abs(ratio - (1.0 if face.ortho else 4.0 / 3.0)) < 0.03, ratio


def test_soft_interval_modes_and_search_taps(planes):
    """The search grid decides where a penumbra is found: one tap (the receiver's own texel) finds
    no blocker on the lit side of the edge, so the outer half of the penumbra stays lit; the
    depth-dependent spacing finds the same planar blocker as the constant one."""
    frame, _ = planes
    r = lambda **p: get("sm_dpsv_soft").render(frame, p).visibility["panel"].numpy()  # noqa: E731
    a, one, depth = r(), r(search_taps=1), r(interval_mode="depth", interval_k=64.0)
    for v in (a, one, depth):
        assert ((v >= 0) & (v <= 1)).all()
    outer = (a > 0.55) & (a < 0.95)
    assert outer.sum() > 50 and (one[outer] == 1.0).mean() > 0.9
    assert np.abs(depth - a).max() < 0.05


# ---------------------------------------------------------------------------------------------
# bad input

def test_area_lights_and_triangle_free_scenes_exit_2(capsys, tmp_path, mitsuba_backend):
    for tech in ("dpsv", "sm_dpsv"):
        rc = cli.main(["compare", "parallel_planes", "-t", tech, "--out", str(tmp_path / tech)])
        err = capsys.readouterr().err
        assert rc == 2 and "rect (area) light" in err and "sm_dpsv_soft" in err and "Traceback" not in err, err
    rc = cli.main(["compare", "mandelbulb", "-t", "sm_dpsv_soft", "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert rc == 2 and "SDF-only objects" in err and "Traceback" not in err, err
    from shadowlab.scene import parse
    sdf_only = parse({"name": "s", "camera": CAMERA, "lights": [LIGHTS["point"]],
                      "sdf": [{"name": "ball", "type": "sphere", "radius": 0.5}]}, str(tmp_path / "s.toml"))
    for tech in ("dpsv", "sm_dpsv", "sm_dpsv_soft"):
        assert "no triangles" in get(tech).unsupported(sdf_only)
