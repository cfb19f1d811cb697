"""References that measure nothing (issue 27, "Vacuous results stored or reported as good").

A reference is refused (exit 2, nothing stored) when nothing in it is measurable: the camera sees
no surface, or every light is enclosed by geometry or reaches no surface the camera sees (its
``range``). A reference where only some lights measure nothing is stored with a warning that the
``reference`` command prints, ``references`` lists and every command that reads it repeats. An
older reference that measures nothing (stored before this check) is never compared with: the
comparison exits 2 instead of "rmse 0, psnr inf". Each scene is a real one rendered by Mitsuba at
16×16 through the CLI.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from shadowlab import cli
from shadowlab.io.exr import read_exr, write_exr
from shadowlab.pipeline import references as refs_mod
from shadowlab.reference import store, vacuous

ROOT = Path(__file__).resolve().parents[1]
FAST = ["--max-rounds", "2", "--spp", "0"]

_CAMERA = '[camera]\nposition = [0.0, 3.2, 6.0]\ntarget = [0.0, 0.4, 0.0]\nfov = 45\nresolution = [16, 16]\n'
_FLOOR = ('[[shapes]]\nname = "floor"\ntype = "rectangle"\nrotate = [1, 0, 0, -90]\nscale = 4.0\n'
          'albedo = [0.75, 0.75, 0.75]\n')
_KEY = ('[[lights]]\nname = "key"\nkind = "rect"\nposition = [1.2, 4.0, 1.0]\ntarget = [0.0, 0.0, 0.0]\n'
        'size = [1.0, 1.0]\npower = 300\n')
_SHORT = '[[lights]]\nname = "short"\nkind = "point"\nposition = [0.0, 3.0, 0.0]\nintensity = 20\nrange = 0.5\n'
_BOXED = '[[lights]]\nname = "boxed"\nkind = "point"\nposition = [0.0, 2.0, 0.0]\nintensity = 20\n'
_BOX = '[[shapes]]\nname = "box"\ntype = "cube"\ntranslate = [0.0, 2.0, 0.0]\nscale = 0.4\n'


def _write(tmp_path, name, *parts, camera=_CAMERA):
    p = tmp_path / f"{name}.toml"
    p.write_text(f'name = "{name}"\n\n' + camera + "\n" + "\n".join(parts))
    return p


@pytest.fixture
def base(tmp_path, monkeypatch):
    b = tmp_path / "refs"
    b.mkdir()
    monkeypatch.setenv(store.ROOT_ENV, str(b))
    return b


def _run(args, capsys):
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "internal error" not in err, err
    return rc, out, err


def _stored(base: Path) -> list[str]:
    return sorted(str(p.relative_to(base)) for p in base.rglob("meta.json"))


@pytest.mark.parametrize("case, words", [
    ("blind", "the camera sees no surface"),
    ("enclosed", "light 'boxed' is blocked on every surface it reaches (enclosed by geometry"),
    ("unreached", "light 'short' reaches no surface the camera sees"),
])
def test_a_reference_that_measures_nothing_is_refused(case, words, tmp_path, base, capsys):
    scene = {
        "blind": lambda: _write(tmp_path, "blind", _KEY, _FLOOR, camera=_CAMERA.replace("[0.0, 0.4, 0.0]",
                                                                                      "[0.0, 10.0, 12.0]")),
        "enclosed": lambda: _write(tmp_path, "enclosed", _BOXED, _FLOOR, _BOX),
        "unreached": lambda: _write(tmp_path, "unreached", _SHORT, _FLOOR),
    }[case]()
    rc, out, err = _run(["reference", scene, *FAST], capsys)
    assert rc == 2, (out, err)
    assert words in err and "measures nothing" in err and "nothing was stored" in err, err
    assert f"shadowlab reference {scene}" in err                  # the fix names the path the user gave
    assert _stored(base) == [] and "reference written" not in out


def test_a_light_that_measures_nothing_beside_one_that_does_warns_everywhere(tmp_path, base, capsys):
    scene = _write(tmp_path, "mixed", _KEY, _SHORT, _FLOOR)
    rc, out, err = _run(["reference", scene, *FAST], capsys)
    assert rc == 0 and "reference written" in out, err
    assert "warning: light 'short' reaches no surface the camera sees" in err, err
    (meta_path,) = base.rglob("meta.json")
    assert set(json.loads(meta_path.read_text())["vacuous"]) == {"short"}
    rc, out, err = _run(["references"], capsys)
    assert rc == 0 and "light 'short' reaches no surface the camera sees" in out, out
    store._WARNED.clear()                                          # a new process: the warning again
    rc, out, err = _run(["compare", scene, "-t", "hard", "--out", tmp_path / "cmp"], capsys)
    assert rc == 0, err
    assert "warning: the reference at" in err and "light 'short' reaches no surface" in err, err
    metrics = json.loads((tmp_path / "cmp" / "metrics.json").read_text())
    assert np.isfinite(metrics["techniques"]["hard"]["per_light"]["key"]["rmse"])   # the key light still measures


def test_an_old_reference_that_measures_nothing_is_not_compared(tmp_path, base, capsys, monkeypatch):
    """Stored before the check (here: with the check switched off), a reference of a blind camera
    would compare as "rmse 0, psnr inf"; the comparison and `references` refuse it instead."""
    scene = _write(tmp_path, "old", _BOXED, _FLOOR, _BOX)
    monkeypatch.setattr(refs_mod, "_check_measures", lambda *a, **k: None)
    rc, _, err = _run(["reference", scene, *FAST], capsys)
    assert rc == 0 and len(_stored(base)) == 1, err
    monkeypatch.undo()
    monkeypatch.setenv(store.ROOT_ENV, str(base))
    rc, out, err = _run(["compare", scene, "-t", "hard", "--out", tmp_path / "cmp"], capsys)
    assert rc == 2 and "measures nothing" in err and "enclosed by geometry" in err and "--force" in err, (out, err)
    assert "psnr" not in out and not (tmp_path / "cmp").exists()
    rc, out, _ = _run(["references"], capsys)
    assert rc == 0 and "empty: it measures nothing" in out, out


def test_references_lists_a_truth_without_its_mask_channel_as_damaged(tmp_path, base, capsys):
    scene = _write(tmp_path, "maskless", _KEY, _FLOOR)
    assert _run(["reference", scene, *FAST], capsys)[0] == 0
    (meta_path,) = base.rglob("meta.json")
    exr = meta_path.with_name("truth.exr")
    ch = read_exr(exr)
    del ch["mask"]
    write_exr(exr, ch)
    meta = json.loads(meta_path.read_text())
    meta[store.CHECKSUM_KEY] = store.sha256_file(exr)       # consistent: only the channel is missing
    meta_path.write_text(json.dumps(meta))
    rc, out, _ = _run(["references"], capsys)
    assert rc == 0 and "damaged: truth.exr has no channel mask" in out and "--force" in out, out


def test_findings_in_closed_form():
    m = np.zeros((3, 3), bool)
    m[1:, 1:] = True                      # 4 visible pixels
    U = {"a": np.zeros((3, 3, 3)), "b": np.zeros((3, 3, 3))}
    U["a"][1, 1] = 1.0                    # a reaches one visible pixel ...
    U["b"][0, 0] = 1.0                    # ... b only a pixel the camera does not see
    V = {"a": np.zeros((3, 3)), "b": np.ones((3, 3))}
    assert vacuous.findings(m, U, V) == {"a": "enclosed", "b": "unreached"}
    V["a"][1, 1] = 0.01                   # one ray of a gets through: a measures
    assert vacuous.findings(m, U, V) == {"b": "unreached"}
    with pytest.raises(Exception, match="measures nothing"):
        vacuous.refuse_empty({"a": "enclosed", "b": "unreached"}, ["a", "b"], where="r", fix_tail="x")
    vacuous.refuse_empty({"b": "unreached"}, ["a", "b"], where="r", fix_tail="x")    # a still measures


def test_references_lists_a_truth_of_another_size_as_damaged(tmp_path, base, capsys):
    scene = _write(tmp_path, "resized", _KEY, _FLOOR)
    assert _run(["reference", scene, *FAST], capsys)[0] == 0
    (meta_path,) = base.rglob("meta.json")
    exr = meta_path.with_name("truth.exr")
    write_exr(exr, {k: v[:8] for k, v in read_exr(exr).items()})          # 16x8 in a 16x16 directory
    meta = json.loads(meta_path.read_text())
    meta[store.CHECKSUM_KEY] = store.sha256_file(exr)
    meta_path.write_text(json.dumps(meta))
    rc, out, _ = _run(["references"], capsys)
    assert rc == 0 and "damaged: truth.exr is 16x8, not 16x16" in out, out


def test_on_a_cluster_the_refusal_is_one_line_without_a_dask_dump(tmp_path, base, capfd):
    """A job's refusal on a worker (here: the blind camera) ends the command with its one line and
    exit code, as in one process; the worker does not print Dask's "Compute Failed" traceback
    (capfd: the worker processes write to this process's stderr)."""
    blind = _write(tmp_path, "blind", _KEY, _FLOOR, camera=_CAMERA.replace("[0.0, 0.4, 0.0]", "[0.0, 10.0, 12.0]"))
    fine = _write(tmp_path, "fine", _KEY, _FLOOR)
    rc = cli.main(["reference", str(blind), str(fine), "--workers", "2", *FAST])
    out, err = capfd.readouterr()
    lines = [l for l in err.splitlines() if l.strip() and not l.startswith("warning:")]
    assert rc == 2 and len(lines) == 1 and "the camera sees no surface" in lines[0], err
    assert "Compute Failed" not in err and "Traceback" not in err
