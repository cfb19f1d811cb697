"""Virtual shadow maps (``vtsm``, ``fvsm``; shadowlab/techniques/virtual_maps.py, render/tiles.py):
Eq. (1) gives the G-buffer's points; the demand quantisation against its closed form on a plane
seen head-on and at a grazing angle; SMTG histogram buckets and the discard rule on a synthetic
demand; traversal leaves meet t_max and cover every demanding cell once; memory per tile mode
equals its formula; a tile equals the matching texels of one big map; a large ξ is one ordinary
focused map; FVSM's error falls with ξ and at ξ = 0 is within a stated factor of VTSM's with a
fraction of its tiles; bad values exit 2 naming the valid ones."""

import copy
import math
import subprocess
import sys

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.techniques import base
from shadowlab.render.tiles import cells_of
from shadowlab.techniques.virtual_maps import (GRIDS, SMTMM, bucket, cell_demand, demand_level, leaf_cells,
                                               memory_texels, pyramid, tile_grid, traverse)

from outdoor_scene import CAMERA, OUTDOOR as _OUTDOOR, SHAPES, SUN  # noqa: E402

OUTDOOR = {**_OUTDOOR, "camera": {**CAMERA, "resolution": [128, 72]}}
SMALL = {"t_max": 256, "grid": 8, "warp": "ortho"}   # the closed forms below are the orthographic map's


def _frame(scene: dict):
    from scene_builder import frame_from
    return frame_from(copy.deepcopy(scene))


@pytest.fixture(scope="module")
def outdoor(mitsuba_backend):
    return _frame(OUTDOOR)


@pytest.fixture(scope="module")
def centre(outdoor):
    from shadowlab.reference.truth import centre_visibility
    return centre_visibility(outdoor, "sun").numpy() >= 0.5


def _error_rate(frame, centre, result) -> float:
    valid = np.asarray(frame.gbuffer.valid.numpy(), bool)
    v = result.visibility["sun"].numpy() >= 0.5
    return float(np.mean(v[valid] != centre[valid]))


# ----------------------------------------------------------------------------- Eq. (1)

def test_eq1_unprojection_gives_the_gbuffer_points(outdoor):
    import drjit as dr
    import mitsuba as mi
    from shadowlab.render.gbuffer import vec_numpy
    cam, gb, scr = outdoor.camera, outdoor.gbuffer, outdoor.screen
    valid = np.asarray(gb.valid.numpy(), bool)
    xw = (mi.Float(scr.x) + 0.5) / scr.width
    yw = (mi.Float(scr.y) + 0.5) / scr.height
    p = cam.eye_unproject(xw, yw, scr.depth)
    dr.eval(p)
    got, want = vec_numpy(p)[valid], vec_numpy(gb.p)[valid]
    dist = np.linalg.norm(want - cam.position, axis=1)
    assert np.max(np.linalg.norm(got - want, axis=1) / dist) < 1e-5
    # the numpy path is the same map
    got_np = cam.eye_unproject(xw.numpy(), yw.numpy(), scr.depth.numpy())[valid]
    assert np.max(np.linalg.norm(got_np - want, axis=1) / dist) < 1e-5


# ----------------------------------------------------------------------------- the demand

def test_demand_level_is_round_half_up_of_minus_log2_delta_plus_half():
    k = np.arange(0, 20)
    assert demand_level(2.0 ** -k).tolist() == (k + 1).tolist()          # −log2 Δ an integer: one level up
    assert demand_level(np.array([0.3, 0.26, 0.24, 1e-4])).tolist() == [2, 2, 3, 14]
    assert demand_level(np.array([0.0, -1.0])).tolist() == [255, 255]
    import drjit as dr  # noqa: F401
    import mitsuba as mi
    d = np.geomspace(1e-6, 2.0, 257)
    assert demand_level(mi.Float(d.astype(np.float32))).numpy().astype(int).tolist() == \
        demand_level(d.astype(np.float32).astype(np.float64)).tolist()


def _plane_scene(camera: dict, direction) -> dict:
    sun = {**SUN, "direction": list(direction)}
    return {"name": "plane", "lights": [sun], "shapes": [SHAPES[0]], "camera": camera}


def _expected_levels(frame, face):
    """Closed form on the floor y = 0: each pixel's neighbours are the exact intersections of their
    camera rays with the plane; the footprint's NDC half extents give L = floor(−log2 Δ + 1)."""
    cam = frame.camera
    W, H = cam.width, cam.height
    X, Y = np.meshgrid(np.arange(W), np.arange(H), indexing="xy")

    def hit(px, py):
        p = cam.unproject(px.ravel() + 0.5, py.ravel() + 0.5, np.ones(px.size))
        d = p - cam.position
        t = -cam.position[1] / d[:, 1]
        return (cam.position + t[:, None] * d).reshape(*px.shape, 3)

    P = hit(X, Y)
    z = (P - cam.position) @ cam.forward
    steps = []
    for dx, dy in ((1, 0), (0, 1)):
        Pm, Pp = hit(X - dx, Y - dy), hit(X + dx, Y + dy)
        zm, zp = (Pm - cam.position) @ cam.forward, (Pp - cam.position) @ cam.forward
        use_p = np.abs(zp - z) <= np.abs(zm - z)
        steps.append(np.where(use_p[..., None], Pp - P, P - Pm))
    R = np.array(face.R)
    ax, ay = (np.abs(steps[0] @ R[i]) / face.scale for i in range(2))
    bx, by = (np.abs(steps[1] @ R[i]) / face.scale for i in range(2))
    dx_, dy_ = 0.5 * (ax + bx), 0.5 * (ay + by)
    return dx_, dy_


