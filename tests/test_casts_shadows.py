"""``casts_shadows`` (issue 27): a light's own panel casts no shadow of the other lights unless the scene
says so, and a shape that is told not to cast blocks no light; the truth's shadow rays and every
technique (light views, tiles, the TOP tree, the SDF) honour both.

The scene: a floor under a sun shining straight down and a 0.8 m soft box (a rect light facing down)
1.5 m above the floor, so the panel lies on the sun's path to the floor under it. The sun is a delta
light, so the truth is one exact shadow ray per point: V = 1 where the floor under the panel is lit.
"""

import numpy as np
import pytest

from scene_builder import floor, frame_from, spec_of
from shadowlab import render_technique, techniques_for, visibility
from shadowlab.errors import SceneError
from shadowlab.reference.truth import centre_visibility
from shadowlab.reference.truth import visibility as truth_visibility

CAM = {"position": [0, 4.0, 2.0], "target": [0, 0, 0], "fov": 50, "resolution": [64, 64]}
SUN = {"name": "sun", "kind": "directional", "direction": [0.0, -1.0, 0.0], "irradiance": 3.0, "shadow_map": 512}
BOX = {"name": "softbox", "kind": "rect", "position": [0.0, 1.5, 0.0], "target": [0.0, 0.0, 0.0],
       "up": [0, 0, 1], "size": [0.8, 0.8], "power": 40.0, "shadow_map": 256}


#: the sun's own techniques (cascades, virtual maps, dpsv's TOP tree) beside the soft box's pcf
SUN_TECHNIQUES = ["sun=csm,softbox=pcf", "sun=vtsm,softbox=pcf", "sun=dpsv,softbox=pcf"]


def _doc(*, box_casts=None, card_casts=None, sun=SUN):
    box = dict(BOX, **({} if box_casts is None else {"casts_shadows": box_casts}))
    shapes = [floor(2.0)]
    if card_casts is not None:  # the same square as a shape instead of a light panel
        shapes.append({"name": "card", "type": "rectangle", "rotate": [1, 0, 0, 90], "scale": 0.4,
                       "translate": [0, 1.5, 0], "casts_shadows": card_casts})
        return {"name": "card", "camera": CAM, "lights": [sun], "shapes": shapes}
    return {"name": "softbox", "camera": CAM, "lights": [SUN, box], "shapes": shapes}


def _under(frame):
    """(H, W) bool: floor pixels well inside the panel's vertical shadow (|x|, |z| < 0.3 m)."""
    p = frame.gbuffer.to_image(np.stack([frame.gbuffer.p.x.numpy(), frame.gbuffer.p.y.numpy(),
                                         frame.gbuffer.p.z.numpy()], 1))
    m = (np.abs(p[..., 0]) < 0.3) & (np.abs(p[..., 2]) < 0.3) & (np.abs(p[..., 1]) < 1e-3)
    return m & frame.gbuffer.to_image(frame.gbuffer.valid.numpy().astype(float)).astype(bool)


def _truth(frame, light="sun"):
    return truth_visibility(frame, light, max_rounds=1).V


@pytest.fixture(scope="module")
def frames(mitsuba_backend, tmp_path_factory):
    d = tmp_path_factory.mktemp("casts")
    return {c: frame_from(_doc(box_casts=c), d / f"softbox_{c}.toml") for c in (False, True)}


def test_the_default_is_a_panel_that_casts_no_shadow():
    spec = spec_of(_doc())
    assert spec.light("softbox").casts_shadows is False and spec.shapes[0].casts_shadows is True


def test_truth_under_a_panel_that_does_not_cast_is_lit_and_under_one_that_casts_is_dark(frames):
    off, on = frames[False], frames[True]
    m = _under(off)
    assert m.sum() > 50
    assert np.all(_truth(off)[m] == 1.0)
    assert np.all(_truth(on)[m] == 0.0)
    # the exact centre visibility (what shadow-map aliasing is measured against) agrees
    assert np.all(off.image(centre_visibility(off, "sun").numpy())[m] == 1.0)
    assert np.all(on.image(centre_visibility(on, "sun").numpy())[m] == 0.0)
    # the soft box's own light: its panel never shadows itself, either way
    assert _truth(off, "softbox")[m].min() > 0.99 and _truth(on, "softbox")[m].min() > 0.99


