"""``shadowlab sweep``: a point's metrics are ``compare``'s, the results are the same bits on Dask
workers as in this process, a bias sweep follows what a bias does, bad input exits 2 before any
job runs, and the report has a chart per metric per scene."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from shadowlab import cli, pipeline
from shadowlab.errors import InputError
from shadowlab.report.jsonable import to_jsonable
from shadowlab.sweep import parse_range, results_only, sweep

RES = (48, 48)
SCENES = ["contact", "parallel_planes"]
# hard's receiver-side constant bias: z̃ = z − constant_bias, lit where the stored depth ≥ z̃, so a
# larger bias lights a superset of the pixels; 10 world units lie beyond every depth in these scenes
PARAM = "constant_bias=0:10:3"


@pytest.fixture(scope="module")
def store48(tmp_path_factory, mitsuba_backend):
    """A reference store with contact and parallel_planes at 48×48 (cheap truths)."""
    base = tmp_path_factory.mktemp("refs")
    for s in SCENES:
        pipeline.reference(s, RES, base=base, progress=False, max_rounds=16, spp=0)
    return base


@pytest.fixture(scope="module")
def embedded(store48, tmp_path_factory):
    """The sweep in this process, with its report."""
    out = tmp_path_factory.mktemp("sweep") / "report"
    rec = sweep(SCENES, "hard", PARAM, resolution=RES, base=store48, out=out)
    return rec, out


def test_a_sweep_point_is_what_compare_measures(embedded, store48):
    rec, _ = embedded
    pts = rec["scenes"]["contact"]["points"]
    assert [p["value"] for p in pts] == [0.0, 5.0, 10.0]
    # the middle point (evaluated on a FrameContext the first point already used) and the default
    run = pipeline.compare("contact", ["hard"], sets=[f"hard.constant_bias={pts[1]['value']!r}"], resolution=RES,
                           base=store48, progress=False)
    t = run["techniques"]["hard"]
    assert pts[1]["metrics"] == to_jsonable(t["metrics"]) and pts[1]["per_light"] == to_jsonable(t["per_light"])
    assert t["params"]["constant_bias"] == 5.0
    default = pipeline.compare("contact", ["hard"], resolution=RES, base=store48, progress=False)["techniques"]["hard"]
    assert default["params"]["constant_bias"] == pts[0]["value"]
    assert pts[0]["metrics"] == to_jsonable(default["metrics"])
    assert pts[0]["metrics"] != pts[2]["metrics"]            # the parameter reaches the technique


def test_dask_workers_give_the_same_bits(embedded, store48, dask_workers):
    rec, _ = embedded
    dist = sweep(SCENES, "hard", PARAM, resolution=RES, base=store48, executor=dask_workers)
    assert dist["executor"]["kind"] == "dask" and dist["executor"]["workers"] == 2
    assert results_only(dist) == results_only(rec)
    assert json.dumps(results_only(dist), sort_keys=True) == json.dumps(results_only(rec), sort_keys=True)


def test_a_larger_constant_bias_lights_more_pixels(embedded):
    """Leaks (umbra shown lit) never fall and over-darkening (lit shown dark) never rises as the
    bias grows; past the scene's depth range every pixel is lit: leak rate 1, over-darkening 0."""
    rec, _ = embedded
    for name, s in rec["scenes"].items():
        leak = [p["metrics"]["leak_rate"] for p in s["points"]]
        dark = [p["metrics"]["overdark_rate"] for p in s["points"]]
        assert leak == sorted(leak) and dark == sorted(dark, reverse=True), (name, leak, dark)
        assert dark[-1] == 0.0
        if name == "contact":                   # it has umbra pixels (parallel_planes' light may have none)
            assert leak[0] < 1.0 and leak[-1] == 1.0
        for ln, m in s["points"][-1]["per_light"].items():
            assert m["overdark_rate"] == 0.0, ln
        assert s["best"]["leak_rate"]["index"] == 0 and s["best"]["psnr"]["metric"] == max(
            p["metrics"]["psnr"] for p in s["points"])


