"""``shadowlab.gate.run_gate_file`` (the package's Python API) passes every argument on to
:func:`shadowlab.gate.runner.run_gate_file`: it used to drop ``force``, ``frame`` and ``frames``."""

from __future__ import annotations

import inspect

import pytest

import shadowlab.gate as gate
from shadowlab.errors import InputError
from shadowlab.gate import runner

_GATE = """version = 1
references = "{refs}"
[[gate]]
name = "contact/truth"
scene = "contact"
resolution = [16, 16]
target = "visibility"
candidate = {{ truth = true, seed = 3 }}
statistical = {{}}
"""


def test_the_wrapper_takes_every_argument_of_the_runner():
    assert list(inspect.signature(gate.run_gate_file).parameters) == \
        list(inspect.signature(runner.run_gate_file).parameters)


def test_every_argument_reaches_the_runner(monkeypatch):
    seen = {}

    def fake(path, **kw):
        seen.update(kw, path=path)
        return 0, []

    monkeypatch.setattr(gate, "_run", fake)
    gate.run_gate_file("g.toml", out_dir="o", only=["a"], variant="llvm_ad_rgb", echo=None, force=True, frame=2,
                       frames="0:3")
    assert seen == dict(path="g.toml", out_dir="o", only=["a"], variant="llvm_ad_rgb", echo=None, force=True, frame=2,
                        frames="0:3")


def test_force_and_frame_act(tmp_path):
    """A foreign output directory is refused without ``force``; with it, the run goes on and
    ``frame`` is checked against the scene (contact has no camera path): exit-2 input errors that
    come before anything is rendered or written."""
    g = tmp_path / "gates.toml"
    g.write_text(_GATE.format(refs=tmp_path / "refs"))
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("not shadowlab's")
    with pytest.raises(InputError, match="did not create"):
        gate.run_gate_file(g, out_dir=out, echo=None, frame=5)
    with pytest.raises(InputError, match="frame") as e:
        gate.run_gate_file(g, out_dir=out, echo=None, force=True, frame=5)
    assert "did not create" not in str(e.value)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]      # nothing written
