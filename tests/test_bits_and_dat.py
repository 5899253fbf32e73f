"""Stages: bit packing and .dat frame conversion, on real bytes."""

import numpy as np
import pytest

from stages.capture.bits import count_spikes, pack_rows, packed_width, unpack_rows
from stages.capture.dat import DatLayout, dat_to_packed, packed_to_dat
from stages.errors import InputError


@pytest.mark.parametrize("width", [8, 13, 250, 400, 1000])
def test_pack_unpack_round_trip(width):
    bits = (np.random.default_rng(width).random((3, 5, width)) < 0.3).astype(np.uint8)
    packed = pack_rows(bits)
    assert packed.shape == (3, 5, packed_width(width))
    np.testing.assert_array_equal(unpack_rows(packed, width), bits)
    assert count_spikes(packed) == bits.sum()


def test_pack_is_lsb_first():
    row = np.zeros((1, 8), np.uint8)
    row[0, 0] = 1
    assert pack_rows(row)[0, 0] == 1
    row[0] = 0
    row[0, 7] = 1
    assert pack_rows(row)[0, 0] == 128


@pytest.mark.parametrize("height,width,head,flip", [(250, 400, 0, True), (10, 13, 0, False), (6, 250, 3, True), (4, 400, 16, False)])
def test_dat_round_trip_and_pixel_order(height, width, head, flip):
    layout = DatLayout(height, width, head, flip)
    rng = np.random.default_rng(height)
    stored = (rng.random((3, height, width + head)) < 0.4).astype(np.uint8)
    stored[:, :, width:] = 0  # header columns (at the end of each row) come back zero-filled
    raw = np.packbits(stored.reshape(3, -1), axis=-1, bitorder="little")
    assert raw.shape[1] == layout.frame_bytes
    packed = dat_to_packed(raw, layout)
    upright = stored[:, ::-1, :width] if flip else stored[:, :, :width]
    np.testing.assert_array_equal(unpack_rows(packed, width), upright)
    np.testing.assert_array_equal(packed_to_dat(packed, layout), raw)


def test_frame_count_names_the_surplus():
    layout = DatLayout(250, 400)
    assert layout.frame_count(12_500 * 301) == 301
    with pytest.raises(InputError, match="7 bytes too many"):
        layout.frame_count(12_500 * 3 + 7)


def test_layout_rejects_nonsense():
    with pytest.raises(InputError, match="height"):
        DatLayout(0, 400)
    with pytest.raises(InputError, match="width"):
        DatLayout(250, -8)
