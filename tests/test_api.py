"""The public API (``import shadowlab``) and ``-t all``.

The API's docstring examples run as doctests (tests/test_doctests.py); here: a user's own pytest
gate written with it, as the README shows, that passes for a good technique and fails for a bad
one, and ``-t all`` for ``compare`` and ``fit`` on a 24² copy of ``contact``.
"""

from pathlib import Path

import numpy as np
import pytest

import shadowlab
from shadowlab.techniques import get
from shadowlab import cli, pipeline
from shadowlab.errors import InputError

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def planes(mitsuba_backend):
    frame = shadowlab.make_frame(shadowlab.load_scene("parallel_planes"))
    return frame, shadowlab.load_reference("parallel_planes")


def test_a_users_gate_written_with_the_api(planes):
    """The README's example: pcss passes a penumbra budget that hard fails."""
    frame, truth = planes
    good = shadowlab.visibility(frame, shadowlab.render_technique(frame, "pcss"), "panel")
    bad = shadowlab.visibility(frame, shadowlab.render_technique(frame, "hard"), "panel")
    assert shadowlab.gate_image(good, truth, target="visibility", light="panel", rmse_penumbra=0.02).passed
    r = shadowlab.gate_image(bad, truth, target="visibility", light="panel", rmse_penumbra=0.02)
    assert not r.passed and any(line.startswith("FAIL") for line in r.lines())


def test_compare_per_light_and_pooled_agree_for_one_light(planes):
    frame, truth = planes
    res = shadowlab.render_technique(frame, "pcf", kernel=5)
    pooled, one = shadowlab.compare(frame, truth, res), shadowlab.compare(frame, truth, res, light="panel")
    assert np.isclose(pooled["vis_rmse_penumbra"], one["rmse_penumbra"])
    assert np.isclose(pooled["leak_rate"], one["leak_rate"])


def test_bad_input_names_the_fix(planes):
    frame, truth = planes
    with pytest.raises(InputError, match="kernel"):
        shadowlab.render_technique(frame, "pcf", kernel=999)
    with pytest.raises(InputError, match="registered techniques"):
        shadowlab.render_technique(frame, "nope")
    with pytest.raises(InputError, match="its lights: panel"):
        shadowlab.visibility(frame, shadowlab.render_technique(frame, "hard"), "sun")
    with pytest.raises(InputError, match="unknown threshold"):
        shadowlab.gate_image(np.zeros((2, 2)), np.zeros((2, 2)), rmse_everywhere=0.1)


def test_techniques_that_apply(mitsuba_backend):
    t = shadowlab.techniques_for("parallel_planes")
    assert t["pcss"] is None and t["hard"] is None
    assert "directional" in t["csm"] and "area" in t["dpsv"]
    # without a scene only what this machine lacks stops a technique (an engine without its npm packages)
    assert all(v is None or v == get(n).unavailable() for n, v in shadowlab.techniques_for().items())
    assert all(v is None for n, v in shadowlab.techniques_for().items() if not get(n).external)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, mitsuba_backend):
    d = tmp_path_factory.mktemp("api_all")
    text = (ROOT / "scenes" / "contact.toml").read_text()
    text = text.replace("resolution = [128, 128]", "resolution = [24, 24]").replace('name = "contact"', 'name = "tiny"')
    scene = d / "tiny.toml"
    scene.write_text(text)
    base = d / "refs"
    pipeline.reference(str(scene), base=base, progress=False, max_rounds=16, spp=0)
    return scene, base


def test_compare_all_runs_every_technique_that_applies(tiny, tmp_path, capsys, monkeypatch):
    scene, base = tiny
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    rc = cli.main(["compare", str(scene), "-t", "all", "--out", str(tmp_path / "r")])
    out, err = capsys.readouterr()
    why = shadowlab.techniques_for(str(scene))
    external = [n for n in why if get(n).external]      # real engines run only when named
    applies = [n for n, w in why.items() if w is None and n not in external]
    skipped = [n for n, w in why.items() if w and n not in external]
    assert rc == 0, err
    assert skipped and all(f"skipping {n}:" in err for n in skipped)
    assert external and f"not in all: {', '.join(external)}" in err
    import json
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert sorted(metrics["techniques"]) == sorted(applies)


def test_fit_all_lists_what_does_not_apply(tiny, tmp_path, capsys, monkeypatch):
    scene, base = tiny
    monkeypatch.setenv("SHADOWLAB_REFERENCES", str(base))
    rc = cli.main(["fit", str(scene), "-t", "all", "--evals", "3", "--steps", "2", "--grid-points", "3",
                   "--rounds", "1", "--out", str(tmp_path / "f")])
    out, err = capsys.readouterr()
    assert rc == 0, err
    for n, why in shadowlab.techniques_for(str(scene)).items():
        if why and not get(n).external:
            assert f"| {n} | skipped: {why.split(':')[0]}" in out, n


def test_no_api_name_shadows_a_subpackage():
    """``import shadowlab.render.frame`` must keep working: an API function named like a
    sub-package or module of shadowlab would replace it as the package's attribute."""
    import pkgutil
    mods = {m.name for m in pkgutil.iter_modules(shadowlab.__path__)}
    assert not mods & set(shadowlab.__all__), mods & set(shadowlab.__all__)
    import shadowlab.render.frame as frame_module
    import shadowlab.techniques.pcf as pcf_module
    assert frame_module.make_frame and pcf_module.PCF_PARAMS


def test_shadow_maps_do_not_apply_to_sdf_only_scenes():
    """Shadow maps are Mitsuba ray casts from the light, which miss SDF-only objects: ``-t all``
    (``techniques_for``) must skip them with the reason rather than fail mid-run."""
    why = shadowlab.techniques_for("mandelbulb")
    for n in ("hard", "pcf", "pcss", "vsm", "csm", "vtsm", "ssss", "sm_dpsv"):
        assert why[n] and "SDF-only" in why[n], n
    assert why["sdf_hard"] is None
    assert all(v is None or "SDF-only" not in v for v in shadowlab.techniques_for("contact").values())
