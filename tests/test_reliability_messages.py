"""Messages that name the wrong thing (issue 27, "Wrong or misleading messages").

* a preset given where a scene is expected says it is a preset and names ``--preset``;
* an "already exists" fix names the path the user gave for a scene file, not its ``name``;
* every parameter an example in fit's messages and the preset format names is a declared Param;
* several scenes that are the same reference are refused before any work (as fit and sweep do),
  in this process and on a Dask cluster alike;
* a reader that arrives while a writer swaps the reference in (between the two renames of the
  fallback) waits for it instead of being told there is no reference.
"""

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from shadowlab import cli
from shadowlab.errors import InputError
from shadowlab.fit import preset as preset_mod
from shadowlab.fit import run as fit_run
from shadowlab.reference import store
from shadowlab.scene import load_spec
from shadowlab.techniques import base as tbase

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--max-rounds", "2", "--spp", "0"]


def _scene(d: Path, name="tiny", res=16) -> Path:
    text = (ROOT / "scenes" / "contact.toml").read_text()
    text = text.replace("resolution = [128, 128]", f"resolution = [{res}, {res}]").replace(
        'name = "contact"', f'name = "{name}"')
    p = d / f"my-{name}.toml"                 # the file name differs from the scene's name
    p.write_text(text)
    return p


def _run(args, capsys):
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "internal error" not in err, err
    return rc, out, err


@pytest.fixture
def base(tmp_path, monkeypatch):
    b = tmp_path / "refs"
    b.mkdir()
    monkeypatch.setenv(store.ROOT_ENV, str(b))
    return b


def test_a_preset_given_as_a_scene_says_so(tmp_path, capsys):
    p = preset_mod.save(tmp_path / "fitted.toml", "fitted", {"pcss": {"light_scale": 1.5}}, preset_mod.FIT_DESCRIPTION)
    for args in (["compare", p, "-t", "pcss"], ["reference", p], ["fit", p, "-t", "pcss"]):
        rc, _, err = _run(args, capsys)
        assert rc == 2 and "this is a preset" in err and f"--preset {p}" in err, (args, err)
        assert "unknown key" not in err


def test_already_exists_names_the_scene_file_given(tmp_path, base, capsys):
    scene = _scene(tmp_path)
    assert _run(["reference", scene, *FAST], capsys)[0] == 0
    rc, _, err = _run(["reference", scene, *FAST], capsys)
    assert rc == 2 and "already exists" in err, err
    assert f"shadowlab reference {scene} --resolution 16x16 --force" in err, err


def _declared() -> set:
    return {p.name for n in tbase.names() for p in tbase.get(n).params}


def test_every_parameter_an_example_names_is_declared():
    declared = _declared()
    with pytest.raises(InputError) as e:
        fit_run.parse_params(" , ")
    named = re.findall(r"such as --params (\w+)", str(e.value))
    with pytest.raises(InputError) as e:
        fit_run.parse_ranges(["bad"], ["pcss"])
    named += re.findall(r"e\.g\. (\w+)=", str(e.value))
    named += re.findall(r"^\s+(\w+) = [0-9.]+$", preset_mod.__doc__, re.M)          # the preset format's TOML
    named += re.findall(r'"pcss": \{"(\w+)"', preset_mod.__doc__)                     # and its JSON
    assert len(named) == 4 and set(named) <= declared, (named, sorted(declared))


@pytest.mark.parametrize("workers", [[], ["--workers", "2"]], ids=["in-process", "dask"])
def test_the_same_scene_twice_is_refused_before_any_work(workers, tmp_path, base, capsys):
    """As fit and sweep do, in this process and on a cluster alike (was exit 0 in process, exit 2
    with a Dask dump on the cluster): exit 2 before any work, nothing stored."""
    scene = _scene(tmp_path)
    rc, out, err = _run(["reference", scene, str(scene), *workers, *FAST], capsys)
    assert rc == 2 and f"scene {scene} is given twice" in err and "name each scene once" in err, (out, err)
    assert len(err.strip().splitlines()) == 1 and "reference written" not in out
    assert list(base.rglob("meta.json")) == []


# the fallback save (no renameat2) of tests/test_store_faults.py, paused between its two renames
_PAUSED_WRITER = r"""
import sys, time
from pathlib import Path
from shadowlab.reference import store
from shadowlab.scene import load_spec
scene, base, sync = sys.argv[1:4]
store._exchange = lambda a, b: False
def checkpoint(p):
    if p == "old-moved":
        Path(sync + ".ready").touch()
        time.sleep(float(sys.argv[4]))
store._checkpoint = checkpoint
spec = load_spec(scene)
truth, meta = store.load(spec, base=Path(base))
meta.update(seed=99)
store.save(truth, meta, store.path_for(spec.name, spec.camera.resolution, Path(base)), force=True)
"""


def test_a_reader_during_a_swap_waits_for_the_new_reference(tmp_path, base, capsys, monkeypatch):
    scene = _scene(tmp_path)
    assert _run(["reference", scene, *FAST], capsys)[0] == 0
    sync = tmp_path / "sync"
    pause = 7.0                       # longer than recover() waits (5 s)
    p = subprocess.Popen([sys.executable, "-c", _PAUSED_WRITER, str(scene), str(base), str(sync), str(pause)],
                         cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        t = time.monotonic()
        while not Path(str(sync) + ".ready").exists():
            assert p.poll() is None and time.monotonic() - t < 60, p.stderr.read()
            time.sleep(0.02)
        truth, meta = store.load(load_spec(scene), base=base)       # the old one is away: wait, then read
        assert meta["seed"] == 99
    finally:
        p.wait(timeout=60)
    assert p.returncode == 0, p.stderr.read()


def test_a_reader_whose_files_move_away_mid_read_reads_the_new_reference(tmp_path, base, capsys, monkeypatch):
    """The writer's first rename (old reference away) lands just after the reader checked that the
    reference is there; the new one is placed 0.5 s later: the reader retries and reads it."""
    import shutil
    import threading
    scene = _scene(tmp_path)
    assert _run(["reference", scene, *FAST], capsys)[0] == 0
    d = store.path_for("tiny", (16, 16), base)
    new = tmp_path / "new"
    shutil.copytree(d, new)
    problem = store._problem

    def writer_moves_old_away(path):
        out = problem(path)
        if Path(path) == d and d.exists():
            d.rename(d.parent / f".{d.name}.old-99999")
            threading.Timer(0.5, lambda: (new.rename(d), shutil.rmtree(d.parent / f".{d.name}.old-99999"))).start()
        return out

    monkeypatch.setattr(store, "_problem", writer_moves_old_away)
    truth, meta = store.load(load_spec(scene), base=base)
    assert d.exists() and meta[store.CHECKSUM_KEY] == store.sha256_file(d / "truth.exr")
