"""Transfer: a shadowlab shadow-map technique's parameters → an engine's own shadow parameters.

"Can I fit in shadowlab and paste into my engine?" A shadowlab bias or filter and an engine's act
on different maps: the engine fits its own shadow frustum (three.js: a spot camera with the cone's
field of view, its own near/far, ``mapSize`` texels [Cabello 2026]), shadowlab its light view, and
each stores its own depth (Direct3D's rules, [Buljan 2020, §2.3]). A constant in one is therefore
not a constant in the other. What is the same in both is what a parameter does to a receiver
point in world units, so the transfer is made point by point and then summarised:

1. At every receiver point p the light reaches (a valid G-buffer point with unshadowed light,
   inside shadowlab's light view and the engine's shadow camera), shadowlab's technique at the
   given values moves the compared depth toward the light by

       Δz(p) = zbias(p) + B(p) / (∂d/∂z)_shadowlab(p)      (world units),

   zbias the receiver-side constant and slope biases, B the rasterizer depth bias (DepthBias·r +
   SlopeScaledDepthBias·slope, clamped) that ``shadow_map.stored_depth`` adds to the texel the
   point reads, and (∂d/∂z) the light view's stored depth per world unit at the point's depth;
   it moves the point along its normal by ``normal_offset`` × the texel's world size; and it
   averages depth tests over a footprint whose per-axis variance is the technique's
   :meth:`~shadowlab.techniques.shadow_map.ShadowMapTechnique.filter_variance` × the texel's
   world size squared.
2. The engine adapter (:meth:`~shadowlab.techniques.engines.EngineTechnique.from_shadowlab`)
   turns each point's world quantities into its own parameters with its shadow camera at that
   point (depth per world unit, texel size), so each point has the engine value that does there
   exactly what shadowlab does.
3. The engine takes one value per parameter: the median over the points, pooled over the lights.
   The 10th–90th percentiles are returned beside it; where they are far apart no constant can do
   what shadowlab does everywhere (a slope-scaled bias, a perspective map's depth), and the
   measured engine error with the median says how much that costs.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..errors import InputError
from ..render.gbuffer import vec_numpy
from .base import get, names
from .engines import EngineTechnique, ReceiverPoints, shadow_cameras
from .shadow_map import (ShadowMapTechnique, map_settings, opaque_bias, receiver, stored_depth, texel_index,
                         to_light, view_for)

SOURCE = "[Buljan 2020, §2.3]"


def depth_per_unit(near: float, far: float, z: np.ndarray, ortho: bool) -> np.ndarray:
    """Window (NDC) depth per world unit at depth z along a light camera's axis, the same for
    Direct3D's and OpenGL's [0, 1] depth: 1/(f − n) for an orthographic map, f·n / ((f − n)·z²) for a
    perspective one (d = f/(f − n)·(1 − n/z)).

    >>> depth_per_unit(1.0, 3.0, np.array([1.0, 2.0]), False).tolist()
    [1.5, 0.375]
    >>> depth_per_unit(1.0, 3.0, np.ones(1), True).tolist()
    [0.5]
    """
    n, f = float(near), float(far)
    if ortho:
        return np.full_like(z, 1.0 / (f - n), dtype=np.float64)
    return f * n / ((f - n) * np.maximum(z, 1e-12) ** 2)


def receiver_points(frame, technique: ShadowMapTechnique, values: dict, light_name: str,
                    camera: dict) -> ReceiverPoints:
    """What ``technique`` at ``values`` does at each receiver point of ``light_name`` (world units),
    with the engine's shadow ``camera`` there (see the module docstring)."""
    gb = frame.gbuffer
    view = view_for(frame, light_name, values)
    bias = opaque_bias(technique.bias_values(values))
    rec = receiver(frame, view, bias)
    _, _, b = stored_depth(view, rec["face"], texel_index(rec["u"]), texel_index(rec["v"]), bias)
    first = view.lookup(gb.p)
    p = vec_numpy(gb.p).astype(np.float64)
    keep = (np.asarray(rec["active"].numpy(), bool) & np.asarray(first["inside"].numpy(), bool)
            & frame.lit_mask(light_name).reshape(-1))
    texel = np.broadcast_to(np.asarray(first["texel"].numpy(), np.float64), keep.shape)   # one value: orthographic
    z = np.asarray(first["z"].numpy(), np.float64)
    cam = camera_at(camera, p)
    keep &= cam["inside"]
    scale = cam["texel"][keep] / texel[keep]                # engine texels per shadowlab texel, in world size
    f0 = view.proj.faces[0]
    raster = np.asarray(b.numpy(), np.float64)[keep] / depth_per_unit(f0.near, f0.far, z[keep], f0.ortho)
    cos = np.abs(np.asarray(dr.dot(rec["ng"], to_light(view, gb.p)).numpy(), np.float64))[keep]
    dz = np.asarray(rec["zbias"].numpy(), np.float64)[keep] + raster * scale
    return ReceiverPoints(dz=dz, normal=float(values["normal_offset"]) * cam["texel"][keep], cos=cos,
                          filter_var=technique.filter_variance(values) * texel[keep] ** 2,
                          engine_z=cam["z"][keep], engine_texel=cam["texel"][keep],
                          engine_depth_per_unit=cam["depth_per_unit"][keep])