@pytest.mark.parametrize("camera, direction", [
    # head-on: looking straight down at the floor, the sun straight down too
    ({"position": [0.0, 10.0, 0.0], "target": [0.0, 0.0, 0.0], "up": [0, 0, -1], "fov": 50, "resolution": [48, 32],
      "near": 0.1, "far": 100.0}, [0.0, -1.0, 0.0]),
    # grazing: eye height 1.5 m over the floor, looking 40 m ahead; an oblique sun
    ({"position": [0.0, 1.5, 0.0], "target": [0.0, 0.0, -40.0], "fov": 60, "resolution": [48, 32],
      "near": 0.1, "far": 100.0}, [0.3, -1.0, 0.2]),
])
def test_demand_quantisation_matches_its_closed_form_on_a_plane(mitsuba_backend, camera, direction):
    frame = _frame(_plane_scene(camera, direction))
    t = base.get("fvsm")
    values = t.resolve({"grid": 4, "t_max": 256, "warp": "ortho"})
    face = t.base(frame, frame.lights[0], values).faces[0]
    d = t.demand(frame, t.base(frame, frame.lights[0], values), values)
    dx, dy = _expected_levels(frame, face)
    lx = d["lx"].numpy().reshape(dx.shape)
    ly = d["ly"].numpy().reshape(dy.shape)
    valid = frame.gbuffer.valid.numpy().reshape(dx.shape)
    # interior pixels (the border's outer neighbour is off screen), away from level boundaries
    inner = valid.copy()
    inner[[0, -1], :] = inner[:, [0, -1]] = False
    for got, delta in ((lx, dx), (ly, dy)):
        x = -np.log2(delta) + 1.0
        clear = inner & (np.abs(x - np.round(x)) > 1e-3)
        assert clear.sum() > 0.8 * inner.sum()
        assert np.array_equal(got[clear], demand_level(delta)[clear])
    if direction == [0.0, -1.0, 0.0]:
        # head-on: one pixel of world width w = 2·tan(fov/2)·z/W spans Δ = w/(2·scale) per axis
        cam = frame.camera
        w = 2.0 * cam.tan_x * 10.0 / cam.width
        R = np.array(face.R)
        ex, ey = cam.right * w, -cam.up * w
        delta = 0.5 * (abs(ex @ R[0]) + abs(ey @ R[0])) / face.scale
        assert set(lx[inner].tolist()) == {int(demand_level(np.array([delta]))[0])}
    else:
        # grazing: the demand grows toward the horizon (far pixels are smaller on the floor)
        assert np.mean(lx[2]) > np.mean(lx[-3]) or np.mean(ly[2]) > np.mean(ly[-3])


# ----------------------------------------------------------------------------- SMTG and the discard rule

def _smtmm(cells, levels, n):
    """A synthetic SMTMM: one pixel per (cell, level x, level y), pixel k at column k."""
    cells = np.asarray(cells)
    x = -1.0 + (cells[:, 0] + 0.5) * 2.0 / n
    y = 1.0 - (cells[:, 1] + 0.5) * 2.0 / n
    lx, ly = (np.asarray(levels)[:, i] for i in range(2))
    k = len(x)
    return SMTMM((1, k), 1, x, y, lx, ly, np.ones(k, bool))


def test_histogram_buckets_and_the_discard_rule_on_a_synthetic_demand():
    assert bucket([0, 16, 17, 18, 22, 23, 200], 17, 22).tolist() == [0, 0, 1, 2, 6, 7, 7]
    a = [10] * 96 + [18] * 3 + [25]              # cell (0, 0): 100 pixels
    b = [23, 24, 30]                              # cell (1, 0): all above η1
    cells = [(0, 0)] * len(a) + [(1, 0)] * len(b)
    levels = [(v, 5) for v in a] + [(v, 5) for v in b]
    g = tile_grid(_smtmm(cells, levels, 2), 2, 17, 22)
    assert g.count.tolist() == [[100, 3], [0, 0]]
    assert g.hist["x"][0, 0].tolist() == [96, 0, 3, 0, 0, 0, 0, 1]
    assert g.hist["x"][0, 1].tolist() == [0, 0, 0, 0, 0, 0, 0, 3]
    assert g.max["x"].tolist() == [[25, 30], [-1, -1]] and g.lo_max["x"][0, 0] == 10
    assert g.rect[0, 0].tolist() == [0, 0, 99, 0] and g.rect[0, 1].tolist() == [100, 0, 102, 0]

    def demand(frac):
        dx, dy, dropped = cell_demand(g, frac)
        return dx.tolist(), dy.tolist(), dropped.tolist()
    assert demand(0.0) == ([[25, 30], [-1, -1]], [[5, 5], [-1, -1]], [[0, 0], [0, 0]])
    # 1 % of 100: the one pixel at 25 goes; the three in cell (1, 0) are one bucket and stay
    assert demand(0.01)[0] == [[18, 30], [-1, -1]] and demand(0.01)[2][0] == [1, 0]
    # up to 4 pixels: the 18s go too, the demand is the highest level below η0
    assert demand(0.04)[0] == [[10, 30], [-1, -1]] and demand(0.04)[2][0] == [4, 0]
    assert demand(0.5)[0][0][0] == 10
    # the rule counts pixels, not levels: 3 % leaves the 18s (4 pixels > 3)
    assert demand(0.03)[0][0][0] == 18


