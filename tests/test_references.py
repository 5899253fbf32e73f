"""Stages: the test set's ceilings (references made from the truth), against the sensor itself."""

import numpy as np
import pytest

from stages.reconstruction.colour import rate_to_rgb
from stages.errors import InputError
from stages.measures.metrics import psnr
from stages.measures.references import (exact_lr_bicubic, exact_mosaic_demosaicked, mean_level_per_period, read_periods,
                               steady_state_mosaic)
from stages.simulation.sensor import SensorModel, area_downsample, cfa_sample, fire, increments, initial_state
from stages.reconstruction.tfp import tfp_rate
from tests.test_sensor import smooth_rgb

COLOUR = (200, 100, 30)


@pytest.mark.parametrize("cfa", ["rggb", "gbrg"])
def test_a_flat_colour_is_its_own_exact_references(cfa):
    truth = np.empty((64, 64, 3), np.uint8)
    truth[...] = COLOUR
    np.testing.assert_array_equal(exact_lr_bicubic(truth, 4), truth)
    np.testing.assert_array_equal(exact_mosaic_demosaicked(truth, cfa, 4), truth)  # red and blue in their places
    np.testing.assert_array_equal(steady_state_mosaic(truth, cfa, 4, 0.8, "subtract"), truth)


@pytest.mark.parametrize("brightness", [0.6, 1.0])
def test_zero_reset_reads_every_intensity_of_one_period_alike(brightness):
    """I = 0.749: every 2nd frame at alpha 1, every 3rd at alpha 0.6; both read back as rho = 2/3 -> 170."""
    truth = np.full((32, 32, 3), 191, np.uint8)
    assert np.unique(steady_state_mosaic(truth, "rggb", 4, brightness, "zero")).tolist() == [170]


def test_tfp_s_long_run_reading_is_what_the_sensor_gives_a_still_scene():
    """The long-run TFP of a still picture through the simulated zero-reset sensor equals the reference."""
    brightness, scale, cfa, frames = 0.8, 4, "rggb", 2520  # 2520: a whole number of every period 1..10
    truth = np.round(smooth_rgb(128, 128, seed=4) * 255).astype(np.uint8)  # (128, 128, 3)
    mosaic = cfa_sample(area_downsample(truth.astype(np.float32) / 255, scale), cfa)  # (32, 32)
    model = SensorModel(brightness=brightness, reset="zero", seed=2)
    fired = fire(increments(model, np.broadcast_to(mosaic, (frames, *mosaic.shape)), 0),
                 initial_state(model, *mosaic.shape), reset="zero")
    measured = rate_to_rgb(tfp_rate(fired.packed, mosaic.shape[1], reset="zero"), cfa, gain=1 / brightness, scale=scale)
    ceiling = steady_state_mosaic(truth, cfa, scale, brightness, "zero")
    assert np.mean(np.abs(measured.astype(int) - ceiling) <= 1) > 0.99
    assert psnr(exact_mosaic_demosaicked(truth, cfa, scale), truth) > psnr(ceiling, truth) + 1  # the period costs


def test_the_best_reading_of_a_period_is_the_mean_intensity_that_has_it():
    """At alpha 1, I = 0.749 and I = 0.6 both fire every 2nd frame: read alike, as their mean; 0.2 every 5th."""
    truth = np.empty((32, 64, 3), np.uint8)
    truth[:, :32], truth[:, 32:48], truth[:, 48:] = 191, 153, 51  # 0.749, 0.6, 0.2
    levels = mean_level_per_period([truth], "rggb", 4, 1.0)
    assert sorted(levels) == [2, 5]
    assert levels[2] == pytest.approx((2 * 191 + 153) / 3 / 255) and levels[5] == pytest.approx(51 / 255)
    read = read_periods(truth, "rggb", 4, 1.0, levels)
    assert np.abs(read[8:-8, 8:32].astype(int) - round(levels[2] * 255)).max() <= 1  # away from borders and seams
    with pytest.raises(InputError, match=r"no level for period\(s\) \[5\]"):
        read_periods(truth, "rggb", 4, 1.0, {2: 0.7})


def test_bad_reset_or_brightness_is_refused():
    truth = np.zeros((8, 8, 3), np.uint8)
    with pytest.raises(InputError, match="unknown reset mode 'sideways'"):
        steady_state_mosaic(truth, "rggb", 2, 0.8, "sideways")
    with pytest.raises(InputError, match="brightness must be in"):
        steady_state_mosaic(truth, "rggb", 2, 0.0, "zero")
