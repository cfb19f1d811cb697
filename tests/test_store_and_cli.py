"""The reference store's safety rules and the CLI's answers to bad input (exit codes, messages)."""

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shadowlab import backend, pipeline
from shadowlab.errors import ReferenceError_, SceneError
from shadowlab.reference import store
from shadowlab.scene import load_spec
from conftest import llvm_only

ROOT = Path(__file__).resolve().parents[1]
backend.init()


def _digest(d: Path) -> dict:
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()
    }


def _tiny_scene(tmp_path, power=300):
    text = (ROOT / "scenes" / "contact.toml").read_text()
    text = text.replace("resolution = [128, 128]", "resolution = [32, 32]").replace("power = 300", f"power = {power}")
    p = tmp_path / "tiny.toml"
    p.write_text(text.replace('name = "contact"', 'name = "tiny"'))
    return p


def cli(*args, env=None):
    e = dict(os.environ)
    e.update(env or {})
    return subprocess.run([sys.executable, "-m", "shadowlab.cli", *args], capture_output=True, text=True, env=e,
                          cwd=ROOT, timeout=600)


def test_reference_is_not_overwritten_and_interrupts_leave_it_intact(tmp_path, monkeypatch):
    scene = _tiny_scene(tmp_path)
    base = tmp_path / "refs"
    path, meta = pipeline.reference(str(scene), base=base, progress=False, max_rounds=16)
    before = _digest(path)
    with pytest.raises(ReferenceError_, match="--force"):
        pipeline.reference(str(scene), base=base, progress=False)
    assert _digest(path) == before

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline.references, "render_truth", boom)
    with pytest.raises(KeyboardInterrupt):
        pipeline.reference(str(scene), base=base, force=True, progress=False)
    assert _digest(path) == before
    monkeypatch.undo()

    # a failure while writing leaves the old reference and no temporary directory behind
    def disk_full(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(store, "write_json_atomic", disk_full)
    with pytest.raises(OSError):
        pipeline.reference(str(scene), base=base, force=True, progress=False, max_rounds=16)
    monkeypatch.undo()
    assert _digest(path) == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_stale_reference_is_reported_not_used(tmp_path):
    scene = _tiny_scene(tmp_path)
    base = tmp_path / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=16)
    spec = load_spec(scene)
    store.load(spec, base=base)  # fresh: fine
    scene.write_text(scene.read_text().replace("power = 300", "power = 301"))
    with pytest.raises(ReferenceError_, match="different version"):
        store.load(load_spec(scene), base=base)


def test_missing_reference_names_the_command(tmp_path):
    with pytest.raises(ReferenceError_, match="shadowlab reference contact --resolution 64x64"):
        store.load(load_spec(ROOT / "scenes" / "contact.toml"), (64, 64), base=tmp_path)


@pytest.mark.parametrize("text, key", [
    ("name = 'x'\n[camera]\nposition = [0, 1, 2]\n", "camera.target"),
    ("[camera]\nposition=[0,1,5]\ntarget=[0,0,0]\n[[lights]]\nkind='rect'\nposition=[0,3,0]\ntarget=[0,0,0]\nsize=[1]\npower=1\n"
     "[[shapes]]\ntype='sphere'\n", "lights[0].size"),
    ("[camera]\nposition=[0,1,5]\ntarget=[0,0,0]\n[[lights]]\nkind='laser'\n", "lights[0].kind"),
    ("[camera]\nposition=[0,1,5]\ntarget=[0,0,0]\n[[lights]]\nkind='point'\nposition=[0,3,0]\npower=1\n"
     "[[shapes]]\ntype='sphere'\nradius=-1\n", "shapes[0].radius"),
    ("[camera]\nposition=[0,1,5]\ntarget=[0,0,0]\nresolution=[0, 5]\n", "camera.resolution"),
])
def test_malformed_scene_names_file_and_key(tmp_path, text, key):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SceneError) as e:
        load_spec(p)
    assert str(p) in str(e.value) and key in str(e.value) and "expected" in str(e.value)


