"""Report building from synthetic arrays: files, PNG validity, metrics.json shape, HTML links,
heat-map colours and the bad-input guarantee (InputError, out_dir untouched)."""

from __future__ import annotations

import json
import math
import re
import struct
import zlib

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.io.png import encode_png, to_srgb8, write_png
from shadowlab.report import build, summary_table
from shadowlab.report.images import common_exposure, signed_error_heatmap

N = 64


def parse_png(data: bytes) -> np.ndarray:
    """Minimal PNG decoder for our own files (8-bit, no interlace, filter type 0 rows)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        chunks.append((kind, body))
        pos += 12 + length
    assert chunks[0][0] == b"IHDR" and chunks[-1][0] == b"IEND"
    w, h, depth, ctype, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, comp, filt, interlace) == (8, 0, 0, 0)
    c = {0: 1, 2: 3, 6: 4}[ctype]
    raw = zlib.decompress(b"".join(b for k, b in chunks if k == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(h, 1 + w * c)
    assert np.all(rows[:, 0] == 0)
    return rows[:, 1:].reshape(h, w, c)


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def make_run(names=("pcf", "pcss")) -> dict:
    y, x = np.mgrid[0:N, 0:N] / (N - 1)
    truth_vis = {"key": np.clip((x - 0.3) / 0.4, 0, 1), "fill": np.clip((y - 0.2) / 0.5, 0, 1)}
    albedo = np.stack([0.8 * np.ones_like(x), 0.6 * np.ones_like(x), 0.4 * np.ones_like(x)], -1)
    shade = lambda v: albedo * (0.7 * v["key"] + 0.3 * v["fill"])[..., None]  # noqa: E731
    techniques, timgs = {}, {}
    for i, name in enumerate(names):
        vis = {k: np.clip(v + 0.05 * (i + 1) * np.sin(7 * x + i), 0, 1) for k, v in truth_vis.items()}
        timgs[name] = {"shaded": shade(vis), "vis": vis}
        techniques[name] = {
            "params": {"light_size": np.float32(0.1 * (i + 1)), "taps": 16},
            "time_s": 0.01 * (i + 1),
            "metrics": {"rmse": np.float64(0.02 * (i + 1)), "psnr": 30.0 - i, "ssim": 0.9 + 0.01 * i,
                        "leak_rate": float("nan") if i == 0 else 0.001},
            "per_light": {"key": {"rmse": 0.01 * (i + 1), "leak_rate": 0.0}, "fill": {"rmse": 0.03}},
        }
    return {
        "scene": "contact",
        "resolution": [N, N],
        "reference": {"spp": 256, "max_std_error": 0.004, "seed": 7},
        "lights": ["key", "fill"],
        "images": {"truth": {"shaded": shade(truth_vis), "vis": truth_vis}, "mitsuba": shade(truth_vis) * 1.01,
                   "techniques": timgs},
        "techniques": techniques,
        "machine": {"cpu": "test", "threads": np.int64(2)},
        "command": ["shadowlab", "compare", "contact"],
    }


def test_encode_png_known_pixels(tmp_path):
    img = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255]], [[0, 0, 0], [128, 128, 128], [255, 255, 255]]], np.uint8)
    data = encode_png(img)
    assert png_size(data) == (3, 2)
    assert np.array_equal(parse_png(data), img)
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert np.array_equal(parse_png(encode_png(grey))[..., 0], grey)
    p = write_png(tmp_path / "sub" / "f.png", np.array([[0.0, 1.0], [0.5, 2.0]]))
    dec = parse_png(p.read_bytes())
    assert dec.shape == (2, 2, 3) and dec[0, 0].tolist() == [0, 0, 0] and dec[0, 1].tolist() == [255] * 3
    assert dec[1, 0].tolist() == [188] * 3  # sRGB(0.5) = 0.7354
    assert [f.name for f in p.parent.iterdir()] == ["f.png"]  # no temp file left
    with pytest.raises(InputError):
        to_srgb8(np.array([[np.nan]]))


def test_heatmap_colours():
    e = np.array([[0.0, 0.5, -0.5, 3.0, -3.0]])
    hm = signed_error_heatmap(e, scale=1.0)
    assert hm.dtype == np.uint8 and hm.shape == (1, 5, 3)
    assert hm[0, 0].tolist() == [255, 255, 255]
    r, g, b = (hm[0, 1].astype(int))
    assert r > b and r > g  # positive: red (brighter)
    r, g, b = (hm[0, 2].astype(int))
    assert b > r  # negative: blue (darker)
    assert np.array_equal(hm[0, 3], signed_error_heatmap(np.array([[1.0]]), 1.0)[0, 0])  # saturates
    # default scale: 99th percentile of |err|, at least 1e-6 -> all-zero error is all white
    assert np.all(signed_error_heatmap(np.zeros((4, 4))) == 255)
    assert common_exposure(np.full((4, 4, 3), 0.45)) == pytest.approx(2.0)


def test_build_report(tmp_path):
    run = make_run()
    out = tmp_path / "reports" / "run1"
    index = build(out, run)
    assert index == out / "index.html"
    for f in ("index.html", "summary.md", "metrics.json"):
        assert (out / f).is_file()
    pngs = sorted(p.name for p in (out / "img").glob("*.png"))
    assert pngs
    for name in pngs:
        data = (out / "img" / name).read_bytes()
        if name != "colorbar.png":
            assert png_size(data) == (N, N), name
        parse_png(data)
    # 2 techniques × (2 lights × 2 + 2) + truth (shaded + 2 vis) + mitsuba (2) + colorbar
    assert len(pngs) == 2 * 6 + 3 + 2 + 1
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temp dir left

    # metrics.json: exact shape, round trip, NaN -> null
    m = json.loads((out / "metrics.json").read_text())
    assert set(m) == {"scene", "resolution", "reference", "techniques", "lights", "machine", "command"}
    assert m["scene"] == "contact" and m["resolution"] == [N, N] and m["reference"]["spp"] == 256
    for name, t in m["techniques"].items():
        assert set(t) == {"params", "time_s", "metrics", "per_light"}
    assert m["techniques"]["pcf"]["metrics"]["leak_rate"] is None
    assert m["techniques"]["pcf"]["params"]["light_size"] == pytest.approx(0.1)
    assert m["machine"]["threads"] == 2
    assert json.loads(json.dumps(m)) == m
    assert summary_table(m) == summary_table(run)  # the summary also works on a loaded metrics.json

    # HTML references exactly the PNGs that exist
    html = (out / "index.html").read_text()
    srcs = set(re.findall(r'src="img/([^"]+)"', html))
    assert srcs == set(pngs)
    assert "contact" in html and "64×64" in html and "256 shadow rays" in html and "image-rendering: pixelated" in html

    # summary.md: reference line, one row per technique, 4 significant digits, best in bold
    md = (out / "summary.md").read_text()
    assert "Reference: 256 shadow rays per pixel and light (mean; " in md and "max standard error 0.004" in md
    rows = [ln for ln in md.splitlines() if ln.startswith("| pcf") or ln.startswith("| pcss")]
    assert len(rows) == 2
    assert "**0.02**" in rows[0] and "**30**" in rows[0]  # lowest rmse, highest psnr
    assert "**0.91**" in rows[1] and "n/a" in rows[0]  # highest ssim; NaN leak_rate

    # rebuilding into an existing out_dir keeps the user's files
    (out / "notes.txt").write_text("mine")
    (out / "img" / "stale.png").write_bytes(b"x")
    build(out, make_run(names=("pcf",)))
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "img" / "stale.png").exists()
    assert list(json.loads((out / "metrics.json").read_text())["techniques"]) == ["pcf"]


@pytest.mark.parametrize(
    "breaker, key",
    [
        (lambda r: r["images"]["techniques"]["pcss"]["vis"]["key"].__setitem__((3, 3), np.nan),
         "run.images.techniques.pcss.vis.key"),
        (lambda r: r["images"]["truth"].__setitem__("shaded", np.zeros((N, N + 1, 3))), "run.images.truth.shaded"),
        (lambda r: r["techniques"]["pcf"].pop("metrics"), "metrics"),
        (lambda r: r["images"]["truth"]["vis"].pop("fill"), "fill"),
        (lambda r: r["reference"].pop("spp"), "spp"),
        (lambda r: r.__setitem__("machine", object()), "run.machine"),
    ],
)
def test_bad_run_leaves_out_dir_untouched(tmp_path, breaker, key):
    out = tmp_path / "rep"
    build(out, make_run())
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    bad = make_run()
    breaker(bad)
    with pytest.raises(InputError, match=re.escape(key)):
        build(out, bad)
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rep"]


def test_bad_run_into_missing_dir_creates_nothing(tmp_path):
    bad = make_run()
    bad["images"]["truth"]["shaded"][0, 0, 0] = math.nan
    with pytest.raises(InputError, match="run.images.truth.shaded"):
        build(tmp_path / "new", bad)
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------
# the page as a comparison tool: two metric tables, charts, the comparator's data, the gate's
# verdict, the light summary, lights in view left out of the colour scale, the gate page's bars


def _tables(html: str) -> list[list[str]]:
    """The header cells of each metrics table of the page, in order."""
    return [
        re.findall(r"<th>([^<]*)</th>", t) for t in re.findall(r'<table class="metrics"><thead>(.*?)</thead>', html)
    ]


def _scale_after(html: str, alt: str) -> float:
    i = html.index(f'alt="{alt}"')
    return float(re.search(r"<span>0</span><span>\+([^<]+)</span>", html[i:]).group(1))


def test_metrics_are_split_into_key_columns_and_the_rest(tmp_path):
    run = make_run()
    for t in run["techniques"].values():
        t["metrics"].update({"rmse_penumbra": 0.1, "mae": 0.01, "mae_penumbra": 0.02, "flip_penumbra": 0.3})
    html = build(tmp_path / "r", run).read_text()
    key, rest = _tables(html)[:2]
    assert key == ["technique", "rmse", "rmse_penumbra", "leak_rate", "psnr", "ssim", "time_s"]
    assert rest == ["technique", "mae", "mae_penumbra", "flip_penumbra"]
    assert "| mae_penumbra |" in (tmp_path / "r" / "summary.md").read_text()  # the Markdown keeps one table


def test_scatter_labels_of_clustered_points_do_not_overlap():
    """Techniques of nearly equal time and error (vsm/evsm/msm, sdf_linear/sdf_convex) used to
    print their labels on top of each other; each label box is now clear of the others and of
    every point, and a label moved away has a leader line to its point."""
    from shadowlab.report.charts import _CHAR_W, _LABEL_H, scatter_chart
    names = ["vsm", "evsm", "msm", "sdf_linear", "sdf_convex", "hard"]
    pts = [(n, 0.010 + 1e-5 * i, 0.050 + 1e-5 * i, "#000") for i, n in enumerate(names[:-1])] + \
        [("hard", 0.5, 0.2, "#000")]
    svg = scatter_chart("t", pts, xlabel="time", ylabel="rmse")
    labels = re.findall(r'<text x="([-\d.]+)" y="([-\d.]+)">([a-z_]+)</text>', svg)
    assert sorted(n for _, _, n in labels) == sorted(names)
    boxes = {n: (float(x) - 1, float(y) + 3 - _LABEL_H, _CHAR_W * len(n) + 2, _LABEL_H) for x, y, n in labels}
    centres = re.findall(r'<circle cx="([\d.]+)" cy="([\d.]+)"', svg)
    dots = [(float(cx) - 5, float(cy) - 5, 10, 10) for cx, cy in centres]

    def hit(a, b):
        return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]
    items = list(boxes.items())
    assert not [(a, b) for i, (a, ba) in enumerate(items) for b, bb in items[i + 1:] if hit(ba, bb)]
    assert not [n for n, b in boxes.items() for d in dots if hit(b, d)]
    assert svg.count("<line") - svg.count('stroke="#eee"') >= 3          # leader lines of the moved labels


def test_charts_and_comparator_data(tmp_path):
    run = make_run()
    band = lambda r: [{"lo": 0.0, "hi": 5.0, "pixels": 3, "rmse": r, "rmse_penumbra": r, "leak_rate": 0.0,  # noqa: E731
                       "overdark_rate": 0.0}, {"lo": 5.0, "hi": float("inf"), "pixels": 3, "rmse": 2 * r,
                                               "rmse_penumbra": r, "leak_rate": 0.0, "overdark_rate": 0.0}]
    run["techniques"]["pcf"]["bands"] = {"key": {"distance": band(0.1)}}
    run["techniques"]["pcss"]["bands"] = {"key": {"distance": band(0.2)}}
    run["techniques"]["pcss"]["per_light"]["key"]["rmse_penumbra"] = 0.02
    out = tmp_path / "r"
    html = build(out, run).read_text()
    charts = re.findall(r'<svg class="chart".*?</svg>', html, re.S)
    assert len(charts) == 4                                    # penumbra RMSE, leak rate, time scatter, bands of key
    assert "<title>pcss · key: 0.02</title>" in charts[0]     # per-light bars carry their exact value
    assert "<title>pcf · key: n/a</title>" in charts[0]       # missing: n/a, no bar
    assert "<title>pcf · key: 0</title>" in charts[1]
    assert charts[2].count("<circle") == 2 and "log scale" not in charts[2]
    assert "key: visibility RMSE by distance" in charts[3] and "≥5" in charts[3]
    assert '<script src=' not in html and "http" not in "".join(charts).replace("http://www.w3.org/2000/svg", "")
    data = json.loads(re.search(r'<script type="application/json" id="cmp-data">(.*?)</script>', html, re.S).group(1))
    assert (data["width"], data["height"]) == (N, N)
    assert [i["name"] for i in data["items"]] == ["pcf", "pcss", "mi.render (Mitsuba direct)"]
    assert [l["label"] for l in data["items"][0]["layers"]] == ["shaded", "key visibility", "fill visibility"]
    for it in data["items"]:                                   # every image the comparator shows exists
        for l in it["layers"]:
            assert all((out / l[k]).is_file() for k in ("a", "b", "err")), l
            assert float(l["scale"]) > 0


def test_a_light_in_view_is_left_out_of_the_mitsuba_error_scale(tmp_path):
    run = make_run()
    before = _scale_after(build(tmp_path / "a", run).read_text(), "signed error mi.render - truth")
    run["images"]["mitsuba"][10:20, 10:20] = 32.0             # a sphere light in view: 2.4 % of the pixels
    run["images"]["truth"]["shaded"][10:20, 10:20] = 0.0       # no shading point there in the truth
    guessed = _scale_after(build(tmp_path / "b", run).read_text(), "signed error mi.render - truth")
    assert guessed < 0.1 and before < 0.1
    em = np.zeros((N, N), bool)
    em[10:20, 10:20] = True
    run["images"]["emitter"] = em                              # the G-buffer's pixels on a light
    exact = _scale_after(build(tmp_path / "c", run).read_text(), "signed error mi.render - truth")
    assert exact == pytest.approx(guessed, rel=0.05)
    run["images"]["emitter"] = em[:, :-1]
    with pytest.raises(InputError, match="run.images.emitter"):
        build(tmp_path / "d", run)


def test_emitter_pixels_from_the_gbuffer_shape_ids():
    from shadowlab.report.images import emitter_pixels, error_scale, grow
    sid = np.full((4, 4, 4), 0, np.int32)
    sid[1, 1, 0] = 3                                           # one sub-pixel sees the light's shape
    em = emitter_pixels(sid, {"bulb": 3, "sun": 5})
    assert em.sum() == 1 and em[1, 1]
    assert grow(em).sum() == 9
    err = np.zeros((4, 4))
    err[1, 1] = 32.0
    err[3, 3] = 0.25
    assert error_scale(err, 100) == 32.0 and error_scale(err, 100, exclude=grow(em)) == 0.25


def test_the_light_summary_says_a_spot_with_a_radius_has_no_cone(tmp_path):
    from shadowlab.report.lights import light_info
    from shadowlab.scene.spec import LightSpec
    run = make_run()
    run["light_info"] = light_info([LightSpec("key", "spot", radius=0.2, angle=35.0),
                                    LightSpec("fill", "spot", radius=0.0, angle=20.0)])
    html = build(tmp_path / "r", run).read_text()
    table = re.search(r'<table class="metrics lights">.*?</table>', html, re.S).group(0)
    assert "no cone in the truth" in table and "radius 0.2 m, angle 35°" in table
    assert "hard cone of half-angle 20°" in table
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["light_info"]["key"]["kind"] == "spot"
    run["light_info"] = {"key": "spot"}
    with pytest.raises(InputError, match="run.light_info.key"):
        build(tmp_path / "s", run)


def test_the_gate_verdict_is_at_the_top_not_a_json_dump(tmp_path):
    run = make_run()
    run["ingest"] = {"image": "frame.exr", "mode": "visibility", "against": "V", "channels": {"key": "shadow.key"},
                     "notes": ["a note"]}
    run["gate"] = {"file": "gate.toml", "passed": False, "failed": ["g stat.pixels"], "lines": ["…"],
                   "checks": [{"gate": "g", "check": "budget.rmse", "kind": "budget", "value": 0.01, "threshold": 0.05,
                               "op": "<=", "passed": True, "text": "ok"},
                              {"gate": "g", "check": "stat.pixels", "kind": "stat", "value": 0.9, "threshold": 0.99,
                               "op": ">=", "passed": False, "text": "fraction of pixels that pass"}]}
    html = build(tmp_path / "r", run).read_text()
    verdict = html.index('<div class="verdict fail" id="verdict"><span class="word">FAIL</span>')
    assert verdict < html.index("<h2>Metrics</h2>") and verdict < html.index("Reference: 256 shadow rays")
    rows = re.findall(r'<td class="(pass|fail)">', html)
    assert rows == ["fail", "pass"]                            # failed checks first
    assert "shadow.key" in html and "note: a note" in html
    assert '"passed"' not in html and '"checks"' not in html   # no JSON of the gate or the ingest
    assert "## Gate: FAIL (gate.toml)" in (tmp_path / "r" / "summary.md").read_text()
    run["gate"]["passed"], run["gate"]["failed"] = True, []
    html = build(tmp_path / "r", run).read_text()
    assert '<div class="verdict pass" id="verdict"><span class="word">PASS</span>' in html


def test_the_gate_pages_heat_maps_have_colour_bars():
    from types import SimpleNamespace as NS

    from shadowlab.gate.html import page_html
    ref = np.full((8, 8), 0.5)
    err = np.linspace(-0.2, 0.2, 64).reshape(8, 8)
    check = NS(name="stat.pixels", passed=False, value=0.5, op=">=", threshold=0.99, text="")
    r = NS(name="g", passed=False, target="visibility", info={"alpha_value": 1e-6}, failed=[check], checks=[check],
           images={"candidate": ref + err, "reference": ref, "error": err, "pvalue": np.full((8, 8), 0.5),
                   "failed_pixels": np.zeros((8, 8), bool)})
    html = page_html([r])
    assert html.count("data:image/png;base64,") == 4          # the bars are CSS, not images
    assert html.count('class="cbar err"') == 1 and html.count('class="cbar pv"') == 1
    s = f"{float(re.search(r'±([0-9.e-]+)', html).group(1)):.3g}"
    assert f"<span>&minus;{s}</span><span>0</span><span>+{s}</span>" in html
    assert "p = 1e-06" in html and "untested" in html
