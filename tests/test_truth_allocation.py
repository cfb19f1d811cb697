"""The truth's ``contribution`` allocation (issue 12): rays across lights in proportion to each
light's share of a pixel's unshadowed light, with the shaded pixel's error bound kept."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shadowlab import backend
from shadowlab.reference.truth import CONTRIBUTION_MAX_SE, light_targets, render_truth, target_missed
from shadowlab.render.frame import make_frame
from shadowlab.scene import load
from shadowlab.scene.build import build
from shadowlab.scene.spec import parse

backend.init()
TARGET = 0.005


def test_targets_keep_the_shaded_bound_and_spend_rays_by_share():
    rng = np.random.default_rng(3)
    U = {f"L{i}": rng.uniform(0.0, 1.0, (500, 3)) * rng.uniform(0.2, 1.0, (500, 1)) ** 2 for i in range(6)}
    U["L0"][:20] = 0.0
    t = light_targets(U, TARGET)
    lum = {n: u.sum(-1) for n, u in U.items()}
    S = sum(lum.values())
    capped = sum((t[n] >= CONTRIBUTION_MAX_SE) for n in U)
    free = capped == 0
    assert free.sum() > 100
    # Σ U_L² t_L² = (t·S)² exactly where no light is capped, below it where one is
    var = sum((lum[n] * t[n]) ** 2 for n in U)
    np.testing.assert_allclose(var[free], (TARGET * S[free]) ** 2, rtol=1e-12)
    assert (var <= (TARGET * S) ** 2 * (1 + 1e-12)).all()
    # a point's rounds grow as var/t²: a light's rays there are in proportion to its share
    share = {n: lum[n] / S for n in U}
    rays = {n: 1.0 / t[n] ** 2 for n in U}
    for n in U:
        np.testing.assert_allclose(rays[n][free] / share[n][free], 1.0 / TARGET ** 2, rtol=1e-9)
    assert (t["L0"][lum["L0"] == 0] == CONTRIBUTION_MAX_SE).all()
    assert all((t[n] >= TARGET).all() for n in U)  # never stricter than per_light


def test_the_scene_key_is_validated_and_hashed_only_when_set():
    base = {"name": "a", "camera": {"position": [0, 3, 5], "target": [0, 0, 0], "resolution": [8, 8]},
            "lights": [{"name": "k", "kind": "point", "position": [0, 3, 0], "power": 10.0}],
            "shapes": [{"name": "f", "type": "rectangle", "rotate": [1, 0, 0, -90]}]}
    plain = parse(base, "s.toml")
    assert plain.truth_allocation == "per_light"
    assert parse({**base, "truth_allocation": "per_light"}, "s.toml").digest() == plain.digest()
    assert parse({**base, "truth_allocation": "contribution"}, "s.toml").digest() != plain.digest()
    with pytest.raises(Exception, match="truth_allocation: expected one of per_light, contribution"):
        parse({**base, "truth_allocation": "equal"}, "s.toml")


@pytest.fixture(scope="module")
def both():
    sc = load("many_lights", (48, 48))
    assert sc.spec.truth_allocation == "contribution"
    out = {}
    for alloc in ("contribution", "per_light"):
        frame = make_frame(build(replace(sc.spec, truth_allocation=alloc)))
        out[alloc] = render_truth(frame, target_se=TARGET, spp=0)
    return out


def test_many_light_truth_samples_each_light_where_it_adds_light(both):
    tr = both["contribution"]
    assert tr.stats["allocation"] == "contribution"
    for name, lt in tr.lights.items():
        reach = tr.U[name].sum(-1) > 0
        assert (lt.samples[tr.mask & ~reach] == 0).all() and (lt.V[tr.mask & ~reach] == 1.0).all()
        assert (lt.samples[tr.mask & reach] > 0).all()
    per = both["per_light"]
    assert tr.stats["shadow_rays"] < 0.25 * per.stats["shadow_rays"]
    # each light meets its own target, so the shaded pixel meets the bound relative to its light
    assert target_missed(tr, TARGET, 64)["pixels"] == 0
    S = sum(u.sum(-1) for u in tr.U.values())
    se = np.sqrt(sum((tr.U[n].sum(-1) * lt.V_se) ** 2 for n, lt in tr.lights.items()))
    m = tr.mask & (S > 0)
    assert (se[m] <= TARGET * S[m] * 1.001).all()


def test_contribution_agrees_with_per_light_within_their_errors(both):
    a, b = both["contribution"], both["per_light"]
    S = sum(u.sum(-1) for u in a.U.values())
    m = a.mask & (S > 0)
    d = (a.shaded - b.shaded).sum(-1)[m]
    sd = np.sqrt(a.shaded_var.sum(-1) + b.shaded_var.sum(-1))[m]
    # unanimous pixels have se 0 on both sides; bound their difference by the rule of three instead
    ok = np.abs(d) <= 4 * sd + 3.0 / 256 * S[m]
    assert ok.mean() > 0.995, ok.mean()
