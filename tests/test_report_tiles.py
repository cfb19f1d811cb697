"""The report's virtual-shadow-map AOV images (vtsm/fvsm, [Giegl 2007, §4]): tile colours (a
distinct colour per tile id, grey for −1, × visibility), the SMTG grid overlay exactly at cell
boundaries, the demand and undersampling heat maps, their place in the HTML page of a synthetic run
(and the bad-input guarantee for them), and an end-to-end ``shadowlab compare street --techniques
fvsm`` that writes the tile image."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_report import N, make_run, parse_png, png_size

from shadowlab.errors import InputError
from shadowlab.report import build
from shadowlab.report.images import level_heatmap, level_range, undersampling_heatmap
from shadowlab.techniques import get
from shadowlab.techniques.virtual_maps import TILE_COLOURS, cell_edges, tile_colours, undersampling

ROOT = Path(__file__).resolve().parents[1]
GREY = [128, 128, 128]
WHITE = [255, 255, 255]


def test_distinct_tiles_get_distinct_colours_and_no_tile_is_grey():
    k = len(TILE_COLOURS)
    ids = np.arange(-1, 2 * k, dtype=np.float64)[None, :]       # −1, then two turns of the palette
    img = tile_colours(ids)
    assert img.dtype == np.uint8 and img.shape == (1, 2 * k + 1, 3)
    first = img[0, 1:k + 1]
    assert len({tuple(c) for c in first.tolist()}) == k          # ids 0 … k−1: all different
    assert img[0, 0].tolist() == GREY                             # −1: grey
    assert GREY not in first.tolist() and WHITE not in first.tolist()  # neither "no tile" nor a grid line
    assert np.array_equal(img[0, k + 1:], first)                 # the palette cycles: id j and j + k agree
    assert np.array_equal(tile_colours(ids + 1e-4), img)         # float AOVs round to the nearest id
    # × visibility like the cascade image; the grey of "no tile" is not darkened
    vis = np.linspace(0.0, 1.0, ids.shape[1])[None, :]
    dark = tile_colours(ids, visibility=vis)
    assert dark[0, 0].tolist() == GREY
    want = np.round(TILE_COLOURS[np.arange(2 * k) % k] * vis[0, 1:, None]).astype(np.uint8)
    assert np.array_equal(dark[0, 1:], want)
    assert tile_colours(np.array([[3.0]]), visibility=np.zeros((1, 1))).tolist() == [[[0, 0, 0]]]


def _loop_edges(c: np.ndarray) -> np.ndarray:
    """Reference (explicit loops): a pixel is on a line when its right or lower neighbour is in another cell."""
    h, w = c.shape
    out = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            for yy, xx in ((y, x + 1), (y + 1, x)):
                if yy < h and xx < w and c[y, x] >= 0 and c[yy, xx] >= 0 and c[y, x] != c[yy, xx]:
                    out[y, x] = True
    return out


def test_grid_lines_appear_exactly_at_cell_boundaries():
    h, w, n, cw, ch = 12, 20, 4, 5, 3                              # a 4 × 4 grid of 5 × 3-pixel cells
    y, x = np.mgrid[0:h, 0:w]
    cell = ((y // ch) * n + x // cw).astype(np.float32)
    edges = cell_edges(cell)
    want = ((x % cw == cw - 1) & (x < w - 1)) | ((y % ch == ch - 1) & (y < h - 1))
    assert np.array_equal(edges, want)
    tile = (x // 10).astype(np.float64)                            # two tiles, each holding 2 × 4 cells
    plain, lined = tile_colours(tile), tile_colours(tile, cell=cell)
    assert np.all(lined[want] == 255)                              # white lines on the boundaries …
    assert np.array_equal(lined[~want], plain[~want])              # … and the tile colours everywhere else
    # no cell (−1: no surface) draws no line, also not along its border
    cell2 = cell.copy()
    cell2[:, :7] = -1
    e2 = cell_edges(cell2)
    assert not e2[:, :7].any() and np.array_equal(e2[:, 7:], want[:, 7:])
    # an irregular (screen-projected) cell image against the loop reference
    rng = np.random.default_rng(5)
    irregular = np.floor((x + 0.6 * y + rng.normal(0, 0.3, (h, w))) / 4.0) + 3 * (y > 6)
    irregular[rng.random((h, w)) < 0.1] = -1
    assert np.array_equal(cell_edges(irregular), _loop_edges(irregular.astype(int)))
    assert not cell_edges(np.full((h, w), 7.0)).any()             # one cell: no line


def test_demand_and_undersampling_heat_maps():
    d = np.array([[2.0, 10.0, 18.0, 12.0, -1.0]])
    p = np.array([[4.0, 10.0, 11.0, -1.0, 9.0]])
    u = undersampling(d, p)
    assert u[0, :3].tolist() == [0.0, 0.0, 7.0] and np.isnan(u[0, 3:]).all()  # max(d − p, 0); none: NaN
    hm = undersampling_heatmap(u, scale=7)
    assert hm[0, 0].tolist() == WHITE and hm[0, 1].tolist() == WHITE          # demand met: white
    assert hm[0, 2].tolist() == [178, 24, 43] and hm[0, 3].tolist() == GREY   # most undersampled: red; none: grey
    lo, hi = level_range(d, percentile=100)
    assert (lo, hi) == (2, 18)                                                 # −1 is not a level
    lh = level_heatmap(d, lo=lo, hi=hi)
    assert lh[0, 0].tolist() == [33, 102, 172] and lh[0, 1].tolist() == WHITE and lh[0, 2].tolist() == [178, 24, 43]
    assert lh[0, 4].tolist() == GREY
    r = lh[0, :3, 0].astype(int)                                               # more demand: redder
    assert r[0] < r[1] and lh[0, 3, 2] < lh[0, 1, 2]


def _tile_run() -> tuple[dict, dict]:
    """make_run() with fvsm's report images and panels for pcf's light "key" (none for "fill" or pcss)."""
    run = make_run()
    y, x = np.mgrid[0:N, 0:N]
    cell = (y // 16) * 4 + x // 16
    tile = np.where(x < 8, -1, (x >= 32).astype(int) + 2 * (y >= 32))
    rgb = tile_colours(tile, cell, run["images"]["techniques"]["pcf"]["vis"]["key"]) / 255.0
    demand = np.where(x < 8, -1.0, 4.0 + y // 8)
    provided = np.where(x < 8, -1.0, np.full((N, N), 8.0))
    under = {ax: np.nan_to_num(undersampling(d, provided), nan=-1.0) for ax, d in (("x", demand), ("y", demand + 1))}
    aovs = {"tile": {"key": rgb}, "demand_x": {"key": demand}, "demand_y": {"key": demand + 1},
            "under_x": {"key": under["x"]}, "under_y": {"key": under["y"]}, "panels": get("fvsm").panels}
    run["images"]["techniques"]["pcf"].update(aovs)
    return run, {"rgb": rgb, "demand": demand, "provided": provided}


def test_the_html_page_shows_the_tile_demand_and_undersampling_images(tmp_path):
    run, want = _tile_run()
    out = tmp_path / "rep"
    build(out, run)
    pngs = {p.name for p in (out / "img").glob("*.png")}
    html = (out / "index.html").read_text()
    assert set(re.findall(r'src="img/([^"]+)"', html)) == pngs       # every image linked exists, and no other
    extra = {"t0_pcf_tile_0_key.png", "t0_pcf_demand_x_0_key.png", "t0_pcf_demand_y_0_key.png",
             "t0_pcf_under_x_0_key.png", "t0_pcf_under_y_0_key.png", "colorbar_pos.png"}
    assert extra <= pngs
    assert len(pngs) == 2 * 6 + 3 + 2 + 1 + len(extra)                # test_build_report's count + these
    assert not [p for p in pngs if "fill" in p and ("tile" in p or "demand" in p or "under" in p)]
    assert not [p for p in pngs if p.startswith("t1_") and ("tile" in p or "demand" in p)]
    for name in extra - {"colorbar_pos.png"}:
        assert png_size((out / "img" / name).read_bytes()) == (N, N)
    tile_png = parse_png((out / "img" / "t0_pcf_tile_0_key.png").read_bytes())
    assert np.array_equal(tile_png, np.round(want["rgb"] * 255).astype(np.uint8))
    assert "tiles" in html and "SMTG grid" in html and "log₂ texels" in html and "undersampling" in html
    under = parse_png((out / "img" / "t0_pcf_under_x_0_key.png").read_bytes())
    met = want["demand"] <= want["provided"]
    none = want["demand"] < 0
    assert np.all(under[met & ~none] == 255) and np.all(under[none] == 128)
    assert np.all(under[~met & ~none][:, 1] < 255)                    # undersampled: not white
    dem = parse_png((out / "img" / "t0_pcf_demand_x_0_key.png").read_bytes())
    assert np.all(dem[none] == 128) and not np.any(np.all(dem[~none] == 128, axis=-1))
    assert "images" not in json.loads((out / "metrics.json").read_text())  # images stay out of metrics.json


@pytest.mark.parametrize("breaker, key", [
    (lambda r: r["images"]["techniques"]["pcf"]["tile"].__setitem__("key", np.zeros((N, N))),
     "run.images.techniques.pcf.tile.key"),
    (lambda r: r["images"]["techniques"]["pcf"]["demand_x"]["key"].__setitem__((2, 2), np.nan),
     "run.images.techniques.pcf.demand_x.key"),
    (lambda r: r["images"]["techniques"]["pcf"].__setitem__("under_y", [1, 2]),
     "run.images.techniques.pcf.under_y"),
])
def test_bad_tile_images_raise_naming_the_key_and_write_nothing(tmp_path, breaker, key):
    run, _ = _tile_run()
    breaker(run)
    with pytest.raises(InputError, match=re.escape(key)):
        build(tmp_path / "new", run)
    assert not any(tmp_path.iterdir())


def test_compare_street_fvsm_writes_the_tile_image(tmp_path):
    out = tmp_path / "rep"
    env = {k: v for k, v in os.environ.items() if not k.startswith("SHADOWLAB_REF")}
    p = subprocess.run([sys.executable, "-m", "shadowlab.cli", "compare", "street", "--techniques", "fvsm",
                        "--set", "fvsm.t_max=256", "--set", "fvsm.grid=8", "--resolution", "128x72",
                        "--out", str(out)], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    html = (out / "index.html").read_text()
    srcs = set(re.findall(r'src="img/([^"]+)"', html))
    assert "t0_fvsm_tile_0_sun.png" in srcs and "SMTG grid" in html
    assert {"t0_fvsm_demand_x_0_sun.png", "t0_fvsm_demand_y_0_sun.png", "t0_fvsm_under_x_0_sun.png",
            "t0_fvsm_under_y_0_sun.png"} <= srcs
    img = parse_png((out / "img" / "t0_fvsm_tile_0_sun.png").read_bytes())
    assert img.shape == (72, 128, 3)
    px = {tuple(c) for c in img.reshape(-1, 3).tolist()}
    assert tuple(GREY) in px                                          # the sky: no tile
    assert tuple(WHITE) in px                                         # the SMTG grid overlay
    lit = {tuple(c) for c in TILE_COLOURS.tolist()} & px             # fully lit pixels show their tile's colour
    assert len(lit) >= 2                                              # several tiles
