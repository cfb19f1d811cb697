"""``shadowlab ingest``: an image rendered elsewhere against the stored truth.

The proof (issue 5): ``parallel_planes`` is exported at 64×48 (not square, so a swapped width and
height or aspect ratio shows), rendered by a second, independent
implementation (``tests/numpy_raycast.py``: plain numpy ray casting of the exported PLYs,
camera.json and lights.json, no Mitsuba / Dr.Jit) and ingested against a 64×48 Mitsuba truth
rendered here into a temporary store. Agreement is judged by the two estimators' own
statistical errors: the truth's per-pixel standard error se_t (and the rule-of-three bound
B_t = 3/n of its unanimous pixels, read as a standard deviation of B/2), the caster's se_m from
its 8 independent rounds (and its own bound B_m). Per pixel the difference has standard deviation
σ = sqrt(se_t² + se_m² + (B_t/2)² + (B_m/2)²), so

* the RMSE over the lit pixels must be ≤ 1.5 · sqrt(mean σ²) (its expectation is ≤ sqrt(mean σ²):
  unanimous pixels of both sides agree exactly, so the bound terms only over-estimate);
* the penumbra z-scores (V_m − V_t)/sqrt(se_t² + se_m²) must have mean within 4/sqrt(n) + 0.1 of 0
  and standard deviation below 1.5 (measured 1.07; standard errors from 8 rounds are themselves
  noisy, which widens z, README: 1.07 for the truth against closed forms);
* the shaded image (ρ/π · L_e · ∫ G v dA with lights.json's radiance and scene.json's albedo) must
  match the truth's Σ U·V to 1.5 · sqrt(mean(var_t + se_m² + (U B_t/2)²)) + 0.2 % of the mean
  (the truth's U comes from 16×16 strata and carries no stored variance; measured 0.055 %).

A caster that samples pixel corners instead of centres (the classic half-pixel convention bug)
must fail the same checks, so they can fail.
"""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy_raycast as nr  # noqa: E402

from shadowlab.errors import InputError, ReferenceError_  # noqa: E402
from shadowlab.exchange.ingest import ingest  # noqa: E402
from shadowlab.io.exr import read_exr, write_exr  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENE = "parallel_planes"
RES = (64, 48)
LIGHT = "panel"


def _digest(d: Path) -> dict:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()
    }


def cli(*args, env=None):
    e = dict(os.environ)
    e.update(env or {})
    return subprocess.run([sys.executable, "-m", "shadowlab.cli", *args], capture_output=True, text=True, env=e,
                          cwd=ROOT, timeout=600)


@pytest.fixture(scope="module")
def proof(tmp_path_factory, mitsuba_backend):
    """A 64×48 truth in a temporary store, the export, the numpy rendering and its EXR."""
    from shadowlab import pipeline
    from shadowlab.exchange.export import export_scene
    from shadowlab.reference import store
    from shadowlab.scene import load_spec, resolve
    tmp = tmp_path_factory.mktemp("ingest")
    base = tmp / "refs"
    pipeline.reference(SCENE, RES, base=base, progress=False, spp=64)
    spec = load_spec(resolve(SCENE)).with_resolution(*RES)
    truth, meta = store.load(spec, RES, base)
    exp = tmp / "export"
    export_scene(SCENE, exp, resolution=RES)
    r = nr.render(exp, LIGHT, k=8, rounds=8, seed=1)
    img = tmp / "numpy.exr"
    write_exr(img, {"shadow.panel": r["V"], "shadow.panel.se": r["V_se"], "visible.panel": r["A"],
                    "visible.panel.se": r["A_se"], "R": r["shaded"][..., 0], "G": r["shaded"][..., 1],
                    "B": r["shaded"][..., 2], "se.R": r["shaded_se"][..., 0], "se.G": r["shaded_se"][..., 1],
                    "se.B": r["shaded_se"][..., 2]})
    return {"tmp": tmp, "base": base, "truth": truth, "meta": meta, "export": exp, "render": r, "image": img,
            "spec": spec}


def _sigma(truth_l, se_t, est, se_m, rays_m):
    b_t = np.asarray(truth_l.bound, np.float64)
    unanimous_m = (se_m == 0) & ((est == 0) | (est == 1))
    b_m = np.where(unanimous_m, 3.0 / rays_m, 0.0)
    return np.sqrt(se_t ** 2 + se_m ** 2 + (b_t / 2) ** 2 + (b_m / 2) ** 2)