def test_tile_grid_matches_scattered_per_pixel_updates_on_random_pixels():
    rng = np.random.default_rng(5)
    h, w, n, eta0, eta1 = 13, 17, 4, 17, 22
    k = h * w
    sm = SMTMM((h, w), 1, rng.uniform(-1, 1, k), rng.uniform(-1, 1, k), rng.integers(-3, 30, k),
               rng.integers(-3, 30, k), rng.random(k) > 0.25)
    sm.ok &= ~((sm.x < -0.5) & (sm.y > 0.5))                       # the top-left cell stays empty
    corner = (sm.x > 0.5) & (sm.y < -0.5)                            # the bottom-right one's levels are all
    sm.lx[corner], sm.ly[corner] = -3, -2                            # below the empty mark −1
    g = tile_grid(sm, n, eta0, eta1)
    ok = sm.ok
    cx, cy = cells_of(sm.x[ok], sm.y[ok], n)
    cell = cy * n + cx
    px, py = np.nonzero(ok.reshape(h, w))[1], np.nonzero(ok.reshape(h, w))[0]
    for a, L in (("x", sm.lx[ok]), ("y", sm.ly[ok])):
        m, lo = np.full(n * n, -1), np.full(n * n, -1)
        np.maximum.at(m, cell, L)
        np.maximum.at(lo, cell[L < eta0], L[L < eta0])
        hist = np.zeros(n * n * (eta1 - eta0 + 3), np.int64)
        np.add.at(hist, cell * (eta1 - eta0 + 3) + bucket(L, eta0, eta1), 1)
        assert g.max[a].ravel().tolist() == m.tolist() and g.lo_max[a].ravel().tolist() == lo.tolist()
        assert g.hist[a].ravel().tolist() == hist.tolist()
    rect = np.tile(np.array([np.iinfo(np.int64).max] * 2 + [-1, -1]), (n * n, 1))
    for j, (f, v) in enumerate(((np.minimum, px), (np.minimum, py), (np.maximum, px), (np.maximum, py))):
        f.at(rect[:, j], cell, v)
    assert g.rect.reshape(-1, 4).tolist() == rect.tolist()
    assert g.max["x"][0, 0] == -1 and g.count[0, 0] == 0 and (g.count > 0).sum() == n * n - 1


# ----------------------------------------------------------------------------- traversal

def _grid_demand(rng, n, lo, hi, empty=0.3):
    dx = rng.integers(lo, hi + 1, (n, n))
    dy = rng.integers(lo, hi + 1, (n, n))
    count = rng.integers(1, 50, (n, n)) * (rng.random((n, n)) > empty)
    dx, dy = np.where(count > 0, dx, -1), np.where(count > 0, dy, -1)
    rect = np.stack([rng.integers(0, 10, (n, n)), rng.integers(0, 10, (n, n)),
                     rng.integers(10, 20, (n, n)), rng.integers(10, 20, (n, n))], -1)
    rect = np.where(count[..., None] > 0, rect, [[[np.iinfo(np.int64).max] * 2 + [-1] * 2]])
    return dx, dy, count, rect


@pytest.mark.parametrize("seed, n, t_max, xi", [(0, 16, 256, 0), (1, 8, 1024, 0), (2, 32, 64, 2), (3, 16, 256, 3)])
def test_every_leaf_meets_t_max_and_the_leaves_cover_every_demanding_cell_once(seed, n, t_max, xi):
    rng = np.random.default_rng(seed)
    dx, dy, count, rect = _grid_demand(rng, n, 4, int(math.log2(t_max)) + int(math.log2(n)) + 2)
    lv = traverse(pyramid(dx, dy, count, rect), xi, t_max)
    K, lt = int(math.log2(n)), int(math.log2(t_max))
    assert len(lv) > 1
    # a leaf's demand (less ξ) fits t_max along each axis unless it is at the grid's finest level
    assert np.all((lv.lx - xi - lv.px <= lt) | (lv.px == K))
    assert np.all((lv.ly - xi - lv.py <= lt) | (lv.py == K))
    assert np.all((lv.w <= t_max) & (lv.h <= t_max) & (lv.w >= 1) & (lv.h >= 1))
    # the leaf's demand is the maximum over the cells it covers; its size is 2^(L − p) capped at t_max
    cover = np.zeros((n, n), int)
    for k in range(len(lv)):  # a test may loop over leaves: the assertion is per leaf
        sx, sy = n >> lv.px[k], n >> lv.py[k]
        block = (slice(lv.iy[k] * sy, (lv.iy[k] + 1) * sy), slice(lv.ix[k] * sx, (lv.ix[k] + 1) * sx))
        cover[block] += 1
        assert lv.lx[k] == dx[block].max() and lv.ly[k] == dy[block].max() and count[block].sum() > 0
        r = rect[block]   # its screen rectangle merges its cells' (an empty cell's is no rectangle)
        assert lv.rect[k].tolist() == [r[..., 0].min(), r[..., 1].min(), r[..., 2].max(), r[..., 3].max()]
        assert lv.w[k] == 2 ** min(max(lv.lx[k] - lv.px[k], 0), lt)
    assert np.all(cover[count > 0] == 1)
    assert cover.max() <= 1
    cells = leaf_cells(lv, n)
    assert np.all((cells >= 0) == (cover == 1))