def test_every_technique_sees_no_shadow_of_a_panel_that_does_not_cast(frames):
    frame = frames[False]
    m = _under(frame)
    # engines (``three:``, ``babylon:``) render the exported scene in a browser: not here; csm and the virtual
    # maps take scenes whose lights are all directional, so the card scene below has them
    applies = [n for n, why in techniques_for(frame.scene).items() if why is None and ":" not in n]
    assert {"hard", "pcf", "pcss", "vsm", "sm_dpsv_soft", "ssss", "sdf_hard"} <= set(applies)
    applies += SUN_TECHNIQUES
    low = {}
    for n in applies:
        v = visibility(frame, render_technique(frame, n), "sun")[m]
        if v.mean() < 0.97:
            low[n] = round(float(v.mean()), 3)
    assert not low, f"techniques that shadow the floor under a panel that does not cast: {low}"


def test_the_shadow_of_a_panel_that_casts_is_there_for_the_techniques(frames):
    frame = frames[True]
    m = _under(frame)
    why = techniques_for(frame.scene)
    assert "casts_shadows = true" in why["sdf_hard"]        # the panel has no SDF twin
    assert "casts_shadows = true" in why["three:basic"]     # nor a mesh in the glb the engines load
    for n in ("hard", "pcf", "sm_dpsv_soft", "ssss", *SUN_TECHNIQUES):
        assert why.get(n) is None
        v = visibility(frame, render_technique(frame, n), "sun")[m]
        assert v.mean() < 0.1, (n, float(v.mean()))


def test_a_shape_that_does_not_cast_blocks_no_light(mitsuba_backend, tmp_path):
    casting = frame_from(_doc(card_casts=True), tmp_path / "card_on.toml")
    quiet = frame_from(_doc(card_casts=False), tmp_path / "card_off.toml")
    m = _under(quiet)
    assert np.all(_truth(casting)[m] == 0.0) and np.all(_truth(quiet)[m] == 1.0)
    # every technique (a sun alone: the cascades, virtual maps and dpsv's TOP tree apply too)
    applies = [n for n, why in techniques_for(quiet.scene).items() if why is None and ":" not in n]
    assert {"csm", "vtsm", "fvsm", "dpsv", "sm_dpsv", "sdf_hard"} <= set(applies)
    low = {n: v for n in applies if (v := float(visibility(quiet, render_technique(quiet, n), "sun")[m].mean())) < 0.97}
    assert not low, f"techniques that shadow the floor under a shape that does not cast: {low}"
    for n in ("hard", "csm", "vtsm", "dpsv", "sdf_hard"):
        assert visibility(casting, render_technique(casting, n), "sun")[m].mean() < 0.1, n
    # the camera still sees the card: it hides part of the floor in both scenes
    assert quiet.gbuffer.valid.numpy().sum() == casting.gbuffer.valid.numpy().sum()


def test_casts_shadows_on_a_light_without_a_panel_is_refused():
    doc = _doc()
    doc["lights"][0] = dict(SUN, casts_shadows=True)
    with pytest.raises(SceneError, match="casts_shadows.*directional light has no surface"):
        spec_of(doc)
    doc["lights"][0] = dict(SUN, casts_shadows="yes")
    with pytest.raises(SceneError, match="true or false"):
        spec_of(doc)


def test_the_digest_changes_only_where_the_truth_does():
    base = spec_of(_doc()).digest()
    assert spec_of(_doc(box_casts=True)).digest() != base       # the panel now shadows the sun
    one = {"name": "one", "camera": CAM, "lights": [BOX], "shapes": [floor(2.0)]}
    # one light: its own panel never blocks it, so the switch changes nothing and is not hashed
    assert spec_of(one).digest() == spec_of({**one, "lights": [dict(BOX, casts_shadows=True)]}).digest()
    assert spec_of(_doc(card_casts=False)).digest() != spec_of(_doc(card_casts=True)).digest()


@pytest.mark.parametrize("engine", ["three:basic", "babylon:basic"])
def test_engines_draw_a_shape_that_does_not_cast_without_its_shadow(mitsuba_backend, tmp_path, engine):
    """The glb carries casts_shadows in each node's extras; the engine pages leave such a mesh out of
    the shadow casters. The sun is tilted a little (three.js's shadow camera has no orientation for a
    sun straight down its up axis) and a normal bias clears the engines' acne on the floor."""
    sun = dict(SUN, direction=[0.05, -1.0, 0.03])
    casting = frame_from(_doc(card_casts=True, sun=sun), tmp_path / "card_on.toml")
    if why := techniques_for(casting.scene)[engine]:
        pytest.skip(why)
    quiet = frame_from(_doc(card_casts=False, sun=sun), tmp_path / "card_off.toml")
    m = _under(quiet)
    on = visibility(casting, render_technique(casting, engine, normalBias=0.02), "sun")
    off = visibility(quiet, render_technique(quiet, engine, normalBias=0.02), "sun")
    assert on[m].mean() < 0.05 and on[~m].mean() > 0.8
    assert off[m].mean() > 0.97
