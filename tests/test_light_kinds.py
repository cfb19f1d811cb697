"""Light kinds other than the point light of ``test_techniques_shadow_map.py``: delta spot and
directional lights, a point light whose cube map uses all six faces, PLY / OBJ mesh casters,
technique/truth pixel alignment on ``parallel_planes`` and the penumbra of a sun with an
angular size.

"Exact visibility" of a delta light is one Mitsuba shadow ray per G-buffer point: to the light's
position (spot, point) or along −direction to infinity (directional). It is compared on the
pixels the light reaches at all (``frame.lit_mask``: unshadowed light U_L > 0); elsewhere
visibility is multiplied by 0 and does not matter.
"""

import math
import struct

import numpy as np
import pytest

from shadowlab.errors import SceneError
from shadowlab.techniques import base
import lightview_scene
from lightview_scene import SHAPES
from scene_builder import frame_from
from cross_cpu import grazing_pixels

RES = [96, 96]
#: floor (tilted 0.05°, see test_techniques_shadow_map.py), a box and a sphere: lightview_scene.py's, at 96²
CAMERA = {**lightview_scene.CAMERA, "resolution": RES}
SPOT = {"name": "L", "kind": "spot", "position": [-0.4, 3.0, -2.0], "target": [0.1, 0.0, 0.6], "angle": 35.0,
        "power": 100.0, "shadow_map": 1024}
#: two small posts whose shadows land in the spot frustum's corners, outside the cone
POSTS = [{"name": "post", "type": "cube", "translate": [1.45, 0.25, -1.6], "scale": [0.1, 0.25, 0.1]},
         {"name": "post2", "type": "cube", "translate": [-1.7, 0.25, -1.0], "scale": [0.1, 0.25, 0.1]}]
SUN = {"name": "L", "kind": "directional", "direction": [0.3, -1.0, 0.8], "irradiance": 3.0, "shadow_map": 1024}


def _frame(scene_dict, path="scene.toml"):
    return frame_from(scene_dict, path)


def _hard(frame, name, **params):
    tech = base.get("hard")
    return frame.gbuffer.to_image(tech.render(frame, tech.resolve(params)).visibility[name])


def _exact_to_point(frame, position):
    import drjit as dr
    import mitsuba as mi
    gb = frame.gbuffer
    occ = frame.scene.mi_scene.ray_test(gb.si.spawn_ray_to(mi.Point3f(*[float(x) for x in position])), gb.valid)
    return gb.to_image(dr.select(occ, 0.0, 1.0))


def _exact_directional(frame, direction):
    import drjit as dr
    import mitsuba as mi
    gb = frame.gbuffer
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    occ = frame.scene.mi_scene.ray_test(gb.si.spawn_ray(mi.Vector3f(*[float(x) for x in -d])), gb.valid)
    return gb.to_image(dr.select(occ, 0.0, 1.0))


def _inside_frustum(frame, name):
    import drjit as dr
    gb = frame.gbuffer
    rec = frame.light_view(name).lookup(gb.p)
    return gb.to_image(dr.select(rec["inside"], 1.0, 0.0)) > 0.5, rec


def _points(frame):
    from shadowlab.render.gbuffer import vec_numpy
    gb = frame.gbuffer
    return vec_numpy(gb.p).reshape(gb.height, gb.width, 3).astype(np.float64)


# ---------------------------------------------------------------------------------------------
# 1. delta spot and delta directional lights

@pytest.fixture(scope="module")
def spot(mitsuba_backend):
    frame = _frame({"name": "spot_kinds", "camera": CAMERA, "lights": [SPOT], "shapes": SHAPES + POSTS})
    return frame, _hard(frame, "L"), _exact_to_point(frame, SPOT["position"])


def test_hard_spot_equals_exact_visibility(spot):
    """Measured: 1 of 5439 lit pixels differs (0.02 %); 551 lit pixels are in shadow."""
    frame, vis, exact = spot
    lit = frame.lit_mask("L")
    valid = frame.gbuffer.mask[..., 0]
    assert set(np.unique(vis[valid])) <= {0.0, 1.0}
    assert np.count_nonzero(lit & (exact == 0)) > 300
    assert np.mean((vis != exact)[lit]) < 0.005


