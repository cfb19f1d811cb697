"""Camera paths, a truth per frame, --frame / --frames, and the temporal stability (shimmer) metric."""

from __future__ import annotations

import json
import re
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from shadowlab import backend, cli, pipeline
from shadowlab.errors import InputError, ReferenceError_, SceneError
from shadowlab.gate.gatefile import load_gate_file
from shadowlab.gate.runner import run_gate_file
from shadowlab.metrics.temporal import shimmer, shimmer_per_light
from shadowlab.reference import store
from shadowlab.render.frame import make_frame
from shadowlab.render.lightview import FrustumSlice
from shadowlab.scene import load
from shadowlab.scene.spec import load_spec, resolve
from shadowlab.techniques import base as tbase
from shadowlab.techniques.base import LightResult, Technique

SCENE = """
name = "walk"
[camera]
position = [0, 2.5, 6]
target = [0, 0.5, 0]
fov = 50
resolution = [40, 30]
near = 0.1
far = 300
{path}
[[lights]]
name = "sun"
kind = "directional"
direction = [-0.4, -1, -0.3]
angular_diameter = 0.53
irradiance = 3.0
shadow_map = 128
[[shapes]]
name = "floor"
type = "rectangle"
scale = [4, 4, 1]
rotate = [1, 0, 0, -90]
[[shapes]]
name = "box"
type = "cube"
translate = [0, 0.5, 0]
scale = [0.4, 0.5, 0.4]
"""

PATH = """
[camera.path]
frames = {frames}
interpolation = "{interp}"
[[camera.path.keys]]
frame = 0
[[camera.path.keys]]
frame = {last}
position = [{dx}, 2.5, 6]
target = [{dx}, 0.5, 0]
"""

REF = dict(max_rounds=2, target_se=0.05, spp=0, progress=False)


def _write(tmp_path, path_text="", name="walk.toml"):
    p = tmp_path / name
    p.write_text(SCENE.format(path=path_text))
    return p


def _path_scene(tmp_path, frames=3, dx=1.2, interp="linear", name="walk.toml"):
    return _write(tmp_path, PATH.format(frames=frames, last=frames - 1, dx=dx, interp=interp), name)


# ------------------------------------------------------------------------------------ the format
def test_linear_and_catmull_rom_paths(tmp_path):
    s = load_spec(_path_scene(tmp_path, frames=5, dx=2.0))
    assert (s.frames, s.frame) == (5, 0)
    xs = [s.at_frame(i).camera.position[0] for i in range(5)]
    assert xs == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    assert s.at_frame(4).camera.target == (2.0, 0.5, 0.0) and s.at_frame(2).frame == 2
    # keys default to [camera]'s values; the resolution and clip planes are kept
    assert s.at_frame(3).camera.resolution == (40, 30) and s.at_frame(3).camera.far == 300
    # Catmull-Rom through three keys: passes through each key, smooth (not piecewise linear) between
    text = PATH.format(frames=5, last=2, dx=1.0, interp="catmull-rom").replace("frame = 2\n", "frame = 2\n") + \
        "[[camera.path.keys]]\nframe = 4\nposition = [1, 2.5, 8]\nfov = 70\n"
    s = load_spec(_write(tmp_path, text, "cr.toml"))
    assert s.at_frame(2).camera.position == (1.0, 2.5, 6.0) and s.at_frame(4).camera.position == (1.0, 2.5, 8.0)
    assert s.at_frame(3).camera.position[0] > 1.0  # the spline overshoots where a polyline would not
    assert s.at_frame(3).camera.fov == pytest.approx(60.0)  # fov linear between keys 2 (50) and 4 (70)
    # explicit cameras: one per frame, frames may be left out
    cams = "[camera.path]\n" + "".join(f"[[camera.path.cameras]]\nposition = [{x}, 2.5, 6]\ntarget = [0, 0.5, 0]\n"
                                       for x in (0, 1, 2))
    s = load_spec(_write(tmp_path, cams, "cams.toml"))
    assert s.frames == 3 and s.at_frame(2).camera.position == (2.0, 2.5, 6.0)