def _agreement(proof, r, quantity="V"):
    """(rmse, bound, penumbra z) of the caster's V or A against the truth's, over the lit pixels."""
    truth = proof["truth"]
    lt = truth.lights[LIGHT]
    lit = truth.mask & (truth.U[LIGHT].sum(-1) > 0)
    t = np.asarray(getattr(lt, quantity), np.float64)
    se_t = np.asarray(getattr(lt, quantity + "_se"), np.float64)
    est, se_m = r[quantity], r[quantity + "_se"]
    sigma = _sigma(lt, se_t, est, se_m, 8 * 64)
    e = (est - t)[lit]
    rmse = float(np.sqrt(np.mean(e ** 2)))
    bound = 1.5 * float(np.sqrt(np.mean(sigma[lit] ** 2)))
    pen = lit & ((se_t > 0) | (se_m > 0))
    z = (est - t)[pen] / np.sqrt(se_t ** 2 + se_m ** 2)[pen]
    return rmse, bound, z


def test_numpy_caster_sees_the_truths_pixels(proof):
    """camera.json alone puts the caster's camera rays on Mitsuba's: the same hit mask and the same
    distances (float32 precision)."""
    r, truth = proof["render"], proof["truth"]
    assert (r["mask"] == truth.mask).all()
    m = truth.mask
    assert m.sum() > 0.7 * m.size
    assert np.abs(r["depth"][m] - truth.view_depth[m]).max() < 1e-4


@pytest.mark.parametrize("quantity", ["V", "A"])
def test_numpy_caster_agrees_with_truth_within_its_statistical_error(proof, quantity):
    rmse, bound, z = _agreement(proof, proof["render"], quantity)
    assert len(z) > 300  # the penumbra of the 64×48 image (576 pixels)
    assert rmse <= bound, (rmse, bound)
    assert abs(z.mean()) < 4 / np.sqrt(len(z)) + 0.1, z.mean()
    assert z.std() < 1.5, z.std()


def test_half_pixel_offset_is_caught(proof):
    """Sampling pixel corners instead of centres (a convention bug) fails the same checks."""
    r = nr.render(proof["export"], LIGHT, k=8, rounds=8, seed=1, pixel_offset=0.0)
    rmse, bound, z = _agreement(proof, r, "V")
    assert rmse > bound or abs(z.mean()) > 4 / np.sqrt(len(z)) + 0.1 or z.std() > 1.5


def test_ingest_visibility_reports_the_compare_metrics(proof):
    out = proof["tmp"] / "report_v"
    run = ingest(SCENE, proof["image"], channels=["shadow.panel"], base=proof["base"], out=out)
    pl = run["techniques"]["numpy.exr"]["per_light"][LIGHT]
    rmse, bound, _ = _agreement(proof, proof["render"], "V")
    assert pl["rmse"] == pytest.approx(rmse, rel=1e-6)  # the same pixels (hit mask, U > 0) as the test's
    assert pl["rmse"] <= bound
    assert abs(pl["bias"]) < 1e-3
    assert pl["leak_rate"] == 0 and pl["overdark_rate"] == 0
    m = run["techniques"]["numpy.exr"]["metrics"]
    for k in ("rmse", "psnr", "ssim", "flip", "delta_e2000", "rmse_penumbra", "vis_rmse"):
        assert np.isfinite(m[k]), k
    assert m["ssim"] > 0.99
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["ingest"]["channels"] == {LIGHT: "shadow.panel"}
    assert saved["techniques"]["numpy.exr"]["per_light"][LIGHT]["rmse"] == pytest.approx(pl["rmse"])
    assert (out / "index.html").exists() and (out / "summary.md").exists()


def test_ingest_shaded_matches_truth_in_radiance_units(proof):
    """lights.json's radiance and scene.json's albedo give the truth's shaded image."""
    run = ingest(SCENE, proof["image"], shaded=True, base=proof["base"])
    truth, r = proof["truth"], proof["render"]
    m = truth.mask
    t = truth.shaded.astype(np.float64)
    lt = truth.lights[LIGHT]
    var = (truth.shaded_var + (truth.U[LIGHT] * (lt.bound / 2)[..., None]) ** 2 + r["shaded_se"] ** 2)[m]
    bound = 1.5 * np.sqrt(var.mean()) + 0.002 * t[m].mean()
    got = run["techniques"]["numpy.exr"]["metrics"]
    assert got["rmse"] == pytest.approx(np.sqrt(np.mean((r["shaded"] - t)[m] ** 2)), rel=1e-5)
    assert got["rmse"] <= bound, (got["rmse"], bound)
    assert abs(got["bias"]) < 0.002 * t[m].mean()
    assert run["ingest"]["channels"] == {"rgb": ["R", "G", "B"]}


