"""Raw Mitsuba ``ray_test`` in one wavefront: the ceiling a part's rays are measured against.

Shadow rays toward points the emitter samples, ``ray_test`` only: no BSDF, no bookkeeping. The truth
part (:mod:`shadowlab.bench.core`) puts the ground truth's shadow rays beside it, and the frames part
(:mod:`shadowlab.bench.frames`) puts each technique's frame beside the cost of as many rays.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .timing import timed


@dr.syntax
def _ray_test_loop(mi_scene, si, emitter, rng, n):
    """``n`` shadow rays per lane toward uniform points of ``emitter`` (``ray_test`` only): one wavefront."""
    i = mi.UInt32(0)
    v = dr.zeros(mi.Float, dr.width(si.p))
    while i < n:
        ds, _ = emitter.sample_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()), True)
        v += dr.select(mi_scene.ray_test(si.spawn_ray_to(ds.p)), 0.0, 1.0)
        i += 1
    return v


def raw_ray_test(frame, light: str, spp: int = 256, repeats: int = 3, warmup: int = 1) -> dict:
    """Raw Mitsuba ``ray_test`` throughput at the frame's valid G-buffer points: ``spp`` shadow
    rays per point toward points the emitter samples, in one wavefront (a symbolic loop), no
    BSDF, no bookkeeping: the ceiling the truth's sampler is measured against. Median of
    ``repeats`` warm runs."""
    sc, gb = frame.scene, frame.gbuffer
    idx = np.nonzero(gb.valid.numpy())[0].astype(np.uint32)
    si = dr.gather(type(gb.si), gb.si, mi.UInt32(idx))
    rng = mi.PCG32(len(idx), dr.opaque(mi.UInt64, 1), mi.UInt64(dr.arange(mi.UInt32, len(idx))))

    def cast():
        dr.eval(_ray_test_loop(sc.mi_scene, si, sc.emitters[light], mi.PCG32(rng), dr.opaque(mi.UInt32, spp)))

    _, ts = timed(cast, repeats, warmup=warmup)
    t = float(np.median(ts))
    rays = len(idx) * spp
    return {"points": len(idx), "rays_per_point": spp, "rays": rays, "time_s": t, "rays_per_s": rays / t}