@pytest.mark.parametrize("text, needle", [
    (PATH.format(frames=0, last=0, dx=1, interp="linear"), "camera.path.frames: expected an integer in 1..100000"),
    (PATH.format(frames=4, last=2, dx=1, interp="linear"), "a last key at frame 3"),
    (PATH.format(frames=4, last=3, dx=1, interp="linear").replace("frame = 0", "frame = 1"), "first key"),
    (PATH.format(frames=4, last=3, dx=1, interp="linear") + "[[camera.path.keys]]\nframe = 2\n", "strictly increasing"),
    (PATH.format(frames=4, last=3, dx=1, interp="linear").replace("interpolation", "interpolaton"),
     "did you mean 'interpolation'"),
    (PATH.format(frames=4, last=3, dx=1, interp="cubic"), "one of linear, catmull-rom"),
    ("[camera.path]\nframes = 2\n[[camera.path.cameras]]\nposition = [0, 2, 6]\n", "one camera per frame"),
    (PATH.format(frames=4, last=3, dx=1, interp="linear").replace("target = [1, 0.5, 0]", "target = [1, 2.5, 6]"),
     "a point different from its position"),
])
def test_bad_paths_exit_2(tmp_path, text, needle):
    with pytest.raises(SceneError) as e:
        load_spec(_write(tmp_path, text))
    assert needle in str(e.value) and e.value.exit_code == 2


def test_hash_without_path_unchanged_and_path_changes_stale_frames(tmp_path):
    meta = json.loads((store.root() / "contact" / "128x128" / "meta.json").read_text())
    assert load_spec(resolve("contact")).digest() == meta["scene_hash"]   # committed references stay valid
    a = load_spec(_path_scene(tmp_path, dx=1.2))
    b = load_spec(_path_scene(tmp_path, dx=1.3, name="other.toml"))
    assert len({a.at_frame(i).digest() for i in range(3)}) == 3
    assert a.at_frame(0).camera == b.at_frame(0).camera and a.at_frame(0).digest() != b.at_frame(0).digest()
    with pytest.raises(SceneError, match=r"valid frames are 0\.\.2"):
        a.at_frame(3)
    with pytest.raises(SceneError, match="only frame 0 is valid"):
        load_spec(resolve("contact")).at_frame(1)
    assert load_spec(resolve("contact")).at_frame(0).frame is None


def test_scene_at_frame_reuses_geometry(tmp_path):
    backend.init()
    p = _path_scene(tmp_path)
    sc = load(str(p))
    s2 = sc.at_frame(2)
    assert s2.mi_scene is sc.mi_scene and s2.sensor is not sc.sensor and s2.frame == 2
    a, b = make_frame(s2).gbuffer, make_frame(load(str(p), frame=2)).gbuffer
    assert np.array_equal(a.p.numpy(), b.p.numpy()) and np.array_equal(a.mask, b.mask)
    assert not np.array_equal(make_frame(sc).gbuffer.mask, a.mask)


# ---------------------------------------------------------------------------------- the store
@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """A 3-frame path scene with its three truths in a temporary store."""
    d = tmp_path_factory.mktemp("frames")
    p = _path_scene(d)
    base = d / "store"
    done = pipeline.reference_frames(str(p), frames="0:2", base=base, **REF)
    return p, base, done


def test_each_frame_has_its_own_reference(stored, tmp_path):
    p, base, done = stored
    assert [f for f, _, _ in done] == [0, 1, 2]
    assert [path.name for _, path, _ in done] == ["40x30-f0000", "40x30-f0001", "40x30-f0002"]
    assert all(m["frame"] == f and m["frames"] == 3 for f, _, m in done)
    assert (base / ".locks" / "walk.40x30-f0001.lock").exists()
    assert store.path_for("walk", (40, 30), base).name == "40x30"   # no frame: the layout of before
    listed = store.list_references(base)
    assert [(r["resolution"], r["frame"], r["status"]) for r in listed] == [("40x30", f, []) for f in range(3)]
    spec = load_spec(p)
    t1, m1 = store.load(spec.at_frame(1), None, base)
    assert m1["scene_hash"] == spec.at_frame(1).digest() and m1["frame"] == 1
    with pytest.raises(ReferenceError_, match="--frame 1 --force"):
        pipeline.reference(str(p), frame=1, base=base, **REF)   # exists: --force needed, named with its frame
    # the path changes: every frame's reference is stale, for load and for the listing
    q = _path_scene(tmp_path, dx=1.25)
    changed = load_spec(q)
    with pytest.raises(ReferenceError_, match="different version"):
        store.load(changed.at_frame(1), None, base)
    assert store.load(spec.at_frame(2), None, base)[1]["frame"] == 2


