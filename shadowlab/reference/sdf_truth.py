"""Ground truth of ``"sdf"`` scenes, those with SDF-only content [Bán 2019, §3.3.1].

Mitsuba does not see ``[[sdf]]`` objects (a Mandelbulb has no mesh or Mitsuba primitive), so
``shadowlab reference`` cannot ask Mitsuba for their truth. The reference of such a scene is the
thesis' own: the Monte-Carlo integral over the light's disk inside the cone from each surface
point to the spherical light ([Bán 2019, §3.3.1]), ``shadowlab.sdf.soft.mc_cone_visibility(sdf, points,
normals, light_sphere(scene, light), n)``, evaluated at the points of the cone-traced G-buffer. Its meta.json says so
(``truth``: ``"sdf_mc_cone"``, ``not_mitsuba_truth``), and the ``mitsuba.*`` channels are absent.

What is stored per light, as for a Mitsuba truth: ``V`` = ∫ v·cos / ∫ cos over the light
(``cosine=True``: the diffuse visibility ratio) and ``A`` = the visible fraction of the light's
solid angle (``measure="solid_angle"``), each with standard error ``sqrt(x(1 − x)/n)`` (the
binomial error of n independent samples; the randomly shifted Halton points of the estimator
usually do better, so it is an upper estimate), ``N`` = n shadow rays per point.
"""

from __future__ import annotations

import time

import drjit as dr
import numpy as np

from ..errors import InputError
from ..render.gbuffer import vec_numpy
from ..scene.lights import light_sphere
from ..sdf.soft import mc_cone_visibility
from .truth import LightTruth, Truth

TRUTH_KIND = "sdf_mc_cone"
NOTE = ("scene has SDF-only objects ([[sdf]]) that Mitsuba does not see: this truth is the Monte-Carlo cone "
        "reference of [Bán 2019, §3.3.1] (shadowlab.sdf.soft.mc_cone_visibility, sphere-traced shadow rays) at the "
        "cone-traced G-buffer's points, not a Mitsuba truth; V is cosine-weighted, A the solid-angle fraction.")


def render_truth(frame, *, samples: int = 1024, seed: int = 0, progress=None):
    """The :class:`shadowlab.reference.truth.Truth` of an SDF-only scene (module docstring)."""
    scene, gb = frame.scene, frame.gbuffer
    bad = [f"{l.name} ({l.kind})" for l in frame.lights if l.kind != "sphere"]
    if bad:
        raise InputError(f"scene {scene.name!r}: the Monte-Carlo cone reference of SDF-only scenes needs spherical "
                         f"lights ([Bán 2019, §3.2]), not {', '.join(bad)}; make them kind = \"sphere\"")
    if frame.sdf is None:
        raise InputError(f"scene {scene.name!r} has no signed distance field")
    t0 = time.perf_counter()
    lights, U = {}, {}
    shaded = var = 0.0
    mask = gb.to_image(gb.mask.reshape(-1).astype(np.float32)) > 0.5
    n = int(samples)
    valid = gb.valid.numpy()
    img = gb.to_image
    s2 = gb.ss * gb.ss

    def image(x):
        x = np.where(valid, np.clip(x.numpy().astype(np.float64), 0.0, 1.0), 1.0)
        se = np.sqrt(x * (1.0 - x) / n)
        return img(x), np.sqrt(img(se * se) / s2)  # a pixel is the mean of its s² points

    for l in frame.lights:
        # A (solid-angle fraction) and V (cosine-weighted) from the same n rays per point
        A, V = mc_cone_visibility(frame.sdf, gb.p, gb.n, light_sphere(scene, l), n, seed=seed, cosine="both")
        dr.eval(A, V)
        (A, A_se), (V, V_se) = image(A), image(V)
        lt = LightTruth(V=V, V_se=V_se, A=A, A_se=A_se, samples=img(np.where(valid, float(n), 0.0)) * s2,
                        bound=np.zeros_like(V), rays=int(valid.sum()) * n)
        lights[l.name] = lt
        U[l.name] = gb.to_image(vec_numpy(frame.unshadowed[l.name]))
        shaded = shaded + U[l.name] * lt.V[..., None]
        var = var + (U[l.name] * lt.V_se[..., None]) ** 2
        if progress:
            progress(lt.rays)
    dr.sync_thread()
    stats = {"visibility_time_s": time.perf_counter() - t0, "mitsuba_time_s": 0.0,
             "shadow_rays": int(sum(l.rays for l in lights.values())),
             "max_std_error": float(max(float(l.V_se[mask].max()) if mask.any() else 0.0 for l in lights.values())),
             "spp_mitsuba": 0, "mc_cone_samples": n, "seed": seed, "truth": TRUTH_KIND}
    return Truth(lights=lights, U=U, shaded=np.asarray(shaded, np.float32), shaded_var=np.asarray(var, np.float32),
                 mitsuba=None, mitsuba_var=None, mask=mask, view_depth=gb.to_image(gb.view_depth.reshape(-1)),
                 stats=stats)
