"""Images for reports: signed error heat maps, a colour bar, visibility and shaded PNGs.

Conventions
- Signed error = technique − truth. Blue: the technique is darker than the truth (negative),
  white: equal, red: brighter (positive). The colour saturates at ``±scale``.
- Three-channel inputs to a heat map are reduced to Rec. 709 luminance first (linear, so the
  luminance of the difference is the difference of the luminances).
- Visibility PNGs map visibility v ∈ [0, 1] linearly to grey level round(255 v) (no sRGB curve:
  the grey level reads as the value).
- Shaded PNGs use one exposure per report, from ``common_exposure(truth)``, then the sRGB OETF.
- Cascade images (``csm``'s ``cascade`` AOV): cascade 0, 1, 2 red, green, blue as [Buljan 2020,
  Slika 4.3/4.5], then yellow, magenta, cyan, orange, violet; a blend band mixes the two cascades'
  colours by the blend weight; points of no cascade are grey; optionally darkened by the
  visibility, as Code A.14's visualisation (colour × shadow factor).

>>> import numpy as np
>>> signed_error_heatmap(np.array([[-1.0, 0.0, 1.0]]), scale=1.0)[0].tolist()
[[33, 102, 172], [255, 255, 255], [178, 24, 43]]
"""

from __future__ import annotations

import numpy as np

from shadowlab.errors import InputError
from shadowlab.io.png import encode_png, to_srgb8

__all__ = [
    "LUMA",
    "luminance",
    "error_scale",
    "signed_error_heatmap",
    "colorbar",
    "colorbar_png",
    "visibility_png",
    "common_exposure",
    "shaded_png",
    "CASCADE_COLOURS",
    "cascade_colours",
    "cascade_png",
]

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB primaries, linear
_WHITE = np.array([255.0, 255.0, 255.0])
_RED = np.array([178.0, 24.0, 43.0])  # ColorBrewer RdBu end points (sRGB 8-bit)
_BLUE = np.array([33.0, 102.0, 172.0])
_NAN_GREY = np.array([128, 128, 128], np.uint8)


