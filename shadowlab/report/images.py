"""Images for reports: signed error heat maps, a colour bar, visibility and shaded PNGs.

Conventions
- Signed error = technique − truth. Blue: the technique is darker than the truth (negative),
  white: equal, red: brighter (positive). The colour saturates at ``±scale``.
- Three-channel inputs to a heat map are reduced to Rec. 709 luminance first (linear, so the
  luminance of the difference is the difference of the luminances).
- Visibility PNGs map visibility v ∈ [0, 1] linearly to grey level round(255 v) (no sRGB curve:
  the grey level reads as the value).
- Shaded PNGs use one exposure per report, from ``common_exposure(truth)``, then the sRGB OETF.
- Colour images a family builds from its AOVs (``Technique.report_images``, e.g. a colour per
  label) are shown as they are; grey (:data:`shadowlab.io.png.NO_DATA`) means "none" there too.
- Level heat maps (log₂ levels, e.g. texels across a virtual map [Giegl 2007, §4.3]): blue (low) →
  white → red (high) between two integer levels, the colour bar's colours; levels in excess
  (``undersampling_heatmap``) white (0) → red. Negative levels (−1: none) and NaN are grey.
- Pixels on a light (the camera sees a light's shape: a sphere light in view, the sun's disk) show
  the light's radiance in ``mi.render`` and in an engine's image but have no shading point in the
  truth (0); their error says nothing about shadows and would set the colour scale (±32 for a
  sphere light in view). ``error_scale(err, exclude=...)`` leaves them out, with their 8
  neighbours (which a box-filtered pixel mixes with the light): :func:`emitter_pixels` finds
  them from the G-buffer's shape ids, :func:`emitter_guess` from the images alone (truth 0 and
  the other image brighter than the truth's brightest pixel).

>>> import numpy as np
>>> signed_error_heatmap(np.array([[-1.0, 0.0, 1.0]]), scale=1.0)[0].tolist()
[[33, 102, 172], [255, 255, 255], [178, 24, 43]]
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io.png import NO_DATA, encode_png, to_srgb8

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
    "level_range",
    "level_heatmap",
    "undersampling_heatmap",
    "emitter_pixels",
    "emitter_guess",
    "grow",
]

LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB primaries, linear
_WHITE = np.array([255.0, 255.0, 255.0])
_RED = np.array([178.0, 24.0, 43.0])  # ColorBrewer RdBu end points (sRGB 8-bit)
_BLUE = np.array([33.0, 102.0, 172.0])
_NAN_GREY = NO_DATA


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


def error_scale(err, percentile: float = 99.0, *, exclude=None) -> float:
    """Default symmetric heat-map range: the 99th percentile of |err| (finite values), at least
    1e-6; ``exclude``: an H×W bool mask of pixels left out (the pixels on a light, see the module
    docstring).

    >>> error_scale(np.zeros((4, 4)))
    1e-06
    >>> e = np.zeros((4, 4)); e[0, 0] = 32.0; e[1:, 1:] = 0.5
    >>> error_scale(e, 100), error_scale(e, 100, exclude=e > 1)
    (32.0, 0.5)
    """
    e = np.abs(luminance(err))
    ok = np.isfinite(e)
    if exclude is not None:
        ok &= ~np.asarray(exclude, bool).reshape(e.shape)
    e = e[ok]
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


def colorbar(width: int = 256, height: int = 12, *, signed: bool = True) -> np.ndarray:
    """uint8 height×width×3 legend of the heat-map colours, from −scale (left) to +scale (right);
    ``signed=False``: its positive half only, 0 (white, left) to +scale (red, right).

    The colours do not depend on the scale; the report prints the range next to it.

    >>> colorbar(3, 1)[0].tolist()
    [[33, 102, 172], [255, 255, 255], [178, 24, 43]]
    >>> colorbar(2, 1, signed=False)[0].tolist()
    [[255, 255, 255], [178, 24, 43]]
    """
    ramp = np.linspace(-1.0 if signed else 0.0, 1.0, int(width))[None, :].repeat(int(height), axis=0)
    return signed_error_heatmap(ramp, scale=1.0)


def colorbar_png(width: int = 256, height: int = 12, *, signed: bool = True) -> bytes:
    """PNG bytes of ``colorbar(width, height, signed=signed)``.

    >>> colorbar_png()[:4]
    b'\\x89PNG'
    """
    return encode_png(colorbar(width, height, signed=signed))


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


def _levels(a) -> np.ndarray:
    """Float H×W levels with NaN where negative (−1: none) or not finite."""
    x = np.asarray(a, np.float64)
    return np.where(np.isfinite(x) & (x >= 0), x, np.nan)


def level_range(*levels, percentile: float = 99.0, lo: int | None = None) -> tuple[int, int]:
    """Integer colour range (lo, hi) of level images ([Giegl 2007, §4.3]: log₂ texels): from the
    lowest level (or ``lo``) to the ``percentile`` of their levels (≥ 0, finite), rounded out;
    hi > lo. (0, 1) when there are none.

    >>> level_range(np.array([[3.0, 5.0, -1.0]]), np.array([[9.0]]), percentile=100)
    (3, 9)
    >>> level_range(np.zeros((2, 2)), lo=0)
    (0, 1)
    """
    v = np.concatenate([_levels(a).ravel() for a in levels]) if levels else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (0 if lo is None else int(lo)), (1 if lo is None else int(lo) + 1)
    a = int(np.floor(v.min())) if lo is None else int(lo)
    b = int(np.ceil(np.percentile(v, percentile)))
    return a, max(b, a + 1)


def level_heatmap(level, *, lo: float, hi: float) -> np.ndarray:
    """uint8 H×W×3 heat map of a level image: blue at ``lo`` → white → red at ``hi`` (the colour
    bar's colours, saturating outside), grey where −1 or NaN (no surface).

    >>> level_heatmap(np.array([[2.0, 6.0, 10.0, -1.0]]), lo=2, hi=10)[0].tolist()
    [[33, 102, 172], [255, 255, 255], [178, 24, 43], [128, 128, 128]]
    """
    if not hi > lo:
        raise InputError(f"level_heatmap: expected hi > lo, got lo={lo}, hi={hi}")
    t = 2.0 * (_levels(level) - lo) / (hi - lo) - 1.0
    return signed_error_heatmap(t, scale=1.0)


def undersampling_heatmap(under, *, scale: float) -> np.ndarray:
    """uint8 H×W×3: white where 0 (demand met) → red at ``scale`` levels (saturating), grey where
    NaN; the colours of ``colorbar(signed=False)``.

    >>> undersampling_heatmap(np.array([[0.0, 4.0, np.nan]]), scale=4)[0].tolist()
    [[255, 255, 255], [178, 24, 43], [128, 128, 128]]
    """
    return signed_error_heatmap(np.maximum(np.asarray(under, np.float64), 0.0), scale=scale)


def grow(mask) -> np.ndarray:
    """An H×W bool mask grown by one pixel (its 8 neighbours), by shifted slices.

    >>> grow(np.eye(1, 4, 1, dtype=bool).reshape(1, 4)).astype(int).tolist()
    [[1, 1, 1, 0]]
    """
    m = np.asarray(mask, bool)
    out = m.copy()
    h, w = m.shape
    for dy in (-1, 0, 1):          # 9 shifted views, not a loop over pixels
        for dx in (-1, 0, 1):
            out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
                m[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


def emitter_pixels(shape_id, light_shapes) -> np.ndarray:
    """H×W bool: the pixels whose camera ray (any sub-pixel's) hits a light's shape. ``shape_id``:
    the G-buffer's (H, W[, ss²]) Mitsuba shape indices (−1 = miss,
    :class:`shadowlab.render.gbuffer.GBuffer`); ``light_shapes``: {light: shape index}
    (``Scene.light_shapes``; delta lights have none).

    >>> emitter_pixels(np.array([[[0], [2]], [[-1], [2]]]), {"bulb": 2}).tolist()
    [[False, True], [False, True]]
    """
    sid = np.asarray(shape_id)
    hit = np.isin(sid, np.asarray(list(dict(light_shapes).values()), dtype=sid.dtype))
    return hit.any(axis=2) if hit.ndim == 3 else hit


def emitter_guess(truth, other) -> np.ndarray:
    """H×W bool: the pixels that look like a light seen by the camera, from the images alone:
    the truth (shaded, linear) is 0 there and ``other`` (``mi.render`` or an engine's image) is
    brighter than the truth's brightest pixel. For when the G-buffer's :func:`emitter_pixels` is
    not at hand.

    >>> emitter_guess(np.array([[0.0, 0.5, 0.0]]), np.array([[9.0, 0.5, 0.1]])).tolist()
    [[True, False, False]]
    """
    t, o = luminance(truth), luminance(other)
    top = float(np.max(t[np.isfinite(t)], initial=0.0))
    return (t == 0) & np.isfinite(o) & (o > top)
