"""Ground truth: per-light visibility at the G-buffer points and the shaded image (Mitsuba).

Visibility of light L at shading point x (docs/ARCHITECTURE.md, Reference):

    V_L(x) = ∫ f(x, y) v(x, y) dy / ∫ f(x, y) dy     (shadowed / unshadowed direct light)
    A_L(x) = mean of v over the emitter's sample domain (visible area or solid-angle fraction)

with f = bsdf · Le · cos / pdf from Mitsuba's emitter sampling and v from Mitsuba shadow rays
(``render/shading.py``). Sampling is adaptive, in rounds of k×k jittered strata:

1. every pixel gets ``min_rounds`` rounds;
2. a pixel whose samples all agreed (all visible or all blocked) is done: lit and umbra
   pixels converge at once (its error bound is then the rule of three, 3/n, stored as ``bound``);
3. the others (penumbra) get a pilot of 8 rounds, whose variance plans the number of rounds
   R = 1.25 · var / target_se², at least 16 (so half the rounds are fresh) and at most
   ``max_rounds``; the standard error reported is
   sqrt(var_rounds / R) over all rounds. Planning from the pilot rather than stopping when the
   running estimate first dips below the target keeps the reported error honest (stopping
   on it under-reports the error by ~20%, measured on analytic_sphere).

The rounds are independent, so the standard error is an honest estimate. The shaded truth is
Σ_L U_L · V_L at the same pixel centres as the techniques (so metrics isolate shadows), and
Mitsuba's own ``direct`` integrator image (``mi.render``, box filter over the pixel) is stored
beside it with a per-pixel variance from independent passes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from ..render.frame import FrameContext
from ..render.gbuffer import vec_numpy
from ..render.lightview import cast_first_hit
from ..render.shading import sample_light
from ..scene.lights import forward as lights_fwd

#: the largest seed a truth render takes: Mitsuba's ``mi.render`` gets seed·1000 + i (i < 1000), a 32-bit
#: unsigned integer (``shadowlab reference --seed`` has the same range)
SEED_MAX = (2 ** 32 - 1000) // 1000

MIN_SE_ROUNDS = 8  # pilot rounds of a penumbra pixel before its number of rounds is planned
PLAN_MARGIN = 1.25  # planned rounds = margin · pilot variance / target²


@dataclass
class LightTruth:
    V: np.ndarray          # (H, W) visibility ratio
    V_se: np.ndarray       # (H, W) standard error of V
    A: np.ndarray          # (H, W) plain visible fraction
    A_se: np.ndarray
    samples: np.ndarray    # (H, W) shadow rays per pixel
    bound: np.ndarray      # (H, W) error bound for unanimous pixels (3/n), 0 elsewhere
    rays: int = 0


@dataclass
class Truth:
    lights: dict                      # name -> LightTruth
    U: dict                           # name -> (H, W, 3) unshadowed radiance
    shaded: np.ndarray                # (H, W, 3) Σ U V
    shaded_var: np.ndarray            # (H, W, 3)
    mitsuba: np.ndarray | None        # (H, W, 3) mi.render direct
    mitsuba_var: np.ndarray | None
    mask: np.ndarray                  # (H, W) bool
    view_depth: np.ndarray            # (H, W)
    stats: dict = field(default_factory=dict)


def visibility(frame: FrameContext, light_name: str, *, k: int = 8, target_se: float = 0.005,
               min_rounds: int = 4, max_rounds: int = 64, seed: int = 0, progress=None) -> LightTruth:
    """Adaptive ground-truth visibility of one light (see the module docstring).

    ``progress(n)`` is called with the number of shadow rays of each round.
    """

    scene, gb = frame.scene, frame.gbuffer
    spec = scene.spec.light(light_name)
    emitter = scene.emitters[light_name]
    n_pts = gb.size
    valid = gb.valid.numpy()
    if spec.is_delta:
        k, min_rounds, max_rounds = 1, 1, 1
    kk = k * k
    s_v = np.zeros(n_pts)
    s_v2 = np.zeros(n_pts)
    s_a = np.zeros(n_pts)
    s_a2 = np.zeros(n_pts)
    s_vis = np.zeros(n_pts)          # visible samples
    rounds = np.zeros(n_pts, np.int64)
    planned = np.zeros(n_pts, np.int64)
    active = np.nonzero(valid)[0]
    rays = 0
    r = 0
    while len(active) and r < max_rounds:
        idx = mi.UInt32(active.astype(np.uint32))
        si = dr.gather(type(gb.si), gb.si, idx)
        _, fv, fsum, v = sample_light(scene, si, emitter, k, seed, r, True)
        dr.eval(fv, fsum, v)
        fv, fsum, v = fv.numpy().astype(np.float64), fsum.numpy().astype(np.float64), v.numpy().astype(np.float64)
        Vr = np.where(fsum > 0, fv / np.where(fsum > 0, fsum, 1), 1.0)
        Ar = v / kk
        s_v[active] += Vr
        s_v2[active] += Vr * Vr
        s_a[active] += Ar
        s_a2[active] += Ar * Ar
        s_vis[active] += v
        rounds[active] += 1
        n_rays = len(active) * kk
        rays += n_rays
        if progress:
            progress(n_rays)
        r += 1
        if r < min_rounds:
            continue
        R = rounds[active]
        n = R * kk
        unanimous = (s_vis[active] == 0) | (s_vis[active] == n)
        mean = s_v[active] / R
        var = np.maximum(s_v2[active] / R - mean * mean, 0.0) * R / np.maximum(R - 1, 1)
        se = np.sqrt(var / R)
        # plan the number of rounds from the pilot; re-plan only if the plan fell short
        need = np.ceil(PLAN_MARGIN * var / target_se ** 2)
        replan = (R >= MIN_SE_ROUNDS) & ((planned[active] == 0) | ((R >= planned[active]) & (se > target_se)))
        planned[active] = np.where(replan, np.clip(need, np.maximum(R + (planned[active] > 0), 2 * MIN_SE_ROUNDS),
                                                   max_rounds), planned[active])
        done = unanimous | ((planned[active] > 0) & (R >= planned[active]))
        active = active[~done]
    R = np.maximum(rounds, 1)
    V = np.where(valid, s_v / R, 1.0)
    A = np.where(valid, s_a / R, 1.0)

    def _se(s, s2):
        m = s / R
        var = np.maximum(s2 / R - m * m, 0.0) * R / np.maximum(R - 1, 1)
        return np.where(rounds > 1, np.sqrt(var / R), 0.0)

    n = rounds * kk
    unanimous = valid & ((s_vis == 0) | (s_vis == n))
    bound = np.where(unanimous & ~np.bool_(spec.is_delta), 3.0 / np.maximum(n, 1), 0.0)
    img = gb.to_image
    s2 = gb.ss * gb.ss  # a pixel's value is the mean of its s² independent sub-pixel estimates

    def se_img(se):
        return np.sqrt(img(se * se) / s2)

    return LightTruth(V=img(V), V_se=se_img(_se(s_v, s_v2)), A=img(A), A_se=se_img(_se(s_a, s_a2)),
                      samples=img(n.astype(np.float64)) * s2, bound=img(bound), rays=int(rays))


def mitsuba_render(scene, spp: int = 256, passes: int = 4, seed: int = 0):
    """Mitsuba's own ``direct`` integrator image and the variance of its mean over ``passes``
    independent renders of spp/passes samples each."""
    integrator = mi.load_dict({"type": "direct"})
    per = max(1, spp // passes)
    imgs = [np.asarray(mi.render(scene.mi_scene, sensor=scene.sensor, spp=per, seed=seed * 1000 + i,
                                    integrator=integrator))
            for i in range(passes)]
    stack = np.stack(imgs).astype(np.float64)
    mean = stack.mean(0)
    var = stack.var(0, ddof=1) / passes if passes > 1 else np.zeros_like(mean)
    return mean.astype(np.float32), var.astype(np.float32)


def render_truth(frame: FrameContext, *, k: int = 8, target_se: float = 0.005, max_rounds: int = 64,
                 seed: int = 0, spp: int = 256, progress=None) -> Truth:
    """The whole ground truth of a frame: every light's visibility, Σ U·V and mi.render."""
    gb = frame.gbuffer
    t0 = time.perf_counter()
    lights, U = {}, {}
    shaded = 0.0
    var = 0.0
    for l in frame.lights:
        lt = visibility(frame, l.name, k=k, target_se=target_se, max_rounds=max_rounds, seed=seed, progress=progress)
        lights[l.name] = lt
        U[l.name] = gb.to_image(vec_numpy(frame.unshadowed[l.name]))
        shaded = shaded + U[l.name] * lt.V[..., None]
        var = var + (U[l.name] * lt.V_se[..., None]) ** 2
    dr.sync_thread()
    t_vis = time.perf_counter() - t0
    mean, mvar = mitsuba_render(frame.scene, spp=spp, seed=seed) if spp else (None, None)
    dr.sync_thread()
    mask = gb.to_image(gb.mask.reshape(-1).astype(np.float32)) > 0.5
    stats = {"visibility_time_s": t_vis, "mitsuba_time_s": time.perf_counter() - t0 - t_vis,
             "shadow_rays": int(sum(l.rays for l in lights.values())),
             "max_std_error": float(max(float(l.V_se[mask].max()) if mask.any() else 0.0 for l in lights.values())),
             "spp_mitsuba": spp, "strata": k, "target_se": target_se, "max_rounds": max_rounds, "seed": seed}
    return Truth(lights=lights, U=U, shaded=np.asarray(shaded, np.float32), shaded_var=np.asarray(var, np.float32),
                 mitsuba=mean, mitsuba_var=mvar, mask=mask, view_depth=gb.to_image(gb.view_depth.reshape(-1)),
                 stats=stats)


