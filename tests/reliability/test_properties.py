"""Property-based tests of the pure stages: bit packing, TFP/TFI rates, the sensor, .dat frames.

Each property is checked on arrays and parameters drawn by hypothesis (no example database is
kept, so runs leave no files behind); example counts keep the whole file well under 30 s.
"""

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from stages.capture.bits import count_spikes, pack_rows, packed_width, unpack_rows
from stages.capture.dat import HEAD_SIDES, DatLayout, dat_to_packed, packed_to_dat
from stages.errors import InputError
from stages.simulation.sensor import UNITS, SensorModel, fire, increments, initial_state, pixel_thresholds
from stages.reconstruction.tfi import tfi_rate
from stages.reconstruction.tfp import tfp_rate, undo_zero_reset
from tests.conftest import write_dat

FAST = settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
SLOW = settings(max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def spike_frames(draw, max_frames=12, max_height=6, max_width=37, min_frames=1):
    """(n, h, w) uint8 0/1 arrays; widths cover multiples of 8 and every remainder."""
    n = draw(st.integers(min_frames, max_frames))
    h = draw(st.integers(1, max_height))
    w = draw(st.integers(1, max_width))
    return draw(hnp.arrays(np.uint8, (n, h, w), elements=st.integers(0, 1)))


# --- stages.capture.bits ----------------------------------------------------------------------------

@FAST
@given(spike_frames())
def test_pack_unpack_round_trip_and_count(bits):
    n, h, w = bits.shape
    packed = pack_rows(bits)
    assert packed.dtype == np.uint8 and packed.shape == (n, h, packed_width(w))
    assert packed_width(w) == math.ceil(w / 8)
    np.testing.assert_array_equal(unpack_rows(packed, w), bits)
    assert count_spikes(packed) == int(bits.sum())
    # spare bits of a partly used last byte are zero (they would otherwise count as spikes)
    spare = packed_width(w) * 8 - w
    if spare:
        assert not (packed[..., -1] >> (8 - spare)).any()
    # LSB first: pixel x sits in bit x % 8 of byte x // 8
    x = w - 1
    np.testing.assert_array_equal((packed[..., x // 8] >> (x % 8)) & 1, bits[..., x])


@FAST
@given(hnp.arrays(np.uint8, st.integers(0, 70), elements=st.integers(0, 255)))
def test_count_spikes_is_popcount_for_any_length(raw):
    """count_spikes splits into 64-bit words plus a tail: every length must count every bit."""
    expected = int(np.unpackbits(raw).sum()) if raw.size else 0
    assert count_spikes(raw) == expected


# --- stages.reconstruction.tfp / stages.reconstruction.tfi ----------------------------------------------------------------

@FAST
@given(spike_frames(max_frames=41))
def test_tfp_rate_bounds_and_mean(bits):
    _, h, w = bits.shape
    packed = pack_rows(bits)
    rate = tfp_rate(packed, w, "subtract")
    zero = tfp_rate(packed, w, "zero")
    assert_rates_in_bounds(rate, zero, (h, w))
    np.testing.assert_allclose(rate, bits.mean(axis=0), rtol=1e-6, atol=1e-7)
    assert (zero >= rate - 1e-7).all()  # the correction only ever brightens
    np.testing.assert_allclose(zero, undo_zero_reset(rate), rtol=1e-6)


def assert_rates_in_bounds(rate: np.ndarray, zero: np.ndarray, shape: tuple[int, int]) -> None:
    """A subtract-reset rate image: float32, finite, in [0, 1]; its zero-reset reading: finite, in [0, 2]
    (undo_zero_reset(1) == 2)."""
    assert rate.dtype == np.float32 and rate.shape == shape
    assert np.isfinite(rate).all() and np.isfinite(zero).all()
    assert (rate >= 0).all() and (rate <= 1).all()
    assert (zero >= 0).all() and (zero <= 2 + 1e-6).all()


def test_undo_zero_reset_end_points():
    np.testing.assert_allclose(undo_zero_reset(np.array([0.0, 0.5, 1.0])), [0.0, 2 / 3, 2.0], rtol=1e-6)


@FAST
@given(spike_frames(max_frames=41, min_frames=3))
def test_tfi_rate_bounds_and_finite(bits):
    """TFI is 1/interval (interval >= 1 frame) or the TFP fallback: in [0, 1]; zero reset in [0, 2]."""
    n, h, w = bits.shape
    packed = pack_rows(bits)
    rate = tfi_rate(packed, w, "subtract")
    zero = tfi_rate(packed, w, "zero")
    assert_rates_in_bounds(rate, zero, (h, w))
    # a pixel that never fires reads 0 with both resets; one that always fires reads 1 (subtract)
    silent, busy = bits.sum(axis=0) == 0, bits.sum(axis=0) == n
    assert (rate[silent] == 0).all() and (zero[silent] == 0).all()
    assert np.allclose(rate[busy], 1)


@pytest.mark.parametrize("n", [1, 2])
def test_tfi_rate_short_window_falls_back_to_tfp(n):
    bits = np.tile(np.array([[[1, 0, 1, 1, 0, 0, 0, 1, 1]]], np.uint8), (n, 1, 1))  # (N, H=1, W=9)
    np.testing.assert_array_equal(tfi_rate(pack_rows(bits), 9), bits.mean(axis=0, dtype=np.float32))


@FAST
@given(period=st.integers(1, 12), phase=st.integers(0, 11), n=st.integers(25, 41), w=st.integers(1, 19))
def test_tfi_recovers_a_periodic_pixel(period, phase, n, w):
    """A pixel firing every p frames with spikes on both sides of the centre reads exactly 1/p
    (subtract) and 1/(p - 1/2) (zero reset, the module docstring's correction)."""
    phase %= period
    frames = np.zeros((n, 1, w), np.uint8)
    frames[phase::period] = 1
    centre = n // 2
    assume(frames[: centre + 1].any() and frames[centre + 1 :].any())
    packed = pack_rows(frames)
    np.testing.assert_allclose(tfi_rate(packed, w, "subtract"), 1 / period, rtol=1e-6)
    np.testing.assert_allclose(tfi_rate(packed, w, "zero"), 1 / (period - 0.5), rtol=1e-6)


# --- stages.simulation.sensor --------------------------------------------------------------------------

def _fire_constant(alpha, intensity, n, h, w, reset, seed):
    model = SensorModel(brightness=alpha, threshold=1.0, noise="none", reset=reset, seed=seed)
    q = increments(model, np.full((n, h, w), intensity, np.float32), 0)
    fired = fire(q, initial_state(model, h, w), reset=reset)
    counts = unpack_rows(fired.packed, w).sum(axis=0, dtype=np.int64)
    assert fired.spikes == int(counts.sum())
    return q, counts


sensor_cases = {
    "alpha": st.floats(0.05, 2.0), "intensity": st.floats(0.01, 1.0), "n": st.integers(1, 400),
    "h": st.integers(1, 4), "w": st.integers(1, 20), "seed": st.integers(0, 2**31),
}


@SLOW
@given(**sensor_cases)
def test_subtract_reset_counts_follow_alpha_times_intensity(alpha, intensity, n, h, w, seed):
    """Subtract reset keeps the remainder: over n frames a pixel fires within 1 of n·min(αI, 1)."""
    q, counts = _fire_constant(alpha, intensity, n, h, w, "subtract", seed)
    rate = min(alpha * intensity, 1.0)
    assert np.abs(q - rate * UNITS).max() <= 2  # round(α·I·2^24), I held as float32
    slack = 1 + n * 2 / UNITS  # quantisation of αI to 2^-24 of θ, accumulated over n frames
    assert np.abs(counts - n * rate).max() <= slack, (counts, n * rate)


@SLOW
@given(**sensor_cases)
def test_zero_reset_rate_is_one_over_ceil(alpha, intensity, n, h, w, seed):
    """Zero reset throws the remainder away: one spike every ceil(θ/(αI)) frames, within 1 spike."""
    rate = min(alpha * intensity, 1.0)
    steps = 1 / rate
    assume(abs(steps - round(steps)) > 1e-4)  # exact-integer periods are covered below
    _, counts = _fire_constant(alpha, intensity, n, h, w, "zero", seed)
    expected = n / math.ceil(steps)
    assert np.abs(counts - expected).max() <= 1, (counts, expected)


@pytest.mark.parametrize("alpha,intensity,period", [(1.0, 1.0, 1), (1.0, 0.5, 2), (0.5, 0.5, 4), (0.6, 1.0, 2),
                                                      (2.0, 0.75, 1), (0.25, 0.5, 8)])
def test_zero_reset_exact_periods(alpha, intensity, period):
    n = 160
    _, counts = _fire_constant(alpha, intensity, n, 3, 11, "zero", 7)
    assert np.abs(counts - n / period).max() <= 1


@SLOW
@given(data=st.data(), noise=st.sampled_from(["none", "realistic"]), reset=st.sampled_from(["subtract", "zero"]))
def test_fire_does_not_depend_on_chunking(data, noise, reset):
    """Splitting the frames into two calls (state carried over) gives the same bits as one call."""
    n, h, w = data.draw(st.integers(2, 30)), data.draw(st.integers(1, 5)), data.draw(st.integers(1, 19))
    split = data.draw(st.integers(1, n - 1))
    seed = data.draw(st.integers(0, 1000))
    mosaic = data.draw(hnp.arrays(np.float32, (n, h, w), elements=st.floats(0, 1, width=32)))
    model = SensorModel(brightness=data.draw(st.floats(0.1, 1.5)), noise=noise, reset=reset, seed=seed)
    thresholds = pixel_thresholds(model, h, w)
    state = initial_state(model, h, w)
    whole = fire(increments(model, mosaic, 0), state, reset=reset, thresholds=thresholds)
    first = fire(increments(model, mosaic[:split], 0), state, reset=reset, thresholds=thresholds)
    second = fire(increments(model, mosaic[split:], split), first.state, reset=reset, thresholds=thresholds)
    np.testing.assert_array_equal(np.concatenate([first.packed, second.packed]), whole.packed)
    np.testing.assert_array_equal(second.state, whole.state)
    assert first.spikes + second.spikes == whole.spikes
    if reset == "subtract" and thresholds is None:
        assert (whole.state >= 0).all() and (whole.state < UNITS).all()


# --- stages.capture.dat -----------------------------------------------------------------------------

@FAST
@given(bits=spike_frames(max_frames=5, max_height=5, max_width=34), head=st.integers(0, 17), flip=st.booleans(),
       head_at=st.sampled_from(HEAD_SIDES), data=st.data())
def test_dat_frames_round_trip(bits, head, flip, head_at, data):
    """packed -> .dat -> packed is the identity for any geometry, with head columns and flip;
    reading a .dat built independently (the test helper's layout) gives the upright frames."""
    n, h, w = bits.shape
    layout = DatLayout(h, w, head_columns=head, flip=flip, head_at=head_at)
    packed = pack_rows(bits)
    raw = packed_to_dat(packed, layout)
    assert raw.shape == (n, layout.frame_bytes) and raw.dtype == np.uint8
    assert layout.frame_count(raw.size) == n
    np.testing.assert_array_equal(dat_to_packed(raw, layout), packed)

    # an independent writer: head columns of random bits, rows stored bottom-up when flipped
    head_bits = data.draw(hnp.arrays(np.uint8, (n, h, head), elements=st.integers(0, 1)))
    stored = np.concatenate([head_bits, bits] if head_at == "start" else [bits, head_bits], axis=-1)
    file_frames = stored[:, ::-1] if flip else stored
    independent = np.packbits(file_frames.reshape(n, -1), axis=-1, bitorder="little")
    np.testing.assert_array_equal(dat_to_packed(independent, layout), packed)
    if head == 0:
        np.testing.assert_array_equal(independent, raw)  # same bytes as the exporter writes


@FAST
@given(bits=spike_frames(max_frames=4, max_height=6, max_width=40), flip=st.booleans())
def test_dat_bytes_match_the_conftest_writer(tmp_path_factory, bits, flip):
    _, h, w = bits.shape
    path = tmp_path_factory.mktemp("dat") / "c.dat"
    written = write_dat(path, bits, flip=flip)
    assert packed_to_dat(pack_rows(bits), DatLayout(h, w, flip=flip)).tobytes() == written


@FAST
@given(height=st.integers(1, 50), width=st.integers(1, 50), head=st.integers(0, 20), frames=st.integers(1, 20),
       surplus=st.integers(0, 400))
def test_dat_frame_count_accepts_exact_sizes_only(height, width, head, frames, surplus):
    layout = DatLayout(height, width, head_columns=head)
    assert layout.frame_bytes == math.ceil(height * (width + head) / 8)
    assert layout.frame_count(frames * layout.frame_bytes) == frames
    surplus %= layout.frame_bytes
    if surplus:
        with pytest.raises(InputError, match="not a multiple of the frame size"):
            layout.frame_count(frames * layout.frame_bytes + surplus)
    with pytest.raises(InputError, match="empty"):
        layout.frame_count(0)


@pytest.mark.parametrize("height,width,head", [(0, 8, 0), (8, 0, 0), (-1, 8, 0), (8, -8, 0), (8, 8, -1), (8.0, 8, 0)])
def test_dat_layout_refuses_nonsense_geometry(height, width, head):
    with pytest.raises(InputError):
        DatLayout(height, width, head_columns=head)
