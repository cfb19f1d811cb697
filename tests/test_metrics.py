"""Metrics: closed forms and properties (identity, monotonicity, masks' strictness, empty masks)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from shadowlab.errors import InputError
from shadowlab.metrics import (
    PENUMBRA_HI,
    PENUMBRA_LO,
    SHADED_KEYS,
    VISIBILITY_KEYS,
    compare_shaded,
    compare_visibility,
    delta_e2000,
    delta_e2000_map,
    display_exposure,
    flip,
    flip_map,
    leak_mean,
    leak_rate,
    lit_mask,
    mae,
    overdark_mean,
    overdark_rate,
    penumbra_mask,
    psnr,
    rmse,
    ssim,
    ssim_map,
    umbra_mask,
)


def _smooth_image(seed=0, shape=(64, 64, 3), scale=2.0):
    """A smooth HDR-ish test image with structure (not constant)."""
    rng = np.random.default_rng(seed)
    a = gaussian_filter(rng.random(shape), sigma=(4, 4, 0)[: len(shape)])
    a = (a - a.min()) / (a.max() - a.min())
    return scale * a


# ----------------------------------------------------------------------------- pixel-wise
def test_rmse_mae_psnr_hand_computed():
    ref = np.array([[1.0, 2.0], [4.0, 4.0]])
    test = ref + np.array([[0.1, -0.1], [0.0, 0.0]])
    assert rmse(test, ref) == pytest.approx(math.sqrt(0.02 / 4))
    assert mae(test, ref) == pytest.approx(0.05)
    assert psnr(test, ref) == pytest.approx(10 * math.log10(16 / 0.005))  # peak = max ref = 4
    top = np.array([[True, True], [False, False]])
    assert rmse(test, ref, top) == pytest.approx(0.1)
    assert mae(test, ref, top) == pytest.approx(0.1)
    assert psnr(test, ref, top) == pytest.approx(10 * math.log10(4 / 0.01))  # peak over mask = 2
    assert psnr(test, ref, top, peak=1.0) == pytest.approx(20.0)
    assert rmse(np.zeros((2, 2)), np.ones((2, 2))) == 1.0


def test_colour_mask_counts_all_channels():
    ref = np.zeros((2, 2, 3))
    test = ref.copy()
    test[0, 0] = [3.0, 0.0, 0.0]
    m = np.array([[True, False], [False, False]])
    assert rmse(test, ref, m) == pytest.approx(math.sqrt(9 / 3))
    assert mae(test, ref, m) == pytest.approx(1.0)
    assert rmse(test, ref) == pytest.approx(math.sqrt(9 / 12))


def test_identical_images_give_perfect_scores():
    x = _smooth_image(1)
    assert rmse(x, x) == 0.0 and mae(x, x) == 0.0
    assert psnr(x, x) == math.inf
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    assert flip(x, x) == 0.0
    assert delta_e2000(x, x) == 0.0


def test_empty_mask_gives_nan_everywhere():
    x = _smooth_image(2, (16, 16, 3))
    empty = np.zeros((16, 16), bool)
    for f in (rmse, mae, psnr, ssim, flip, delta_e2000):
        assert math.isnan(f(x, x * 0.5, empty)), f.__name__


def test_bad_inputs_raise_input_error():
    x = np.zeros((8, 8))
    with pytest.raises(InputError, match="same size"):
        rmse(x, np.zeros((8, 9)))
    with pytest.raises(InputError, match="boolean"):
        rmse(x, x, np.ones((8, 8)))
    with pytest.raises(InputError, match="mask has shape"):
        rmse(x, x, np.ones((4, 4), bool))
    y = x.copy()
    y[3, 5] = np.nan
    with pytest.raises(InputError, match=r"\(x=5, y=3\)"):
        rmse(y, x)
    outside = np.ones((8, 8), bool)
    outside[3, 5] = False
    assert rmse(y, x, outside) == 0.0  # NaN outside the mask does not matter pixel-wise
    with pytest.raises(InputError, match="non-finite"):
        ssim(y, x, outside)  # but SSIM filters neighbourhoods
    with pytest.raises(InputError, match="channels"):
        flip(np.zeros((8, 8, 4)), np.zeros((8, 8, 4)))


# ----------------------------------------------------------------------------- SSIM
def test_ssim_of_constant_images_is_the_luminance_term():
    a, b, L = 0.5, 1.0, 1.0
    c1 = (0.01 * L) ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)  # sigmas are 0: contrast/structure term = 1
    got = ssim(np.full((16, 16), a), np.full((16, 16), b), data_range=L)
    assert got == pytest.approx(expected, rel=1e-12)


def test_ssim_decreases_with_noise_and_mask_selects_map():
    ref = _smooth_image(3, (64, 64))
    rng = np.random.default_rng(4)
    noise = rng.standard_normal(ref.shape)
    values = [ssim(ref + s * noise, ref) for s in (0.0, 0.02, 0.1, 0.4)]
    assert values[0] == pytest.approx(1.0)
    assert all(a > b for a, b in zip(values, values[1:]))
    m = np.zeros((64, 64), bool)
    m[10:30, 5:50] = True
    test = ref + 0.1 * noise
    assert ssim(test, ref, m) == pytest.approx(ssim_map(test, ref)[m].mean())


def test_ssim_colour_is_mean_of_channels():
    ref = _smooth_image(5)
    test = ref + 0.05 * np.random.default_rng(6).standard_normal(ref.shape)
    L = ref.max()
    per_channel = [ssim(test[..., c], ref[..., c], data_range=L) for c in range(3)]
    assert ssim(test, ref) == pytest.approx(np.mean(per_channel))


# ----------------------------------------------------------------------------- FLIP
def test_flip_zero_for_identity_and_grows_with_error():
    ref = _smooth_image(7, (64, 64, 3))
    rng = np.random.default_rng(8)
    noise = rng.standard_normal(ref.shape)
    errs = [flip(np.clip(ref + s * noise, 0, None), ref) for s in (0.0, 0.05, 0.2, 0.6)]
    assert errs[0] == 0.0
    assert all(a < b for a, b in zip(errs, errs[1:]))
    assert 0.0 <= errs[-1] <= 1.0


def test_flip_map_and_masked_mean_agree_and_grey_is_replicated():
    ref = _smooth_image(9, (32, 32))
    test = ref * 0.7
    fmap = flip_map(test, ref)
    assert fmap.shape == (32, 32)
    assert np.all((fmap >= 0) & (fmap <= 1))
    m = np.zeros((32, 32), bool)
    m[:, :10] = True
    assert flip(test, ref, m) == pytest.approx(fmap[m].mean(), rel=1e-6)
    grey3 = flip(np.repeat(test[..., None], 3, 2), np.repeat(ref[..., None], 3, 2))
    assert flip(test, ref) == pytest.approx(grey3, rel=1e-6)


def test_flip_survives_black_and_constant_images():
    z = np.zeros((16, 16, 3))
    assert flip(z, z) == 0.0
    assert flip(np.full((16, 16, 3), 0.5), z) > 0.0  # white-ish vs black is an error
    assert flip(np.full((16, 16), 3.0), np.full((16, 16), 3.0)) == 0.0


def test_exposure_is_common_and_from_reference():
    ref = np.full((10, 10, 3), 4.0)
    assert display_exposure(ref) == pytest.approx(0.25)
    # scaling both images together does not change FLIP/ΔE (same display image)...
    ref2 = _smooth_image(10, (32, 32, 3))
    test2 = ref2 * 0.8
    assert flip(10 * test2, 10 * ref2) == pytest.approx(flip(test2, ref2), abs=1e-5)
    assert delta_e2000(10 * test2, 10 * ref2) == pytest.approx(delta_e2000(test2, ref2), abs=1e-6)
    # ...but a brightness error of the test alone is an error
    assert flip(test2, ref2) > 0.0 and delta_e2000(test2, ref2) > 0.0


# ----------------------------------------------------------------------------- ΔE2000
def _colour():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
    return colour


def test_delta_e2000_matches_colour_science_directly():
    colour = _colour()
    a = np.array([0.2, 0.4, 0.1])
    b = np.array([0.25, 0.3, 0.15])
    # reference: white (luminance exactly 1 -> exposure 1) with one pixel of colour a
    ref = np.ones((10, 10, 3))
    ref[0, 0] = a
    test = ref.copy()
    test[0, 0] = b
    assert display_exposure(ref) == pytest.approx(1.0)
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lab_a = colour.XYZ_to_Lab(colour.RGB_to_XYZ(a, srgb, apply_cctf_decoding=False), srgb.whitepoint)
        lab_b = colour.XYZ_to_Lab(colour.RGB_to_XYZ(b, srgb, apply_cctf_decoding=False), srgb.whitepoint)
        expected = float(colour.delta_E(lab_b, lab_a, method="CIE 2000"))
    assert expected > 1.0
    m = np.zeros((10, 10), bool)
    m[0, 0] = True
    assert delta_e2000(test, ref, m) == pytest.approx(expected, rel=1e-6)
    assert delta_e2000(test, ref) == pytest.approx(expected / 100, rel=1e-6)
    dmap = delta_e2000_map(test, ref)
    assert dmap.shape == (10, 10) and dmap[0, 0] == pytest.approx(expected, rel=1e-6)
    assert np.count_nonzero(dmap) == 1


def test_delta_e2000_white_is_l100_and_grey_replicated():
    # linear sRGB white (1,1,1) is the D65 white: Lab (100, 0, 0); black is (0, 0, 0): ΔE00 = 100
    white = np.ones((4, 4, 3))
    black_dot = white.copy()
    black_dot[0, 0] = 0.0
    m = np.zeros((4, 4), bool)
    m[0, 0] = True
    assert delta_e2000(black_dot, white, m) == pytest.approx(100.0, abs=1e-3)
    assert delta_e2000(black_dot[..., 0], white[..., 0], m) == pytest.approx(100.0, abs=1e-3)


# ----------------------------------------------------------------------------- masks
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_masks_are_strict_at_thresholds(dtype):
    t = np.array([[0.0, 0.02, 0.0201, 0.5, 0.9799, 0.98, 1.0]], dtype=dtype)
    assert umbra_mask(t).tolist() == [[True, True, False, False, False, False, False]]
    assert penumbra_mask(t).tolist() == [[False, False, True, True, True, False, False]]
    assert lit_mask(t).tolist() == [[False, False, False, False, False, True, True]]
    assert (PENUMBRA_LO, PENUMBRA_HI) == (0.02, 0.98)


def test_masks_partition_valid_pixels():
    rng = np.random.default_rng(11)
    t = np.clip(rng.random((32, 32)) * 1.2 - 0.1, 0, 1)
    valid = rng.random((32, 32)) > 0.3
    u, p, l = umbra_mask(t, valid), penumbra_mask(t, valid), lit_mask(t, valid)
    assert not (u & p).any() and not (u & l).any() and not (p & l).any()
    np.testing.assert_array_equal(u | p | l, valid)


def test_leak_and_overdark_rates_on_constructed_arrays():
    truth = np.array([[0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.5, 0.0]])
    vis = np.array([[0.9, 0.6, 0.5, 0.0, 0.4, 1.0, 0.0, 1.0]])
    valid = np.array([[True] * 7 + [False]])  # the last pixel would leak but is not valid
    # umbra (valid): vis 0.9, 0.6, 0.5, 0.0 -> > 0.5 strictly: 2 of 4
    assert leak_rate(vis, truth, valid) == 0.5
    assert leak_mean(vis, truth, valid) == pytest.approx((0.9 + 0.6 + 0.5 + 0.0) / 4)
    # lit: vis 0.4, 1.0 -> < 0.5: 1 of 2
    assert overdark_rate(vis, truth, valid) == 0.5
    assert overdark_mean(vis, truth, valid) == pytest.approx((0.6 + 0.0) / 2)
    assert leak_rate(vis, truth) == pytest.approx(3 / 5)


def test_rates_are_zero_for_empty_regions():
    all_lit = np.ones((4, 4))
    assert leak_rate(np.ones((4, 4)), all_lit) == 0.0
    assert leak_mean(np.ones((4, 4)), all_lit) == 0.0
    all_dark = np.zeros((4, 4))
    assert overdark_rate(all_dark, all_dark) == 0.0
    assert overdark_mean(all_dark, all_dark) == 0.0


# ----------------------------------------------------------------------------- compare
def test_compare_visibility_keys_and_values():
    truth = np.array([[0.0, 0.0, 0.5, 0.5, 1.0, 1.0]])
    vis = np.array([[1.0, 0.0, 0.7, 0.5, 0.0, 1.0]])
    m = compare_visibility(vis, truth)
    assert tuple(m) == VISIBILITY_KEYS
    assert all(type(v) is float for v in m.values())
    assert m["rmse"] == pytest.approx(math.sqrt((1 + 0.04 + 1) / 6))
    assert m["mae"] == pytest.approx(2.2 / 6)
    assert m["rmse_penumbra"] == pytest.approx(math.sqrt(0.04 / 2))
    assert m["mae_penumbra"] == pytest.approx(0.1)
    assert m["leak_rate"] == 0.5 and m["overdark_rate"] == 0.5
    assert m["leak_mean"] == 0.5 and m["overdark_mean"] == 0.5
    assert m["penumbra_fraction"] == pytest.approx(2 / 6)
    valid = np.array([[False, True, True, True, True, True]])
    assert compare_visibility(vis, truth, valid)["penumbra_fraction"] == pytest.approx(2 / 5)


def test_compare_visibility_no_penumbra_and_nan_outside_valid():
    truth = np.array([[0.0, 1.0, np.nan]])
    vis = np.array([[0.0, 1.0, np.nan]])
    m = compare_visibility(vis, truth, np.array([[True, True, False]]))
    assert math.isnan(m["rmse_penumbra"]) and math.isnan(m["mae_penumbra"])
    assert m["rmse"] == 0.0 and m["penumbra_fraction"] == 0.0 and m["leak_rate"] == 0.0


def test_compare_shaded_matches_individual_metrics():
    ref = _smooth_image(12, (48, 48, 3))
    rng = np.random.default_rng(13)
    test = np.clip(ref + 0.05 * rng.standard_normal(ref.shape), 0, None)
    pen = np.zeros((48, 48), bool)
    pen[20:30, 10:40] = True
    valid = np.ones((48, 48), bool)
    valid[:, :4] = False
    m = compare_shaded(test, ref, penumbra=pen, valid=valid)
    assert tuple(m) == SHADED_KEYS
    assert all(type(v) is float and math.isfinite(v) for v in m.values())
    assert m["rmse"] == pytest.approx(rmse(test, ref, valid))
    assert m["rmse_penumbra"] == pytest.approx(rmse(test, ref, pen & valid))
    assert m["mae_penumbra"] == pytest.approx(mae(test, ref, pen & valid))
    peak = ref[valid].max()
    assert m["psnr"] == pytest.approx(psnr(test, ref, valid, peak=peak))
    assert m["psnr_penumbra"] == pytest.approx(psnr(test, ref, pen & valid, peak=peak))
    assert m["ssim_penumbra"] == pytest.approx(ssim(test, ref, pen & valid))
    assert m["flip"] == pytest.approx(flip(test, ref, valid))
    assert m["flip_penumbra"] == pytest.approx(flip(test, ref, pen & valid))
    assert m["delta_e2000_penumbra"] == pytest.approx(delta_e2000(test, ref, pen & valid))


def test_compare_shaded_without_penumbra_gives_nan_penumbra_only():
    x = _smooth_image(14, (16, 16, 3))
    m = compare_shaded(x, x)
    for k in ("rmse", "mae", "psnr", "ssim", "flip", "delta_e2000"):
        assert math.isnan(m[k + "_penumbra"])
    assert m["rmse"] == 0.0 and m["ssim"] == pytest.approx(1.0) and m["psnr"] == math.inf