def test_cli_frame_ranges_exit_2(stored, capsys, monkeypatch):
    p, base, _ = stored
    monkeypatch.setenv(store.ROOT_ENV, str(base))
    for args, needle in [(["reference", str(p), "--frame", "3"], "valid frames are 0..2"),
                         (["compare", str(p), "--frames", "1:5", "-t", "hard"], "valid frames are 0..2"),
                         (["compare", "contact", "--frame", "1", "-t", "hard"], "only frame 0 is valid"),
                         (["compare", str(p), "--frames", "2:1", "-t", "hard"], "0 <= A <= B"),
                         (["compare", str(p), "--frames", "1", "-t", "hard"], "expected A:B"),
                         (["fit", str(p), "-t", "hard", "--frames", "0:5"], "valid frames are 0..2")]:
        assert cli.main(args) == 2, args
        assert needle in capsys.readouterr().err


# ---------------------------------------------------------------------------------- shimmer
def test_shimmer_formula_by_hand():
    V = np.array([[0.0, 0.2, 1.0, 0.3],
                  [0.5, 0.2, 0.0, 0.3],
                  [0.5, 1.0, 0.0, 0.9]])
    valid = np.array([True, True, True, False])
    d = np.array([0.5, 0.0, 1.0, 0.0, 0.8, 0.0])   # |ΔV| of points 0..2 for pairs (0,1), (1,2)
    s = shimmer(V, valid)
    assert s["mean"] == pytest.approx(d.mean()) and s["p99"] == pytest.approx(np.percentile(d, 99))
    assert (s["pairs"], s["points"], s["samples"], s["max"]) == (2, 3, 6, 1.0)
    per, pooled = shimmer_per_light({"a": (V, valid), "b": (np.zeros((3, 2)), None)})
    assert per["b"]["mean"] == 0.0 and pooled["samples"] == 10
    assert pooled["mean"] == pytest.approx(d.sum() / 10)
    assert shimmer(V[:1], valid)["mean"] is None   # one frame: no pair


class _FollowBox(Technique):
    """A shadow map fitted to the camera frustum's light-space box, not snapped: it follows the camera."""

    name = "follow_box_test"
    title = "test"
    summary = "test"
    source = "[Williams 1978]"
    params = ()

    def render_light(self, frame, light, values, ctx):
        view = frame.light_view(light.name, res=64, fit=FrustumSlice(0.5, 10.0, snap=False, bound="box"))
        q = view.lookup(frame.gbuffer.p)
        D = view.fetch("depth", q["face"], mi.Int32(dr.floor(q["u"])), mi.Int32(dr.floor(q["v"])))
        lit = (D >= 1.0) | (D + 2e-3 >= q["d"])
        return LightResult(dr.select(lit, 1.0, 0.0), active=frame.gbuffer.valid & q["inside"])


def test_shimmer_zero_for_hard_positive_for_camera_following_fit(stored):
    p, base, _ = stored
    backend.init()
    sc = load(str(p))
    scenes = [sc.at_frame(i) for i in range(3)]
    fixed = make_frame(scenes[0])
    tech = _FollowBox()
    results = {n: (t.render(fixed, t.resolve({})), t.resolve({})) for n, t in (("hard", tbase.get("hard")),
                                                                            (tech.name, tech))}
    sh = pipeline.shimmer(scenes, fixed, results, techniques={tech.name: tech})
    assert sh["techniques"]["hard"]["pooled"]["mean"] == 0.0 and sh["techniques"]["hard"]["pooled"]["p99"] == 0.0
    box = sh["techniques"][tech.name]["pooled"]
    assert box["mean"] > 0 and box["max"] == 1.0 and box["pairs"] == 2
    # the camera moved by several of the map's texels: check the premise
    fr1 = make_frame(scenes[1])
    v0 = fixed.light_view("sun", res=64, fit=FrustumSlice(0.5, 10.0, snap=False, bound="box"))
    v1 = fr1.light_view("sun", res=64, fit=FrustumSlice(0.5, 10.0, snap=False, bound="box"))
    pt = fixed.gbuffer.p
    du = np.abs(np.asarray(v1.lookup(pt)["u"].numpy()) - np.asarray(v0.lookup(pt)["u"].numpy()))
    assert float(np.median(du[np.asarray(fixed.gbuffer.valid.numpy())])) > 1.0
    assert sh["truth"]["pooled"]["mean"] == 0.0 and "only the camera moves" in sh["truth"]["why"]


