"""Deterministic host-side random streams for the fixed sample patterns of the techniques
(Poisson disks, blocker-search sets): a counter-based splitmix64, so a pattern depends on its seed
only, never on the numpy version or on what was drawn before."""
from __future__ import annotations

import numpy as np


def splitmix64(seed: int, start: int, count: int) -> np.ndarray:
    """``count`` outputs of splitmix64 from counter ``start`` (vectorised)."""
    i = np.arange(start + 1, start + count + 1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = np.uint64(seed) + i * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return z


def uniform(seed: int, start: int, count: int) -> np.ndarray:
    """``count`` uniform doubles in [0, 1) from counter ``start`` of the stream ``seed``.

    >>> uniform(1, 0, 3).shape
    (3,)
    """
    return (splitmix64(seed, start, count) >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