def test_the_report_has_a_chart_per_metric_per_scene(embedded):
    rec, out = embedded
    assert rec["report"] == str(out / "index.html")
    for f in ("sweep.json", "summary.md", "index.html", ".shadowlab-report"):
        assert (out / f).is_file(), f
    data = json.loads((out / "sweep.json").read_text())
    assert data["param"]["values"] == [0.0, 5.0, 10.0] and list(data["scenes"]) == SCENES
    assert data["scenes"]["contact"]["points"][1]["metrics"] == rec["scenes"]["contact"]["points"][1]["metrics"]
    html = (out / "index.html").read_text()
    metrics = rec["metrics"]
    assert len(metrics) >= 10 and "leak_rate" in metrics and "psnr" in metrics
    assert html.count('<svg class="chart"') == len(metrics) * len(SCENES)
    for name in SCENES:
        block = html.split(f"data-scene='{name}'", 1)[1].split("</div>", 1)[0]
        assert re.findall(r'data-metric="([^"]+)"', block) == metrics
        assert block.count('class="best"') == len(rec["scenes"][name]["best"])
    md = (out / "summary.md").read_text()
    assert md.count("| constant_bias |") == len(SCENES) and "**" in md
    # a second sweep into the same (ours) directory replaces only its files
    (out / "notes.txt").write_text("mine")
    base = Path(rec["scenes"]["contact"]["reference"]).parents[1]
    sweep(["contact"], "hard", "constant_bias=0:1:2", resolution=RES, base=base, out=out)
    assert (out / "notes.txt").read_text() == "mine"
    assert list(json.loads((out / "sweep.json").read_text())["scenes"]) == ["contact"]


def test_parse_range():
    assert parse_range("depth_bias=0:3:5", "hard").values == (0, 1, 2, 3)        # rounded, duplicates merged
    assert parse_range("hard.constant_bias=0:1:3", "hard").values == (0.0, 0.5, 1.0)
    r = parse_range("softness=0.25:4:5:log", "pcf")
    assert r.values == (0.25, 0.5, 1.0, 2.0, 4.0) and r.spacing == "log"
    for text, msg in (("depth_bias=0:1:1", "N >= 2"), ("constant_bias=1:0:3", "greater than HI"),
                      ("depth_bias=0:0.4:3", "only the value 0"), ("constant_bias=0:20:3", "out of range"),
                      ("nope=0:1:3", "no parameter 'nope'"), ("bias_mode=0:1:3", "choice parameter"),
                      ("constant_bias=0:1", "NAME=LO:HI:N"), ("constant_bias=a:1:3", "must be numbers"),
                      ("constant_bias=0:1:3:log", "LO > 0"), ("pcf.kernel=1:3:3", "names technique 'pcf'")):
        with pytest.raises(InputError, match=re.escape(msg)):
            parse_range(text, "hard")


def test_bad_input_exits_2_before_any_job(store48, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(store48))
    out = tmp_path / "sw"
    cases = [
        (["contact", "-t", "hard", "--param", "constant_bias=0:1:1"], "N >= 2"),
        (["contact", "-t", "hard", "--param", "constant_bias=1:0:3"], "LO <= HI"),
        (["contact", "-t", "hard", "--param", "nope=0:1:3"], "no parameter 'nope'"),
        (["contact", "-t", "pcf", "--param", "pattern=0:1:3"], "not a number"),
        (["contact", "-t", "nosuch", "--param", "x=0:1:3"], "unknown technique 'nosuch'"),
        (["contact", "-t", "hard", "--param", "constant_bias=0:1:3", "--set", "hard.constant_bias=1"],
         "leave it out of --set"),
        (["contact", "parallel_planes", "-t", "hard", "--param", "constant_bias=0:1:3", "-r", "40x40"],
         "shadowlab reference contact --resolution 40x40"),
        (["contact", "-t", "hard", "--param", "constant_bias=0:1:3", "--workers", "0"], "--workers 0"),
    ]
    for args, msg in cases:
        res = [] if "-r" in args else ["-r", "48x48"]
        rc = cli.main(["sweep", *args, *res, "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err, (args, rc, err)
        assert "Traceback" not in err
    assert not out.exists()                                  # nothing written, no job run