def test_ingest_gate_passes_with_the_images_own_error_and_fails_without(proof, tmp_path):
    gate = tmp_path / "gate.toml"
    gate.write_text('statistical = {}\nbudget = { rmse_penumbra = 0.02 }\nstd_error = "shadow.panel.se"\n')
    run = ingest(SCENE, proof["image"], channels=["shadow.panel"], base=proof["base"], gate=gate)
    assert run["gate"]["passed"], run["gate"]["lines"]
    assert {c["check"] for c in run["gate"]["checks"]} >= {"stat.pixels", "stat.bias", "budget.rmse_penumbra"}
    # a visibility shifted by one row is a convention error: the gate catches it
    ch = read_exr(proof["image"])
    shifted = tmp_path / "shifted.exr"
    write_exr(
        shifted, {"shadow.panel": np.roll(ch["shadow.panel"], 1, axis=0), "shadow.panel.se": ch["shadow.panel.se"]}
    )
    run = ingest(SCENE, shifted, channels=["shadow.panel"], base=proof["base"], gate=gate)
    assert not run["gate"]["passed"]
    assert any(f.endswith("stat.pixels") for f in run["gate"]["failed"])
    # the shaded image passes the statistical test against the truth's shaded image, with its own error
    gate_rgb = tmp_path / "gate_rgb.toml"
    gate_rgb.write_text('statistical = {}\nstd_error = "se"\n')
    run = ingest(SCENE, proof["image"], shaded=True, base=proof["base"], gate=gate_rgb)
    assert run["gate"]["passed"], run["gate"]["lines"]


def test_ingest_cli_ok_and_gate_exit_code(proof, tmp_path):
    env = {"SHADOWLAB_REFERENCES": str(proof["base"])}
    out = tmp_path / "rep"
    r = cli("ingest", SCENE, str(proof["image"]), "--channel", "shadow.panel", "--out", str(out), env=env)
    assert r.returncode == 0, r.stderr
    assert "panel: rmse" in r.stdout and "report:" in r.stdout
    assert (out / "metrics.json").exists()
    gate = tmp_path / "strict.toml"
    gate.write_text("budget = { rmse = 0.0001 }\n")
    r = cli("ingest", SCENE, str(proof["image"]), "--channel", "visible.panel", "--against", "A", "--out",
            str(tmp_path / "rep2"), "--gate", str(gate), env=env)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "FAIL" in r.stdout and "budget.rmse" in r.stdout


def test_ingest_bad_input_exits_2_and_touches_nothing(proof, tmp_path, monkeypatch, capsys):
    """The CLI's answers to bad input (in-process ``shadowlab.cli.main``, the console script's entry)."""
    from shadowlab.cli import main
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(proof["base"]))
    before = _digest(proof["base"])
    img = proof["image"]
    ch = read_exr(img)

    def run(*args):
        out = tmp_path / "never"
        capsys.readouterr()
        code = main(["ingest", *args, "--out", str(out)])
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert not out.exists()
        return err

    # unknown channel: the message lists the image's channels
    err = run(SCENE, str(img), "--channel", "shadow.key")
    assert "no channel 'shadow.key'" in err and "shadow.panel" in err and "visible.panel" in err
    # neither --channel nor --shaded
    assert "--channel" in run(SCENE, str(img))
    # NaN / Inf: count and first pixel
    bad = dict(ch)
    v = bad["shadow.panel"].copy()
    v[7, 3], v[20, 40] = np.nan, np.inf
    bad["shadow.panel"] = v
    write_exr(tmp_path / "nan.exr", bad)
    err = run(SCENE, str(tmp_path / "nan.exr"), "--channel", "shadow.panel")
    assert "2 non-finite values (NaN/Inf)" in err and "(x=3, y=7)" in err
    # a channel that is no visibility (outside [0, 1]): named, with its range and the fix
    write_exr(tmp_path / "radiance.exr", {"shadow.panel": ch["shadow.panel"] * 5.0})
    err = run(SCENE, str(tmp_path / "radiance.exr"), "--channel", "shadow.panel")
    assert "'shadow.panel'" in err and "outside" in err and "--shaded" in err
    # wrong size: no reference at that size; the message names the stored one and the command
    write_exr(tmp_path / "small.exr", {k: a[:32, :48] for k, a in ch.items()})
    err = run(SCENE, str(tmp_path / "small.exr"), "--channel", "shadow.panel")
    assert "48x32" in err and "64x48" in err and f"shadowlab reference {SCENE} --resolution 48x32" in err
    err = run(SCENE, str(img), "--channel", "shadow.panel", "--resolution", "128x128")
    assert "is 64x48" in err and "128x128" in err
    # stale reference: the scene changed since the truth was rendered
    stale = tmp_path / "parallel_planes.toml"
    stale.write_text((ROOT / "scenes" / "parallel_planes.toml").read_text().replace("power = 300", "power = 310"))
    err = run(str(stale), str(img), "--channel", "shadow.panel")
    assert "different version" in err and "--force" in err
    # a missing image, an unknown scene, a report inside the store
    assert "does not exist" in run(SCENE, str(tmp_path / "missing.exr"), "--channel", "shadow.panel")
    assert "unknown scene" in run("no_such_scene", str(img), "--channel", "shadow.panel")
    assert main(["ingest", SCENE, str(img), "--channel", "shadow.panel", "--out", str(proof["base"] / "x")]) == 2
    assert "inside the reference store" in capsys.readouterr().err
    with pytest.raises(InputError, match="inside the reference store"):  # also a store given as base
        ingest(SCENE, img, channels=["shadow.panel"], base=proof["base"], out=proof["base"] / "y")
    # a malformed gate file
    g = tmp_path / "bad_gate.toml"
    g.write_text("budget = { nonsense = 1 }\n")
    assert "nonsense" in run(SCENE, str(img), "--channel", "shadow.panel", "--gate", str(g))
    assert _digest(proof["base"]) == before