def test_spot_frustum_covers_the_cone_and_is_lit_outside_it(spot):
    """The spot's light camera is one perspective face with tan(half fov) = tan(cone angle): a
    square frustum circumscribing the cone. Every pixel the spot lights lies in the cone and in
    the frustum. Outside the frustum the technique reports visibility 1; in the frustum's
    corners (outside the cone, where U = 0) it still depth-tests, like any point of the map:
    there it equals the exact ray test, shadows of the two posts included (46 pixels measured),
    and is not forced to 1."""
    frame, vis, exact = spot
    view = frame.light_view("L")
    assert view.nfaces == 1 and not view.proj.cube
    face = view.proj.faces[0]
    assert not face.ortho
    assert face.scale == pytest.approx(math.tan(math.radians(SPOT["angle"])), rel=1e-12)

    P = _points(frame)
    fwd = np.subtract(SPOT["target"], SPOT["position"])
    fwd /= np.linalg.norm(fwd)
    rel = P - np.array(SPOT["position"])
    cos = rel @ fwd / np.linalg.norm(rel, axis=-1)
    valid = frame.gbuffer.mask[..., 0]
    in_cone = valid & (cos >= math.cos(math.radians(SPOT["angle"])))
    lit = frame.lit_mask("L")
    inside, _ = _inside_frustum(frame, "L")
    assert lit.sum() > 3000
    assert not np.any(lit & (cos < math.cos(math.radians(SPOT["angle"])) - 1e-4))  # the spot lights its cone only
    assert np.all(inside[in_cone]), "the frustum must cover the cone"

    outside = valid & ~inside
    assert outside.sum() > 500
    assert np.all(vis[outside] == 1.0)
    corners = valid & inside & ~in_cone
    assert corners.sum() > 100
    assert not lit[corners].any()
    assert np.count_nonzero(exact[corners] == 0) > 20
    assert np.array_equal(vis[corners], exact[corners])


@pytest.fixture(scope="module")
def sun(mitsuba_backend):
    frame = _frame({"name": "sun_kinds", "camera": CAMERA, "lights": [SUN], "shapes": SHAPES})
    return frame, _hard(frame, "L"), _exact_directional(frame, SUN["direction"])


def test_hard_directional_equals_exact_visibility(sun):
    """Orthographic light camera along the direction, fitted to the scene's bounding sphere: every
    valid pixel projects into it. Measured: 2 of 6849 lit pixels differ (0.03 %), 301 shadowed."""
    frame, vis, exact = sun
    view = frame.light_view("L")
    face = view.proj.faces[0]
    assert view.nfaces == 1 and face.ortho
    d = np.asarray(SUN["direction"], float)
    assert np.allclose(face.R[2], d / np.linalg.norm(d))
    assert face.scale == pytest.approx(frame.scene.radius)
    valid = frame.gbuffer.mask[..., 0]
    inside, _ = _inside_frustum(frame, "L")
    assert np.all(inside[valid])
    lit = frame.lit_mask("L")
    assert set(np.unique(vis[valid])) <= {0.0, 1.0}
    assert np.count_nonzero(lit & (exact == 0)) > 200
    assert np.mean((vis != exact)[lit]) < 0.005


# ---------------------------------------------------------------------------------------------
# 2. a point light inside a ring of occluders: all six cube faces

