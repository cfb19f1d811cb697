"""What a family declares on its Technique instead of being named by fit, pipeline and report
(docs/ARCHITECTURE.md, Technique): ``Param.kind`` is checked against ``base.KINDS``; a "from the
scene" value (``Param.from_scene``) is what fit centres a window on and the floor it keeps;
``fit_params`` / ``fit_loss`` give the same defaults the fit used before they moved into the
families; ``Panel`` kinds are the ones the report can draw."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from shadowlab.fit.objective import check_loss
from shadowlab.fit.run import default_loss, default_params, reference_value, scene_floor
from shadowlab.report.run import PANEL_CHANNELS
from shadowlab.techniques import base, get, names


def test_param_kind_is_checked_when_a_param_is_made():
    for kind in base.KINDS:
        base.Param("x", 1, kind, choices=(1, 2) if kind == "choice" else ())
    with pytest.raises(ValueError, match="kind 'number' is not one of float, int, bool, choice"):
        base.Param("x", 1.0, "number")
    with pytest.raises(ValueError, match="needs its choices"):
        base.Param("x", 1, "choice")


def test_every_declared_param_has_a_known_kind():
    assert {p.kind for n in names() for p in get(n).params} <= set(base.KINDS)


#: the defaults fit used when they were tables in fit/run.py (DEFAULT_PARAMS, DEFAULT_LOSS and the
#: duck-typed fit_params hooks of csm and the virtual maps): the declarations must give the same
BIASES = ("slope_scaled_depth_bias", "depth_bias")
BEFORE = {"hard": BIASES, "pcf": ("kernel", "softness"), "vtsm": BIASES, "fvsm": BIASES,
          "csm": ("split_lambda", "blend", "pull", "pcf_kernel", "pcf_softness")}
RMSE_LOSS = {"hard", "vtsm", "fvsm"}
#: the engines (techniques/engine_*.py) fit their own bias and filter properties (none is differentiable)
ENGINES = {"three:basic": ("bias", "normalBias"), "three:pcf": ("bias", "normalBias", "radius"),
           "three:vsm": ("bias", "normalBias", "radius"), "three:csm": ("shadowBias", "normalBias"),
           "babylon:basic": ("bias", "normalBias"), "babylon:pcf": ("bias", "normalBias"),
           "babylon:poisson": ("bias", "normalBias"), "babylon:esm": ("bias", "depthScale"),
           "babylon:esm_blur": ("bias", "depthScale", "blurBoxOffset"), "babylon:esm_close": ("bias", "depthScale"),
           "babylon:pcss": ("bias", "normalBias", "contactHardeningLightSizeUVRatio"),
           "babylon:csm": ("bias", "normalBias", "lambda")}


@pytest.mark.parametrize("name", names())
def test_fit_defaults_are_the_families_declarations_and_unchanged(name):
    t = get(name)
    want = BEFORE.get(name, ENGINES.get(name, tuple(p.name for p in t.params if p.differentiable)))
    assert default_params(t) == want == default_params(t, t.resolve({}))
    for n in want:
        t.param(n)
    assert default_loss(name) == ("rmse" if name in RMSE_LOSS else "rmse_penumbra")
    assert check_loss(t.fit_loss) == t.fit_loss


def test_a_composing_family_asks_its_filter_for_its_fit_defaults():
    csm = get("csm")
    for f, tail in (("pcss", ("pcss_light_scale",)), ("hard", BIASES), ("vsm", ("vsm_min_variance", "vsm_bleed"))):
        assert default_params(csm, csm.resolve({"filter": f})) == ("split_lambda", "blend", "pull") + tail


def test_from_the_scene_values_stand_for_the_scenes_and_keep_a_floor():
    frame = SimpleNamespace(lights=[SimpleNamespace(shadow_map=512), SimpleNamespace(shadow_map=2048)])
    for name in ("hard", "pcf", "pcss", "csm", "ssss"):
        t = get(name)
        p = t.param("resolution")
        assert p.from_scene is not None and p.from_scene.value == 0
        assert reference_value(t, "resolution", 0, frame) == 2048          # the largest light's map
        assert reference_value(t, "resolution", 256, frame) == 256         # a number is itself
        assert scene_floor(t, "resolution", 2048) == 64
    hard = get("hard")
    assert reference_value(hard, "depth_bias", 0, frame) == 0              # no sentinel: 0 is 0
    assert scene_floor(hard, "depth_bias", 0) is None


def test_panel_kinds_are_what_the_report_draws():
    assert set(PANEL_CHANNELS) == set(base.PANEL_KINDS)
    with pytest.raises(ValueError, match="is not one of"):
        base.Panel("sparkles", "t", (("k", ""),), "k")
    declared = [p for n in names() for p in get(n).panels]
    assert declared and {p.kind for p in declared} <= set(base.PANEL_KINDS)


def test_export_writes_the_packages_version():
    import shadowlab
    from shadowlab.exchange.export import _shadowlab_version
    assert _shadowlab_version() == shadowlab.__version__