def test_ingest_channel_to_light_mapping(proof, tmp_path):
    ch = read_exr(proof["image"])
    img = tmp_path / "named.exr"
    write_exr(img, {"vis": ch["shadow.panel"], "R": ch["R"], "G": ch["G"], "B": ch["B"],
                    "beauty.R": ch["R"], "beauty.G": ch["G"], "beauty.B": ch["B"]})
    # one light: any channel name maps to it; NAME=LIGHT names it explicitly
    run = ingest(SCENE, img, channels=["vis"], base=proof["base"])
    assert run["lights"] == [LIGHT]
    run = ingest(SCENE, img, channels=["vis=panel"], base=proof["base"])
    assert run["ingest"]["channels"] == {LIGHT: "vis"}
    with pytest.raises(InputError, match="no light 'sun'"):
        ingest(SCENE, img, channels=["vis=sun"], base=proof["base"])
    with pytest.raises(InputError, match="--against"):
        ingest(SCENE, img, channels=["vis"], against="shaded", base=proof["base"])
    # --shaded prefers R, G, B; --layer picks another layer
    run = ingest(SCENE, img, shaded=True, layer="beauty", base=proof["base"])
    assert run["ingest"]["channels"] == {"rgb": ["beauty.R", "beauty.G", "beauty.B"]}
    with pytest.raises(InputError, match="no channel"):
        ingest(SCENE, img, shaded=True, layer="diffuse", base=proof["base"])
    with pytest.raises(ReferenceError_, match="no reference"):
        ingest(SCENE, img, channels=["vis"], base=tmp_path / "empty_store")


def test_ingest_labels_and_a_default_out_that_keeps_the_previous_report(proof, tmp_path, monkeypatch, capsys):
    """``--label TEXT`` names the image and ``--label CHANNEL=TEXT`` titles a channel in the report;
    without ``--out`` each ingest gets a directory of its own (reports/ingest/SCENE-IMAGE, -2, …)."""
    import json
    from shadowlab import cli as shadowlab_cli
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(proof["base"]))
    monkeypatch.chdir(tmp_path)
    args = ["ingest", SCENE, str(proof["image"]), "--channel", "shadow.panel"]
    rc = shadowlab_cli.main(args + ["--label", "engine build 42", "--label", "shadow.panel=PCF 5x5"])
    assert rc == 0, capsys.readouterr().err
    first = tmp_path / "reports" / "ingest" / f"{Path(SCENE).stem}-numpy"
    run = json.loads((first / "metrics.json").read_text())
    assert list(run["techniques"]) == ["engine build 42"]
    assert "panel</b> visibility (PCF 5x5)" in (first / "index.html").read_text()
    before = (first / "metrics.json").read_bytes()
    assert shadowlab_cli.main(args) == 0
    second = first.with_name(first.name + "-2")
    assert (second / "metrics.json").exists() and (first / "metrics.json").read_bytes() == before
    capsys.readouterr()
    for bad, why in ((["--label", "nope=x"], "not one of the --channel channels"),
                     (["--label", "a", "--label", "b"], "one name for the image")):
        assert shadowlab_cli.main(args + bad + ["--out", str(tmp_path / "x")]) == 2
        assert why in capsys.readouterr().err
