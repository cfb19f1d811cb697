"""Temporal stability along a camera path: each technique's visibility at the first frame's points
with every frame's light views (:mod:`shadowlab.metrics.temporal`)."""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..metrics.temporal import shimmer_per_light
from ..render.frame import FrameContext
from ..render.gbuffer import vec_numpy
from ..techniques import base as tbase

__all__ = ["shimmer"]


def shimmer(scenes: list, fixed, results: dict, techniques: dict | None = None) -> dict:
    """Temporal stability of each technique along ``scenes`` (the loaded scene at each frame of a
    path, in order): visibility at ``fixed``'s G-buffer points (the FrameContext of the first
    frame) with each frame's light views, which read that frame's camera:
    ``FrameContext(scene=scene_t, gbuffer=fixed.gbuffer, unshadowed=fixed.unshadowed, sdf=fixed.sdf)``.
    ``results``: {technique: (ShadowResult on ``fixed``, params, ...)}; the first frame's
    visibility is that result. Points counted: valid and lit by the light (U_L > 0).
    ``techniques``: {name: Technique} for names not in the registry (default: the registry).

    Returns {"techniques": {name: {"pooled": {...}, "per_light": {...}}}, "truth": {...}, "frames": [...]}
    (:func:`shadowlab.metrics.temporal.shimmer_per_light`). The truth's own shimmer is measured from
    what the truth at a fixed point depends on, the lights and the shapes: when they are the same
    in every frame (the scene format moves only the camera), V_t(x) = V_{t−1}(x) and it is 0
    exactly, which ``truth["why"]`` says; otherwise it is not measured (``None``)."""
    out = {"frames": [s.frame for s in scenes], "points": "G-buffer points of frame "
           f"{scenes[0].frame} (valid and lit by the light)", "techniques": {}}
    gvalid = np.asarray(fixed.gbuffer.valid.numpy(), bool).reshape(-1)
    valid = {l.name: gvalid & (vec_numpy(fixed.unshadowed[l.name]).sum(1) > 0) for l in fixed.lights}
    for n, (res0, p, *_rest) in results.items():
        t = (techniques or {}).get(n) or tbase.get(n)
        V = {l.name: [np.asarray(res0.visibility[l.name].numpy(), np.float64).reshape(-1)] for l in fixed.lights}
        for sc_t in scenes[1:]:
            ctx = FrameContext(scene=sc_t, gbuffer=fixed.gbuffer, unshadowed=fixed.unshadowed, sdf=fixed.sdf)
            r = t.render(ctx, p)
            dr.eval(*r.visibility.values())
            for l in fixed.lights:
                V[l.name].append(np.asarray(r.visibility[l.name].numpy(), np.float64).reshape(-1))
        per, pooled = shimmer_per_light({k: (np.stack(v), valid[k]) for k, v in V.items()})
        out["techniques"][n] = {"pooled": pooled, "per_light": per}
    s0 = scenes[0].spec
    static = all(s.spec.lights == s0.lights and s.spec.shapes == s0.shapes and s.spec.sdf == s0.sdf for s in scenes)
    if static:
        zero = {"mean": 0.0, "p99": 0.0, "max": 0.0}
        out["truth"] = {"pooled": dict(zero), "per_light": {l.name: dict(zero) for l in fixed.lights},
                        "why": "0 exactly: the truth at a fixed world point depends only on the lights and the shapes, "
                               "which are the same in every frame of the path (only the camera moves)"}
    else:  # pragma: no cover - the scene format cannot move lights or shapes along a path
        out["truth"] = {"pooled": None, "per_light": None,
                        "why": "not measured: lights or shapes differ between frames"}
    return out
