"""The built-in outdoor scenes ``street`` and ``boulevard``, where cascaded shadow maps matter: a
view range of 0.5 m to ≥ 200 m read from the rendered G-buffer and the stored truth, a sun of the
physical angular diameter, thin casters, and the committed reference at CI resolution."""

import math
from pathlib import Path

import numpy as np
import pytest

from shadowlab.reference import store
from shadowlab.render.frame import make_frame
from shadowlab.render.gbuffer import gbuffer
from shadowlab.pipeline import technique_metrics
from shadowlab.scene import load, load_spec, resolve
from shadowlab.techniques import base as tbase

ROOT = Path(__file__).resolve().parents[1]
REFS = ROOT / "references"
OUTDOOR = ("street", "boulevard")
#: what a caster of the ground is not: the ground, the kerbs and the promenade's paving
GROUND = ("ground", "kerb0", "kerb1", "promenade")


@pytest.fixture(scope="module")
def scenes(mitsuba_backend):
    return {n: load(n) for n in OUTDOOR}


@pytest.fixture(scope="module")
def gbuffers(scenes):
    return {n: gbuffer(sc) for n, sc in scenes.items()}


def _shape_names_at(sc, gb, sel):
    """Names of the scene's shapes seen at the (H, W) pixels ``sel`` (cylinder caps count as their cylinder)."""
    ids = gb.shape_id[..., 0][sel]
    return {sc.shape_names[i].split("__cap")[0] for i in np.unique(ids) if i >= 0}


@pytest.mark.parametrize("name", OUTDOOR)
def test_sun_and_clip_planes(name):
    spec = load_spec(resolve(name))
    (sun,) = spec.lights
    assert sun.kind == "directional" and sun.angular_diameter == 0.53
    assert sun.irradiance is not None and 100 <= sun.irradiance <= 1400       # W/m², a sun's
    elevation = math.degrees(math.asin(-sun.direction[1] / math.hypot(*sun.direction)))
    assert 5 <= elevation <= 25                                                # low: long shadows
    assert spec.camera.far_clip >= 200 and spec.camera.near_clip <= 0.1
    W, H = spec.camera.resolution                                              # CI resolution
    assert 64 <= W <= 128 and (REFS / name / f"{W}x{H}" / "meta.json").is_file()


@pytest.mark.parametrize("name", OUTDOOR)
def test_view_distances_reach_from_near_casters_to_200_m(name, scenes, gbuffers):
    sc, gb = scenes[name], gbuffers[name]
    mask = gb.mask[..., 0]
    dist = gb.view_depth[..., 0]
    assert mask.mean() > 0.75                                        # mostly geometry, little sky
    near = mask & (dist >= 0.5) & (dist <= 3.0)
    far = mask & (dist >= 200.0)
    assert near.sum() >= 20 and far.sum() >= 20
    # casters, not just the ground, at both ends: a bench or a pole within 3 m, trees past 200 m
    # (besides the skyline, whose shadows fall behind it)
    assert _shape_names_at(sc, gb, near) - set(GROUND)
    assert {n for n in _shape_names_at(sc, gb, far) - set(GROUND) if not n.startswith("skyline")}
    # nothing is clipped by the far plane that the scene means to show: the farthest hit lies inside it
    assert float(dist[mask].max()) < sc.spec.camera.far_clip


@pytest.mark.parametrize("name", OUTDOOR)
def test_thin_casters(name, scenes):
    sc = scenes[name]

    def thickness(s):  # the smallest extent of a solid shape, from its definition
        if s.type == "cylinder":
            return 2 * s.radius
        if s.type == "sphere":
            return 2 * s.radius
        if s.type == "cube":
            return 2 * min(s.scale)
        return math.inf  # rectangles and disks are the ground, not casters
    def top(s):  # the highest point of a cylinder or an unrotated-in-height cube
        return max(s.p0[1], s.p1[1]) if s.type == "cylinder" else s.translate[1] + s.scale[1]
    thin = [s for s in sc.spec.shapes if thickness(s) < min(0.1, sc.radius / 100)]
    assert len(thin) >= 5, [s.name for s in thin]
    # some thin casters are high off the ground (wires, cables, signs), so their shadows fall far from them
    assert max(top(s) for s in thin) > 2.0
    assert any(s.type == "cylinder" and abs(s.p0[1] - s.p1[1]) < 1e-9 and top(s) > 2.0 for s in thin)  # a wire


def test_committed_street_reference_loads_and_hard_compares(mitsuba_backend):
    sc = load("street")
    truth, meta = store.load(sc.spec, sc.resolution, base=REFS)      # not stale, checksum verified
    assert meta["scene_hash"] == sc.spec.digest() and meta["target_missed"]["pixels"] == 0
    frame = make_frame(sc, seed=int(meta["seed"]))
    # the truth's depth is the G-buffer's, pixel for pixel
    both = truth.mask & frame.gbuffer.mask[..., 0]
    assert both.sum() == truth.mask.sum() == frame.gbuffer.mask[..., 0].sum()
    assert np.allclose(truth.view_depth[both], frame.gbuffer.view_depth[..., 0][both], rtol=1e-4)
    assert truth.view_depth[both].max() >= 200 and truth.view_depth[both].min() <= 3
    assert truth.mask.mean() > 0.75
    V = truth.lights["sun"].V[truth.mask]
    assert V.min() >= 0 and V.max() <= 1 and (V < 0.02).mean() > 0.05 and ((V > 0.02) & (V < 0.98)).sum() > 20
    assert (truth.lights["sun"].V[truth.mask & (truth.view_depth > 150)] < 0.5).sum() >= 5   # shadows far away too
    t = tbase.get("hard")
    res = t.render(frame, t.resolve({}))
    metrics, per_light, images = technique_metrics(frame, truth, res)
    assert math.isfinite(metrics["rmse"]) and metrics["rmse"] > 0
    v = frame.image(res.visibility["sun"])
    assert v.min() >= 0 and v.max() <= 1
