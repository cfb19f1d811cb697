"""``fvsm`` against its source [Giegl 2007, §3.2, §4.3, §4.5, §4.10, §5]: overlapping tiles
remove the seams at the borders of tiles (§5), a later tile overwrites an earlier one (§3.2),
the SMTMM samples each block's centre pixel (§4.3), the exact tile mode's memory stays within
2·4/3·t_max² when aspect ratios are at most 2 (§4.10), and screen rectangles shade a fraction of
the pixels a full-screen pass would (§4.5, §5 Fig. 6)."""

import numpy as np
import pytest

from shadowlab.techniques import base

from scene_builder import floor, frame_from, scene  # noqa: E402  (tests/ is on the path)

SUN = {"name": "sun", "kind": "directional", "direction": [0.3, -1.0, 0.2], "irradiance": 3.0,
       "angular_diameter": 0.0, "shadow_map": 256}
CAM = {"position": [0.0, 6.0, 4.0], "target": [0.0, 0.0, 0.0], "fov": 50}
BARS = [{"name": f"bar{i}", "type": "cube", "translate": [0.0, 1.5, z], "scale": [5.0, 0.05, 0.4]}
        for i, z in enumerate((-2.0, 0.0, 2.0))]
#: a coarse SMTMM over a fine grid: cells between the sampled pixels get no tile, so tile borders
#: run through the shadows of the bars
SEAMY = {"smtmm_scale": 8, "grid": 32, "t_max": 64, "apply": "full", "focus": "visible", "uncovered": "lit",
         "warp": "ortho"}


@pytest.fixture(scope="module")
def bars(mitsuba_backend):
    """Three bars 1.5 m over a floor: shadow bands across the whole view."""
    return frame_from(scene("seam", camera=CAM, resolution=(96, 64), lights=[SUN], shapes=[floor(8.0)] + BARS))


@pytest.fixture(scope="module")
def centre(bars):
    from shadowlab.reference.truth import centre_visibility
    return centre_visibility(bars, "sun").numpy() >= 0.5


def _plan(frame, values):
    """(the base light camera, the leaves, the tiles, the points' map NDC x, y) of fvsm."""
    from shadowlab.render.tiles import face_ndc
    from shadowlab.techniques.virtual_maps import tile_rects
    t = base.get("fvsm")
    v = t.resolve(values)
    light = frame.lights[0]
    b = t.base(frame, light, v)
    lv = t.demand(frame, b, v)["leaves"]
    x, y, _ = face_ndc(b.faces[0], frame.gbuffer.p)
    scr = frame.screen
    rs = None if v["apply"] == "full" else int(v["smtmm_scale"])
    return b, lv, tile_rects(lv, int(v["overlap"]), rs, (scr.width, scr.height)), x.numpy(), y.numpy()


# ----------------------------------------------------------------------------- overlap (§5)

def test_overlapping_tiles_remove_the_seams_at_tile_borders(bars, centre):
    """§5: "tile borders visible in the shadows from precision issues ... fixed by letting the
    tiles overlap slightly". Without overlap the points just past a tile's border in a cell that
    got no tile of its own are written by no tile and stay lit, shadows included (a seam); with
    one texel of overlap the neighbouring tile writes them, exactly those within one of its
    texels of its border, and gets them right."""
    valid = bars.gbuffer.valid.numpy().astype(bool)
    r0 = base.get("fvsm").render(bars, {**SEAMY, "overlap": 0})
    r1 = base.get("fvsm").render(bars, {**SEAMY, "overlap": 1})
    t0, t1 = (np.asarray(r.aovs["sun.tile"]).reshape(-1) for r in (r0, r1))
    v0, v1 = (r.visibility["sun"].numpy() >= 0.5 for r in (r0, r1))
    seam = valid & (t0 < 0)
    assert seam.sum() > 20 and np.all(v0[seam])                      # unwritten: lit
    new = seam & (t1 >= 0)
    assert (new & ~centre).sum() >= 5                                 # seams through shadows
    assert np.array_equal(v1[new], centre[new])                      # the overlap shades them right
    # the newly written points lie within one texel of their tile's own rectangle (overlap 0)
    _, lv, core, x, y = _plan(bars, {**SEAMY, "overlap": 0})
    k = t1[new].astype(np.int64)
    tx, ty = (core.x1 - core.x0) / lv.w, (core.y1 - core.y0) / lv.h
    out_x = np.maximum(np.maximum(core.x0[k] - x[new], x[new] - core.x1[k]), 0.0)
    out_y = np.maximum(np.maximum(core.y0[k] - y[new], y[new] - core.y1[k]), 0.0)
    assert np.all(out_x <= tx[k] * (1 + 1e-4)) and np.all(out_y <= ty[k] * (1 + 1e-4))
    assert np.all((out_x > 0) | (out_y > 0))


