"""Image metrics between a test image and a reference: RMSE, MAE, PSNR, SSIM, FLIP, ΔE2000.

Conventions shared by every function here:

* ``test`` and ``ref`` are linear float images, H×W or H×W×C, of one shape (an H×W image next to an
  H×W×C one is broadcast to C channels). ``mask`` is an H×W bool array selecting the pixels that are
  averaged (None = all pixels); a colour pixel counts with all its channels.
* An empty mask returns ``float('nan')``: there is nothing to measure. This is the only NaN.
* Pixel-wise metrics (RMSE, MAE, PSNR) require finite values only inside the mask. SSIM and FLIP
  filter neighbourhoods and ΔE2000/FLIP take their exposure from the whole reference, so they
  require the whole images to be finite. Non-finite input raises :class:`InputError`.
* The error maps (``ssim_map``, ``flip_map``, ``delta_e2000_map``) are whole-image H×W arrays; the
  scalar metric with a mask is the mean of its map over the mask, so one map serves several masks.

Display exposure (FLIP and ΔE2000). Both compare what a viewer would see, so both images are put on
one display exposure taken from the reference: they are multiplied by ``1 / Y99`` where ``Y99`` is
the 99th percentile of the reference's luminance (Rec. 709 / linear sRGB weights; the maximum if the
percentile is 0; no scaling for an all-black reference), then clipped to [0, 1]. The same scale is
applied to the test image, so an overall brightness error is still an error.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import gaussian_filter

from ..errors import InputError
from ..io.exr import check_finite

__all__ = [
    "rmse", "mae", "psnr", "ssim", "ssim_map", "flip", "flip_map",
    "delta_e2000", "delta_e2000_map", "display_exposure", "srgb_encode",
]

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # radius 5 px: the 11×11 Gaussian window of Wang et al. 2004
SSIM_K1 = 0.01
SSIM_K2 = 0.03
EXPOSURE_PERCENTILE = 99.0
_LUMA = np.array([0.2126, 0.7152, 0.0722])


# ----------------------------------------------------------------------------- input handling
def image_pair(test, ref, *, what: str = "image"):
    """``test`` and ``ref`` as float64 arrays of one shape (H×W or H×W×C); InputError naming ``what`` otherwise."""
    t = np.asarray(test, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    if t.ndim == 2 and r.ndim == 3 and t.shape == r.shape[:2]:
        t = np.repeat(t[..., None], r.shape[2], axis=2)
    elif r.ndim == 2 and t.ndim == 3 and r.shape == t.shape[:2]:
        r = np.repeat(r[..., None], t.shape[2], axis=2)
    if t.ndim not in (2, 3) or t.shape != r.shape or t.size == 0:
        raise InputError(
            f"test {what} has shape {t.shape} and reference {r.shape}; both must be H×W or H×W×C of "
            "the same size. Render the test at the reference's resolution."
        )
    return t, r


def mask_of(mask, shape2d):
    """A boolean H×W mask (None: every pixel), checked against ``shape2d``."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.dtype != bool:
        raise InputError(
            f"mask must be a boolean H×W array, got dtype {m.dtype}; build it with a comparison "
            "(e.g. penumbra_mask(truth))."
        )
    if m.shape != tuple(shape2d):
        raise InputError(
            f"mask has shape {m.shape} but the images are {tuple(shape2d)}; pass an H×W mask of the "
            "images' resolution."
        )
    return m


def _select(a: np.ndarray, m) -> np.ndarray:
    """The masked pixels of ``a`` (all channels), as a 1-D or N×C array."""
    return a if m is None else a[m]


def _empty(m) -> bool:
    return m is not None and not m.any()


def masked_mean(map2d: np.ndarray, m) -> float:
    """Mean of a per-pixel map over the mask ``m``; NaN for an empty mask."""
    if _empty(m):
        return float("nan")
    return float(np.mean(_select(map2d, m), dtype=np.float64))


def _prepare_pointwise(test, ref, mask):
    t, r = image_pair(test, ref)
    m = mask_of(mask, t.shape[:2])
    if not _empty(m):
        check_finite("test image", t, m)
        check_finite("reference image", r, m)
    return t, r, m


def _prepare_whole(test, ref, mask=None):
    t, r = image_pair(test, ref)
    m = mask_of(mask, t.shape[:2])
    check_finite("test image", t)
    check_finite("reference image", r)
    return t, r, m


def _rgb(a: np.ndarray, what: str) -> np.ndarray:
    if a.ndim == 2:
        return np.repeat(a[..., None], 3, axis=2)
    if a.shape[2] == 1:
        return np.repeat(a, 3, axis=2)
    if a.shape[2] != 3:
        raise InputError(
            f"{what} needs greyscale or RGB images, got {a.shape[2]} channels; drop alpha or extra "
            "AOV channels first."
        )
    return a