def test_cli_bad_inputs_exit_2_with_clear_messages(tmp_path):
    r = cli("compare", "no_such_scene")
    assert r.returncode == 2 and "built-in scenes" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed")
    r = cli("reference", str(bad))
    assert r.returncode == 2 and "not valid TOML" in r.stderr and str(bad) in r.stderr
    r = cli("compare", "contact", "--techniques", "hard,nope")
    assert r.returncode == 2 and "unknown technique 'nope'" in r.stderr and "pcf" in r.stderr
    r = cli("compare", "contact", "--techniques", "pcf", "--set", "pcf.no_param=3")
    assert r.returncode == 2 and "no parameter 'no_param'" in r.stderr and "kernel" in r.stderr
    r = cli("compare", "contact", "--techniques", "pcf", "--set", "pcf.kernel=99")
    assert r.returncode == 2 and "out of range" in r.stderr
    r = cli("compare", "contact", "--bogus-option")
    assert r.returncode == 2
    r = cli("reference", "contact")  # committed reference exists: refuse without --force
    assert r.returncode == 2 and "--force" in r.stderr


@llvm_only("under cuda_ad_rgb the CLI never loads libLLVM, so a bad DRJIT_LIBLLVM_PATH cannot fail it")
def test_cli_reports_unusable_libllvm_exit_3(tmp_path):
    old = [p for p in ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", "/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1",
                       "/usr/lib/aarch64-linux-gnu/libLLVM-15.so.1") if os.path.exists(p)]
    env = {"XDG_CACHE_HOME": str(tmp_path)}
    r = cli("compare", "contact", env={**env, "DRJIT_LIBLLVM_PATH": str(tmp_path / "libLLVM-19.so")})
    assert r.returncode == 3 and "does not exist" in r.stderr and "libllvm19" in r.stderr
    if old:
        r = cli("compare", "contact", env={**env, "DRJIT_LIBLLVM_PATH": old[0]})
        assert r.returncode == 3 and "abort" in r.stderr and "libllvm19" in r.stderr


def test_compare_writes_report_and_refuses_bad_input_without_touching_it(tmp_path):
    out = tmp_path / "report"
    pipeline.compare("contact", ["hard", "pcf"], ["pcf.kernel=3"], out=out)
    m = json.loads((out / "metrics.json").read_text())
    assert m["scene"] == "contact" and m["resolution"] == [128, 128]
    assert {"spp", "max_std_error"} <= set(m["reference"])
    for n in ("hard", "pcf"):
        t = m["techniques"][n]
        assert {"params", "time_s", "metrics"} <= set(t)
        assert {"rmse", "psnr", "ssim", "flip", "delta_e2000", "rmse_penumbra", "leak_rate"} <= set(t["metrics"])
    assert m["techniques"]["pcf"]["params"]["kernel"] == 3
    assert (out / "index.html").exists() and (out / "summary.md").exists()
    before = _digest(out)
    r = cli("compare", "contact", "--techniques", "pcf", "--set", "pcf.kernel=abc", "--out", str(out))
    assert r.returncode == 2
    assert _digest(out) == before


def test_supersampled_reference_and_compare_use_the_same_points(tmp_path):
    """With --ss 2 the truth and the techniques average the same 4 sub-pixel points; the
    pixel-centre truth differs from it only where a pixel straddles an edge."""
    scene = _tiny_scene(tmp_path)
    base = tmp_path / "refs"
    path, meta = pipeline.reference(str(scene), base=base, progress=False, ss=2, max_rounds=16)
    assert meta["supersampling"] == 2
    run = pipeline.compare(str(scene), ["hard"], base=base)
    assert run["reference"]["supersampling"] == 2
    truth, _ = store.load(load_spec(scene), base=base)
    v = run["images"]["techniques"]["hard"]["vis"]["key"]
    # sub-pixel averaging gives fractional hard-shadow pixels along edges (1/4 steps)
    frac = v[(v > 0) & (v < 1)]
    assert len(frac) > 0 and np.allclose(frac * 4, np.round(frac * 4), atol=1e-5)
