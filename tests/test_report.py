"""Report building from synthetic arrays: files, PNG validity, metrics.json shape, HTML links,
heat-map colours and the bad-input guarantee (InputError, out_dir untouched)."""

from __future__ import annotations

import json
import math
import re
import struct
import zlib
from pathlib import Path

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
    assert "contact" in html and "64×64" in html and "256 spp" in html and "image-rendering: pixelated" in html

    # summary.md: reference line, one row per technique, 4 significant digits, best in bold
    md = (out / "summary.md").read_text()
    assert "Reference: 256 spp, max standard error 0.004" in md
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