def test_compare_frames_report(stored, tmp_path):
    p, base, _ = stored
    out = tmp_path / "rep"
    s = pipeline.compare(str(p), ["hard"], out=out, base=base, frames="0:2", progress=False)
    assert sorted(x.name for x in out.iterdir() if x.is_dir()) == ["frame_0000", "frame_0001", "frame_0002"]
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == [0, 1, 2] and set(m["per_frame"]) == {"0", "1", "2"}
    assert m["shimmer"]["techniques"]["hard"]["pooled"]["mean"] == 0.0
    assert "only the camera moves" in m["shimmer"]["truth"]["why"]
    sub = json.loads((out / "frame_0001" / "metrics.json").read_text())
    assert sub["frame"] == 1 and sub["reference"]["path"].endswith("40x30-f0001")
    assert m["per_frame"]["1"]["hard"]["metrics"]["rmse"] == sub["techniques"]["hard"]["metrics"]["rmse"]
    md = (out / "summary.md").read_text()
    assert "| hard |" in md and "Temporal stability" in md and "frame 2" in md
    page = (out / "index.html").read_text()
    assert "frame_0002/index.html" in page
    # styled like a frame's report, with its charts and every thumbnail it shows present on disk
    measured = [k for k in ("rmse", "rmse_penumbra", "vis_rmse")
                if any(m["per_frame"][f]["hard"]["metrics"].get(k) is not None for f in m["per_frame"])]
    assert "table.metrics" in page and page.count('<svg class="chart"') == len(measured) + 1   # + the shimmer
    thumbs = re.findall(r'<img class="im thumb" src="([^"]+)"', page)
    assert len(thumbs) == 3 * 2 and all((out / t).is_file() for t in thumbs), thumbs
    one = pipeline.compare(str(p), ["hard"], base=base, frame=2, progress=False)
    assert one["frame"] == 2
    for k in ("rmse", "vis_rmse", "mae"):
        assert one["techniques"]["hard"]["metrics"][k] == s["runs"][2]["techniques"]["hard"]["metrics"][k]


def test_gate_frames(stored, tmp_path):
    p, base, _ = stored
    g = tmp_path / "gates.toml"
    g.write_text(f'version = 1\nreferences = "{base}"\n[[gate]]\nname = "walk"\nscene = "{p}"\nframes = "1:2"\n'
                 '[gate.candidate]\ntechnique = "hard"\n[gate.budget]\nrmse = 1.0\n'
                 f'[[gate]]\nname = "one"\nscene = "{p}"\nframe = 0\n[gate.candidate]\ntechnique = "hard"\n'
                 '[gate.budget]\nrmse = 1.0\n')
    gf = load_gate_file(g)
    assert [(x.name, x.frame) for x in gf.gates] == [("walk@frame1", 1), ("walk@frame2", 2), ("one", 0)]
    assert [x.name for x in gf.select(["walk"])] == ["walk@frame1", "walk@frame2"]
    code, res = run_gate_file(g, only=["walk", "one"], echo=None)
    assert code == 0 and [r.info["reference"][-11:] for r in res] == ["40x30-f0001", "40x30-f0002", "40x30-f0000"]
    code, res = run_gate_file(g, only=["one"], echo=None, frames="1:2")
    assert [r.name for r in res] == ["one@frame1", "one@frame2"]
    g.write_text(g.read_text().replace('frames = "1:2"', 'frames = "1:3"'))
    with pytest.raises(InputError, match=r"valid frames are 0\.\.2"):
        load_gate_file(g)


def test_a_fit_over_frames_minimises_the_mean_of_the_frames_losses(stored):
    """``fit --frames A:B``: one preset for the path; its objective is the mean of each frame's
    objective against that frame's own truth (checked against single-frame objectives)."""
    from shadowlab.fit import run as R
    from shadowlab.fit.objective import Objective
    p, base, _ = stored
    run = R.fit(str(p), "hard", params=["slope_scaled_depth_bias"], method="golden", loss="rmse", frames="0:2",
                base=base, budget=R.Budget(evals=4))
    assert run["frames"] == [0, 1, 2]
    r = run["techniques"]["hard"]
    start = {"slope_scaled_depth_bias": r["params"]["slope_scaled_depth_bias"]["start"]}
    singles = []
    for sc, truth, meta, frame in R.prepare_frames(str(p), None, base, frames="0:2"):
        o = Objective(frame, truth, tbase.get("hard"), "rmse")
        singles.append((o.value(start), o.noise_floor))
    assert r["objective_before"] == pytest.approx(np.mean([v for v, _ in singles]), rel=1e-6)
    assert r["loss_before"] == pytest.approx(math.sqrt(max(np.mean([v - f for v, f in singles]), 0.0)), rel=1e-6)
    assert r["objective_after"] <= r["objective_before"] and r["loss"]["frames"] == 3
    one = R.fit(str(p), "hard", params=["slope_scaled_depth_bias"], method="golden", loss="rmse", frame=1,
                base=base, budget=R.Budget(evals=4))["techniques"]["hard"]
    assert one["objective_before"] == pytest.approx(singles[1][0], rel=1e-6)