# ----------------------------------------------------------------------------- pixel-wise
def rmse(test, ref, mask=None) -> float:
    """Root-mean-square error over the masked pixels (and all channels); NaN for an empty mask.

    >>> import numpy as np
    >>> rmse(np.zeros((2, 2)), np.ones((2, 2)))
    1.0
    """
    t, r, m = _prepare_pointwise(test, ref, mask)
    if _empty(m):
        return float("nan")
    d = _select(t - r, m)
    return float(np.sqrt(np.mean(d * d)))


def mae(test, ref, mask=None) -> float:
    """Mean absolute error over the masked pixels (and all channels); NaN for an empty mask.

    >>> import numpy as np
    >>> mae(np.array([[0.0, 1.0]]), np.array([[0.5, 0.5]]))
    0.5
    """
    t, r, m = _prepare_pointwise(test, ref, mask)
    if _empty(m):
        return float("nan")
    return float(np.mean(np.abs(_select(t - r, m))))


def psnr(test, ref, mask=None, *, peak: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(peak² / MSE)`` over the masked pixels.

    ``peak`` defaults to the maximum of ``ref`` over the mask (HDR images have no fixed peak).
    Identical images give ``inf``; an empty mask gives NaN; a zero peak with a non-zero error gives
    ``-inf``.

    >>> import numpy as np
    >>> psnr(np.zeros((2, 2)), np.full((2, 2), 0.1), peak=1.0)
    20.0
    """
    t, r, m = _prepare_pointwise(test, ref, mask)
    if _empty(m):
        return float("nan")
    d = _select(t - r, m)
    mse = float(np.mean(d * d))
    if peak is None:
        peak = float(np.max(_select(r, m)))
    if mse == 0.0:
        return float("inf")
    if peak <= 0.0:
        return float("-inf")
    return float(20.0 * np.log10(peak) - 10.0 * np.log10(mse))


# ----------------------------------------------------------------------------- SSIM
def ssim_map(test, ref, *, data_range: float | None = None) -> np.ndarray:
    """Per-pixel SSIM (Wang et al. 2004), H×W float64; colour images average their channel maps.

    Gaussian window sigma 1.5 truncated at 3.5 sigma (11×11), K1 = 0.01, K2 = 0.03, population
    (co)variances, borders handled by reflection. ``data_range`` L defaults to the maximum of the
    whole reference (1.0 if that is not positive); C1 = (K1 L)², C2 = (K2 L)².

    >>> import numpy as np
    >>> x = np.linspace(0, 1, 64).reshape(8, 8)
    >>> float(ssim_map(x, x).min())
    1.0
    """
    t, r, _ = _prepare_whole(test, ref)
    return ssim_kernel(t, r, data_range)


def ssim_kernel(t: np.ndarray, r: np.ndarray, data_range) -> np.ndarray:
    """The SSIM map of a checked pair (:func:`image_pair`); :func:`ssim_map` for any input."""
    if data_range is None:
        data_range = float(r.max())
        if data_range <= 0.0:
            data_range = 1.0
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    sigma = (SSIM_SIGMA, SSIM_SIGMA) + ((0.0,) if t.ndim == 3 else ())

    def blur(a):
        return gaussian_filter(a, sigma=sigma, truncate=SSIM_TRUNCATE, mode="reflect")

    mu_t, mu_r = blur(t), blur(r)
    s_tt = blur(t * t) - mu_t * mu_t
    s_rr = blur(r * r) - mu_r * mu_r
    s_tr = blur(t * r) - mu_t * mu_r
    num = (2.0 * mu_t * mu_r + c1) * (2.0 * s_tr + c2)
    den = (mu_t * mu_t + mu_r * mu_r + c1) * (s_tt + s_rr + c2)
    smap = num / den
    return smap.mean(axis=2) if smap.ndim == 3 else smap


def ssim(test, ref, mask=None, *, data_range: float | None = None) -> float:
    """Mean SSIM over the masked pixels of :func:`ssim_map`; 1.0 for identical images, NaN for an
    empty mask. The map is computed on the whole images; the mask only selects what is averaged.

    >>> import numpy as np
    >>> x = np.linspace(0, 1, 64).reshape(8, 8)
    >>> ssim(x, x)
    1.0
    """
    t, r, m = _prepare_whole(test, ref, mask)
    if _empty(m):
        return float("nan")
    return masked_mean(ssim_kernel(t, r, data_range), m)


# ----------------------------------------------------------------------------- display exposure
def display_exposure(ref) -> float:
    """The scale that puts ``ref`` on the display: ``1 / Y99`` (99th percentile of luminance).

    Falls back to ``1 / max(Y)`` when the percentile is 0 and to 1.0 for an all-black reference.

    >>> import numpy as np
    >>> display_exposure(np.full((4, 4, 3), 2.0))
    0.5
    """
    r = np.asarray(ref, dtype=np.float64)
    y = r if r.ndim == 2 else (_rgb(r, "display_exposure") @ _LUMA)
    y99 = float(np.percentile(y, EXPOSURE_PERCENTILE))
    if not y99 > 0.0:
        y99 = float(np.max(y))
    return 1.0 / y99 if y99 > 0.0 else 1.0


def srgb_encode(x) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values clipped to [0, 1].

    >>> import numpy as np
    >>> srgb_encode(np.array([0.0, 0.0031308, 1.0])).round(6).tolist()
    [0.0, 0.04045, 1.0]
    """
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def _display_pair(t: np.ndarray, r: np.ndarray, what: str):
    """Both images in RGB at the reference's display exposure, clipped to [0, 1] (still linear)."""
    t3, r3 = _rgb(t, what), _rgb(r, what)
    s = display_exposure(r3)
    return np.clip(t3 * s, 0.0, 1.0), np.clip(r3 * s, 0.0, 1.0)


# ----------------------------------------------------------------------------- FLIP
def flip_kernel(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The FLIP map of a checked pair (:func:`image_pair`); :func:`flip_map` for any input."""
    import flip_evaluator

    td, rd = _display_pair(t, r, "FLIP")
    enc_t = np.ascontiguousarray(srgb_encode(td), dtype=np.float32)
    enc_r = np.ascontiguousarray(srgb_encode(rd), dtype=np.float32)
    err, _, _ = flip_evaluator.evaluate(enc_r, enc_t, "LDR", inputsRGB=True, applyMagma=False,
                                        computeMeanError=False)
    return np.asarray(err, dtype=np.float64).reshape(t.shape[:2])


def flip_map(test, ref) -> np.ndarray:
    """Per-pixel LDR-FLIP error in [0, 1] (flip_evaluator, 67 pixels per degree), H×W float64.

    Choice: LDR-FLIP on a display-exposed pair rather than HDR-FLIP. Both images are scaled by the
    reference's display exposure (module docstring: its 99th-percentile luminance maps to 1),
    clipped to [0, 1] and sRGB-encoded, then compared with LDR-FLIP. Reasons: HDR-FLIP chooses its
    exposure range from the image content and aborts the whole process (``sys.exit`` in
    flip_evaluator) when that range is empty, e.g. for a constant or black reference, which shadow
    tests produce; LDR-FLIP is about twice as fast (≈0.2 s at 512² vs ≈0.45 s); and one exposure
    from the reference compares all techniques of a scene on the same footing. Greyscale images are
    replicated to 3 channels.

    >>> import numpy as np
    >>> x = np.linspace(0, 1, 256).reshape(16, 16)
    >>> float(flip_map(x, x).max())
    0.0
    """
    t, r, _ = _prepare_whole(test, ref)
    return flip_kernel(t, r)


def flip(test, ref, mask=None) -> float:
    """Mean LDR-FLIP error over the masked pixels (see :func:`flip_map`); 0.0 for identical images,
    NaN for an empty mask.

    >>> import numpy as np
    >>> x = np.linspace(0, 1, 256).reshape(16, 16)
    >>> flip(x, x)
    0.0
    """
    t, r, m = _prepare_whole(test, ref, mask)
    if _empty(m):
        return float("nan")
    return masked_mean(flip_kernel(t, r), m)


# ----------------------------------------------------------------------------- CIEDE2000
def _colour():
    with warnings.catch_warnings():  # colour warns that matplotlib is absent; we do not plot
        warnings.simplefilter("ignore")
        import colour
    return colour


def delta_e2000_kernel(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The CIEDE2000 map of a checked pair (:func:`image_pair`); :func:`delta_e2000_map` for any input."""
    colour = _colour()
    td, rd = _display_pair(t, r, "delta_e2000")
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    d65 = srgb.whitepoint
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lab_t = colour.XYZ_to_Lab(colour.RGB_to_XYZ(td, srgb, apply_cctf_decoding=False), d65)
        lab_r = colour.XYZ_to_Lab(colour.RGB_to_XYZ(rd, srgb, apply_cctf_decoding=False), d65)
        de = colour.delta_E(lab_t, lab_r, method="CIE 2000")
    return np.asarray(de, dtype=np.float64)


def delta_e2000_map(test, ref) -> np.ndarray:
    """Per-pixel CIEDE2000 colour difference, H×W float64.

    Both images are put on the reference's display exposure and clipped to [0, 1] exactly as for
    FLIP (module docstring), read as linear sRGB (no CCTF decoding), converted to XYZ and to CIE Lab
    under D65 with colour-science, and compared with ``colour.delta_E(..., method="CIE 2000")``.
    Greyscale images are replicated to 3 channels. A ΔE of about 1 is a just noticeable difference.

    >>> import numpy as np
    >>> x = np.full((4, 4, 3), 0.5)
    >>> float(delta_e2000_map(x, x).max())
    0.0
    """
    t, r, _ = _prepare_whole(test, ref)
    return delta_e2000_kernel(t, r)


def delta_e2000(test, ref, mask=None) -> float:
    """Mean CIEDE2000 over the masked pixels (see :func:`delta_e2000_map`); NaN for an empty mask.

    >>> import numpy as np
    >>> delta_e2000(np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 0.5))
    0.0
    """
    t, r, m = _prepare_whole(test, ref, mask)
    if _empty(m):
        return float("nan")
    return masked_mean(delta_e2000_kernel(t, r), m)