def test_traversal_splits_only_the_axis_that_needs_it_and_large_xi_stops_at_the_root():
    n, t_max = 8, 256
    count = np.ones((n, n), int)
    rect = np.zeros((n, n, 4), int)
    dx, dy = np.full((n, n), 10), np.full((n, n), 6)        # x needs 1024 texels, y 64
    lv = traverse(pyramid(dx, dy, count, rect), 0, t_max)
    assert len(lv) == 4 and set(lv.px.tolist()) == {2} and set(lv.py.tolist()) == {0}
    assert lv.w.tolist() == [256] * 4 and lv.h.tolist() == [64] * 4
    lv = traverse(pyramid(np.full((n, n), 10), np.full((n, n), 10), count, rect), 0, t_max)
    assert len(lv) == 16 and set(zip(lv.px.tolist(), lv.py.tolist())) == {(2, 2)}
    one = traverse(pyramid(np.full((n, n), 30), np.full((n, n), 30), count, rect), 30, t_max)
    assert len(one) == 1 and (one.w[0], one.h[0]) == (t_max, t_max)


# ----------------------------------------------------------------------------- memory

def test_memory_accounting_equals_each_tile_modes_formula():
    t = 1024
    w = np.array([1024, 512, 512, 256, 64, 1024, 16])
    h = np.array([1024, 1024, 512, 128, 64, 256, 16])
    m = memory_texels(w, h, t)
    assert m["subrect"] == t * t
    # power-of-two series: texture k = t/2^k holds the tiles whose larger side is t/2^k
    assert m["pow2"] == 1024 ** 2 + 512 ** 2 + 256 ** 2 + 64 ** 2 + 16 ** 2
    assert m["pow2"] <= 4 * t * t / 3
    assert m["exact"] == sum(a * b for a, b in {(1024, 1024), (512, 1024), (512, 512), (256, 128), (64, 64),
                                               (1024, 256), (16, 16)})
    mo = memory_texels(w, h, t, overlap=1)
    assert mo["subrect"] == 1026 ** 2 and mo["pow2"] == sum((s + 2) ** 2 for s in (1024, 512, 256, 64, 16))
    assert memory_texels([], [], t) == {"subrect": 0, "pow2": 0, "exact": 0}


def test_rendered_memory_and_texels_follow_the_leaves(outdoor):
    t = base.get("fvsm")
    values = t.resolve({**SMALL, "overlap": 1})
    b = t.base(outdoor, outdoor.lights[0], values)
    lv = t.demand(outdoor, b, values)["leaves"]
    r = t.render(outdoor, {**SMALL, "overlap": 1, "tile_mode": "exact", "uncovered": "lit"})
    st = r.stats["lights"]["sun"]
    assert st["tiles"] == len(lv) and st["texels"] == int(np.sum((lv.w + 2) * (lv.h + 2)))
    assert st["memory_modes"] == {k: 4 * v for k, v in memory_texels(lv.w, lv.h, 256, 1).items()}
    assert st["memory_bytes"] == st["memory_modes"]["exact"]


# ----------------------------------------------------------------------------- tiles

def test_a_tile_holds_the_texels_of_one_big_map(outdoor):
    from shadowlab.render.lightview import FrustumSlice, light_view, projection
    from shadowlab.render.tiles import Tiles, render_tiles
    light = outdoor.lights[0]
    fit = FrustumSlice(0.1, 60.0, 2.0, False, "sphere")
    big = light_view(outdoor.scene, light, res=128, fit=fit, bits=24)
    proj = projection(light, outdoor.scene, 128, fit)
    # an anisotropic tile: columns 32..95 at full density, rows 64..127 at half density
    x0, x1 = -1.0 + 2 * 32 / 128, -1.0 + 2 * 96 / 128
    y1, y0 = 1.0 - 2 * 64 / 128, -1.0
    tv = render_tiles(outdoor.scene, light, proj, Tiles([x0], [y0], [x1], [y1], [64], [32]), 24)
    got = tv.depth.numpy().reshape(32, 64)
    want = big.depth[0, 64::2, 32:96]
    # the tile's texel centres are the big map's at full density along x; along y every other row's
    # centre moves by half a big texel, so compare where both rows agree (planar floor)
    same = np.abs(big.depth[0, 64::2, 32:96] - big.depth[0, 65::2, 32:96]) < 1e-4
    assert np.mean(np.abs(got - want)[same] <= 2.0 ** -23 + 1e-7) > 0.85
    full = render_tiles(outdoor.scene, light, proj, Tiles([-1], [-1], [1], [1], [128], [128]), 24)
    # float32 texel rays (the light view's are float64 until the cast): the same surface but at an edge
    step = 1.0 / (2 ** 24 - 1)
    assert np.mean(np.abs(full.depth.numpy().reshape(128, 128) - big.depth[0]) <= step + 1e-7) > 0.99
    assert np.mean(np.abs(full.slope.numpy().reshape(128, 128) - big.slope[0]) < 1e-5) > 0.99