RING = {
    "name": "ring",
    "camera": {"position": [0.5, 5.0, 3.0], "target": [0.0, 0.0, 0.0], "fov": 55, "resolution": RES},
    "lights": [{"name": "p", "kind": "point", "position": [0.0, 1.2, 0.0], "power": 100.0, "shadow_map": 512}],
    "shapes": [
        {"name": "floor", "type": "rectangle", "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "scale": 3.0},
        {"name": "east", "type": "cube", "translate": [1.0, 0.35, 0.1], "scale": [0.12, 0.35, 0.3]},
        {"name": "west", "type": "cube", "translate": [-1.0, 0.35, -0.1], "scale": [0.12, 0.35, 0.3]},
        {"name": "north", "type": "sphere", "center": [0.1, 0.35, -1.0], "radius": 0.3},
        {"name": "south", "type": "cylinder", "p0": [-0.2, 0.0, 1.0], "p1": [-0.2, 0.8, 1.0], "radius": 0.2},
        {"name": "lid", "type": "sphere", "center": [0.0, 2.1, 0.0], "radius": 0.25},
    ],
}


def test_point_light_in_a_ring_uses_all_six_cube_faces(mitsuba_backend):
    """Measured: 10 of 7111 lit pixels differ (0.14 %); shadowed lit pixels per face (+x, −x, +y,
    −y, +z, −z) = 454, 327, 0, 28, 540, 59: the four side faces all carry shadows."""
    frame = _frame(RING)
    vis = _hard(frame, "p")
    exact = _exact_to_point(frame, RING["lights"][0]["position"])
    lit = frame.lit_mask("p")
    assert np.mean((vis != exact)[lit]) < 0.005

    lv = frame.light_view("p")
    assert lv.proj.cube and lv.nfaces == 6
    for f in range(6):
        assert lv.hit[f].any(), f"cube face {f} saw nothing"
    # which face each pixel is looked up in
    _, rec = _inside_frustum(frame, "p")
    face = frame.gbuffer.to_image(rec["face"].numpy().astype(np.float32))
    shadowed = lit & (exact == 0)
    for f in (0, 1, 4, 5):  # ±x, ±z
        on_face = shadowed & (face == f)
        assert np.count_nonzero(on_face) > 30, f
        assert np.mean(vis[on_face] != 0) < 0.02, f


# ---------------------------------------------------------------------------------------------
# 3. PLY and OBJ mesh casters

def _write_meshes(d):
    """A regular tetrahedron (binary PLY, vertices (±1, ±1, ±1) with an even number of minus
    signs) and a cube [-1, 1]³ of 12 triangles (OBJ)."""
    (d / "meshes").mkdir(exist_ok=True)
    V = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], "<f4")
    F = [(0, 1, 2), (0, 3, 1), (0, 2, 3), (1, 3, 2)]
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n").encode()
    (d / "meshes" / "tet.ply").write_bytes(head + V.tobytes() + b"".join(struct.pack("<B3i", 3, *f) for f in F))
    cv = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    lines = [f"v {x} {y} {z}" for x, y, z in cv]
    lines += [f"f {a + 1} {b + 1} {c + 1}\nf {a + 1} {c + 1} {e + 1}" for a, b, c, e in quads]
    (d / "box.obj").write_text("\n".join(lines) + "\n")