def camera_at(camera: dict, p: np.ndarray) -> dict:
    """An engine shadow camera (``shadow_cameras``' entries: a square map) at world points p (N, 3):
    depth along its axis ``z``, ``texel`` (world size of one texel there), ``depth_per_unit`` (its
    stored window depth per world unit) and ``inside`` (between its planes, within its square field of view).

    >>> cam = {"projection": "orthographic", "position": [0, 0, 10], "direction": [0, 0, -1], "right": [1, 0, 0],
    ...        "up": [0, 1, 0], "near": 1.0, "far": 21.0, "resolution": 100, "halfWidth": 5.0, "halfHeight": 5.0}
    >>> r = camera_at(cam, np.array([[0.0, 0.0, 0.0], [9.0, 0.0, 0.0]]))
    >>> r["z"].tolist(), r["texel"].tolist(), r["depth_per_unit"].tolist(), r["inside"].tolist()
    ([10.0, 10.0], [0.1, 0.1], [0.05, 0.05], [True, False])
    """
    if camera["projection"] == "matrix":
        return _matrix_camera(camera, p)
    o = np.asarray(camera["position"], np.float64)
    d, right, up = (np.asarray(camera[k], np.float64) for k in ("direction", "right", "up"))
    rel = p - o
    z = rel @ (d / np.linalg.norm(d))
    lateral = np.maximum(np.abs(rel @ (right / np.linalg.norm(right))), np.abs(rel @ (up / np.linalg.norm(up))))
    n, f, N = float(camera["near"]), float(camera["far"]), int(camera["resolution"])
    ortho = camera["projection"] == "orthographic"
    if ortho:
        half = float(camera["halfHeight"])
        texel = np.full_like(z, 2.0 * half / N)
        within = lateral <= half
    else:
        t = np.tan(np.radians(float(camera["fovY"])) / 2.0)
        texel = 2.0 * np.maximum(z, 0.0) * t / N
        within = lateral <= np.maximum(z, 0.0) * t
    return {"z": z, "texel": texel, "depth_per_unit": depth_per_unit(n, f, z, ortho),
            "inside": (z > n) & (z < f) & within}


