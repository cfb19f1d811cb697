"""One-call comparisons of a technique's output with the ground truth, as dicts of python floats.

``compare_visibility`` compares one light's visibility with the reference visibility;
``compare_shaded`` compares the shaded image with the reference image, over the whole image and over
the penumbra. A value is NaN only when its mask is empty (no valid pixel, no penumbra).
"""

from __future__ import annotations

import numpy as np

from ..io.exr import check_finite
from . import image as _im
from . import masks as _mk

__all__ = ["compare_visibility", "compare_shaded", "pooled_visibility", "SHADED_KEYS", "VISIBILITY_KEYS"]

VISIBILITY_KEYS = (
    "rmse", "mae", "rmse_penumbra", "mae_penumbra", "leak_rate", "overdark_rate",
    "leak_mean", "overdark_mean", "penumbra_fraction",
)
_SHADED_BASE = ("rmse", "mae", "psnr", "ssim", "flip", "delta_e2000")
SHADED_KEYS = _SHADED_BASE + tuple(f"{k}_penumbra" for k in _SHADED_BASE)


def compare_visibility(vis, truth, valid=None) -> dict[str, float]:
    """Error of one light's visibility against the truth visibility.

    Keys: ``rmse``, ``mae`` (over the valid pixels), ``rmse_penumbra``, ``mae_penumbra`` (over the
    truth's penumbra, see :func:`penumbra_mask`), ``leak_rate``, ``overdark_rate``, ``leak_mean``,
    ``overdark_mean`` (see :mod:`shadowlab.metrics.masks`; 0.0 when the region is empty) and
    ``penumbra_fraction`` (penumbra pixels / valid pixels). ``vis`` and ``truth`` are H×W or H×W×C;
    colour visibility is reduced to its channel mean for the region tests.

    >>> import numpy as np
    >>> m = compare_visibility(np.array([[1.0, 0.5, 1.0]]), np.array([[0.0, 0.5, 1.0]]))
    >>> m["leak_rate"], m["rmse_penumbra"], round(m["penumbra_fraction"], 3)
    (1.0, 0.0, 0.333)
    """
    x, t = np.asarray(vis, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    pen = _mk.penumbra_mask(t, valid)
    valid_m = _mk.valid_of(valid, pen.shape)
    n_valid = int(np.count_nonzero(valid_m))
    return {
        "rmse": _im.rmse(x, t, valid_m),
        "mae": _im.mae(x, t, valid_m),
        "rmse_penumbra": _im.rmse(x, t, pen),
        "mae_penumbra": _im.mae(x, t, pen),
        "leak_rate": _mk.leak_rate(x, t, valid_m),
        "overdark_rate": _mk.overdark_rate(x, t, valid_m),
        "leak_mean": _mk.leak_mean(x, t, valid_m),
        "overdark_mean": _mk.overdark_mean(x, t, valid_m),
        "penumbra_fraction": (float(np.count_nonzero(pen)) / n_valid) if n_valid else float("nan"),
    }


def pooled_visibility(lights) -> tuple[dict, dict]:
    """Visibility metrics of several lights: ``(per_light, pooled)``.

    ``lights`` maps a light name to ``(vis, truth, valid)``; ``per_light`` holds
    :func:`compare_visibility` of each, ``pooled`` the scene-level numbers of a ``compare`` report:
    ``leak_rate`` and ``overdark_rate`` over the umbra / lit pixels of all lights together,
    ``vis_rmse`` and ``vis_rmse_penumbra`` the means over lights (NaN if no light has a penumbra).

    >>> import numpy as np
    >>> t = np.array([[0.0, 1.0]])
    >>> per, pooled = pooled_visibility({"a": (np.array([[1.0, 1.0]]), t, None),
    ...                                  "b": (np.array([[0.0, 1.0]]), t, None)})
    >>> pooled["leak_rate"], pooled["overdark_rate"]
    (0.5, 0.0)
    """
    per_light, leak, over = {}, [0, 0], [0, 0]
    for name, (vis, truth, valid) in lights.items():
        per_light[name] = compare_visibility(vis, truth, valid)
        x = _mk.scalar_vis("visibility", vis)
        umbra, lit = _mk.umbra_mask(truth, valid), _mk.lit_mask(truth, valid)
        leak[0] += int(np.count_nonzero(umbra & (x > 0.5)))
        leak[1] += int(np.count_nonzero(umbra))
        over[0] += int(np.count_nonzero(lit & (x < 0.5)))
        over[1] += int(np.count_nonzero(lit))
    rp = [d["rmse_penumbra"] for d in per_light.values()]
    pooled = {"leak_rate": leak[0] / leak[1] if leak[1] else 0.0,
              "overdark_rate": over[0] / over[1] if over[1] else 0.0,
              "vis_rmse": float(np.mean([d["rmse"] for d in per_light.values()])),
              "vis_rmse_penumbra": float(np.nanmean(rp)) if any(np.isfinite(rp)) else float("nan")}
    return per_light, pooled


def compare_shaded(img, truth, penumbra=None, valid=None) -> dict[str, float]:
    """Image metrics of a shaded image against the ground-truth image, whole and in the penumbra.

    Keys ``rmse, mae, psnr, ssim, flip, delta_e2000`` over the valid pixels (None = all) and the
    same six with suffix ``_penumbra`` over ``penumbra & valid``; ``penumbra`` is an H×W bool mask
    (for several lights the union of their penumbra masks); None means no penumbra, so the
    ``_penumbra`` values are NaN. SSIM, FLIP and ΔE2000 maps are computed once on the whole images
    and averaged over each mask. Both PSNRs use one peak, the maximum of ``truth`` over the valid
    pixels, so the penumbra PSNR is on the same scale as the whole-image PSNR.

    >>> import numpy as np
    >>> x = np.full((16, 16, 3), 0.5)
    >>> m = compare_shaded(x, x)
    >>> m["rmse"], m["ssim"], m["flip"], m["delta_e2000"], m["psnr"]
    (0.0, 1.0, 0.0, 0.0, inf)
    """
    t, r = _im.image_pair(img, truth)
    shape2d = t.shape[:2]
    valid_m = _im.mask_of(valid, shape2d)
    if valid_m is None:
        valid_m = np.ones(shape2d, dtype=bool)
    pen = _im.mask_of(penumbra, shape2d)
    pen = np.zeros(shape2d, dtype=bool) if pen is None else (pen & valid_m)

    out: dict[str, float] = {}
    if not valid_m.any():
        return {k: float("nan") for k in SHADED_KEYS}
    check_finite("shaded image", t)
    check_finite("reference image", r)
    peak = float(np.max(r[valid_m]))
    maps = {
        "ssim": _im.ssim_kernel(t, r, None),
        "flip": _im.flip_kernel(t, r),
        "delta_e2000": _im.delta_e2000_kernel(t, r),
    }
    for suffix, m in (("", valid_m), ("_penumbra", pen)):
        out["rmse" + suffix] = _im.rmse(t, r, m)
        out["mae" + suffix] = _im.mae(t, r, m)
        out["psnr" + suffix] = _im.psnr(t, r, m, peak=peak)
        for name, mp in maps.items():
            out[name + suffix] = _im.masked_mean(mp, m)
    return {k: out[k] for k in SHADED_KEYS}