def test_tiles_rendered_and_applied_a_wavefront_at_a_time_give_the_same_bits(outdoor, monkeypatch):
    from shadowlab.render import tiles as T
    t = T.Tiles(np.zeros(5), np.zeros(5), np.ones(5), np.ones(5), [4, 8, 2, 8, 1], [4, 8, 2, 8, 1])
    assert T.tile_groups(t, 64) == [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5)]
    assert T.tile_groups(t, 84) == [(0, 3), (3, 5)] and T.tile_groups(t, 10 ** 6) == [(0, 5)]
    whole = base.get("fvsm").render(outdoor, SMALL)
    monkeypatch.setattr(T, "chunk_texels", lambda: 70_000)
    parts = base.get("fvsm").render(outdoor, SMALL)
    assert whole.stats["lights"]["sun"]["tiles"] > 3
    assert np.array_equal(whole.visibility["sun"].numpy(), parts.visibility["sun"].numpy())
    assert np.array_equal(whole.aovs["sun.tile"], parts.aovs["sun.tile"])


def test_a_tile_larger_than_a_wavefront_is_cast_in_several_with_the_same_bits(outdoor, monkeypatch):
    """One 128² tile cast in wavefronts of 5000 texels (joined on the device) equals it cast in one."""
    from shadowlab.render import tiles as T
    from shadowlab.render.lightview import FrustumSlice, projection
    light = outdoor.lights[0]
    proj = projection(light, outdoor.scene, 128, FrustumSlice(0.1, 60.0, 2.0, False, "sphere"))
    tile = T.Tiles([-1], [-1], [1], [1], [128], [128])
    whole = T.render_tiles(outdoor.scene, light, proj, tile, 24)
    monkeypatch.setattr(T, "chunk_texels", lambda: 5000)
    parts = T.render_tiles(outdoor.scene, light, proj, tile, 24)
    assert whole.hit_texels == parts.hit_texels > 0
    for a, b in ((whole.depth, parts.depth), (whole.slope, parts.slope)):
        assert np.array_equal(a.numpy(), b.numpy())


def test_vtsm_is_one_focused_map_of_grid_times_t_max_texels_bit_for_bit(outdoor):
    """n × n tiles of t² hold exactly the texels of one n·t map of the same light camera: VTSM
    equals csm with one cascade (the same sphere fit, snapped) and a hard filter at n·t texels."""
    v = base.get("vtsm").render(outdoor, {"grid": 4, "t_max": 64, "focus": "sphere", "warp": "ortho"})
    c = base.get("csm").render(outdoor, {"cascades": 1, "filter": "hard", "resolution": 256, "blend": 0.0,
                                         "grazing_slope_bias": 0.0})      # tiles have no grazing term
    assert np.array_equal(v.visibility["sun"].numpy(), c.visibility["sun"].numpy())
    assert v.stats["lights"]["sun"]["tiles"] == 16 and v.stats["lights"]["sun"]["texels"] == 256 * 256
    shadowed = v.visibility["sun"].numpy() < 0.5
    assert 0.003 < shadowed.mean() < 0.5                    # shadows are there to compare


def test_a_large_xi_is_one_ordinary_focused_map(outdoor):
    from shadowlab.render.lightview import FrustumSlice
    from shadowlab.techniques.cascades import shadow_range
    from shadowlab.techniques.shadow_map import opaque_bias
    p = {**SMALL, "snap": False, "overlap": 0, "apply": "full", "focus": "sphere"}
    r = base.get("fvsm").render(outdoor, {**p, "xi": 16})
    st = r.stats["lights"]["sun"]
    assert st["tiles"] == 1 and st["texels"] == 256 * 256 and st["demand"][0] >= 8
    one = base.get("vtsm").render(outdoor, {"t_max": 256, "grid": 1, "snap": False, "focus": "sphere",
                                            "warp": "ortho"})
    assert np.array_equal(r.visibility["sun"].numpy(), one.visibility["sun"].numpy())
    # and that map is hard's on the same focused light camera, up to float32 texel-ray rounding
    hard = base.get("hard")
    values = hard.resolve({"resolution": 256, "grazing_slope_bias": 0.0})   # tiles have no grazing term
    n, f = shadow_range(outdoor.camera, outdoor.scene, base.get("fvsm").resolve(p))
    view = outdoor.light_view("sun", res=256, fit=FrustumSlice(n, f, 2.0, False, "sphere"))

    class Ctx:
        bias = opaque_bias(values)
    h = hard.evaluate(outdoor, outdoor.lights[0], view, values, Ctx())
    import drjit as dr
    hv = dr.select(h.active, h.visibility, 1.0).numpy()
    assert np.mean(hv == r.visibility["sun"].numpy()) > 0.999


