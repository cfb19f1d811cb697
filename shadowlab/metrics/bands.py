"""Error of a light's visibility by distance from the camera and by cascade.

Cascaded shadow maps spend their texels by distance ([Buljan 2020, §4.1]): the near cascades are
fine, the far ones coarse, so one error over the image hides where a technique fails. These
functions split the comparison of :func:`shadowlab.metrics.compare_visibility` by a per-pixel
label: a distance band (:func:`by_distance`) or any integer label such as a cascade index
(:func:`by_label`).

>>> import numpy as np
>>> vis = np.array([[1.0, 0.0, 1.0, 1.0]])
>>> truth = np.array([[1.0, 0.0, 0.0, 1.0]])
>>> dist = np.array([[1.0, 3.0, 30.0, 300.0]])
>>> rows = by_distance(vis, truth, dist, edges=(0, 10, 100, np.inf))
>>> [(r["lo"], r["hi"], r["pixels"], r["leak_rate"]) for r in rows]
[(0.0, 10.0, 2, 0.0), (10.0, 100.0, 1, 1.0), (100.0, inf, 1, 0.0)]
"""

from __future__ import annotations

import math

import numpy as np

from .compare import compare_visibility

__all__ = ["DISTANCE_EDGES", "by_distance", "by_label"]

#: default band edges (m): about two bands per decade, from the camera to beyond 200 m
DISTANCE_EDGES = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, math.inf)

_KEYS = ("rmse", "mae", "rmse_penumbra", "leak_rate", "overdark_rate", "penumbra_fraction")


def _row(vis, truth, region) -> dict:
    m = compare_visibility(vis, truth, valid=region)
    return {"pixels": int(region.sum()), **{k: float(m[k]) for k in _KEYS}}


def by_distance(vis, truth, distance, valid=None, *, edges=DISTANCE_EDGES) -> list[dict]:
    """One row per distance band [lo, hi) (m) that holds a valid pixel: ``lo``, ``hi``, ``pixels``
    and the errors ``rmse``, ``mae``, ``rmse_penumbra``, ``leak_rate``, ``overdark_rate``,
    ``penumbra_fraction`` of :func:`~shadowlab.metrics.compare_visibility` over the band.
    ``distance``: (H, W) distance of each pixel's surface from the camera (the truth's ``depth``)."""
    d = np.asarray(distance, np.float64)
    ok = np.isfinite(d) & (np.ones(d.shape, bool) if valid is None else np.asarray(valid, bool))
    e = [float(x) for x in edges]
    if len(e) < 2 or any(b <= a for a, b in zip(e, e[1:])):
        raise ValueError(f"distance band edges must increase, got {edges}")
    rows = []
    for lo, hi in zip(e, e[1:]):
        region = ok & (d >= lo) & (d < hi)
        if region.any():
            rows.append({"lo": lo, "hi": hi, **_row(vis, truth, region)})
    return rows


def by_label(vis, truth, labels, valid=None) -> list[dict]:
    """One row per integer label present among the valid pixels (e.g. the cascade index AOV):
    ``label``, ``pixels`` and the errors of :func:`by_distance`."""
    lab = np.rint(np.asarray(labels, np.float64)).astype(np.int64)
    ok = np.ones(lab.shape, bool) if valid is None else np.asarray(valid, bool)
    return [{"label": int(k), **_row(vis, truth, ok & (lab == k))} for k in np.unique(lab[ok])]
