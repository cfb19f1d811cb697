"""Error metrics of a technique against the ground truth (docs/ARCHITECTURE.md, ``Metrics``).

``image``: RMSE, MAE, PSNR, SSIM, FLIP, ΔE2000 and their error maps; ``masks``: umbra / penumbra /
lit regions of the truth visibility and the light-leak and over-darkening rates; ``compare``: the
dicts of metrics a run stores per technique, light and scene.
"""

from .compare import (SHADED_KEYS, VISIBILITY_KEYS, compare_shaded, compare_visibility,
                                       pooled_visibility)
from .image import (delta_e2000, delta_e2000_map, display_exposure, flip, flip_map, mae, psnr, rmse,
                                     srgb_encode, ssim, ssim_map)
from .masks import (PENUMBRA_HI, PENUMBRA_LO, leak_mean, leak_rate, lit_mask, overdark_mean,
                                     overdark_rate, penumbra_mask, umbra_mask)

__all__ = [
    "rmse", "mae", "psnr", "ssim", "ssim_map", "flip", "flip_map", "delta_e2000", "delta_e2000_map",
    "display_exposure", "srgb_encode",
    "PENUMBRA_LO", "PENUMBRA_HI", "penumbra_mask", "umbra_mask", "lit_mask",
    "leak_rate", "overdark_rate", "leak_mean", "overdark_mean",
    "compare_visibility", "compare_shaded", "pooled_visibility", "VISIBILITY_KEYS", "SHADED_KEYS",
]
