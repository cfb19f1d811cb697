"""Input accepted silently, and a traceback inside a message (issue 27, "Silent acceptance",
"Tracebacks").

* ``ingest --shaded`` refuses an image with negative radiance (exit 2 naming the count, the
  minimum and the first pixel), and still takes the truth's own shaded image (rmse 0);
* ``--variant cuda_ad_rgb`` on a machine without a working CUDA backend exits 3 with one line:
  the reason and the fix, no traceback of the probe inside it.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shadowlab import backend, cli, pipeline
from shadowlab.io.exr import write_exr
from shadowlab.reference import store
from shadowlab.scene import load_spec

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    d = tmp_path_factory.mktemp("silent")
    text = (ROOT / "scenes" / "contact.toml").read_text()
    scene = d / "tiny.toml"
    scene.write_text(text.replace("resolution = [128, 128]", "resolution = [16, 16]").replace(
        'name = "contact"', 'name = "tiny"'))
    base = d / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=2, spp=0)
    truth, _ = store.load(load_spec(scene), base=base)
    return scene, base, truth


def _ingest(scene, base, img, tmp_path, capsys, monkeypatch, name):
    monkeypatch.setenv(store.ROOT_ENV, str(base))
    exr = tmp_path / f"{name}.exr"
    write_exr(exr, {c: img[..., i] for i, c in enumerate("RGB")})
    rc = cli.main(["ingest", str(scene), str(exr), "--shaded", "--out", str(tmp_path / f"out-{name}")])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return rc, out, err, exr


def test_ingest_shaded_refuses_negative_radiance(stored, tmp_path, capsys, monkeypatch):
    scene, base, truth = stored
    img = np.array(truth.shaded, np.float32)
    rc, out, err, _ = _ingest(scene, base, img, tmp_path, capsys, monkeypatch, "same")
    assert rc == 0, err                                        # the truth itself: accepted
    bad = img.copy()
    bad[3, 5, 1] = -0.25 * float(np.abs(img).max())           # one pixel's green channel below 0
    bad[7, 2, :] = -1e-3 * float(np.abs(img).max())
    rc, out, err, exr = _ingest(scene, base, bad, tmp_path, capsys, monkeypatch, "negative")
    assert rc == 2, (out, err)
    assert f"{exr}: the RGB image (R, G, B) is meant to be radiance" in err and "2 pixels have negative" in err, err
    assert "the first at x=5, y=3" in err and not (tmp_path / "out-negative").exists()
    tiny = img.copy()
    tiny[0, 0, 0] = -1e-6 * float(np.abs(img).max())          # round-off: within the tolerance
    assert _ingest(scene, base, tiny, tmp_path, capsys, monkeypatch, "roundoff")[0] == 0


def test_a_variant_that_does_not_work_here_is_one_line(tmp_path):
    if backend.probe("cuda_ad_rgb", None)[0]:
        pytest.skip("the CUDA backend works on this machine")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    r = subprocess.run([sys.executable, "-m", "shadowlab.cli", "compare", "contact", "-t", "hard", "--variant",
                        "cuda_ad_rgb", "--out", str(tmp_path / "out")], capture_output=True, text=True, env=env,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 3, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr and 'File "' not in r.stderr, r.stderr
    assert lines[0].startswith("error: the cuda_ad_rgb backend does not work here (") and "--variant llvm_ad_rgb" \
        in lines[0], lines


def test_probe_reason_keeps_the_exception_line():
    tail = ('Traceback (most recent call last):\n  File "<string>", line 3, in <module>\n    mi.set_variant(x)\n'
            '    ^^^^^^^^^^^^^^^^^\nImportError: jit_init_thread_state(): the CUDA backend hasn\'t been initialized.\n')
    assert backend.probe_reason(tail) == tail.splitlines()[-1]        # the exception line
    assert backend.probe_reason("LLVM ERROR: out of range\n") == "LLVM ERROR: out of range"