def _matrix_camera(camera: dict, p: np.ndarray) -> dict:
    """:func:`camera_at` for a camera given as a world → clip matrix (row vectors, Babylon.js's
    convention: clip = [p, 1]·M) whose map stores the depth metric (z_clip + minZ)/(minZ + maxZ):
    texel sizes and depth per unit by central differences across and along the camera's axis."""
    M = np.asarray(camera["matrix"], np.float64).reshape(4, 4)
    n, f, N = float(camera["minZ"]), float(camera["maxZ"]), int(camera["resolution"])

    def clip(q):
        return np.c_[q, np.ones(len(q))] @ M

    def ndc_metric(q):
        c = clip(q)
        return c[:, :2] / c[:, 3:], (c[:, 2] + n) / (n + f)

    c = clip(p)
    axis = np.cross(M[:3, 0], M[:3, 1])                 # the direction along which clip x and y do not change
    axis /= np.linalg.norm(axis)
    e1 = np.cross(axis, (1.0, 0.0, 0.0) if abs(axis[0]) < 0.9 else (0.0, 1.0, 0.0))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    h = 1e-4 * max(float(np.ptp(p, axis=0).max()), 1e-3)
    ndc, metric = ndc_metric(p)
    per_unit = np.abs(ndc_metric(p + h * axis)[1] - ndc_metric(p - h * axis)[1]) / (2 * h)
    j1 = (ndc_metric(p + h * e1)[0] - ndc_metric(p - h * e1)[0]) / (2 * h)
    j2 = (ndc_metric(p + h * e2)[0] - ndc_metric(p - h * e2)[0]) / (2 * h)
    area = np.abs(j1[:, 0] * j2[:, 1] - j1[:, 1] * j2[:, 0])         # NDC area per m² across the axis
    texel = (2.0 / N) / np.sqrt(np.maximum(area, 1e-30))
    inside = (c[:, 3] > 0) & (np.abs(ndc) <= 1.0).all(1) & (metric >= 0.0) & (metric <= 1.0)
    return {"z": metric, "texel": texel, "depth_per_unit": per_unit, "inside": inside}


def map_size(frame, source: ShadowMapTechnique, values: dict, engine: EngineTechnique) -> dict:
    """``{"mapSize": N}``: the engine's map gets as many texels as shadowlab's (its largest over the
    lights), where the engine declares ``mapSize``; ``{}`` otherwise."""
    if not any(p.name == "mapSize" for p in engine.params):
        return {}
    return {"mapSize": max(map_settings(frame, light.name, values)[0] for light in frame.lights)}


def check_pair(source, target) -> None:
    """InputError unless ``target`` is an engine technique that maps from ``source``."""
    if not isinstance(target, EngineTechnique):
        engines = [t for t in names() if getattr(get(t), "transfer_from", ())]
        raise InputError(f"--to {target.name}: not an engine technique; transfer maps a shadowlab technique onto "
                         f"an engine's parameters ({', '.join(engines)})")
    if not isinstance(source, ShadowMapTechnique) or source.name not in target.transfer_from:
        can = ", ".join(target.transfer_from) or "none"
        raise InputError(f"no transfer from {source.name} to {target.name} (it maps from: {can}); fit the engine "
                         f"itself: shadowlab fit SCENE -t {target.name}")


def transfer(frame, source: ShadowMapTechnique, values: dict, engine: EngineTechnique, engine_values: dict,
             engine_stats: dict) -> dict:
    """The engine's values that do what ``source`` at ``values`` does on ``frame`` (module docstring).

    ``engine_values``: the engine's settings the transfer keeps; ``engine_stats``: the ``stats`` of
    one engine render at them on this frame (its shadow cameras).
    Returns ``{"values": {param: median}, "spread": {param: (p10, p90)}, "points": n}``."""
    check_pair(source, engine)
    cams = shadow_cameras(engine_stats)
    per = [receiver_points(frame, source, values, light.name, cams[light.name]) for light in frame.lights
           if light.name in cams]
    pts = ReceiverPoints.pooled(per)
    if pts.size == 0:
        raise InputError(f"no receiver point of {frame.scene.name!r} is lit and inside both {source.name}'s light "
                         f"view and {engine.name}'s shadow camera: nothing to transfer")
    mapped = engine.from_shadowlab(pts, engine_values)
    out = {k: float(np.median(v)) for k, v in mapped.items()}
    spread = {k: (float(np.percentile(v, 10)), float(np.percentile(v, 90))) for k, v in mapped.items()}
    return {"values": engine.clip_values(out), "spread": spread, "points": int(pts.size)}