def test_fvsm_error_falls_with_xi_and_nears_vtsm_with_a_fraction_of_its_tiles(outdoor, centre):
    """Hard-shadow error rate against the light centre's exact visibility. Stated factor: at ξ = 0
    FVSM's error is within 5× VTSM's (the same t_max, grid and focus; measured 4.6× with the
    default visible focus, 2.0× with the sphere) with at most a quarter of its tiles: FVSM sizes each
    tile for one texel per pixel, VTSM gives every tile t_max², several texels per pixel almost
    everywhere, so fewer pixel centres fall on the wrong side of a texel's edge."""
    err, tiles = [], []
    for xi in range(6):
        r = base.get("fvsm").render(outdoor, {**SMALL, "xi": xi, "apply": "full"})
        err.append(_error_rate(outdoor, centre, r))
        tiles.append(r.stats["lights"]["sun"]["tiles"])
    assert all(b >= a - 1e-3 for a, b in zip(err, err[1:])), err       # falls as ξ decreases, within noise
    assert err[0] < 0.6 * err[5] and tiles[0] > tiles[5] == 1
    v = base.get("vtsm").render(outdoor, SMALL)
    ev, tv = _error_rate(outdoor, centre, v), v.stats["lights"]["sun"]["tiles"]
    assert tv == 64 and ev < err[5]
    assert err[0] <= 5.0 * ev and tiles[0] <= tv / 4


def test_where_the_demand_exceeds_the_grid_fvsm_renders_vtsm_s_tile_and_agrees_bit_for_bit(outdoor):
    """A finest-level tile of t_max × t_max texels is VTSM's tile of that cell (the same virtual
    texel grid): every pixel FVSM shadows with one has VTSM's visibility, bit for bit."""
    p = {**SMALL, "overlap": 0, "apply": "full"}
    f = base.get("fvsm").render(outdoor, p)
    v = base.get("vtsm").render(outdoor, SMALL)
    fv = base.get("fvsm")
    values = fv.resolve(p)
    lv = fv.demand(outdoor, fv.base(outdoor, outdoor.lights[0], values), values)["leaves"]
    full = np.flatnonzero((lv.px == 3) & (lv.py == 3) & (lv.w == 256) & (lv.h == 256))
    assert len(full) >= 1
    tile = f.aovs["sun.tile"].ravel()
    at = np.isin(tile, full)
    assert at.sum() > 100
    assert np.array_equal(f.visibility["sun"].numpy()[at], v.visibility["sun"].numpy()[at])


def test_rect_application_leaves_only_pixels_the_smtmm_did_not_sample(outdoor):
    """Screen rectangles (§4.5) come from the SMTMM's samples: with one sample per pixel nothing
    is missed; with every 4th the pixels no sample stood for may be (counted, and lit, with
    ``uncovered`` = ``lit``, the source's clear value)."""
    full = base.get("fvsm").render(outdoor, {**SMALL, "smtmm_scale": 1, "uncovered": "lit"})
    assert full.stats["lights"]["sun"]["unshadowed_fraction"] == 0.0
    sub = base.get("fvsm").render(outdoor, {**SMALL, "smtmm_scale": 4, "uncovered": "lit"})
    tile = sub.aovs["sun.tile"]
    valid = outdoor.gbuffer.to_image(outdoor.gbuffer.valid) > 0
    frac = float(((tile < 0) & valid).sum()) / valid.sum()
    assert frac == pytest.approx(sub.stats["lights"]["sun"]["unshadowed_fraction"])
    assert np.all(sub.aovs["sun.tile"][~valid] == -1)
    assert np.all(sub.visibility["sun"].numpy()[(tile < 0).ravel()] == 1.0)


# ----------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("tech, values, allowed", [
    ("fvsm", {"t_max": 1000}, r"power of two from 1 to 16384"),
    ("vtsm", {"t_max": 3}, r"power of two from 1 to 16384"),
    ("fvsm", {"t_max": 32768}, r"allowed \[1, 16384\]"),
    ("fvsm", {"grid": 3}, "expected one of " + ", ".join(map(str, GRIDS))),
    ("vtsm", {"grid": 64}, "expected one of " + ", ".join(map(str, GRIDS))),
    ("fvsm", {"xi": -1}, r"allowed \[0, 16\]"),
    ("fvsm", {"eta0": 22, "eta1": 17}, r"eta0=22 must be below eta1=17"),
    ("fvsm", {"eta0": 20, "eta1": 20}, r"eta0=20 must be below eta1=20"),
    ("fvsm", {"warp": "psm"}, "expected one of ortho, lispsm"),
    ("vtsm", {"lispsm_n": 0.0}, r"allowed \[0.05, 100.0\] × n_opt"),
])
def test_bad_values_exit_2_naming_the_valid_values(tech, values, allowed):
    with pytest.raises(InputError, match=allowed) as e:
        base.get(tech).resolve(values)
    assert e.value.exit_code == 2


