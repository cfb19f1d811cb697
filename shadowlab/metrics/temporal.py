"""Temporal stability (shimmer) of a technique along a camera path: pure numpy on arrays.

A technique's light views may follow the camera (a shadow map fitted to the view frustum moves
and resizes its texel grid when the camera moves), so its visibility at a *fixed* world point can
change from frame to frame although nothing in the scene did: the shimmer (crawling shadow edges)
of [Buljan 2020, ch. 4]. It is measured at a fixed set of world points x (the G-buffer points of
the first frame of the path), evaluated with each frame's light views:

    shimmer = |V_t(x) − V_{t−1}(x)|   over the points x (valid and lit by the light) and the
                                       frame pairs (t − 1, t),

reported as its mean and its 99th percentile (``numpy.percentile``, linear interpolation), per
light and pooled over the lights (every light's differences together).

>>> import numpy as np
>>> V = np.array([[0.0, 1.0, 0.5], [1.0, 1.0, 0.5], [1.0, 0.0, 0.5]])   # 3 frames × 3 points
>>> s = shimmer(V, np.array([True, True, False]))
>>> s["mean"], s["pairs"], s["points"], s["samples"]
(0.5, 2, 2, 4)
"""

from __future__ import annotations

import numpy as np

__all__ = ["shimmer", "shimmer_per_light", "SHIMMER_KEYS"]

#: the keys of a shimmer dict
SHIMMER_KEYS = ("mean", "p99", "max", "pairs", "points", "samples")


def _abs_diffs(values, valid) -> np.ndarray:
    V = np.asarray(values, np.float64)
    if V.ndim != 2:
        raise ValueError(f"shimmer: values must be (frames, points), got shape {V.shape}")
    m = np.ones(V.shape[1], bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if m.shape[0] != V.shape[1]:
        raise ValueError(f"shimmer: valid has {m.shape[0]} points, values {V.shape[1]}")
    return np.abs(np.diff(V[:, m], axis=0)).reshape(-1)


def _stats(d: np.ndarray, pairs: int, points: int) -> dict:
    if d.size == 0:
        return {"mean": None, "p99": None, "max": None, "pairs": pairs, "points": points, "samples": 0}
    return {"mean": float(d.mean()), "p99": float(np.percentile(d, 99)), "max": float(d.max()),
            "pairs": pairs, "points": points, "samples": int(d.size)}


def shimmer(values, valid=None) -> dict:
    """Shimmer of one light: ``values`` (T, N), visibility of frame t at fixed point n; ``valid``
    (N,) bool, the points counted (None: all). Returns {mean, p99, max, pairs = T − 1, points,
    samples = points · pairs}; mean/p99/max are None when nothing is counted (T < 2 or no point)."""
    V = np.asarray(values)
    d = _abs_diffs(V, valid)
    points = int(V.shape[1] if valid is None else np.count_nonzero(valid))
    return _stats(d, max(0, V.shape[0] - 1), points)


def shimmer_per_light(lights: dict) -> tuple[dict, dict]:
    """``lights``: {light: (values (T, N), valid (N,))} -> ({light: shimmer dict}, pooled dict),
    the pooled one over every light's differences together."""
    per, diffs, points, pairs = {}, [], 0, 0
    for name, (values, valid) in lights.items():
        per[name] = shimmer(values, valid)
        diffs.append(_abs_diffs(values, valid))
        points += per[name]["points"]
        pairs = max(pairs, per[name]["pairs"])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    return per, _stats(d, pairs, points)
