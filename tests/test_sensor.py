"""Sensor model: downsampling, CFA sampling, increments and integrate-and-fire (known answers)."""

import math

import numba
import numpy as np
import pytest

from stages.capture.bits import pack_rows, unpack_rows
from stages.reconstruction.cfa import BAYER_PATTERNS, colour_index
from stages.errors import InputError
from stages.simulation.sensor import (UNITS, SensorModel, area_downsample, cfa_sample, dark_increments, fire, increments,
                           initial_state, pixel_thresholds)


def smooth_rgb(height: int, width: int, seed: int = 0, low: float = 0.05, high: float = 0.95) -> np.ndarray:
    """(H, W, 3) float32 smooth random colours in [low, high]."""
    import cv2

    coarse = np.random.default_rng(seed).random((max(height // 16, 2), max(width // 16, 2), 3))
    image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR)
    image = (image - image.min()) / np.ptp(image)
    return (low + (high - low) * image).astype(np.float32)


def static(frame: np.ndarray, frames: int) -> np.ndarray:
    """(H, W) -> (frames, H, W) view of a still scene."""
    return np.broadcast_to(frame, (frames, *frame.shape))


def rates(model: SensorModel, scene: np.ndarray) -> np.ndarray:
    """(n, H, W) intensities -> (H, W) spikes per frame over the whole run, from the model's seed."""
    n, height, width = scene.shape
    fired = fire(increments(model, scene, 0), initial_state(model, height, width), reset=model.reset,
                 thresholds=pixel_thresholds(model, height, width))
    return unpack_rows(fired.packed, width).mean(axis=0)


def reference_fire(q, state, reset, thresholds=None):
    """Plain numpy integrate-and-fire, frame by frame: (n, H, W) 0/1 spikes and the final state."""
    acc, thr = state.astype(np.int64), np.full(state.shape, UNITS) if thresholds is None else thresholds
    bits = np.empty(q.shape, np.uint8)
    for t in range(q.shape[0]):
        acc += q[t]
        bits[t] = acc >= thr
        acc = np.minimum(acc - bits[t] * thr, thr - 1) if reset == "subtract" else np.where(bits[t], 0, acc)
    return bits, acc


@pytest.mark.parametrize("brightness, threshold", [(0.6, 1.0), (0.9, 1.5)])
def test_subtract_rate_is_alpha_i_over_theta_per_pixel(brightness, threshold):
    model = SensorModel(brightness=brightness, threshold=threshold, reset="subtract", seed=3)
    mosaic = cfa_sample(area_downsample(smooth_rgb(128, 160), 4), "rggb")  # (32, 40)
    frames = 1000
    measured = rates(model, static(mosaic, frames))
    expected = model.brightness * mosaic.astype(np.float64) / model.threshold
    assert np.ptp(expected) > 0.3  # a real spread of intensities
    assert np.abs(measured - expected).max() <= 1 / frames + 1e-6


@pytest.mark.parametrize("intensity, period", [(0.25, 7), (0.45, 4), (0.9, 2)])
def test_zero_reset_fires_at_one_over_ceil_theta_over_alpha_i(intensity, period):
    model = SensorModel(brightness=0.6, threshold=1.0, reset="zero")
    assert math.ceil(model.threshold / (model.brightness * intensity)) == period
    frames = 2800
    spikes = rates(model, static(np.full((4, 6), intensity, np.float32), frames)) * frames
    assert np.abs(spikes - frames / period).max() <= 1  # one spike of slack for the initial state
    assert np.abs(spikes - frames * model.brightness * intensity / model.threshold).min() > 10  # not α·I/θ


@pytest.mark.parametrize("reset", ["zero", "subtract"])
@pytest.mark.parametrize("noise", ["none", "realistic"])
def test_rate_never_exceeds_one_spike_per_frame(reset, noise):
    model = SensorModel(brightness=5.0, reset=reset, noise=noise, threshold_mismatch=0.2)
    scene = static(np.full((6, 10), 0.9, np.float32), 50)  # α·I/θ = 4.5: clipped to 1
    q = increments(model, scene, 0)
    assert q.max() == UNITS and (q == UNITS).all() == (noise == "none")  # noise is added after the clip
    thresholds = pixel_thresholds(model, 6, 10)
    thresholds = np.full((6, 10), UNITS) if thresholds is None else thresholds
    fired = fire(q, initial_state(model, 6, 10), reset=reset, thresholds=thresholds)
    every_frame = unpack_rows(fired.packed, 10)[1:].all(axis=0)  # (H, W), after the first frame
    assert every_frame[thresholds <= q.min(axis=0)].all() and every_frame.any()
    if noise == "none":
        assert every_frame.all()
    assert (fired.state < thresholds).all()  # no charge piles up past one threshold


def test_increments_are_rounded_clipped_units():
    model = SensorModel(brightness=0.7, threshold=1.3)
    scene = np.random.default_rng(0).uniform(-0.2, 1.2, (3, 5, 9)).astype(np.float32)
    scene[0, 0, 0], scene[0, 0, 1] = np.nan, 2.0
    q = increments(model, scene, 17)
    assert q.dtype == np.int32 and q.shape == scene.shape
    intensity = np.nan_to_num(scene.astype(np.float64))
    rate = np.clip(intensity * model.brightness / model.threshold, 0, 1)
    assert np.abs(q - np.round(rate * UNITS)).max() <= 1  # the textbook formula, up to float rounding
    scale = model.brightness / model.threshold * UNITS
    np.testing.assert_array_equal(q, np.rint(np.clip(intensity * scale, 0, UNITS)))  # the exact one
    assert q[0, 0, 0] == 0 and q[0, 0, 1] == UNITS and q.min() == 0


@pytest.mark.parametrize("reset", ["zero", "subtract"])
@pytest.mark.parametrize("noise", ["none", "realistic"])
def test_fire_matches_a_plain_numpy_loop(reset, noise):
    model = SensorModel(reset=reset, noise=noise, seed=5, threshold_mismatch=0.1)
    scene = np.random.default_rng(1).random((30, 6, 21), dtype=np.float32)  # width 21: a partly used byte
    q, state = increments(model, scene, 0), initial_state(model, 6, 21)
    thresholds = pixel_thresholds(model, 6, 21)
    fired = fire(q, state, reset=reset, thresholds=thresholds)
    bits, final = reference_fire(q, state, reset, thresholds)
    np.testing.assert_array_equal(fired.packed, pack_rows(bits))  # spare bits of the last byte are zero
    np.testing.assert_array_equal(fired.state, final)
    assert fired.spikes == bits.sum() > 0
    assert not np.array_equal(fired.state, state) and np.array_equal(state, initial_state(model, 6, 21))


@pytest.mark.parametrize("reset", ["zero", "subtract"])
@pytest.mark.parametrize("noise", ["none", "realistic"])
def test_chunked_runs_are_bit_identical(reset, noise):
    model = SensorModel(reset=reset, noise=noise, seed=11)
    frames, height, width = 50, 10, 36
    scene = np.random.default_rng(2).random((frames, height, width), dtype=np.float32)  # a moving scene
    thresholds, state = pixel_thresholds(model, height, width), initial_state(model, height, width)
    whole = fire(increments(model, scene, 0), state, reset=reset, thresholds=thresholds)
    packed, spikes = [], 0
    for start, stop in ((0, 7), (7, 30), (30, 50)):
        part = fire(increments(model, scene[start:stop], start), state, reset=reset, thresholds=thresholds)
        packed.append(part.packed)
        state, spikes = part.state, spikes + part.spikes
    np.testing.assert_array_equal(np.concatenate(packed), whole.packed)
    np.testing.assert_array_equal(state, whole.state)
    assert spikes == whole.spikes


def test_fire_does_not_depend_on_the_thread_count():
    model = SensorModel(reset="subtract", noise="realistic")
    q = increments(model, np.random.default_rng(3).random((20, 16, 24), dtype=np.float32), 0)
    state, thresholds = initial_state(model, 16, 24), pixel_thresholds(model, 16, 24)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = fire(q, state, reset="subtract", thresholds=thresholds)
        single_q = increments(model, np.random.default_rng(3).random((20, 16, 24), dtype=np.float32), 0)
    finally:
        numba.set_num_threads(before)
    many = fire(q, state, reset="subtract", thresholds=thresholds)
    np.testing.assert_array_equal(single.packed, many.packed)
    np.testing.assert_array_equal(single.state, many.state)
    np.testing.assert_array_equal(single_q, q)


def test_area_downsample_is_the_exact_block_mean():
    image = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_array_equal(area_downsample(image, 2), [[2.5, 4.5], [10.5, 12.5]])
    rgb = np.stack([image, 2 * image, image + 1], axis=-1)  # (4, 4, 3)
    small = area_downsample(rgb, 4)
    assert small.shape == (1, 1, 3) and small.dtype == np.float32
    np.testing.assert_array_equal(small[0, 0], [7.5, 15.0, 8.5])
    assert area_downsample(image, 1) is not image and np.array_equal(area_downsample(image, 1), image)
    with pytest.raises(InputError, match="6x5 .*not divisible by scale 2"):
        area_downsample(np.zeros((6, 5)), 2)
    with pytest.raises(InputError, match="scale"):
        area_downsample(image, 0)


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_cfa_sample_keeps_the_filtered_colour(cfa):
    rgb = np.random.default_rng(4).random((2, 6, 8, 3), dtype=np.float32)
    index = colour_index(cfa, 6, 8)
    mosaics = cfa_sample(rgb, cfa)
    assert mosaics.shape == (2, 6, 8) and mosaics.dtype == np.float32
    for frame, mosaic in zip(rgb, mosaics):
        np.testing.assert_array_equal(mosaic, np.choose(index, np.moveaxis(frame, -1, 0)))
        np.testing.assert_array_equal(cfa_sample(frame, cfa), mosaic)
    first = "rgb".index(cfa[0])
    assert mosaics[0, 0, 0] == rgb[0, 0, 0, first] and mosaics[0, 2, 4] == rgb[0, 2, 4, first]


def test_cfa_sample_mono_is_rec601_luma():
    rgb = np.array([[[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.2, 0.8]]], np.float32)  # (1, 4, 3)
    np.testing.assert_allclose(cfa_sample(rgb, "mono")[0], [0.299, 0.587, 0.114, 0.3581], rtol=1e-6)
    with pytest.raises(InputError, match="odd"):
        cfa_sample(np.zeros((3, 4, 3)), "rggb")
    with pytest.raises(InputError, match="RGB"):
        cfa_sample(np.zeros((4, 4)), "rggb")


@pytest.mark.parametrize("kwargs, words", [
    ({"brightness": 0}, "brightness α must be > 0, got 0"),
    ({"brightness": -0.5}, "brightness α must be > 0, got -0.5"),
    ({"brightness": float("nan")}, "brightness α must be > 0"),
    ({"threshold": 0.0}, "threshold θ must be > 0, got 0.0"),
    ({"reset": "hard"}, "unknown reset mode 'hard': expected one of subtract, zero"),
    ({"noise": "poisson"}, "unknown noise 'poisson': expected one of none, realistic"),
    ({"electrons_per_threshold": 0}, "electrons_per_threshold must be > 0"),
    ({"threshold_mismatch": -0.1}, "threshold_mismatch must be >= 0"),
    ({"seed": -1}, "seed must be an integer >= 0"),
])
def test_sensor_model_rejects_bad_parameters(kwargs, words):
    with pytest.raises(InputError) as error:
        SensorModel(**kwargs)
    assert words in str(error.value) and "\n" not in str(error.value)


def test_gain_is_theta_over_alpha():
    assert SensorModel(brightness=0.5, threshold=2.0).gain == 4.0


def test_fire_rejects_bad_shapes_and_resets():
    q = np.zeros((2, 4, 6), np.int32)
    with pytest.raises(InputError, match="reset"):
        fire(q, np.zeros((4, 6), np.int64), reset="hard")
    with pytest.raises(InputError, match="state of shape"):
        fire(q, np.zeros((4, 5), np.int64), reset="zero")
    with pytest.raises(InputError, match="thresholds must lie"):
        fire(q, np.zeros((4, 6), np.int64), reset="zero", thresholds=np.zeros((4, 6), np.int64))


@pytest.mark.parametrize("intensity", [0.3, 0.5, 0.8])
def test_realistic_noise_keeps_the_mean_rate_and_adds_fixed_pattern(intensity):
    scene = static(np.full((32, 32), intensity, np.float32), 1000)
    clean = rates(SensorModel(reset="subtract"), scene)
    noisy = rates(SensorModel(reset="subtract", noise="realistic"), scene)
    expected = 0.6 * intensity
    assert abs(clean.mean() - expected) < 1e-3 and clean.std() < 1e-3  # uniform without noise
    assert abs(noisy.mean() / expected - 1) < 0.03
    assert noisy.std() > 0.5 * 0.02 * expected  # 2 % threshold mismatch: about 0.02 * rate
    inverse_threshold = UNITS / pixel_thresholds(SensorModel(noise="realistic"), 32, 32)
    assert np.corrcoef(noisy.ravel(), inverse_threshold.ravel())[0, 1] > 0.9  # the pattern is the thresholds'


def test_realistic_noise_is_seeded():
    scene = np.random.default_rng(6).random((40, 8, 16), dtype=np.float32)

    def run(seed):
        model = SensorModel(noise="realistic", seed=seed)
        fired = fire(increments(model, scene, 100), initial_state(model, 8, 16), reset=model.reset,
                     thresholds=pixel_thresholds(model, 8, 16))
        return fired.packed, fired.state

    first, again, other = run(1), run(1), run(2)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not np.array_equal(first[0], other[0]) and not np.array_equal(first[1], other[1])
    noisy = increments(SensorModel(noise="realistic"), scene, 0)
    assert not np.array_equal(noisy, increments(SensorModel(noise="realistic"), scene, 1))  # keyed by frame


def test_dark_current_has_the_configured_mean_and_only_with_noise():
    model = SensorModel(noise="realistic", dark_rate=1e-3)
    dark = dark_increments(model, 256, 256)
    assert dark.dtype == np.float32 and abs(dark.mean() / 1e-3 - 1) < 0.02 and dark.std() > 2e-4
    assert dark_increments(SensorModel(), 4, 4) is None and pixel_thresholds(SensorModel(), 4, 4) is None
    black = static(np.zeros((16, 16), np.float32), 200)
    assert increments(SensorModel(), black, 0).max() == 0
    assert increments(model, black, 0).mean() > 0.5e-3 * UNITS  # dark current (plus its shot noise)
