"""Stages: CFA handling, demosaicking (OpenCV edge-aware) and the TFP picture."""

import numpy as np
import pytest

from stages.capture.bits import pack_rows
from stages.reconstruction.cfa import BAYER_PATTERNS, check_cfa, colour_index, flip_vertically
from stages.reconstruction.colour import auto_gain, demosaic, rate_to_rgb
from stages.errors import InputError
from stages.reconstruction.tfp import tfp_rate


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
@pytest.mark.parametrize("colour", [(0.8, 0.2, 0.1), (0.1, 0.7, 0.3), (0.2, 0.3, 0.9)])
def test_demosaic_recovers_a_flat_colour(cfa, colour):
    index = colour_index(cfa, 16, 16)
    mosaic = np.choose(index, colour).astype(np.float32)
    rgb = rate_to_rgb(mosaic, cfa, gain=1.0)
    np.testing.assert_allclose(rgb[4:-4, 4:-4].reshape(-1, 3).mean(0), np.array(colour) * 255, atol=2)


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_a_crop_demosaics_to_the_whole_pictures_pixels_wherever_it_ends(cfa):
    """A pixel's colour depends on its neighbourhood, not on where its row ends: OpenCV's VNG computes a row's last
    few pixels with scalar code that rounds a level apart from its vector code, and a TFP tile's right columns
    differed from the whole frame's by a level (tile 8 against 16, 2026-11-29). Crops of every even offset and
    width (the Bayer phase kept) give the whole picture's values 3 pixels in from their edges."""
    rate = np.random.default_rng(1).random((48, 96)).astype(np.float32)
    whole = demosaic(rate, cfa)
    for width in (8, 10, 14, 16, 18, 24, 32, 40):
        for x0 in range(0, 96 - width + 1, 2):
            for y0 in sorted({0, 2, 10, 48 - width} & set(range(0, 48 - width + 1, 2))):
                crop = demosaic(rate[y0 : y0 + width, x0 : x0 + width], cfa)
                np.testing.assert_array_equal(crop[3:-3, 3:-3], whole[y0 + 3 : y0 + width - 3, x0 + 3 : x0 + width - 3],
                                              err_msg=f"crop y {y0}, x {x0}, {width} wide")


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_flip_vertically_matches_the_flipped_mask(cfa):
    np.testing.assert_array_equal(colour_index(cfa, 8, 8)[::-1], colour_index(flip_vertically(cfa, 8), 8, 8))


def test_check_cfa_errors():
    assert check_cfa("RGGB", 4, 4) == "rggb"
    with pytest.raises(InputError, match="unknown CFA 'rgbw'"):
        check_cfa("rgbw")
    with pytest.raises(InputError, match="height 5 is odd"):
        check_cfa("rggb", 5, 4)
    assert check_cfa("mono", 5, 7) == "mono"


def test_tfp_is_the_window_mean_and_upsamples():
    bits = (np.random.default_rng(1).random((41, 6, 10)) < 0.25).astype(np.uint8)
    rate = tfp_rate(pack_rows(bits), 10)
    np.testing.assert_allclose(rate, bits.mean(0), rtol=1e-6)
    image = rate_to_rgb(rate, "mono", gain=2.0, scale=4)
    assert image.shape == (24, 40, 3) and image.dtype == np.uint8


def test_rate_to_rgb_applies_the_brightness_rule():
    rate = np.full((4, 4), 0.3, np.float32)
    assert rate_to_rgb(rate, "mono", gain=2.0)[0, 0, 0] == round(0.6 * 255)
    assert rate_to_rgb(rate, "mono", gain=10.0)[0, 0, 0] == 255  # clipped
    with pytest.raises(InputError, match="gain"):
        rate_to_rgb(rate, "mono", gain=0)


def test_auto_gain_puts_the_mean_at_mid_grey_without_much_clipping():
    rate = np.random.default_rng(0).uniform(0.05, 0.15, (64, 64)).astype(np.float32)
    gain = auto_gain(rate)
    assert gain * rate.mean() == pytest.approx(0.45, rel=1e-3)
    assert (rate * gain > 1).mean() <= 0.01
