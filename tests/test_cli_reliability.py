"""The CLI under bad input, interruption and misdirected output (issue 15).

What must hold, each tested here:

* SIGINT exits 130 and SIGTERM 143, with one line on stderr and nothing partial in the store
  (real processes: a running ``shadowlab reference``, a running ``shadowlab gate``); an
  interrupted gate run never looks green (its junit.xml records the interruption).
* A gate never passes on an empty or too-small pixel set (fewer than ``MIN_GATE_PIXELS``).
* No command overwrites a file it did not create without ``--force``; ``--out`` on an existing
  file or inside the reference store exits 2.
* An internal error exits 4 with one "please report" line (the traceback only with
  ``SHADOWLAB_DEBUG=1``); 1 only for a failed gate.
* Numeric options are range-checked, ``--variant`` is validated, and fix texts name a scene
  given as a path by that path.
"""

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from shadowlab import cli, pipeline
from shadowlab.errors import InputError, ReferenceError_
from shadowlab.fit import preset as P
from shadowlab.gate import check
from shadowlab.gate.check import MIN_GATE_PIXELS
from shadowlab.gate.junit import junit_xml
from shadowlab.reference import store
from shadowlab.reference.truth import LightTruth, Truth
from shadowlab.io.outdir import MARKER
from shadowlab.scene import load_spec
from conftest import CUDA

ROOT = Path(__file__).resolve().parents[1]


def _scene(tmp_path, name="tiny", res=24, camera_target=None):
    text = (ROOT / "scenes" / "contact.toml").read_text()
    text = text.replace("resolution = [128, 128]", f"resolution = [{res}, {res}]")
    text = text.replace('name = "contact"', f'name = "{name}"')
    if camera_target is not None:  # the camera looks away from everything: no pixel hits a surface
        assert "target = [0.0, 0.4, 0.0]" in text
        text = text.replace("target = [0.0, 0.4, 0.0]", f"target = {camera_target}", 1)
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


def _digest(d: Path) -> dict:
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(d.rglob("*")) if p.is_file()}


def _main(args, capsys, monkeypatch=None, env=None):
    if env and monkeypatch is not None:
        for k, v in env.items():
            monkeypatch.setenv(k, v)
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def _leftovers(base: Path) -> list:
    """Files in a store other than lock files: what an interrupted run must not leave."""
    return sorted(str(p.relative_to(base)) for p in base.rglob("*") if p.is_file() and not p.name.endswith(".lock"))


