"""Alpha textures of alpha-tested casters ([Buljan 2020, §2.4], "Transparentni objekti").

A shape's ``alpha_texture`` is an image file read with ``mitsuba.Bitmap`` (PNG, JPEG, EXR, …):

* an image with an alpha channel (grey + alpha or RGBA): its alpha channel (colour is ignored);
* a greyscale image without alpha: its grey value (its luminance); an RGB image without alpha
  whose three channels are equal in every pixel counts as greyscale;
* a colour RGB image without alpha is refused (a colour image is not a mask: add an alpha
  channel or convert it to greyscale).

Integer images are read as stored codes divided by the format's maximum (255 or 65535) with no
sRGB decoding: alpha is linear data in PNG, and a greyscale mask is treated as data, as game
engines do. Float images (EXR) are used as stored. Row 0 is the image's top row and is the
texture's v ∈ [0, 1/H) (Mitsuba's ``bitmap`` convention), column 0 is u ∈ [0, 1/W).

The cut-off test is thresholded once, at load: a texel is opaque when alpha ≥ cutoff, else
transparent (a shadow-map fragment shader's ``discard``); :func:`opacity_mask` gives that binary
mask. :func:`leaf_alpha` generates the built-in leaf texture (``scenes/textures/leaf.png``).
"""

from __future__ import annotations

import math
from pathlib import Path

import mitsuba as mi
import numpy as np


class AlphaTextureError(ValueError):
    """The file exists but is not a usable alpha texture (message says why)."""


def read_alpha(path) -> np.ndarray:
    """Alpha (H, W) float32 in [0, 1] of the image at ``path`` (see the module docstring)."""
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as e:  # Mitsuba's message names the format problem
        raise AlphaTextureError(f"could not be read as an image ({str(e).strip().splitlines()[-1]})") from e
    PF = mi.Bitmap.PixelFormat
    fmt = bmp.pixel_format()
    a = np.array(bmp, copy=True)
    if a.ndim == 2:
        a = a[..., None]
    if fmt in (PF.YA, PF.RGBA, PF.XYZA):
        ch = a[..., -1]
    elif fmt == PF.Y:
        ch = a[..., 0]
    elif fmt == PF.RGB and np.array_equal(a[..., 0], a[..., 1]) and np.array_equal(a[..., 0], a[..., 2]):
        ch = a[..., 0]  # greyscale stored as RGB
    else:
        raise AlphaTextureError(f"has pixel format {str(fmt).split('.')[-1]} without an alpha channel "
                                "(and is not greyscale); give an image with alpha (RGBA or grey + alpha) "
                                "or a greyscale mask")
    if np.issubdtype(ch.dtype, np.integer):
        ch = ch.astype(np.float64) / float(np.iinfo(ch.dtype).max)
    ch = np.asarray(ch, np.float32)
    if ch.shape[0] < 1 or ch.shape[1] < 1 or not np.all(np.isfinite(ch)):
        raise AlphaTextureError("has no pixels or non-finite alpha values")
    return np.clip(ch, 0.0, 1.0)


def opacity_mask(alpha: np.ndarray, cutoff: float) -> np.ndarray:
    """Binary opacity (H, W) float32: 1 where alpha ≥ cutoff (kept), 0 where discarded."""
    return (np.asarray(alpha) >= np.float32(cutoff)).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# the built-in leaf texture

# (centre u, centre v, length, width, angle in degrees) of each leaf, in texture units
_LEAVES = ((0.30, 0.30, 0.50, 0.20, 35.0), (0.70, 0.28, 0.44, 0.17, -50.0), (0.26, 0.74, 0.46, 0.18, -30.0),
           (0.72, 0.70, 0.52, 0.21, 60.0), (0.50, 0.50, 0.34, 0.13, 95.0))


def leaf_alpha(size: int = 128, edge: float = 0.03) -> np.ndarray:
    """Alpha (size, size) uint8 of a cluster of five almond-shaped leaves with soft edges.

    Each leaf is the set |t| < w·(1 − s²) in its own axes (s along the leaf in [−1, 1], t across,
    both in units of half the leaf's length / its width); alpha falls linearly from 1 to 0 across
    a band of ``edge`` (texture units) at the outline, so different cut-offs keep different
    outlines. A thin midrib and two pairs of veins are transparent slits (alpha 0.35, below the
    default cut-off 0.5, above 0.25): a cut-off of 0.25 closes them. Deterministic.
    """
    c = (np.arange(size) + 0.5) / size
    U, V = np.meshgrid(c, c, indexing="xy")  # row j is v = (j + 0.5) / size
    alpha = np.zeros((size, size))
    for cu, cv, length, width, deg in _LEAVES:
        th = math.radians(deg)
        du, dv = U - cu, V - cv
        s = (du * math.cos(th) + dv * math.sin(th)) / (0.5 * length)      # along, [-1, 1] inside
        t = (-du * math.sin(th) + dv * math.cos(th))                      # across, texture units
        half_w = 0.5 * width * (1.0 - s * s)                            # < 0 past the tips
        body = np.clip((half_w - np.abs(t)) / edge + 0.5, 0.0, 1.0)       # soft outline
        # slits: midrib along the leaf, veins at s = ±0.35 (only inside the leaf body)
        rib = (np.abs(t) < 0.012) & (np.abs(s) < 0.8)
        veins = np.zeros_like(rib)
        for s0 in (-0.35, 0.35):
            veins |= (np.abs((s - s0) * 0.5 * length - 0.6 * np.abs(t)) < 0.01) & (np.abs(t) < 0.8 * half_w)
        leaf = np.where(rib | veins, np.minimum(body, 0.35), body)
        alpha = np.maximum(alpha, leaf)
    return np.round(alpha * 255.0).astype(np.uint8)


def write_leaf_png(path, size: int = 128, edge: float = 0.03, color=(0.20, 0.45, 0.12)) -> np.ndarray:
    """Write the leaf texture as an 8-bit RGBA PNG (RGB a flat sRGB green, A = :func:`leaf_alpha`);
    returns the alpha (uint8). ``python -m shadowlab.scene.textures`` regenerates
    ``scenes/textures/leaf.png``."""
    a = leaf_alpha(size, edge)
    rgb = np.broadcast_to(np.round(np.asarray(color) * 255).astype(np.uint8), (*a.shape, 3))
    img = np.ascontiguousarray(np.concatenate([rgb, a[..., None]], axis=-1))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(img, pixel_format=mi.Bitmap.PixelFormat.RGBA).write(str(path))
    return a


def _main():  # pragma: no cover
    p = Path(__file__).resolve().parents[2] / "scenes" / "textures" / "leaf.png"  # spec.builtin_dir()
    a = write_leaf_png(p)
    print(f"wrote {p}: {a.shape[1]}x{a.shape[0]}, opaque fraction at cut-off 0.5: {np.mean(a >= 128):.3f}")


if __name__ == "__main__":  # pragma: no cover
    _main()