def target_missed(truth: Truth, target_se: float, max_rounds: int, worst: int = 32) -> dict:
    """The pixels whose standard error is still above ``target_se`` after the round cap.

    Returns ``{"target_se", "max_rounds", "pixels", "worst_se", "lights": {light: {"pixels",
    "worst_se", "worst": [[x, y, se], …]}}}`` (the ``worst`` pixels of each light, worst first);
    ``pixels`` is 0 when every pixel met the target. ``meta.json`` records it as ``target_missed``."""
    lights = {}
    for name, lt in truth.lights.items():
        se = np.where(truth.mask, lt.V_se, 0.0)
        ys, xs = np.nonzero(se > target_se)
        if len(xs) == 0:
            continue
        order = np.argsort(-se[ys, xs], kind="stable")[:worst]
        lights[name] = {"pixels": int(len(xs)), "worst_se": float(se[ys, xs].max()),
                        "worst": [[int(xs[i]), int(ys[i]), float(se[ys[i], xs[i]])] for i in order]}
    return {"target_se": float(target_se), "max_rounds": int(max_rounds),
            "pixels": int(sum(v["pixels"] for v in lights.values())),
            "worst_se": float(max((v["worst_se"] for v in lights.values()), default=0.0)), "lights": lights}


def centre_visibility(frame: FrameContext, light_name: str):
    """Exact hard-shadow visibility of the light's centre at the G-buffer points (flat ``mi.Float``,
    1 lit, 0 blocked; 1 where there is no surface): one Mitsuba ray per point toward the centre of
    a positional light, or against a directional light's direction, skipping the light's own
    shape (the truth's emitter: the sun's far disk, a sphere light's sphere) and, in scenes with
    alpha-tested casters, their transparent texels. The truth a shadow map's aliasing is measured
    against: a map of the light's centre converges to it as its resolution grows [Giegl 2007, §5]."""
    gb = frame.gbuffer
    spec = frame.scene.spec.light(light_name)
    si = gb.si
    if spec.kind == "directional":
        d = np.asarray(lights_fwd(spec), np.float64)
        ray = si.spawn_ray(mi.Vector3f(*[float(-x) for x in d]))
        far = None
    else:
        ray = si.spawn_ray_to(mi.Point3f(*[float(x) for x in spec.position]))
        far = ray.maxt
        ray.maxt = dr.inf
    scene = frame.scene
    own = scene.light_shapes.get(light_name)
    shapes = scene.mi_scene.shapes_dr()
    own_ptr = dr.gather(type(shapes), shapes, own) if own is not None else None
    hit = cast_first_hit(scene.mi_scene, ray, False, own_ptr, bool(getattr(scene, "has_alpha", False)))
    blocked = hit.is_valid() & gb.valid
    if far is not None:
        blocked &= hit.t < far
    return dr.select(blocked, 0.0, 1.0)