def _child_env(store_dir):
    env = dict(os.environ, SHADOWLAB_REFERENCES=str(store_dir),
               PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    env.pop(cli.DEBUG_ENV, None)
    return env


# ----------------------------------------------------------------------------- signals, real processes
_WRAPPER = ("import sys\nimport shadowlab.cli as c\nprint('ready', flush=True)\n"
            "sys.exit(c.main(sys.argv[1:]))\n")


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_stops_a_running_reference_with_one_line_and_nothing_stored(tmp_path, sig, code):
    """A real `shadowlab reference` process (its imports done, then the command running: a slow
    truth, target error 0.0002 and a 4096-round cap on 256²: seconds of rendering) gets the signal: exit 128 + signal,
    one line on stderr, no
    traceback, and the store holds nothing (no reference, no temporary directory)."""
    # the truth's few-wavefront sampler renders a 64² one within the 1.5 s below (on 2 cores too), and
    # a GPU is faster still: 256² here, 1024² on cuda_ad_rgb
    scene = _scene(tmp_path, res=1024 if CUDA else 256)
    base = tmp_path / "refs"
    base.mkdir()                 # an existing store: creating one would print a note of its own
    p = subprocess.Popen([sys.executable, "-c", _WRAPPER, "reference", str(scene), "--target-se", "0.0002",
                          "--max-rounds", "4096"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_child_env(base), cwd=ROOT)
    try:
        assert p.stdout.readline().strip() == "ready"
        time.sleep(1.5)  # main() is running (handlers installed, scene loading or the truth rendering)
        assert p.poll() is None, "the reference finished before the signal; make the render slower"
        p.send_signal(sig)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == code, (out, err)
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"interrupted by {signal.Signals(sig).name}"), err
    assert "Traceback" not in err and "reference written" not in out
    assert not base.exists() or _leftovers(base) == [], _leftovers(base)


def _gate_file(tmp_path, scene, base, n_slow=4):
    gates = ['[[gate]]\nname = "fast"\nscene = "%s"\ncandidate = { technique = "hard" }\nbudget = { rmse = 1.0 }\n'
             % scene]
    gates += ['[[gate]]\nname = "truth%d"\nscene = "%s"\ncandidate = { truth = true, seed = %d }\nstatistical = {}\n'
              % (i, scene, i + 1) for i in range(n_slow)]
    gf = tmp_path / "gates.toml"
    gf.write_text(f'version = 1\nreferences = "{base}"\n\n' + "\n".join(gates))
    return gf


def test_interrupted_gate_exits_130_and_its_junit_is_not_green(tmp_path):
    scene = _scene(tmp_path, res=48)
    base = tmp_path / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=16, spp=0)
    before = _digest(base)
    gf = _gate_file(tmp_path, scene, base)
    out_dir = tmp_path / "gate-out"
    p = subprocess.Popen([sys.executable, "-m", "shadowlab.cli", "gate", str(gf), "--out", str(out_dir)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_child_env(base), cwd=ROOT)
    try:
        first = p.stdout.readline()          # the fast gate's line: the truth gates are running now
        assert "fast" in first, first
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, (first, out, err)
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted by SIGINT: after 1 of 5 gates"), err
    assert "gates passed" not in out                      # no green summary line
    xml = (out_dir / "junit.xml").read_text()
    assert 'errors="1"' in xml and 'name="interrupted"' in xml and "<error" in xml
    assert _digest(base) == before                        # the store was only read


# ----------------------------------------------------------------------------- in-process exit codes
def test_keyboard_interrupt_inside_a_command_exits_130_not_0(monkeypatch, capsys):
    """typer turns a KeyboardInterrupt into Exit(130) and *returns* it; main used to drop it (exit 0)."""
    def boom():
        raise KeyboardInterrupt
    monkeypatch.setattr(cli, "builtin_names", boom)
    rc, _, err = _main(["scenes", "--names"], capsys)
    assert rc == 130 and "interrupted" in err


def test_internal_error_exits_4_with_one_line_and_the_traceback_only_in_debug(monkeypatch, capsys):
    def bug():
        raise ZeroDivisionError("oops")
    monkeypatch.setattr(cli, "builtin_names", bug)
    monkeypatch.delenv(cli.DEBUG_ENV, raising=False)
    rc, _, err = _main(["scenes", "--names"], capsys)
    assert rc == 4 and "internal error: ZeroDivisionError: oops" in err and "please report" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    monkeypatch.setenv(cli.DEBUG_ENV, "1")
    rc, _, err = _main(["scenes", "--names"], capsys)
    assert rc == 4 and "Traceback" in err and "ZeroDivisionError" in err


def test_unwritable_file_is_an_environment_problem_exit_3(monkeypatch, capsys):
    def denied():
        raise PermissionError(13, "Permission denied", "/some/store/meta.json")
    monkeypatch.setattr(cli, "builtin_names", denied)
    rc, _, err = _main(["scenes", "--names"], capsys)
    assert rc == 3 and "/some/store/meta.json" in err and "Permission denied" in err and "Traceback" not in err


@pytest.mark.parametrize("args, option", [
    (["--target-se", "-1"], "--target-se"), (["--target-se", "nan"], "--target-se"),
    (["--target-se", "0"], "--target-se"), (["--seed", "-1"], "--seed"), (["--spp", "-5"], "--spp"),
])
def test_reference_options_are_range_checked(tmp_path, capsys, monkeypatch, args, option):
    scene = _scene(tmp_path)
    base = tmp_path / "refs"
    rc, _, err = _main(["reference", scene, *args], capsys, monkeypatch, env={"SHADOWLAB_REFERENCES": str(base)})
    assert rc == 2 and option in err
    assert not base.exists()
    with pytest.raises(InputError, match="--target-se"):  # the Python API checks too
        pipeline.reference(str(scene), base=base, target_se=float("nan"), progress=False)


def test_unknown_variant_is_refused_by_every_command(capsys):
    for args in (["ingest", "contact", "x.exr", "--channel", "V.key"], ["compare", "contact"], ["gate", "g.toml"]):
        rc, _, err = _main([*args, "--variant", "bogus"], capsys)
        assert rc == 2 and "unknown variant 'bogus'" in err, (args, err)


def test_fix_text_names_a_scene_file_by_its_path(tmp_path):
    scene = _scene(tmp_path, name="mine")
    with pytest.raises(ReferenceError_) as e:
        store.load(load_spec(scene), base=tmp_path / "refs")
    assert f"shadowlab reference {scene} --resolution 24x24" in str(e.value)
    with pytest.raises(ReferenceError_, match="shadowlab reference contact --resolution 64x64"):  # built-in: its name
        store.load(load_spec(ROOT / "scenes" / "contact.toml"), (64, 64), base=tmp_path / "refs")


# ----------------------------------------------------------------------------- gates on nothing
def _truth(V, U, mask):
    z = np.zeros_like(V)
    lt = LightTruth(V=V, V_se=z + 0.01, A=V, A_se=z + 0.01, samples=z + 256, bound=z)
    shaded = U * V[..., None]
    return Truth(lights={"key": lt}, U={"key": U}, shaded=shaded, shaded_var=shaded * 0 + 1e-4, mitsuba=None,
                 mitsuba_var=None, mask=mask, view_depth=z + 1)


def test_a_gate_never_passes_on_an_empty_or_too_small_pixel_set():
    hw = (16, 16)
    V = np.ones(hw)
    # the light inside a closed box: the camera sees surfaces, but no light reaches them
    dark = _truth(V, np.zeros(hw + (3,)), np.ones(hw, bool))
    for target in ("shaded", "visibility"):
        r = check(dark.shaded if target == "shaded" else V, dark, {"statistical": {}, "budget": {"rmse": 1.0}},
                  target=target, name="boxed")
        assert not r.passed and not r.check("pixels").passed, r.lines()
        assert f"need >= {MIN_GATE_PIXELS}" in r.check("pixels").text
        assert r.check("budget.rmse").passed  # the other checks alone would have been green
    # the light inside a closed box as Mitsuba sees it: unshadowed light U > 0 on every surface, but
    # the box blocks it all (truth V = 0 everywhere): a technique that is just as black must not pass
    boxed = _truth(np.zeros(hw), np.ones(hw + (3,)), np.ones(hw, bool))
    for target in ("shaded", "visibility"):
        r = check(boxed.shaded if target == "shaded" else np.zeros(hw), boxed, {"budget": {"rmse": 1.0}},
                  target=target, name="boxed")
        assert not r.passed and not r.check("pixels").passed, r.lines()
    # the camera looking at nothing: no pixel hits a surface
    blind = _truth(V, np.ones(hw + (3,)), np.zeros(hw, bool))
    assert not check(blind.shaded, blind, {"budget": {"rmse": 1.0}}).passed
    # arrays: too few valid pixels fail, exactly the minimum passes
    few = np.zeros(hw, bool)
    few.flat[:MIN_GATE_PIXELS - 1] = True
    assert not check(V, V, {"budget": {"rmse": 1.0}}, target="visibility", valid=few).passed
    few.flat[MIN_GATE_PIXELS - 1] = True
    r = check(V, V, {"budget": {"rmse": 1.0}}, target="visibility", valid=few)
    assert r.passed and [c.name for c in r.checks] == ["budget.rmse"]


def test_gate_file_on_a_scene_the_camera_does_not_see_never_passes(tmp_path, capsys, monkeypatch):
    """Such a reference is no longer stored (tests/test_reliability_vacuous.py); one stored before
    that check (here: with it switched off) is refused by the gate as it is read: exit 2, never green."""
    scene = _scene(tmp_path, name="blind", res=16, camera_target="[0.0, 10.0, 12.0]")
    base = tmp_path / "refs"
    with pytest.raises(ReferenceError_, match="the camera sees no surface"):
        pipeline.reference(str(scene), base=base, progress=False, max_rounds=16, spp=0)
    monkeypatch.setattr(pipeline.references, "_check_measures", lambda *a, **k: None)
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=16, spp=0)
    gf = tmp_path / "gates.toml"
    gf.write_text(f'version = 1\nreferences = "{base}"\n[[gate]]\nname = "blind/hard"\nscene = "{scene}"\n'
                  'candidate = { technique = "hard" }\nbudget = { rmse = 0.5, flip = 0.5 }\n')
    rc, out, err = _main(["gate", gf, "--out", tmp_path / "g"], capsys)
    assert rc == 2 and "measures nothing: the camera sees no surface" in err, (out, err)
    assert "passed" not in out