MESH_LIGHT = {"name": "p", "kind": "point", "position": [0.0, 3.0, -1.2], "power": 100.0, "shadow_map": 512}
MESH_SHAPES = [
    {"name": "floor", "type": "rectangle", "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "scale": 3.0},
    {"name": "tet", "type": "ply", "filename": "meshes/tet.ply", "translate": [-0.8, 0.9, 0.0], "scale": 0.35},
    {"name": "crate", "type": "obj", "filename": "box.obj", "translate": [0.8, 0.6, 0.2], "rotate": [0, 1, 0, 20],
     "scale": 0.3},
]


def _mesh_scene():
    return {"name": "meshes", "camera": {"position": [0.0, 4.0, 4.0], "target": [0.0, 0.0, 0.3], "fov": 50,
                                         "resolution": RES},
            "lights": [MESH_LIGHT], "shapes": MESH_SHAPES}


def test_ply_and_obj_meshes_are_seen_and_cast_shadows(mitsuba_backend, tmp_path):
    """Measured: G-buffer pixels tet 171, crate 257; floor umbra pixels whose shadow ray first
    hits tet 317, crate 283; hard vs exact: 12 of 7242 lit pixels differ (0.17 %)."""
    import drjit as dr
    import mitsuba as mi
    from shadowlab.reference.truth import visibility

    _write_meshes(tmp_path)
    frame = _frame(_mesh_scene(), tmp_path / "meshes.toml")
    scene, gb = frame.scene, frame.gbuffer
    assert [s.filename for s in scene.spec.shapes[1:]] == [str((tmp_path / "meshes" / "tet.ply").resolve()),
                                                         str((tmp_path / "box.obj").resolve())]
    ids = {n: scene.shape_names.index(n) for n in ("floor", "tet", "crate")}
    # the transform applies to meshes: the tetrahedron's box is translate ± scale
    lo, hi = scene.shape_boxes[ids["tet"]]
    assert np.allclose(lo, [-1.15, 0.55, -0.35], atol=1e-5) and np.allclose(hi, [-0.45, 1.25, 0.35], atol=1e-5)
    sid = gb.shape_id[..., 0]
    for n in ("tet", "crate"):
        assert np.count_nonzero(sid == ids[n]) > 50, n

    lt = visibility(frame, "p")
    exact = _exact_to_point(frame, MESH_LIGHT["position"])
    lit = frame.lit_mask("p")
    assert np.array_equal(lt.V[lit], exact[lit])  # a delta light: one exact shadow ray
    # which shape blocks each shadow ray
    si = scene.mi_scene.ray_intersect(gb.si.spawn_ray_to(mi.Point3f(*MESH_LIGHT["position"])), gb.valid)
    shapes = scene.mi_scene.shapes_dr()
    blocker = dr.full(mi.Int32, -1, dr.width(si.p))
    for i in range(len(scene.shape_names)):
        blocker = dr.select(si.is_valid() & (si.shape == dr.gather(type(shapes), shapes, i)), i, blocker)
    blocker = blocker.numpy().reshape(gb.height, gb.width)
    umbra = (sid == ids["floor"]) & (lt.V < 0.02)
    for n in ("tet", "crate"):
        assert np.count_nonzero(umbra & (blocker == ids[n])) > 50, n

    vis = _hard(frame, "p")
    assert np.mean((vis != exact)[lit]) < 0.005


def test_missing_mesh_file_raises_scene_error_naming_filename(tmp_path):
    from shadowlab.scene import parse
    d = _mesh_scene()
    with pytest.raises(SceneError) as e:
        parse(d, str(tmp_path / "meshes.toml"))  # no mesh files written
    msg = str(e.value)
    assert "shapes[1].filename" in msg and "tet.ply" in msg and str(tmp_path) in msg


# ---------------------------------------------------------------------------------------------
# 4. the technique's pixels and the truth's pixels are the same points

def _edge_offsets(vis, A, floor):
    """Per image column: (row of the hard shadow's 0→1 flip, at the boundary between pixel
    centres r−1 and r, i.e. r − 0.5) − (row where the truth's A crosses 0.5, linearly
    interpolated between pixel centres). Columns with not exactly one of each are skipped."""
    H, W = vis.shape
    out = []
    for c in range(W):
        f = floor[1:, c] & floor[:-1, c]
        flips = np.nonzero(f & (vis[:-1, c] == 0) & (vis[1:, c] == 1))[0]
        ups = np.nonzero(f & (A[:-1, c] < 0.5) & (A[1:, c] >= 0.5))[0]
        if len(flips) == 1 and len(ups) == 1:
            r = ups[0]
            ra = r + (0.5 - A[r, c]) / (A[r + 1, c] - A[r, c])
            out.append(flips[0] + 0.5 - ra)
    return np.array(out)


def test_hard_edge_on_parallel_planes_sits_on_the_truths_half_visible_contour(mitsuba_backend):
    """Square light of side 1 at height 4, half-plane occluder x < 0 at height 2: the hard shadow
    from the light's centre ends at x = 0, where exactly half the light is visible (A = 0.5).
    The edge is along z, i.e. along image rows. Measured over 128 columns: mean offset
    −0.13 px (the edge's position inside its pixel row), std 0.05 px, max |offset| 0.33 px;
    shifting the technique's image by one row gives +0.87 / −1.13 px."""
    from shadowlab.reference import store
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build, load_spec, resolve

    spec = load_spec(resolve("parallel_planes"))
    truth, _ = store.load(spec)
    frame = make_frame(build(spec), u_strata=1)
    gb = frame.gbuffer
    assert truth.lights["panel"].A.shape == (gb.height, gb.width) == (128, 128)
    # the committed truth's mask is this machine's G-buffer's but for rays that graze an edge (tests/cross_cpu.py)
    assert (truth.mask != gb.mask[..., 0]).sum() <= grazing_pixels(truth.mask.size)
    vis = _hard(frame, "panel")
    A = truth.lights["panel"].A
    floor = (gb.shape_id[..., 0] == frame.scene.shape_names.index("floor")) & gb.mask[..., 0]

    off = _edge_offsets(vis, A, floor)
    assert len(off) > 100
    assert abs(off.mean()) < 0.5, off.mean()
    assert np.mean(np.abs(off) < 0.5) > 0.95
    for shift in (1, -1):
        moved = _edge_offsets(np.roll(vis, shift, axis=0), A, floor)
        assert len(moved) > 100
        assert abs(moved.mean()) >= 0.5, (shift, moved.mean())


# ---------------------------------------------------------------------------------------------
# 5. a sun with an angular size: penumbra width h·tan(θ/2)·(s90 − s10)

def _disk_fraction(s):
    """Fraction of a unit disk on one side of a straight line at signed offset s (radii)."""
    s = np.clip(s, -1.0, 1.0)
    return 0.5 + (s * np.sqrt(1.0 - s * s) + np.arcsin(s)) / np.pi


def test_sun_penumbra_width_matches_the_disk_closed_form(mitsuba_backend):
    """Sun of angular diameter θ = 4° straight overhead, half-plane occluder x < 0 at height
    h = 1, camera looking straight down at the floor (x constant along image columns). A floor
    point at x sees the edge at x/(h·tan(θ/2)) disk radii from the sun's centre, so the visible
    fraction is τ(s) = 1/2 + (s√(1−s²) + asin s)/π; τ = 0.1, 0.9 at s = ∓0.6870, the 10–90 %
    width is 1.3741·h·tan(θ/2) = 0.04798. Measured: 0.04804 (ratio 1.001), A = 0.5 at
    x = 0.0003, column means within 0.005 of τ."""
    from scipy.optimize import brentq
    from shadowlab.reference.truth import visibility

    h, theta = 1.0, 4.0
    scene = {
        "name": "sun_edge",
        "camera": {"position": [0.0, 0.5, 0.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, 1], "fov": 30,
                   "resolution": RES},
        "lights": [{"name": "sun", "kind": "directional", "direction": [0, -1, 0], "angular_diameter": theta,
                    "irradiance": 3.0}],
        "shapes": [{"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 2.0},
                   {"name": "occluder", "type": "rectangle", "translate": [-2.0, h, 0.0], "rotate": [1, 0, 0, 90],
                    "scale": 2.0}],
    }
    frame = _frame(scene)
    gb = frame.gbuffer
    assert np.all(gb.shape_id[..., 0] == frame.scene.shape_names.index("floor"))
    lt = visibility(frame, "sun")
    P = _points(frame)
    assert np.ptp(P[..., 0], axis=0).max() < 1e-5  # x is constant down each column
    x, a = P[0, :, 0], lt.A.mean(axis=0)
    order = np.argsort(x)
    x, a = x[order], a[order]
    assert a[0] == 0.0 and a[-1] == 1.0 and np.all(np.diff(a) >= -0.01)

    def crossing(level):
        i = np.nonzero((a[:-1] < level) & (a[1:] >= level))[0]
        assert len(i) == 1
        i = i[0]
        return x[i] + (level - a[i]) / (a[i + 1] - a[i]) * (x[i + 1] - x[i])

    half = math.tan(math.radians(theta / 2))
    s10 = brentq(lambda s: _disk_fraction(s) - 0.1, -1, 1)
    s90 = brentq(lambda s: _disk_fraction(s) - 0.9, -1, 1)
    assert s90 == pytest.approx(-s10) and s90 == pytest.approx(0.68705, abs=1e-4)
    expected = (s90 - s10) * h * half
    width = crossing(0.9) - crossing(0.1)
    pixel = abs(x[1] - x[0])
    assert expected > 10 * pixel  # the penumbra spans many pixels
    assert width == pytest.approx(expected, rel=0.05), (width, expected)
    assert abs(crossing(0.5)) < pixel
    assert np.max(np.abs(a - _disk_fraction(x / (h * half)))) < 0.02