def test_the_cli_refuses_a_bad_t_max_with_exit_2_and_no_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "shadowlab.cli", "compare", "street", "--techniques", "fvsm",
                        "--set", "fvsm.t_max=1000", "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "power of two" in r.stderr + r.stdout and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_virtual_maps_refuse_lights_that_are_not_directional(mitsuba_backend):
    spot = {"name": "lamp", "kind": "spot", "position": [0, 5, 0], "target": [0, 0, -5], "angle": 40.0, "power": 100.0}
    from shadowlab.scene import parse
    spec = parse({**copy.deepcopy(OUTDOOR), "lights": [spot]}, "spot.toml")
    for name in ("fvsm", "vtsm"):
        why = base.get(name).unsupported(spec)
        assert "'lamp'" in why and "directional" in why


def test_fitting_searches_the_biases_of_the_test_every_tile_applies():
    from shadowlab.fit.run import default_loss, default_params
    for name in ("fvsm", "vtsm"):
        t = base.get(name)
        assert default_params(t, t.resolve({})) == default_params(base.get("hard"))
        assert default_loss(name) == default_loss("hard")


def test_visible_focus_holds_every_visible_point_and_its_texel_grid_holds_still(outdoor):
    import dataclasses
    from shadowlab.render.frame import make_frame
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.render.tiles import face_ndc
    from shadowlab.scene import build
    t = base.get("fvsm")
    values = t.resolve(SMALL)
    b0 = t.base(outdoor, outdoor.lights[0], values)
    f0 = b0.faces[0]
    x, y, z = (a.numpy() for a in face_ndc(f0, outdoor.gbuffer.p))
    valid = outdoor.gbuffer.valid.numpy()
    assert np.all(np.abs(x[valid]) <= 1) and np.all(np.abs(y[valid]) <= 1)
    assert np.all((z[valid] > f0.near) & (z[valid] < f0.far))
    # the camera moves 3 mm: new points, the same square size, a centre on the same texel grid
    spec = outdoor.scene.spec
    cam = dataclasses.replace(spec.camera, position=tuple(np.add(spec.camera.position, (0.003, 0.0, -0.002))),
                              target=tuple(np.add(spec.camera.target, (0.003, 0.0, -0.002))))
    moved = make_frame(build(dataclasses.replace(spec, camera=cam)), u_strata=1)
    assert not np.array_equal(vec_numpy(moved.gbuffer.p), vec_numpy(outdoor.gbuffer.p))
    fit0, fit1 = b0.fit, t.base(moved, moved.lights[0], values).fit
    assert fit0.half == fit1.half
    texel = 2.0 * fit0.half / (SMALL["grid"] * SMALL["t_max"])
    for a, b in ((fit0.cx, fit1.cx), (fit0.cy, fit1.cy)):
        steps = (b - a) / texel
        assert abs(steps - round(steps)) < 1e-6
    # without snapping the square follows the points
    free = t.resolve({**SMALL, "snap": False})
    assert t.base(moved, moved.lights[0], free).fit != t.base(outdoor, outdoor.lights[0], free).fit


def test_a_frame_seen_by_another_camera_takes_its_demand_and_focus_from_that_view(outdoor):
    """The shimmer evaluates frame 0's points with frame t's camera: a virtual map's tiles are frame
    t's, so its demand and focus come from what frame t's camera sees, not from frame 0's points."""
    import dataclasses
    from shadowlab.render.frame import FrameContext
    from shadowlab.render.gbuffer import gbuffer, vec_numpy
    from shadowlab.scene import build
    assert outdoor.own_gbuffer is outdoor.gbuffer and outdoor.own_screen is outdoor.screen
    spec = outdoor.scene.spec
    step = (0.0, 0.0, -5.0)
    cam = dataclasses.replace(spec.camera, position=tuple(np.add(spec.camera.position, step)),
                              target=tuple(np.add(spec.camera.target, step)))
    sc = build(dataclasses.replace(spec, camera=cam))
    moved = FrameContext(scene=sc, gbuffer=outdoor.gbuffer, unshadowed=outdoor.unshadowed, sdf=outdoor.sdf)
    own = moved.own_gbuffer
    assert own is not outdoor.gbuffer and own is moved.own_gbuffer
    assert np.array_equal(vec_numpy(own.p), vec_numpy(gbuffer(sc).p))
    t = base.get("fvsm")
    values = t.resolve(SMALL)
    assert t.base(moved, moved.lights[0], values).fit != t.base(outdoor, outdoor.lights[0], values).fit
    r = t.render(moved, SMALL)
    assert r.visibility["sun"].numpy().shape == outdoor.gbuffer.valid.numpy().shape
    assert r.stats["lights"]["sun"]["tiles"] >= 1