def luminance(img) -> np.ndarray:
    """H×W, H×W×1 or H×W×3 linear image -> H×W (Rec. 709 luminance for three channels).

    >>> luminance(np.ones((2, 2, 3))).round(6).tolist()
    [[1.0, 1.0], [1.0, 1.0]]
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    if a.ndim == 3 and a.shape[2] == 3:
        return a @ LUMA
    if a.ndim == 2:
        return a
    raise InputError(f"expected an H×W, H×W×1 or H×W×3 image, got shape {a.shape}")


def error_scale(err, percentile: float = 99.0) -> float:
    """Default symmetric heat-map range: the 99th percentile of |err| (finite values), at least 1e-6.

    >>> error_scale(np.zeros((4, 4)))
    1e-06
    """
    e = np.abs(luminance(err))
    e = e[np.isfinite(e)]
    if e.size == 0:
        return 1e-6
    return max(float(np.percentile(e, percentile)), 1e-6)


def signed_error_heatmap(err, scale: float | None = None) -> np.ndarray:
    """Signed error (technique − truth, H×W or H×W×3) -> uint8 H×W×3 diverging colour map.

    Blue for negative (technique darker), white for 0, red for positive (brighter); saturates at
    ``±scale`` (default ``error_scale(err)``). NaN pixels are mid grey.

    >>> signed_error_heatmap(np.array([[0.5, -2.0]]), scale=1.0)[0].tolist()
    [[216, 140, 149], [33, 102, 172]]
    """
    e = luminance(err)
    if scale is None:
        scale = error_scale(e)
    scale = float(scale)
    if not np.isfinite(scale) or scale <= 0:
        raise InputError(f"signed_error_heatmap: scale must be a finite number > 0, got {scale}")
    nan = ~np.isfinite(e)
    t = np.clip(np.where(nan, 0.0, e) / scale, -1.0, 1.0)[..., None]
    end = np.where(t >= 0, _RED, _BLUE)
    rgb = _WHITE + np.abs(t) * (end - _WHITE)
    out = np.round(rgb).astype(np.uint8)
    out[nan] = _NAN_GREY
    return out


def colorbar(width: int = 256, height: int = 12) -> np.ndarray:
    """uint8 height×width×3 legend of the heat-map colours, from −scale (left) to +scale (right).

    The colours do not depend on the scale; the report prints the range next to it.

    >>> colorbar(3, 1)[0].tolist()
    [[33, 102, 172], [255, 255, 255], [178, 24, 43]]
    """
    ramp = np.linspace(-1.0, 1.0, int(width))[None, :].repeat(int(height), axis=0)
    return signed_error_heatmap(ramp, scale=1.0)


def colorbar_png(width: int = 256, height: int = 12) -> bytes:
    """PNG bytes of ``colorbar(width, height)``.

    >>> colorbar_png()[:4]
    b'\\x89PNG'
    """
    return encode_png(colorbar(width, height))


def visibility_png(vis) -> bytes:
    """PNG bytes of a visibility image (H×W grey, or H×W×3 for coloured shadows), linear v -> 255 v.

    >>> visibility_png(np.full((2, 2), 0.5))[:4]
    b'\\x89PNG'
    """
    a = np.asarray(vis, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise InputError(f"visibility_png: expected H×W or H×W×3 visibility, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("visibility_png: the visibility contains NaN or inf values")
    return encode_png(np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8))


def common_exposure(truth_shaded, target: float = 0.9, percentile: float = 99.0) -> float:
    """Exposure that maps the truth's 99th-percentile luminance to ``target`` (0.9); 1.0 for a black image.

    Use the same value for every shaded image of one report so that they compare.

    >>> common_exposure(np.full((4, 4), 0.45))
    2.0
    """
    lum = luminance(truth_shaded)
    lum = lum[np.isfinite(lum)]
    p = float(np.percentile(lum, percentile)) if lum.size else 0.0
    return target / p if p > 0 else 1.0


def shaded_png(img, exposure: float) -> bytes:
    """PNG bytes of a linear shaded image (H×W×3) scaled by ``exposure``, through the sRGB OETF.

    >>> shaded_png(np.ones((2, 2, 3)), exposure=0.5)[:4]
    b'\\x89PNG'
    """
    return encode_png(to_srgb8(img, exposure))


#: colours of cascades 0 … 7 (linear [0, 1]): red, green, blue as Slika 4.3/4.5, then more
CASCADE_COLOURS = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 0.5, 0],
                            [0.5, 0, 1]], np.float64)


def cascade_colours(index, weight=None, visibility=None) -> np.ndarray:
    """H×W×3 uint8 image of a cascade index AOV (−1 = none, grey); ``weight``: the blend weight
    toward cascade index + 1; ``visibility``: multiplies the colour (Code A.14's visualisation).

    >>> cascade_colours(np.array([[0, 1, 2, -1]]))[0].tolist()
    [[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128]]
    >>> cascade_colours(np.array([[0.0]]), np.array([[0.5]]))[0].tolist()
    [[128, 128, 0]]
    """
    idx = np.rint(np.asarray(index, np.float64)).astype(np.int64)
    if idx.ndim == 3 and idx.shape[2] == 1:
        idx = idx[:, :, 0]
    k = len(CASCADE_COLOURS)
    a = CASCADE_COLOURS[np.clip(idx, 0, k - 1)]
    if weight is not None:
        w = np.clip(np.asarray(weight, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
        a = (1.0 - w) * a + w * CASCADE_COLOURS[np.clip(idx + 1, 0, k - 1)]
    if visibility is not None:
        a = a * np.clip(np.asarray(visibility, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
    a = np.where((idx < 0)[..., None], _NAN_GREY / 255.0, a)
    return np.round(a * 255.0).astype(np.uint8)


def cascade_png(index, weight=None, visibility=None) -> bytes:
    """PNG bytes of :func:`cascade_colours`.

    >>> cascade_png(np.zeros((2, 2)))[:4]
    b'\\x89PNG'
    """
    return encode_png(cascade_colours(index, weight, visibility))