def test_junit_of_an_interrupted_run_has_an_error():
    xml = junit_xml([], suite="s", interrupted="interrupted by SIGTERM after 0 of 2 gates")
    assert 'errors="1"' in xml and 'tests="1"' in xml and "after 0 of 2 gates" in xml
    assert 'errors="0"' in junit_xml([], suite="s")


# ----------------------------------------------------------------------------- output paths
@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    d = tmp_path_factory.mktemp("c2store")
    scene = _scene(d)
    base = d / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=16, spp=0)
    (base / "gates.toml").write_text(f'version = 1\n[[gate]]\nname = "t"\nscene = "{scene}"\n'
                                     'candidate = { technique = "hard" }\nbudget = { rmse = 1.0 }\n')
    return scene, base


def test_save_preset_never_replaces_a_file_fit_did_not_write(tmp_path, tiny_store, capsys, monkeypatch):
    scene, base = tiny_store
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    before = _digest(base)
    meta = next(base.rglob("meta.json"))
    other = tmp_path / "notes.json"
    other.write_text('{"mine": 1}\n')
    for target, why in ((meta, "inside the reference store"), (base / "gates.toml", "inside the reference store"),
                        (other, "was not written by shadowlab")):
        rc, _, err = _main(["fit", scene, "-t", "pcss", "--save-preset", target, "--out", tmp_path / "fit"], capsys)
        assert rc == 2 and why in err and "--save-preset" in err, err
    assert _digest(base) == before and other.read_text() == '{"mine": 1}\n'
    assert not (tmp_path / "fit").exists()                 # refused before any fitting
    # --force lets a foreign file outside the store be replaced, never one inside the store
    assert P.check_writable(other, force=True) == other
    with pytest.raises(InputError, match="inside the reference store"):
        P.check_writable(base / "gates.toml", force=True, protected=[base])
    # a preset fit wrote is replaced without --force
    ours = P.save(tmp_path / "p.toml", "x", {"pcss": {"light_scale": 1.0}}, P.FIT_DESCRIPTION)
    assert P.written_by_fit(ours) and P.check_writable(ours) == ours
    assert not P.written_by_fit(other)