def test_discarding_extreme_demands_never_raises_a_cell_demand_or_adds_tiles(outdoor):
    """On a rendered frame: a larger discard share lowers cell demands (never raises them), makes
    no more tiles and drops at least as many pixels; with the paper's η0 = 17 every level of this
    small frame shares the lowest bucket, which the rule cannot split, so nothing is dropped."""
    t = base.get("fvsm")
    out = []
    for frac in (0.0, 0.1, 0.5):
        # η0 low enough that the histogram tells this small frame's levels apart (17 lumps them all)
        values = t.resolve({**SMALL, "discard": frac, "smtmm_scale": 1, "eta0": 4, "eta1": 20})
        d = t.demand(outdoor, t.base(outdoor, outdoor.lights[0], values), values)
        cdx, cdy, dropped = cell_demand(d["grid"], frac)
        out.append((cdx, cdy, dropped, len(d["leaves"])))
    for (ax, ay, da, ta), (bx, by, db, tb) in zip(out, out[1:]):
        assert np.all(bx <= ax) and np.all(by <= ay) and tb <= ta and db.sum() >= da.sum()
    assert out[0][2].sum() == 0 and out[-1][2].sum() > 0
    assert np.any(out[-1][0] < out[0][0]) or np.any(out[-1][1] < out[0][1])
    values = t.resolve({**SMALL, "discard": 0.5, "smtmm_scale": 1})
    d = t.demand(outdoor, t.base(outdoor, outdoor.lights[0], values), values)
    sm = d["smtmm"].numpy()
    assert d["dropped"].sum() == 0 and sm.lx[sm.ok].max() < 17


def _grids_equal(a, b) -> bool:
    return (a.n, a.eta0, a.eta1) == (b.n, b.eta0, b.eta1) and all(
        np.array_equal(x, y) and x.dtype == y.dtype for x, y in
        [(a.count, b.count), (a.rect, b.rect)] + [(getattr(a, f)[k], getattr(b, f)[k])
                                                  for f in ("max", "hist", "lo_max") for k in ("x", "y")])


def test_the_device_grid_is_the_numpy_grid(outdoor, mitsuba_backend):
    """A frame's SMTMM stays on the device and its SMTG is accumulated there: the same grid, cell for
    cell and bin for bin, as numpy's from the same samples read back (on a rendered frame, every
    grid size, and on random samples with an empty cell and levels below the empty mark)."""
    import mitsuba as mi

    from shadowlab.techniques.virtual_maps import DeviceSMTMM
    t = base.get("fvsm")
    for n in (1, 4, 16):
        values = t.resolve({**SMALL, "grid": n, "smtmm_scale": 2, "eta0": 4, "eta1": 20})
        d = t.demand(outdoor, t.base(outdoor, outdoor.lights[0], values), values)
        assert isinstance(d["smtmm"], DeviceSMTMM) and d["grid"].count.sum() > 0
        assert _grids_equal(d["grid"], tile_grid(d["smtmm"].numpy(), n, 4, 20)), n
    rng = np.random.default_rng(6)
    h, w, n, k = 13, 17, 4, 13 * 17
    x, y = rng.uniform(-1.2, 1.2, k), rng.uniform(-1.2, 1.2, k)
    ok = (rng.random(k) > 0.25) & ~((x < -0.5) & (y > 0.5)) & (np.abs(x) <= 1) & (np.abs(y) <= 1)
    lx, ly = rng.integers(-3, 30, k), rng.integers(-3, 30, k)
    host = SMTMM((h, w), 1, x, y, lx, ly, ok)
    dev = DeviceSMTMM((h, w), 1, mi.Float64(x), mi.Float64(y), mi.Int32(lx.astype(np.int32)),
                      mi.Int32(ly.astype(np.int32)), mi.Bool(ok))
    g = tile_grid(dev, n, 17, 22)
    assert _grids_equal(g, tile_grid(host, n, 17, 22)) and g.count[0, 0] == 0


@pytest.mark.parametrize("name, frame", [("street", None), ("boulevard", 0), ("boulevard", 11)])
def test_the_focus_bounds_read_from_the_device_are_numpys(mitsuba_backend, name, frame):
    """visible_square's light-space bounds, reduced on the device and settled by numpy on the few
    points near the extremes, are bit for bit numpy's over every point (and ±inf over none)."""
    import mitsuba as mi

    from shadowlab.render.frame import make_frame
    from shadowlab.render.gbuffer import vec_numpy
    from shadowlab.render.lightview import light_frame
    from shadowlab.scene import load
    from shadowlab.techniques.virtual_maps import light_bounds
    sc = load(name, resolution=(97, 61))
    f = make_frame(sc if frame is None else sc.at_frame(frame), u_strata=1)
    gb, R = f.gbuffer, light_frame(f.lights[0])
    q = vec_numpy(gb.p)[np.asarray(gb.valid.numpy(), bool)] @ R.T
    lo, hi = light_bounds(gb.p, gb.valid, R)
    assert np.array_equal(lo, q.min(axis=0)) and np.array_equal(hi, q.max(axis=0))
    lo, hi = light_bounds(gb.p, mi.Bool(np.zeros(len(q) * 0 + gb.size, bool)), R)
    assert np.all(lo == np.inf) and np.all(hi == -np.inf)
