"""An SDF-only scene is a kind of scene: ``scene.kind`` ("mitsuba" | "sdf") chooses the G-buffer
(make_frame) and the ground truth (the reference command); the benches time with one helper."""

from __future__ import annotations

import numpy as np
import pytest

from shadowlab.bench.timing import timed, warm_median
from shadowlab.errors import InputError
from shadowlab.render.frame import make_frame
from shadowlab.render.gbuffer import GBuffer
from shadowlab.render.sdf_gbuffer import SDFGBuffer
from shadowlab.scene import load
from shadowlab.scene.spec import load_spec, parse, resolve
from scene_builder import write_scene

SDF_ONLY = {"name": "ball", "camera": {"position": [0, 1, 4], "target": [0, 0.5, 0], "resolution": [16, 12]},
            "lights": [{"name": "key", "kind": "sphere", "position": [1, 3, 1], "radius": 0.3, "power": 50}],
            "sdf": [{"type": "sphere", "center": [0, 0.5, 0], "radius": 0.5},
                    {"type": "box", "half": [2, 0.05, 2], "translate": [0, -0.05, 0]}]}


def test_the_kind_of_a_scene_is_whether_it_has_sdf_objects():
    assert load_spec(resolve("mandelbulb")).kind == "sdf"
    for name in ("contact", "sdf_simple", "sdf_composite"):       # twins of Mitsuba shapes only
        assert load_spec(resolve(name)).kind == "mitsuba"
    assert parse(SDF_ONLY).kind == "sdf"
    mitsuba_only = {k: v for k, v in SDF_ONLY.items() if k != "sdf"}
    mitsuba_only["shapes"] = [{"name": "ball", "type": "sphere", "center": [0, 0.5, 0], "radius": 0.5}]
    assert parse(mitsuba_only).kind == "mitsuba"


def test_make_frame_dispatches_on_the_kind(frame_of, tmp_path):
    p = write_scene(tmp_path / "ball.toml", SDF_ONLY)   # the scene as a file, loaded like a user's
    sc = load(str(p))
    assert sc.kind == "sdf"
    fr = make_frame(sc, u_strata=1)
    assert isinstance(fr.gbuffer, SDFGBuffer) and fr.sdf is not None
    assert fr.gbuffer.mask.any()
    with pytest.raises(InputError, match="SDF-only objects"):
        fr.light_view("key")
    fr2 = frame_of("contact", (16, 16), u_strata=1)
    assert fr2.scene.kind == "mitsuba"
    assert type(fr2.gbuffer) is GBuffer


def test_mc_cone_visibility_takes_a_sphere_not_a_light_spec(mitsuba_backend):
    import mitsuba as mi
    from shadowlab.sdf import Sphere
    from shadowlab.sdf.soft import mc_cone_visibility
    light = load_spec(resolve("sdf_simple")).lights[0]
    with pytest.raises(TypeError, match="centre, radius"):
        mc_cone_visibility(Sphere((0, 0, 0), 1.0), mi.Point3f(0, 2, 0), mi.Vector3f(0, 1, 0), light, 4)


def test_timed_runs_warm_ups_untimed_and_times_each_repeat(mitsuba_backend):
    calls = []
    out, ts = timed(lambda: calls.append(1) or len(calls), repeats=3, warmup=2)
    assert len(calls) == 5 and out == 5 and len(ts) == 3 and all(t >= 0 for t in ts)
    out, med = warm_median(lambda: calls.append(1) or len(calls), repeats=4)
    assert len(calls) == 10 and out == 10 and isinstance(med, float) and np.isfinite(med)
