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
- Tile images (``vtsm``/``fvsm``'s ``tile`` AOV, [Giegl 2007, §3, §4.10]): a colour per tile id from
  a fixed palette (Kelly's colours of maximum contrast, without white, black and grey), cycling
  over the ids (id k and k + 19 share a colour); grey where no tile wrote the pixel (−1); darkened
  by the visibility like the cascade image; optionally the SMTG grid ([Giegl 2007, §4.4], the
  ``cell`` AOV) as one-pixel white lines: a pixel is on a line where its right or lower neighbour
  lies in another cell (pixels of no cell, −1, draw none).
- Level heat maps (``fvsm``'s ``demand_x``/``demand_y``, log₂ texels across the virtual map,
  [Giegl 2007, §4.3]): blue (low) → white → red (high) between two integer levels, the colour bar's
  colours; the undersampling max(demand − provided, 0) white (the tile meets the demand) → red.
  Negative levels (−1: no surface / no tile) and NaN are grey.
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
    "TILE_COLOURS",
    "tile_colours",
    "tile_png",
    "cell_edges",
    "level_range",
    "level_heatmap",
    "undersampling",
    "undersampling_heatmap",
    "emitter_pixels",
    "emitter_guess",
    "grow",
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


#: tile colours (sRGB 8-bit): Kelly's 22 colours of maximum contrast without white, black and grey
TILE_COLOURS = np.array([[243, 195, 0], [135, 86, 146], [243, 132, 0], [161, 202, 241], [190, 0, 50],
                         [194, 178, 128], [0, 136, 86], [230, 143, 172], [0, 103, 165], [249, 147, 121],
                         [96, 78, 151], [246, 166, 0], [179, 68, 108], [220, 211, 0], [136, 45, 23],
                         [141, 182, 0], [101, 69, 34], [226, 88, 34], [43, 61, 38]], np.uint8)
_LINE = (255, 255, 255)


def _labels(a) -> np.ndarray:
    """A label AOV (H×W or H×W×1, float) -> int64 H×W, −1 where negative or not finite."""
    x = np.asarray(a, np.float64)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[:, :, 0]
    if x.ndim != 2:
        raise InputError(f"expected an H×W label image, got shape {x.shape}")
    ok = np.isfinite(x) & (x >= -0.5)
    return np.where(ok, np.rint(np.where(ok, x, -1.0)), -1).astype(np.int64)


def cell_edges(cell) -> np.ndarray:
    """bool H×W: the pixels whose right or lower neighbour lies in another SMTG cell
    ([Giegl 2007, §4.4]); pixels of no cell (−1) draw no line and end none.

    >>> cell_edges(np.array([[0, 0, 1], [2, 2, 3], [2, 2, 3]])).astype(int).tolist()
    [[1, 1, 1], [0, 1, 0], [0, 1, 0]]
    """
    c = _labels(cell)
    has = c >= 0
    out = np.zeros(c.shape, bool)
    out[:, :-1] |= (c[:, :-1] != c[:, 1:]) & has[:, :-1] & has[:, 1:]
    out[:-1] |= (c[:-1] != c[1:]) & has[:-1] & has[1:]
    return out


def tile_colours(tile, cell=None, visibility=None, *, line=_LINE) -> np.ndarray:
    """H×W×3 uint8 image of a tile index AOV ([Giegl 2007, §3, §4.10]): ``TILE_COLOURS[id mod 19]``,
    grey where −1 (no tile wrote the pixel); ``visibility`` multiplies the colour (as
    :func:`cascade_colours`); ``cell``: the SMTG cell AOV, drawn as ``line``-coloured lines where
    it changes between neighbouring pixels (:func:`cell_edges`, [Giegl 2007, §4.4]).

    >>> tile_colours(np.array([[0, 1, -1]])).tolist()
    [[[243, 195, 0], [135, 86, 146], [128, 128, 128]]]
    >>> tile_colours(np.array([[0, 0]]), cell=np.array([[3, 4]]), visibility=np.array([[0.5, 0.5]])).tolist()
    [[[255, 255, 255], [122, 98, 0]]]
    """
    idx = _labels(tile)
    a = TILE_COLOURS[np.maximum(idx, 0) % len(TILE_COLOURS)].astype(np.float64)
    if visibility is not None:
        a = a * np.clip(np.asarray(visibility, np.float64).reshape(idx.shape), 0.0, 1.0)[..., None]
    a = np.where((idx < 0)[..., None], _NAN_GREY.astype(np.float64), a)
    if cell is not None:
        a = np.where(cell_edges(np.asarray(cell).reshape(idx.shape))[..., None], np.asarray(line, np.float64), a)
    return np.round(a).astype(np.uint8)


def tile_png(tile, cell=None, visibility=None, *, line=_LINE) -> bytes:
    """PNG bytes of :func:`tile_colours`.

    >>> tile_png(np.zeros((2, 2)))[:4]
    b'\\x89PNG'
    """
    return encode_png(tile_colours(tile, cell, visibility, line=line))


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


def undersampling(demand, provided) -> np.ndarray:
    """Per pixel max(demand − provided, 0) in log₂ levels ([Giegl 2007, §4.3, §4.10]): 0 = the
    pixel's tile gives at least the virtual resolution it needs, k = 2^k times too coarse; NaN
    where either level is missing (−1 or NaN).

    >>> undersampling(np.array([[12.0, 9.0, 12.0]]), np.array([[10.0, 10.0, -1.0]])).tolist()
    [[2.0, 0.0, nan]]
    """
    d, p = _levels(demand), _levels(np.asarray(provided, np.float64).reshape(np.shape(demand)))
    return np.maximum(d - p, 0.0)


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