def test_out_on_a_file_or_inside_the_store_exits_2_for_every_command(tmp_path, tiny_store, capsys, monkeypatch):
    scene, base = tiny_store
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    before = _digest(base)
    a_file = tmp_path / "a_file"
    a_file.write_text("keep me\n")
    inside = base / "reports"
    cmds = {"compare": ["compare", scene, "-t", "hard"], "fit": ["fit", scene, "-t", "pcss"],
            "gate": ["gate", base / "gates.toml"], "export": ["export", scene],
            "demo": ["demo"]}
    for name, args in cmds.items():
        for out, why in ((a_file, "is an existing file"), (a_file / "sub", "is a file, not a directory"),
                         (inside, "inside the reference store")):
            rc, _, err = _main([*args, "--out", out], capsys)
            assert rc == 2 and why in err and "Traceback" not in err, (name, out, err)
    assert a_file.read_text() == "keep me\n" and _digest(base) == before and not inside.exists()


def test_report_directory_is_written_only_if_ours_or_forced(tmp_path, tiny_store, capsys, monkeypatch):
    scene, base = tiny_store
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "index.html").write_text("<p>my own page</p>")
    rc, _, err = _main(["compare", scene, "-t", "hard", "--out", theirs], capsys)
    assert rc == 2 and "did not create" in err and "--force" in err
    assert (theirs / "index.html").read_text() == "<p>my own page</p>"
    (theirs / "notes.txt").write_text("keep")
    rc, _, _ = _main(["compare", scene, "-t", "hard", "--out", theirs, "--force"], capsys)
    assert rc == 0 and (theirs / MARKER).is_file() and (theirs / "notes.txt").read_text() == "keep"
    assert json.loads((theirs / MARKER).read_text())["kind"] == "compare"
    # a directory of ours (new, then again) needs no --force; a gate report is marked too
    ours = tmp_path / "ours"
    for _ in range(2):
        rc, _, _ = _main(["compare", scene, "-t", "hard", "--out", ours], capsys)
        assert rc == 0 and (ours / MARKER).is_file() and (ours / "metrics.json").is_file()
    g = tmp_path / "g"
    for _ in range(2):
        rc, out, err = _main(["gate", base / "gates.toml", "--out", g], capsys)
        assert rc == 0 and (g / MARKER).is_file() and 'errors="0"' in (g / "junit.xml").read_text(), err