# ----------------------------------------------------------------------------- order (§3.2)

def test_a_later_tile_overwrites_an_earlier_one(bars):
    """§3.2: tiles are applied one after another into the shadow result texture, so where tiles
    overlap a point reads the last one (in traversal order) whose texture holds it."""
    vals = {**SEAMY, "overlap": 2}
    r = base.get("fvsm").render(bars, vals)
    tile = np.asarray(r.aovs["sun.tile"]).reshape(-1)
    _, _, tiles, x, y = _plan(bars, vals)
    valid = bars.gbuffer.valid.numpy().astype(bool)
    holds = (x[:, None] >= tiles.x0) & (x[:, None] <= tiles.x1) & (y[:, None] >= tiles.y0) & (y[:, None] <= tiles.y1)
    last = np.where(holds.any(1), len(tiles) - 1 - np.argmax(holds[:, ::-1], axis=1), -1)
    assert (holds.sum(1)[valid] >= 2).sum() > 50                     # overlaps to decide
    assert np.array_equal(tile[valid], last[valid])


# ----------------------------------------------------------------------------- SMTMM (§4.3)

@pytest.mark.parametrize("scale", [2, 4, 8])
def test_the_smtmm_samples_each_blocks_centre_pixel(bars, scale):
    """The SMTMM holds every scale-th pixel, the one at each scale × scale block's centre
    (pixel scale·i + scale/2): its map positions and levels are the per-pixel maps' there."""
    t = base.get("fvsm")
    v = t.resolve({**SEAMY, "smtmm_scale": scale})
    b = t.base(bars, bars.lights[0], v)
    d = t.demand(bars, b, v)
    scr = bars.screen
    H, W = scr.height, scr.width
    img = lambda a: np.asarray(a.numpy(), np.float64).reshape(H, W)[scale // 2::scale, scale // 2::scale]  # noqa: E731
    sm = d["smtmm"].numpy()                     # sampled on the device
    assert sm.shape == (H // scale, W // scale)
    assert np.array_equal(sm.x.reshape(sm.shape), img(d["x"]).astype(np.float32).astype(np.float64))
    assert np.array_equal(sm.lx.reshape(sm.shape), img(d["lx"]).astype(np.int64))
    assert np.array_equal(sm.ly.reshape(sm.shape), img(d["ly"]).astype(np.int64))


# ----------------------------------------------------------------------------- memory (§4.10)

@pytest.mark.parametrize("t_max", [64, 1024, 4096])
def test_the_exact_modes_memory_is_at_most_two_times_four_thirds_of_t_max_squared(t_max):
    """§4.10: with every tile of aspect ratio at most 2, the distinct shapes are s², s × s/2 and
    s/2 × s for s = t_max/2^k, Σ 2·s² = 2·(4/3)·t_max²·(1 − 4^−(K+1)): below 2·4/3·t_max² and close
    to it when every shape occurs; pow2's series stays below 4/3·t_max²."""
    from shadowlab.techniques.virtual_maps import memory_texels
    K = int(np.log2(t_max))
    s = t_max // 2 ** np.arange(K + 1)
    w = np.concatenate([s, s, np.maximum(s // 2, 1)])
    h = np.concatenate([s, np.maximum(s // 2, 1), s])
    m = memory_texels(w, h, t_max)
    bound = 2.0 * 4.0 / 3.0 * t_max ** 2
    assert m["exact"] <= bound and m["exact"] > 0.99 * bound
    assert m["pow2"] <= 4.0 / 3.0 * t_max ** 2 and m["subrect"] == t_max ** 2
    rng = np.random.default_rng(t_max)                                # any subset of those shapes
    for _ in range(20):
        pick = rng.random(len(w)) < 0.5
        assert memory_texels(w[pick], h[pick], t_max)["exact"] <= bound


def test_rendered_tiles_of_aspect_at_most_two_stay_within_the_bound(bars):
    t = base.get("fvsm")
    r = t.render(bars, {**SEAMY, "overlap": 0, "tile_mode": "exact", "t_max": 64})
    _, lv, _, _, _ = _plan(bars, {**SEAMY, "overlap": 0})
    assert np.all(np.maximum(lv.w, lv.h) <= 2 * np.minimum(lv.w, lv.h))
    assert r.stats["lights"]["sun"]["memory_bytes"] <= 4 * 2.0 * 4.0 / 3.0 * 64 ** 2


# ----------------------------------------------------------------------------- rectangles (§4.5)

def test_screen_rectangles_shade_a_fraction_of_the_full_screen_passes(bars):
    """§4.5, §5 Fig. 6: a tile applied through the screen rectangle of its SMTMM pixels (one block
    more on every side) writes far fewer pixels than a full-screen pass; every pixel it writes
    with a tile gets the tile whose texture holds it, as the full pass would where only one does."""
    vals = {**SEAMY, "apply": "rect", "smtmm_scale": 4, "grid": 16, "t_max": 128}
    _, _, tiles, x, y = _plan(bars, vals)
    scr = bars.screen
    area = (tiles.screen[:, 2] - tiles.screen[:, 0]) * (tiles.screen[:, 3] - tiles.screen[:, 1])
    gain = area.sum() / (len(tiles) * scr.width * scr.height)
    assert len(tiles) > 4 and gain < 0.5, gain
    r = base.get("fvsm").render(bars, vals)
    full = base.get("fvsm").render(bars, {**vals, "apply": "full"})
    t_r, t_f = (np.asarray(q.aovs["sun.tile"]).reshape(-1) for q in (r, full))
    holds = (x[:, None] >= tiles.x0) & (x[:, None] <= tiles.x1) & (y[:, None] >= tiles.y0) & (y[:, None] <= tiles.y1)
    one = (holds.sum(1) == 1) & (t_r >= 0)
    assert one.sum() > 100 and np.array_equal(t_r[one], t_f[one])
    assert np.array_equal(r.visibility["sun"].numpy()[one], full.visibility["sun"].numpy()[one])
    # a pixel of a block next to the tile's sampled blocks may fall in its texture: the rectangle
    # takes one more block on every side, so every such pixel in the tile's texture is written
    _, lv, _, _, _ = _plan(bars, vals)
    s = 4
    bx, by = np.asarray(scr.x.numpy()) // s, np.asarray(scr.y.numpy()) // s
    valid = bars.gbuffer.valid.numpy().astype(bool)
    near = np.zeros(len(bx), bool)
    for k in range(len(tiles)):                                       # the tiles, not the pixels
        x0, y0, x1, y1 = lv.rect[k]
        near |= holds[:, k] & (bx >= x0 - 1) & (bx <= x1 + 1) & (by >= y0 - 1) & (by <= y1 + 1)
    edge = near & valid & ~(holds & (bx[:, None] >= lv.rect[:, 0]) & (bx[:, None] <= lv.rect[:, 2])
                             & (by[:, None] >= lv.rect[:, 1]) & (by[:, None] <= lv.rect[:, 3])).any(1)
    assert edge.sum() > 10 and np.all(t_r[edge] >= 0)


# ----------------------------------------------------------------------------- uncovered pixels

@pytest.mark.parametrize("apply", ["rect", "full"])
def test_the_fallback_leaves_no_pixel_without_a_tile(bars, centre, apply):
    """``uncovered`` = ``fallback`` (the default): a pixel no tile writes reads the tile whose
    texture holds it (the one a full-screen pass gives it), else one coarse tile of the whole map
    (appended last, min(t_max, 128) texels across); with ``lit`` (the source's clear value) the
    same pixels stay lit."""
    vals = {**SEAMY, "apply": apply}
    lit = base.get("fvsm").render(bars, vals)
    fb = base.get("fvsm").render(bars, {**vals, "uncovered": "fallback"})
    full = base.get("fvsm").render(bars, {**vals, "apply": "full"})
    valid = bars.gbuffer.valid.numpy().astype(bool)
    t_lit, t_fb, t_full = (np.asarray(r.aovs["sun.tile"]).reshape(-1) for r in (lit, fb, full))
    gap = valid & (t_lit < 0)
    assert gap.sum() > 20 and np.all(lit.visibility["sun"].numpy()[gap])
    assert np.all(t_fb[valid] >= 0) and fb.stats["lights"]["sun"]["unshadowed_fraction"] == 0.0
    by_texture = gap & (t_full >= 0)
    assert np.array_equal(t_fb[by_texture], t_full[by_texture])
    coarse = gap & (t_full < 0)
    n = lit.stats["lights"]["sun"]["tiles"]
    assert coarse.sum() > 5 and np.all(t_fb[coarse] == n) and fb.stats["lights"]["sun"]["tiles"] == n + 1
    assert fb.stats["lights"]["sun"]["texels"] == lit.stats["lights"]["sun"]["texels"] + 64 * 64
    assert fb.stats["lights"]["sun"]["memory_bytes"] == lit.stats["lights"]["sun"]["memory_bytes"] + 4 * 64 * 64
    v = fb.visibility["sun"].numpy() >= 0.5
    assert np.mean(v[coarse] == centre[coarse]) > 0.9 and (~centre[coarse]).sum() > 0
    assert np.array_equal(fb.visibility["sun"].numpy()[valid & ~gap], lit.visibility["sun"].numpy()[valid & ~gap])
