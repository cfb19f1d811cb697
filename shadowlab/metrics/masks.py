"""Regions of the ground-truth visibility and the shadow-specific error rates.

The truth visibility ``t`` of a pixel classifies it (docs/ARCHITECTURE.md, ``Metrics``):

* umbra     ``t <= PENUMBRA_LO`` (0.02)
* penumbra  ``PENUMBRA_LO < t < PENUMBRA_HI`` (strictly between 0.02 and 0.98)
* lit       ``t >= PENUMBRA_HI`` (0.98)

so the three regions partition the valid pixels. Visibility is H×W, or H×W×C for coloured shadows;
an H×W×C array is reduced to its channel mean before it is classified or compared with 0.5.
``valid`` (H×W bool, None = all pixels) removes pixels such as the background; non-finite values
are only refused inside ``valid``.

Light leak: the technique says lit (vis > 0.5) where the truth is umbra. Over-darkening: it says
shadowed (vis < 0.5) where the truth is lit. The rates and the means return 0.0 when their region is
empty (no umbra: nothing can leak).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io.exr import check_finite

__all__ = [
    "PENUMBRA_LO", "PENUMBRA_HI", "penumbra_mask", "umbra_mask", "lit_mask",
    "leak_rate", "overdark_rate", "leak_mean", "overdark_mean",
]

PENUMBRA_LO = 0.02
PENUMBRA_HI = 0.98


def scalar_vis(name: str, vis) -> np.ndarray:
    """A visibility image as float64 H×W (channels of an H×W×C image are averaged); InputError naming ``name``."""
    arr = np.asarray(vis, dtype=np.float64)
    if arr.ndim == 3:
        arr = arr.mean(axis=2)
    if arr.ndim != 2:
        raise InputError(
            f"{name} must be an H×W (or H×W×C) visibility image, got shape {arr.shape}; pass one "
            "light's visibility at a time."
        )
    return arr


def valid_of(valid, shape) -> np.ndarray:
    """A boolean mask of ``shape`` (None: every pixel is valid)."""
    if valid is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(valid)
    if m.dtype != bool:
        raise InputError(
            f"valid mask must be a boolean array, got dtype {m.dtype}; build it with a comparison "
            "(e.g. gbuffer.hit > 0)."
        )
    if m.shape != shape:
        raise InputError(
            f"valid mask has shape {m.shape} but the visibility is {shape}; use the G-buffer hit "
            "mask of the same resolution."
        )
    return m


def _truth(truth, valid):
    t = scalar_vis("truth visibility", truth)
    v = valid_of(valid, t.shape)
    check_finite("truth visibility", t, v)
    return t, v


def _pair(vis, truth, valid):
    t, v = _truth(truth, valid)
    x = scalar_vis("visibility", vis)
    if x.shape != t.shape:
        raise InputError(
            f"visibility has shape {x.shape} but the truth is {t.shape}; render the technique at "
            "the reference's resolution."
        )
    check_finite("visibility", x, v)
    return x, t, v


def penumbra_mask(truth_vis, valid=None) -> np.ndarray:
    """Pixels whose truth visibility is strictly between 0.02 and 0.98 (and valid).

    >>> import numpy as np
    >>> penumbra_mask(np.array([[0.02, 0.5, 0.98]])).tolist()
    [[False, True, False]]
    """
    t, v = _truth(truth_vis, valid)
    return (t > PENUMBRA_LO) & (t < PENUMBRA_HI) & v


def umbra_mask(truth_vis, valid=None) -> np.ndarray:
    """Pixels whose truth visibility is <= 0.02 (and valid).

    >>> import numpy as np
    >>> umbra_mask(np.array([[0.0, 0.02, 0.03]])).tolist()
    [[True, True, False]]
    """
    t, v = _truth(truth_vis, valid)
    return (t <= PENUMBRA_LO) & v


def lit_mask(truth_vis, valid=None) -> np.ndarray:
    """Pixels whose truth visibility is >= 0.98 (and valid).

    >>> import numpy as np
    >>> lit_mask(np.array([[0.97, 0.98, 1.0]])).tolist()
    [[False, True, True]]
    """
    t, v = _truth(truth_vis, valid)
    return (t >= PENUMBRA_HI) & v


def _fraction(flags: np.ndarray, region: np.ndarray) -> float:
    n = int(np.count_nonzero(region))
    return 0.0 if n == 0 else float(np.count_nonzero(flags & region)) / n


def _region_mean(values: np.ndarray, region: np.ndarray) -> float:
    return 0.0 if not region.any() else float(values[region].mean())


def leak_rate(vis, truth, valid=None) -> float:
    """Fraction of umbra pixels where the technique is lit (vis > 0.5); 0.0 if there is no umbra.

    >>> import numpy as np
    >>> leak_rate(np.array([[1.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]))
    0.5
    """
    x, t, v = _pair(vis, truth, valid)
    return _fraction(x > 0.5, (t <= PENUMBRA_LO) & v)


def overdark_rate(vis, truth, valid=None) -> float:
    """Fraction of lit pixels where the technique is shadowed (vis < 0.5); 0.0 if nothing is lit.

    >>> import numpy as np
    >>> overdark_rate(np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 1.0, 0.0]]))
    0.5
    """
    x, t, v = _pair(vis, truth, valid)
    return _fraction(x < 0.5, (t >= PENUMBRA_HI) & v)


def leak_mean(vis, truth, valid=None) -> float:
    """Mean of max(vis - truth, 0) over the umbra; 0.0 if there is no umbra.

    >>> import numpy as np
    >>> leak_mean(np.array([[0.5, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]))
    0.25
    """
    x, t, v = _pair(vis, truth, valid)
    return _region_mean(np.maximum(x - t, 0.0), (t <= PENUMBRA_LO) & v)


def overdark_mean(vis, truth, valid=None) -> float:
    """Mean of max(truth - vis, 0) over the lit region; 0.0 if nothing is lit.

    >>> import numpy as np
    >>> overdark_mean(np.array([[0.5, 1.0, 0.0]]), np.array([[1.0, 1.0, 0.0]]))
    0.25
    """
    x, t, v = _pair(vis, truth, valid)
    return _region_mean(np.maximum(t - x, 0.0), (t >= PENUMBRA_HI) & v)
